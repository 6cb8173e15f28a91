"""`jaxnerf-grid train`: train a NeRF on a dataset into a run directory (`runs.train_run`).

    jaxnerf-grid train --data DIR --method ours|nerf|nerfw [--config FILE] [--out RUN] [--steps N] [--eval]
"""

from __future__ import annotations

import argparse
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid train", description="train a NeRF on a dataset")
    p.add_argument("--data", required=True, help="dataset folder (transforms.json, COLMAP, LLFF, Blender)")
    p.add_argument("--method", choices=["ours", "nerf", "nerfw"], default="ours")
    p.add_argument("--config", default=None, help="JSON file overriding defaults ({'model': {...}, 'train': {...}})")
    p.add_argument("--out", default=None, help="run directory (default runs/<method>)")
    p.add_argument("--steps", type=int, default=None, help="override train.max_steps")
    p.add_argument("--overwrite", action="store_true", help="start the run again if it exists")
    p.add_argument("--eval", action="store_true", help="evaluate and write the report after training")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxnerf_grid import evaluate, runs

    out = args.out or f"runs/{args.method}"
    run_dir, cfg, result = runs.train_run(args.data, args.method, out, runs.read_overrides(args.config),
                                          args.steps, args.overwrite, not args.quiet)
    print(f"trained {cfg.model.method} to step {result.step} in {result.seconds:.0f} s "
          f"(last loss {result.last_loss:.4f}, PSNR {result.last_psnr:.2f} dB, "
          f"{len(result.skipped_steps)} skipped steps): {run_dir}")
    if args.eval:
        m = evaluate.evaluate_run(run_dir, progress=not args.quiet)
        print(f"test PSNR {m['mean']['psnr']:.2f} dB; report: {Path(run_dir) / 'report.md'}")
    return 0
