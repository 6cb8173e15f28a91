"""Convergence against wall-clock time: the MLP field against the hash-grid field.

    python -m benchmarks.convergence [--data DIR] [--scale 1.0] [--out benchmarks/results/convergence]

One run each, on `tower-small` (built with `jaxnerf-grid synth` and masked with the built-in
DPT on first use, cached under benchmarks/.cache), all "ours" (contraction, disparity warp,
mask-weighted loss), one process, the same machine:

  mlp-hierarchical   the MLP field with 32 coarse + 32 fine samples (the demo before the grid)
  grid-hierarchical  the demo's hash grid with the same coarse + fine sampler
  grid-proposal      the `ours` recipe (the experiments'): hash grid + one proposal
                     round (64 -> 32 samples), 2400 steps
  grid-proposal-fast `ours-fast`: a smaller proposal field, 1600 steps (the demo's until ours-lean)
  grid-proposal-lean the demo's recipe now, `ours-lean`: ours-fast with a leaner main field
                     (`--runs grid-proposal,grid-proposal-fast,grid-proposal-lean` puts them side by side)

Each run keeps a checkpoint every `--every` steps (under benchmarks/.cache), stamped with the training wall-clock time
when it was written (the trainer's own time, compile included; evaluation is not counted).
After training every checkpoint is scored on the test views: PSNR against the clean images
and PSNR inside the tower region. Prints a table, writes JSON and a PNG plot of PSNR and
tower PSNR against seconds, and the time each grid run needs to reach the MLP's final PSNR.
`--scale` multiplies every run's steps (0.1 for a smoke test).
"""

from __future__ import annotations

import argparse
import copy
import os
import platform
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from jaxnerf_grid.config import recipes  # noqa: E402
from jaxnerf_grid.config import schema as config_lib  # noqa: E402
from jaxnerf_grid.eval import evaluate, metrics  # noqa: E402
from jaxnerf_grid.render import views  # noqa: E402
from jaxnerf_grid.train import loop as train  # noqa: E402
from jaxnerf_grid.train import runs  # noqa: E402
from jaxnerf_grid.util import io  # noqa: E402

# The demo's recipe before the grid field (see git history of DEMO_CONFIG, in train_cli.py then): changes
# to the `ours-paper-mlp` recipe (RunConfig's defaults for ours): a smaller MLP, 32 + 32 samples, fewer steps.
MLP_CONFIG = {
    "model": {"field": {"depth": 4, "width": 64, "skip": 2, "pos_max_deg": 8, "dir_max_deg": 3, "view_width": 32},
              "sampler": {"kind": "hierarchical", "samples": [32, 32], "union": False}, "contract_radius": 2.0,
              "near": 1.0},
    "train": {"batch_rays": 512, "max_steps": 1000, "lr_init": 4e-3, "lr_final": 2e-4, "warmup": 30,
              "log_every": 20, "chunk": 4096},
}


def _grid_hierarchical() -> dict:
    """The `ours` recipe (the demo's) with NeRF's coarse + fine sampler (two grid fields, 32 + 32 samples)."""
    cfg = recipes.overrides("ours")
    cfg["model"]["sampler"] = {"kind": "hierarchical", "samples": [32, 32], "union": False}
    return cfg


RUNS = {"mlp-hierarchical": MLP_CONFIG, "grid-hierarchical": _grid_hierarchical(),
        "grid-proposal": recipes.overrides("ours"), "grid-proposal-fast": recipes.overrides("ours-fast"),
        "grid-proposal-lean": recipes.overrides("ours-lean")}


def dataset_dir(cache: Path) -> Path:
    from jaxnerf_grid.data.synthetic.generate import generate_scene
    from jaxnerf_grid.masks import write as masking

    data = cache / "tower-small"
    if not (data / "transforms.json").is_file():
        generate_scene("tower-small", data, seed=0, overwrite=True, progress=False)
    if "mask_source" not in io.read_json(data / "transforms.json"):
        masking.write_masks(data, progress=False)
    return data


def score(params, cfg, ds) -> dict:
    """Mean test PSNR and tower-region PSNR of parameters."""
    psnr, tower = [], []
    targets = ds.clean_images if ds.clean_images is not None else ds.images
    for i in np.asarray(ds.split["test"]):
        rgb = np.clip(views.render_view(params, cfg, ds, int(i))["rgb"], 0, 1)
        psnr.append(float(metrics.psnr(rgb, targets[i])))
        region = evaluate.region_masks(ds, int(i)).get("tower")
        if region is not None and region.any():
            tower.append(float(metrics.psnr(rgb, targets[i], region.astype(np.float32))))
    return {"psnr": float(np.mean(psnr)), "tower_psnr": float(np.mean(tower)) if tower else None}


