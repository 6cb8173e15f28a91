"""The steps by which the demo recipe was chosen, each a change to the one before, at 1000 steps.

    python -m benchmarks.recipe_trials [--trials A,B,...] [--steps 1000] [--data DIR]

Each trial is the `ours` recipe (`recipes.overrides("ours")`, the demo's) with some settings put back
(the recipe as it was
before that step), trained with `runs.train_run` on tower-small (the convergence
benchmark's cached, DPT-masked copy) and scored with `evaluate.evaluate_run`. Prints one
line per trial and writes benchmarks/results/recipe_trials.json. docs/GRID.md has the table.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from benchmarks.convergence import dataset_dir  # noqa: E402
from jaxnerf_grid.config import recipes  # noqa: E402
from jaxnerf_grid.eval import evaluate  # noqa: E402
from jaxnerf_grid.train import runs  # noqa: E402
from jaxnerf_grid.util import io  # noqa: E402

FIRST = {"model": {"opaque_far": False, "far": None, "field": {"density_bias": -1.0},
                   "sampler": {"field": {"density_bias": -1.0}}},
         "train": {"adam_b2": 0.999, "lr_init": 1e-2, "lr_final": 1e-3}}
TRIALS = {  # name: (what changed, settings that differ from the ours recipe)
    "A": ("first grid recipe: grid + proposal, sky at the dataset's far (40 units)", FIRST),
    "B": ("+ opaque far bin, density bias -4", {"model": {"far": None}, "train": FIRST["train"]}),
    "C": ("+ Adam b2 0.99", {"model": {"far": None}, "train": {"lr_init": 1e-2, "lr_final": 1e-3}}),
    "E": ("+ far bound 1000 units (sky at infinity)", {"train": {"lr_init": 1e-2, "lr_final": 1e-3}}),
    "F": ("E + distortion weight 0.01", {"train": {"lr_init": 1e-2, "lr_final": 1e-3,
                                                    "distortion_loss_weight": 0.01}}),
    "G": ("E + learning rate 2e-2 (the demo recipe)", {}),
    "H": ("G + learning rate 4e-2", {"train": {"lr_init": 4e-2, "lr_final": 4e-3}}),
}


def merged(extra: dict) -> dict:
    out = recipes.overrides("ours")
    for section, values in extra.items():
        for key, value in values.items():
            if isinstance(value, dict):
                out[section].setdefault(key, {}).update(value)
            elif value is None:
                out[section].pop(key, None)
            else:
                out[section][key] = value
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", default=",".join(TRIALS))
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--data", default=None)
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "recipe_trials.json"))
    args = p.parse_args()
    data = Path(args.data) if args.data else dataset_dir(ROOT / "benchmarks" / ".cache")
    rows = []
    for name in args.trials.split(","):
        what, extra = TRIALS[name]
        t = time.perf_counter()
        run_dir, _, result = runs.train_run(str(data), "ours", ROOT / "benchmarks" / ".cache" / "trials" / name,
                                            merged(extra), args.steps, overwrite=True, progress=False)
        m = evaluate.evaluate_run(run_dir, progress=False, distractor_views=0)
        f = ((m.get("geometry") or {}).get("thresholds") or {}).get("0.02", {}).get("fscore")
        rows.append({"trial": name, "what": what, "steps": args.steps, "train_s": result.seconds,
                     "psnr": m["mean"]["psnr"], "regions": m["regions_mean"], "fscore_0.02": f,
                     "wall_s": time.perf_counter() - t})
        print(f"{name}: {what}: PSNR {m['mean']['psnr']:.2f}, tower {m['regions_mean'].get('tower'):.2f}, "
              f"far {m['regions_mean'].get('far_background'):.2f}, F@0.02 {f if f is None else round(f, 3)}, "
              f"train {result.seconds:.0f} s", flush=True)
    io.write_json(args.out, {"data": str(data), "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
