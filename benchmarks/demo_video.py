"""What the demo's fly-around video costs after its evaluation (docs/VIDEOS.md).

    python -m benchmarks.demo_video --run runs/demo/run [--sizes 16x80 64x80 32x120]
                                    [--out benchmarks/results/demo_video.json]

On a trained run (a demo run: `jaxnerf-grid demo`): first one test view is rendered, as the
demo's evaluation does just before the video, so that the render step is compiled; then
`demo.write_demo_video` at the demo's defaults (reading the dataset, the orbit, report.html
rewritten) and `videos.render_video` for each FRAMESxWIDTH of --sizes are timed, one after the
other in the same process. The videos go to RUN/videos/ (orbit.mp4, bench_FRAMES_WIDTH.mp4 and
their depth). Prints a table and writes the seconds as JSON with the machine's load average.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

from jaxnerf_grid import demo, io, runs, train, views, videos


def parse_size(text: str) -> tuple[int, int]:
    """"32x80" -> (32 frames, 80 px wide)."""
    frames, width = text.lower().split("x")
    return int(frames), int(width)


def time_videos(run: Path, sizes: list[tuple[int, int]]) -> dict:
    """{"warm_up_s", "rows": [{"what", "frames", "width", "height", "seconds"}]} (see the module's docstring)."""
    t = time.perf_counter()
    cfg, _, ds = runs.load_run_and_dataset(run, progress=False)
    params, _ = train.load_params(run, cfg, ds)
    views.render_view(params, cfg, ds, int(ds.split["test"][0]) if len(ds.split["test"]) else 0)
    out = {"warm_up_s": round(time.perf_counter() - t, 1), "rows": []}
    t = time.perf_counter()
    done = demo.write_demo_video(run, demo.DEMO_VIDEO_FRAMES, progress=False)
    out["rows"].append({"what": "demo.write_demo_video (the default)", "frames": done["frames"],
                        "width": done["width"], "height": done["height"], "seconds": round(time.perf_counter() - t, 1)})
    for frames, width in sizes:
        t = time.perf_counter()
        done = videos.render_video(run, frames=frames, width=width, progress=False,
                                   out=run / "videos" / f"bench_{frames}_{width}", dataset=ds)
        out["rows"].append({"what": "videos.render_video", "frames": done["frames"], "width": done["width"],
                            "height": done["height"], "seconds": round(time.perf_counter() - t, 1)})
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.demo_video", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a trained run (a demo run)")
    p.add_argument("--sizes", nargs="*", default=["16x80", "64x80", "32x120"], help="FRAMESxWIDTH, each timed")
    p.add_argument("--out", default="benchmarks/results/demo_video.json")
    args = p.parse_args(argv)
    result = time_videos(Path(args.run), [parse_size(s) for s in args.sizes])
    result.update(machine=platform.node(), cpus=os.cpu_count(), load_average=[round(v, 2) for v in os.getloadavg()])
    print(f"warm-up (dataset, checkpoint, one test view with the compile): {result['warm_up_s']} s")
    print("| video | frames | size | seconds |\n|---|---|---|---|")
    for r in result["rows"]:
        print(f"| `{r['what']}` | {r['frames']} | {r['width']}x{r['height']} | {r['seconds']} |")
    print(f"load average after: {result['load_average']}")
    io.write_json(Path(args.out), result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