def run_one(name: str, overrides: dict, data: Path, ds, out: Path, every: int, scale: float) -> dict:
    overrides = copy.deepcopy(overrides)
    steps = max(2, int(round(overrides["train"]["max_steps"] * scale)))
    every = max(1, int(round(every * scale)))
    overrides["train"].update({"max_steps": steps, "checkpoint_every": every, "keep_checkpoints": 100000})
    stamps = {}
    start = time.perf_counter()
    run_dir = ROOT / "benchmarks" / ".cache" / "convergence_runs" / name  # checkpoints: not committed
    cfg = train.make_config("ours", overrides)
    cfg = config_lib.resolve(cfg, ds, bounds=False)  # as runs.train_run stores it
    io.write_json(run_dir / "config.json", runs.run_config_dict(cfg, data))
    for old in (run_dir / "checkpoints").glob("*") if (run_dir / "checkpoints").is_dir() else []:
        old.unlink()
    result = train.train(ds, cfg, run_dir, progress=False,
                         on_step=lambda step: stamps.__setitem__(step, time.perf_counter() - start))
    from jaxnerf_grid.train import checkpoint

    points = []
    template = train.init_state(cfg)
    for step, path in checkpoint.list_checkpoints(run_dir):
        if not (step <= 8 * every or step % (8 * every) == 0 or step == steps):
            continue  # dense early, sparse later
        state = checkpoint.load_checkpoint(path, template)
        points.append({"step": step, "seconds": stamps.get(step), **score(state["params"], cfg, ds)})
        print(f"  {name:18s} step {step:5d}  {points[-1]['seconds']:6.0f} s  PSNR {points[-1]['psnr']:.2f}  "
              f"tower {points[-1]['tower_psnr'] or float('nan'):.2f}", flush=True)
    return {"name": name, "steps": steps, "batch_rays": cfg.train.batch_rays, "train_seconds": result.seconds,
            "rays_per_s": steps * cfg.train.batch_rays / result.seconds, "points": points}


def _relative(path: Path) -> str:
    """A path inside the repository as a relative one (no machine paths in committed results)."""
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return Path(path).name


def time_to_reach(points: list[dict], target: float) -> float | None:
    """First checkpoint time at which PSNR >= target (None if never)."""
    for p in points:
        if p["psnr"] >= target:
            return p["seconds"]
    return None


def figure(rows: list[dict]) -> np.ndarray:
    """Test PSNR over tower PSNR, each against training seconds, one line per run (the rows of
    convergence.json). Returns an RGB image [H, W, 3] in [0, 1]."""
    from experiments.figures import line_plot

    images = []
    for key, label in (("psnr", "test PSNR (dB)"), ("tower_psnr", "tower PSNR (dB)")):
        series = [{"label": r["name"], "x": [p["seconds"] for p in r["points"]],
                   "y": [p[key] for p in r["points"]], "colour_index": i} for i, r in enumerate(rows)]
        images.append(line_plot(series, "training seconds", label, f"{label} vs wall clock", log2_x=False))
    return np.concatenate(images, axis=0)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=None, help="a masked dataset (default: tower-small, built and cached)")
    p.add_argument("--runs", default=",".join(RUNS))
    p.add_argument("--every", type=int, default=50,
                   help="checkpoint every N steps; scored: the first 8, then every 8th, and the last")
    p.add_argument("--steps", default=None,
                   help="steps per run as name=N,... (default: each recipe's own max_steps)")
    p.add_argument("--scale", type=float, default=1.0, help="multiply every run's steps")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "convergence"))
    p.add_argument("--replot", action="store_true",
                   help="only redraw convergence.png from --out's convergence.json (no run)")
    args = p.parse_args()
    out = Path(args.out)
    if args.replot:
        io.write_png(out / "convergence.png", figure(io.read_json(out / "convergence.json")["runs"]))
        print(f"wrote {out / 'convergence.png'}")
        return 0
    data = Path(args.data) if args.data else dataset_dir(ROOT / "benchmarks" / ".cache")
    from jaxnerf_grid.data.formats import load_dataset

    ds = load_dataset(data, progress=False)
    steps = dict(item.split("=") for item in args.steps.split(",")) if args.steps else {}
    rows = []
    for name in args.runs.split(","):
        recipe = copy.deepcopy(RUNS[name])
        if name in steps:
            recipe["train"]["max_steps"] = int(steps[name])
        rows.append(run_one(name, recipe, data, ds, out, args.every, args.scale))
    by_name = {r["name"]: r for r in rows}
    summary = []
    if "mlp-hierarchical" in by_name:
        mlp = by_name["mlp-hierarchical"]
        target = mlp["points"][-1]["psnr"]
        for r in rows:
            reach = time_to_reach(r["points"], target)
            r["seconds_to_mlp_final_psnr"] = reach
            summary.append(f"{r['name']}: reaches the MLP's final PSNR ({target:.2f} dB) "
                           + (f"at {reach:.0f} s ({reach / mlp['train_seconds']:.2f} of the MLP's "
                              f"{mlp['train_seconds']:.0f} s)" if reach is not None else "never in its run"))
    print()
    print(f"{'run':18s} {'steps':>6s} {'rays/s':>8s} {'train s':>8s} {'PSNR':>6s} {'tower':>6s}")
    for r in rows:
        last = r["points"][-1]
        print(f"{r['name']:18s} {r['steps']:6d} {r['rays_per_s']:8.0f} {r['train_seconds']:8.0f} "
              f"{last['psnr']:6.2f} {last['tower_psnr'] or float('nan'):6.2f}")
    for line in summary:
        print(line)
    result = {"machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                          "load_average": os.getloadavg()},
              "data": _relative(data), "scale": args.scale, "runs": rows, "summary": summary}
    out.mkdir(parents=True, exist_ok=True)
    io.write_json(out / "convergence.json", result)
    io.write_png(out / "convergence.png", figure(rows))
    print(f"wrote {out / 'convergence.json'} and {out / 'convergence.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
