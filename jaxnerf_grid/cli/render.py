"""`jaxnerf-grid render`: render views of a trained run into renders/, depth/, opacity/ (`runs.render_split`),
or a fly-around video (`videos.render_video`, docs/VIDEOS.md).

    jaxnerf-grid render --run RUN [--split test|train|all] [--full-size]
    jaxnerf-grid render --run RUN --orbit [--frames 120] [--fps 24] [--width 160] [--out RUN/videos/orbit]
    jaxnerf-grid render --run RUN --path camera_path.json [--fps F] [--out ...]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

DEVICE_COUNT_FLAG = "--xla_force_host_platform_device_count"


def use_every_cpu_core(environ=os.environ, cores: int | None = None) -> None:
    """One XLA CPU device per core for the videos (`views.frame_renderer` splits each frame over
    the devices): XLA runs the small ops of a 128-ray block on one thread, so with one device
    a 2-core machine renders an orbit on one core (120 frames at 160x120 on the demo's run:
    131 s with one device, 74 s with two, docs/VIDEOS.md). Adds `DEVICE_COUNT_FLAG=cores`
    (default: the cores this process may use) to XLA_FLAGS unless it already names a device
    count; it must run before JAX starts its CPU backend. Training keeps the user's setting:
    the device count changes a run's summation order (docs/DISTRIBUTED.md)."""
    flags = environ.get("XLA_FLAGS", "")
    if DEVICE_COUNT_FLAG in flags:
        return
    count = cores or len(os.sched_getaffinity(0))
    environ["XLA_FLAGS"] = f"{flags} {DEVICE_COUNT_FLAG}={count}".strip()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid render", description="render views of a trained run")
    p.add_argument("--run", required=True, help="run directory")
    p.add_argument("--split", choices=["test", "train", "all"], default="test")
    p.add_argument("--allow-other-data", action="store_true",
                   help="render even though the run's dataset has changed (its fingerprint differs)")
    p.add_argument("--full-size", action="store_true",
                   help="render at the photos' full size (default: the run's working resolution, train.max_side)")
    video = p.add_mutually_exclusive_group()
    video.add_argument("--orbit", action="store_true",
                       help="a fly-around video: an orbit at the training cameras' mean height and radius "
                            "(OUT.mp4 and OUT_depth.mp4)")
    video.add_argument("--path", help="a video along a camera path (nerfstudio's camera-path JSON, docs/VIDEOS.md)")
    p.add_argument("--frames", type=int, default=120, help="frames of the orbit (default 120)")
    p.add_argument("--fps", type=float, default=None,
                   help="frames per second of the video (default: the path's fps, else 24)")
    p.add_argument("--width", type=int, default=160,
                   help="width of the orbit's frames in pixels, the height from the photos' aspect (default 160)")
    p.add_argument("--out", help="the videos' path without .mp4 (default RUN/videos/orbit or RUN/videos/<path stem>)")
    p.add_argument("--quiet", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.orbit or args.path:
        use_every_cpu_core()
        from jaxnerf_grid.render import videos

        done = videos.render_video(args.run, args.path, frames=args.frames, fps=args.fps, width=args.width,
                                   out=args.out, progress=not args.quiet, allow_other_data=args.allow_other_data)
        print(f"wrote {done['video']} and {done['depth_video']} ({done['frames']} frames, "
              f"{done['width']}x{done['height']}, {done['fps']:g} fps)")
        return 0
    from jaxnerf_grid.train import runs

    views = runs.render_split(args.run, args.split, not args.quiet, allow_other_data=args.allow_other_data,
                              full_size=args.full_size)
    print(f"rendered {len(views)} views into {Path(args.run) / 'renders'} (depth/, opacity/ alongside)")
    return 0
