"""`jaxnerf-grid train`: train a NeRF on a dataset into a run directory (`runs.train_run`).

    jaxnerf-grid train --data DIR [--recipe NAME] [--method ours|nerf|nerfw] [--config FILE] [--set KEY=VALUE ...]
                       [--out RUN]
                       [--steps N | --minutes N] [--max-side N] [--overwrite] [--allow-other-data] [--eval]
                       [--coordinator HOST:PORT|auto --num-processes N --process-id I]   (docs/DISTRIBUTED.md)

The settings start from a recipe (`recipes`, docs/RECIPES.md; `jaxnerf-grid recipes` lists them):
--recipe NAME, or with only --method M the recipe named M; neither: `ours`, the recipe that
resolves the tower (the demo's). --method with --recipe trains that recipe's settings as method M.
--config and --set are laid on top.
Without --steps (or train.max_steps in --config / --set) the steps follow the capture: the training
budget (`budget.py`, docs/RECIPES.md) draws each training pixel about twice, at least the recipe's
steps, at most what fits in --minutes of training (default 12) at this machine's speed (timed
first when the minutes may bind, `train/speed.py`).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def add_distributed_flags(p: argparse.ArgumentParser) -> None:
    """--coordinator / --num-processes / --process-id (docs/DISTRIBUTED.md); train and demo."""
    g = p.add_argument_group("multi-process training (jax.distributed; docs/DISTRIBUTED.md)")
    g.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="address of process 0's coordinator; 'auto' lets JAX detect SLURM / Open MPI / "
                        "Kubernetes; default: $JAX_COORDINATOR_ADDRESS, else a single process")
    g.add_argument("--num-processes", type=int, default=None, metavar="N",
                   help="processes of the run, one per host (default $JAX_NUM_PROCESSES or the cluster's)")
    g.add_argument("--process-id", type=int, default=None, metavar="I",
                   help="this process's rank in [0, N) (default $JAX_PROCESS_ID or the cluster's)")


def start_distributed(args) -> bool:
    """Starts jax.distributed when the flags or the environment ask for it (before any device
    is touched). Returns True in a multi-process run."""
    from jaxnerf_grid.config.schema import ConfigError
    from jaxnerf_grid.train import distributed

    try:
        return distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    except ValueError as err:
        raise ConfigError(str(err)) from err


def exit_on_distributed_error(name: str, err) -> None:
    """A dead peer: one line, then exit at once (not waiting for the runtime's shutdown barrier,
    which would only fail after the heartbeat timeout)."""
    print(f"jaxnerf-grid {name}: error: {err}", file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(1)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid train", description="train a NeRF on a dataset")
    p.add_argument("--data", required=True, help="dataset folder (transforms.json, COLMAP, LLFF, Blender)")
    p.add_argument("--recipe", default=None, metavar="NAME",
                   help="the settings to start from (`jaxnerf-grid recipes` lists them; default: the recipe named "
                        "by --method, else ours, the recipe that resolves the tower)")
    p.add_argument("--method", choices=["ours", "nerf", "nerfw"], default=None,
                   help="the method (contraction, warp, masks, NeRF-W's embeddings); alone it picks the recipe of "
                        "its name; with --recipe it replaces the recipe's method")
    p.add_argument("--config", default=None,
                   help="JSON file laid over the recipe ({'model': {...}, 'train': {...}})")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="one config value, dotted key, JSON value (e.g. model.warp=log, train.batch_rays=2048, "
                        "model.sampler.samples=[64,32]); repeatable; applied after --config")
    p.add_argument("--out", default=None, help="run directory (default runs/<recipe>)")
    p.add_argument("--steps", type=int, default=None,
                   help="train.max_steps (default: chosen from the capture's training pixels within --minutes)")
    p.add_argument("--minutes", type=float, default=None, metavar="N",
                   help="the training time budget the steps are chosen within when --steps is not given "
                        "(default 12; the steps fit it at this machine's speed, timed first; budget.py)")
    p.add_argument("--max-side", type=int, default=None, metavar="N",
                   help="train with the photos' long side at most N px (an integer downscale factor, "
                        "intrinsics scaled; 0 = full size; default 640); sets train.max_side")
    p.add_argument("--overwrite", action="store_true",
                   help="start the run again if it exists (clears only the run's own outputs)")
    p.add_argument("--allow-other-data", action="store_true",
                   help="resume a run on a dataset other than the one it was trained on")
    p.add_argument("--eval", action="store_true", help="evaluate and write the report after training")
    p.add_argument("--progress-page", type=int, default=0, metavar="N",
                   help="rewrite RUN/progress.html (loss curves, a test view from the newest checkpoint) every N "
                        "steps while training; open it from disk and reload (default 0: off)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_distributed_flags(p)
    return p


def train_summary(cfg, result, run_dir) -> str:
    """One line on a finished `train_run`: steps, time, the last logged loss and PSNR."""
    last = ("no step logged" if result.last_loss != result.last_loss  # NaN: nothing logged
            else f"last logged loss {result.last_loss:.4f}, PSNR {result.last_psnr:.2f} dB")
    if result.steps_run == 0:
        return f"{run_dir}: already trained to step {result.step} ({last}); nothing to do"
    return (f"trained {cfg.model.method} to step {result.step} in {result.seconds:.0f} s "
            f"({last}, {len(result.skipped_steps)} skipped steps): {run_dir}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    multi = start_distributed(args)
    from jaxnerf_grid.capture.bounds import bounds_line, bounds_warning
    from jaxnerf_grid.config import budget, build
    from jaxnerf_grid.eval import evaluate
    from jaxnerf_grid.train import distributed, runs
    from jaxnerf_grid.train import loop as train

    request = build.Request(args.recipe, args.method, args.config, tuple(args.set), args.max_side, args.steps,
                            args.minutes)
    from jaxnerf_grid.config import recipes
    from jaxnerf_grid.train import speed

    out = args.out or f"runs/{recipes.resolve(args.recipe, args.method)[0]}"
    built = build.build(request, data=args.data, devices_of=train.step_devices,
                        platform=distributed.jax.default_backend(),
                        measure=speed.planner(out, args.overwrite, None if args.quiet else print))
    if built.bounds:
        print(bounds_line(built.bounds))
    if bounds_warning(built.bounds):
        print(bounds_warning(built.bounds))
    if built.budget is not None:
        print(budget.report_line(built.budget))
        if budget.warning(built.budget):
            print(budget.warning(built.budget))
    try:
        run_dir, cfg, result = runs.train_run(args.data, built.method, out, built.overrides, None, args.overwrite,
                                              not args.quiet, allow_other_data=args.allow_other_data,
                                              progress_page=args.progress_page, budget=built.budget)
    except distributed.DistributedError as err:
        exit_on_distributed_error("train", err)
    if multi and not distributed.is_main():
        print(f"process {distributed.jax.process_index()}: trained to step {result.step}; process 0 writes {run_dir}")
        return 0
    print(train_summary(cfg, result, run_dir))
    if args.eval:
        m = evaluate.evaluate_run(run_dir, progress=not args.quiet, allow_other_data=args.allow_other_data)
        print(f"test PSNR {m['mean']['psnr']:.2f} dB; report: {Path(run_dir) / 'report.md'}")
    return 0
