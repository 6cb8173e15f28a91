"""Table 1's robust rows on the GPU machine, on scenes made here and carried (docs/GPU.md).

    python scripts/gpu_table1_runs.py --cache CACHE --seeds 1,2 --sets B,A --out OUT [--budget-min 8]
        [--rows dpt+robust] [--variant TAG:KEY=JSON] [--prior gt] [--dpt-threshold T]

CACHE holds `experiments/scenes.py`'s scenes and the built-in DPT's mask variants of the chosen
seeds and sets (made on this machine with `--prepare`, which trains nothing). Trains, in order,
set by set and seed by seed, the `robust` and `dpt+robust` rows of `experiments/table1_foreground.py`
at --standard through the experiment's own `runner.run_condition` (the same run keys, so the
results read back into the table: copy each OUT/runs/<run> folder into the local cache's runs/
and run the experiment there), and copies each run's small files (metrics.json, experiment.json,
metrics.jsonl, config.json, report_views.png) to OUT/runs/<run>/. No run starts after --budget-min minutes.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

SET_LETTERS = {"A": 0, "B": 1}
ROWS = {"robust": "robust, no masks", "dpt+robust": "built-in DPT masks + Eq. 7 + robust"}
SMALL_FILES = ("metrics.json", "experiment.json", "metrics.jsonl", "config.json", "report_views.png")


def variants(specs: list[str]) -> list[tuple[str, dict]]:
    """[(tag, {"train": overrides})]: the plain row ("", {}) unless variants are given, then each
    "TAG:key=json,key=json" (keys of train.*), e.g. "sp3:robust_spread=3"."""
    if not specs:
        return [("", {})]
    out = []
    for spec in specs:
        tag, _, pairs = spec.partition(":")
        train = {k: json.loads(v) for k, v in (pair.split("=", 1) for pair in pairs.split(",") if pair)}
        out.append((tag, {"train": train}))
    return out


def main(argv=None) -> int:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from experiments import runner, scenes
    from experiments import table1_foreground as t1

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cache", required=True)
    p.add_argument("--seeds", default="1,2")
    p.add_argument("--sets", default="B,A", help="scene sets in the order they run (A, B)")
    p.add_argument("--out", default="gpu_out")
    p.add_argument("--budget-min", type=float, default=None)
    p.add_argument("--prepare", action="store_true", help="make the scenes and DPT masks only")
    p.add_argument("--steps", type=int, default=None, help="training steps (default: --standard's; a smoke test)")
    p.add_argument("--rows", default="robust,dpt+robust", help="which robust rows: robust, dpt+robust")
    p.add_argument("--prior", choices=("dpt", "gt"), default="dpt",
                   help="dpt+robust's prior: the built-in DPT's masks (the table's row) or the ground-truth "
                        "masks + Eq. 7 (an oracle, labelled -gtprior; not in the table)")
    p.add_argument("--dpt-threshold", type=float, default=0.5,
                   help="T of the DPT prior's M = [C > T] (not 0.5: labelled -tT; not in the table)")
    p.add_argument("--variant", action="append", default=[], metavar="TAG:KEY=JSON[,KEY=JSON]",
                   help="train each row with these train overrides instead, labelled -TAG (a sweep; not in the table)")
    args = p.parse_args(argv)
    if args.prior == "gt" and args.dpt_threshold != 0.5:
        p.error("--dpt-threshold sets the DPT prior's masks; it has no meaning with --prior gt")
    flags = ["--standard", "--cache", args.cache, "--results", str(Path(args.out) / "t1"), "--quiet",
             "--ignore-recorded"] + (["--budget-min", str(args.budget_min)] if args.budget_min else []) + \
        (["--steps", str(args.steps)] if args.steps else [])
    ctx = runner.make_context(runner.base_parser("").parse_args(flags), "table1_foreground.py")
    seeds = [int(s) for s in args.seeds.split(",")]
    for letter in args.sets.split(","):
        _, preset, distractors, _, _ = t1.SETS[SET_LETTERS[letter]]
        for seed in seeds:
            scene_dir = scenes.scene(ctx, preset, seed, distractors)
            for condition in [ROWS[r] for r in args.rows.split(",")]:
                data, overrides, _ = t1.condition_data(ctx, scene_dir, condition)
                prior_tag = ""
                if condition == ROWS["dpt+robust"] and args.prior == "gt":
                    data, prior_tag = scenes.mask_variant(ctx, scene_dir, "gt_eq7", "gt", floor=0.0), "-gtprior"
                elif condition == ROWS["dpt+robust"] and args.dpt_threshold != 0.5:
                    data = scenes.mask_variant(ctx, scene_dir, "dpt_builtin_eq7", "dpt", floor=0.0,
                                               threshold=args.dpt_threshold)
                    prior_tag = f"-t{args.dpt_threshold:g}"
                if args.prepare:
                    continue
                for tag, extra in variants(args.variant):
                    label = t1.run_tag(preset, distractors, condition) + prior_tag + (f"-{tag}" if tag else "")
                    rec = runner.run_condition(ctx, data, "ours", seed, label, runner.merge(overrides, extra))
                    if rec is None:
                        continue
                    dest = Path(args.out) / "runs" / Path(rec["run_dir"]).name
                    dest.mkdir(parents=True, exist_ok=True)
                    for name in SMALL_FILES:
                        if (Path(rec["run_dir"]) / name).is_file():
                            shutil.copy(Path(rec["run_dir"]) / name, dest / name)
                    print(f"[gpu] {dest.name}: PSNR {rec['metrics']['mean']['psnr']:.2f}, "
                          f"{rec.get('seconds_per_step')} s/step", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
