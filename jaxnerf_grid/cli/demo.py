"""`jaxnerf-grid demo`: tower-small (or --data DIR) -> masks -> train ours -> render -> report -> a short
fly-around video (`demo.run_demo`).

    jaxnerf-grid demo [--data DIR] [--out runs/demo] [--steps N | --minutes N] [--max-side N]
                      [--set KEY=VALUE ...] [--overwrite]
                      [--masks auto|dpt|robust|dpt+robust|none]   (docs/MASKS.md)
                      [--video-frames N | --no-video]   (docs/VIDEOS.md)
                      [--coordinator HOST:PORT|auto --num-processes N --process-id I]   (docs/DISTRIBUTED.md)
"""

from __future__ import annotations

import argparse
import os


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid demo",
                                description="tower-small scene (or --data DIR) -> masks -> train ours -> render "
                                            "-> report")
    p.add_argument("--data", default=None,
                   help="run the same recipe on this dataset instead of the synthetic tower (skips synth; "
                        "skips mask when the dataset already has masks)")
    p.add_argument("--out", default="runs/demo")
    p.add_argument("--steps", type=int, default=None,
                   help="training steps (default: chosen from the capture's training pixels within --minutes: "
                        "the recipe's 1600 on the synthetic scene, more on a larger capture; budget.py)")
    p.add_argument("--minutes", type=float, default=None, metavar="N",
                   help="the training time budget the steps are chosen within when --steps is not given "
                        "(default 12; the steps fit it at this machine's speed, timed first; budget.py)")
    p.add_argument("--max-side", type=int, default=None, metavar="N",
                   help="train and evaluate with the photos' long side at most N px (an integer downscale "
                        "factor, intrinsics scaled; 0 = full size; default 640; train.max_side)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change one value of the demo's recipe, dotted key, JSON value (e.g. train.batch_rays=512); "
                        "repeatable")
    p.add_argument("--masks", choices=["auto", "dpt", "robust", "dpt+robust", "none"], default="auto",
                   help="which masks train: auto (default) uses the DPT's masks only where the DPT is in its "
                        "domain on these photos, else train.robust = robust; the others force a mode "
                        "(docs/MASKS.md)")
    video = p.add_mutually_exclusive_group()
    video.add_argument("--video-frames", type=int, default=None, metavar="N",
                       help="frames of the fly-around video written after the report (RUN/videos/orbit.mp4 and "
                            "orbit_depth.mp4, 80 px wide, 8 fps; default 32; docs/VIDEOS.md)")
    video.add_argument("--no-video", action="store_true", help="write no fly-around video")
    p.add_argument("--overwrite", action="store_true", help="retrain the run (the data are kept)")
    p.add_argument("--accept-few-cameras", action="store_true",
                   help="train on a `poses` dataset even when it kept too few of the photos or too small an arc "
                        "of the scene (refused by default, docs/POSES.md)")
    p.add_argument("--quiet", action="store_true")
    from jaxnerf_grid.cli.train import add_distributed_flags

    add_distributed_flags(p)
    return p


def sets_training_on_one_device(sets: list[str] | None, devices_forced: bool, backend: str) -> list[str]:
    """The demo's --set list, plus `train.num_devices=1` when the demo itself gave XLA one CPU
    device per core (devices_forced) on the CPU backend and the user named no
    train.num_devices: the evaluation and the video render on every core, training stays on one
    device as before (two devices train no faster on two cores, and the count changes a run's
    summation order, docs/DISTRIBUTED.md)."""
    from jaxnerf_grid.config import run_config
    from jaxnerf_grid.config import schema as config_lib

    sets = list(sets or [])
    named = "num_devices" in config_lib.parse_sets(sets, run_config.RunConfig).get("train", {})
    return sets + ["train.num_devices=1"] if devices_forced and backend == "cpu" and not named else sets


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxnerf_grid.cli.render import DEVICE_COUNT_FLAG, use_every_cpu_core
    from jaxnerf_grid.cli.train import exit_on_distributed_error, start_distributed

    multi = start_distributed(args)
    forced = not multi and DEVICE_COUNT_FLAG not in os.environ.get("XLA_FLAGS", "")
    if forced:  # before JAX starts its CPU backend (render --orbit does the same)
        use_every_cpu_core()
    from jaxnerf_grid import demo
    from jaxnerf_grid.train import distributed

    sets = sets_training_on_one_device(args.set, forced, distributed.jax.default_backend())
    frames = 0 if args.no_video else demo.DEMO_VIDEO_FRAMES if args.video_frames is None else args.video_frames
    try:
        result = demo.run_demo(args.data, args.out, args.steps, args.overwrite, not args.quiet, sets=sets,
                               max_side=args.max_side, masks=args.masks, video_frames=frames,
                               minutes=args.minutes, accept_few_cameras=args.accept_few_cameras)
    except distributed.DistributedError as err:
        exit_on_distributed_error("demo", err)
    if not distributed.is_main():
        print(f"process {distributed.jax.process_index()}: trained {result['run_dir']}; process 0 writes the report")
        return 0
    print(demo.demo_summary(result))
    print(f"report: {result['run_dir'] / 'report.md'}")
    if result["video"]:
        print(f"video: {result['video']['video']}")
    return 0
