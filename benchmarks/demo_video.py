"""What the demo's fly-around video costs after its evaluation (docs/VIDEOS.md).

    python -m benchmarks.demo_video --run runs/demo/run [--sizes 16x80 64x80 32x120]
                                    [--orbit 120x160] [--compare-every 5]
                                    [--out benchmarks/results/demo_video.json]

On a trained run (a demo run: `jaxnerf-grid demo`): first one test view is rendered, as the
demo's evaluation does just before the video, so that the render step is compiled; then
`demo.write_demo_video` at the demo's defaults (reading the dataset, the orbit, report.html
rewritten) and `videos.render_video` for each FRAMESxWIDTH of --sizes are timed, one after the
other in the same process. The videos go to RUN/videos/ (orbit.mp4, bench_FRAMES_WIDTH.mp4 and
their depth). Prints a table and writes the seconds as JSON with the machine's load average.

Then the renderers side by side (`compare_renderers`): every --compare-every'th frame of the
--orbit FRAMESxWIDTH orbit rendered by the old path (`views.render_rays_chunked`, chunks of
`train.chunk` rays, one call each) and by the videos' `views.frame_renderer`, alternating frame by
frame so that both see the same load: seconds (wall and this process's CPU), their ratio, and the
PSNR of the new frame against the old (colour; depth as the largest relative difference). Last,
`jaxnerf-grid render --run RUN --orbit --frames F --width W` in a fresh process (import, dataset,
checkpoint, compile, frames, both videos), timed from outside, with the load average before and
after. First of all, `time_checkpoint_load`: reading the parameters with an abstract template
(`train.load_params`) against one drawn by `train.init_state`.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from jaxnerf_grid import demo
from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.run_config import resolve_devices
from jaxnerf_grid.eval import metrics
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.render import videos, views
from jaxnerf_grid.train import checkpoint, runs
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.util import io


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


def load() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def compare_renderers(run: Path, frames: int, width: int, every: int) -> dict:
    """Every `every`th frame of the orbit (frames, width) by the old and the new renderer,
    alternating; {"frames_compared", "old_s", "new_s", "old_cpu_s", "new_cpu_s" (all frames
    after each renderer's first, which compiles), "old_first_s", "new_first_s", "ratio" (old / new
    wall), "cpu_ratio", "psnr_min", "psnr_mean", "depth_max_rel_diff", "load_before",
    "load_after"}. Writes RUN/videos/compare_frame0.png (old | new)."""
    cfg, _, ds = runs.load_run_and_dataset(run, progress=False)
    params, _ = train.load_params(run, cfg, ds)
    n = resolve_devices(cfg.train)
    w, h, fov = videos.orbit_size(ds, width)
    ids = np.asarray(ds.split["train"]) if len(ds.split["train"]) else np.arange(ds.num_frames)
    poses = videos.orbit_poses(np.asarray(ds.c2w)[ids], frames)[::every]
    near, far = config_lib.near_far(cfg.model, ds)
    focal = 0.5 * h / math.tan(math.radians(fov) / 2)
    old = lambda r: views.render_rays_chunked(params, cfg.model, r, 0, None, cfg.train.chunk, n)  # noqa: E731
    new = views.frame_renderer(params, cfg.model, n)
    out = {"frames_compared": len(poses), "load_before": load()}
    wall = {"old": [], "new": []}
    cpu = {"old": [], "new": []}
    psnrs, depth_rel = [], []
    for k, pose in enumerate(poses):
        r = rays_lib.generate_rays(np.asarray(pose, np.float32), focal, focal, w / 2, h / 2, w, h, near, far)
        views_k = {}
        for name, render in (("old", old), ("new", new)):
            t, c = time.perf_counter(), time.process_time()
            views_k[name] = render(r)
            wall[name].append(time.perf_counter() - t)
            cpu[name].append(time.process_time() - c)
        a, b = views_k["old"], views_k["new"]
        psnrs.append(float(metrics.psnr(b["rgb"], a["rgb"])))
        depth_rel.append(float(np.max(np.abs(b["depth"] - a["depth"]) / np.maximum(np.abs(a["depth"]), 1e-6))))
        if k == 0:
            io.write_png(run / "videos" / "compare_frame0.png", np.concatenate([a["rgb"], b["rgb"]], axis=1))
    for name in ("old", "new"):
        out[f"{name}_first_s"] = round(wall[name][0], 2)
        out[f"{name}_s"] = round(sum(wall[name][1:]), 2)
        out[f"{name}_cpu_s"] = round(sum(cpu[name][1:]), 2)
    out["ratio"] = round(out["old_s"] / max(out["new_s"], 1e-9), 2)
    out["cpu_ratio"] = round(out["old_cpu_s"] / max(out["new_cpu_s"], 1e-9), 2)
    finite = [p for p in psnrs if math.isfinite(p)]
    out.update(psnr_min=round(min(psnrs), 1), psnr_mean=round(float(np.mean(finite)), 1) if finite else math.inf,
               depth_max_rel_diff=float(f"{max(depth_rel):.2g}"), load_after=load())
    return out


def time_checkpoint_load(run: Path) -> dict:
    """Seconds to read the run's parameters: `train.load_params` (an abstract template) and the
    same restore into a template drawn by `train.init_state` (what load_params did before: its
    random draws compile first): {"abstract_s", "drawn_s"}."""
    cfg, _, ds = runs.load_run_and_dataset(run, progress=False)
    t = time.perf_counter()
    train.load_params(run, cfg, ds)
    out = {"abstract_s": round(time.perf_counter() - t, 2)}
    t = time.perf_counter()
    checkpoint.restore_latest(run, train.init_state(config_lib.resolve(cfg, ds, bounds=False),
                                                    train.train_frames_shape(ds)))
    out["drawn_s"] = round(time.perf_counter() - t, 2)
    return out


def time_fresh_orbit(run: Path, frames: int, width: int) -> dict:
    """`jaxnerf-grid render --run RUN --orbit --frames F --width W --quiet` in a fresh process:
    {"frames", "width", "seconds" (wall, everything included), "cpu_seconds" (the process's user +
    system time: on an idle machine of c cores the wall time is at least cpu_seconds / c),
    "load_before", "load_after"}."""
    before = load()
    t = time.perf_counter()
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-m", "jaxnerf_grid", "render", "--run", str(run), "--orbit", "--frames",
                    str(frames), "--width", str(width), "--out", str(run / "videos" / f"bench_orbit_{frames}_{width}"),
                    "--quiet"], check=True)
    seconds = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime + after.ru_stime - used.ru_utime - used.ru_stime
    return {"frames": frames, "width": width, "seconds": round(seconds, 1), "cpu_seconds": round(cpu, 1),
            "load_before": before, "load_after": load()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.demo_video", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a trained run (a demo run)")
    p.add_argument("--sizes", nargs="*", default=["16x80", "64x80", "32x120"], help="FRAMESxWIDTH, each timed")
    p.add_argument("--orbit", default="120x160", help="FRAMESxWIDTH of the renderers' comparison and the fresh run")
    p.add_argument("--compare-every", type=int, default=5, help="compare every Nth frame of the orbit (old vs new)")
    p.add_argument("--out", default="benchmarks/results/demo_video.json")
    args = p.parse_args(argv)
    load_start = load()
    checkpoint_s = time_checkpoint_load(Path(args.run))        # first: before anything compiles init's draws
    result = time_videos(Path(args.run), [parse_size(s) for s in args.sizes])
    result["load_before"] = load_start
    result["checkpoint_load"] = checkpoint_s
    frames, width = parse_size(args.orbit)
    result["renderers"] = compare_renderers(Path(args.run), frames, width, args.compare_every)
    result["fresh_orbit"] = time_fresh_orbit(Path(args.run), frames, width)
    result.update(machine=platform.node(), cpus=os.cpu_count(), load_average=[round(v, 2) for v in os.getloadavg()])
    print(f"warm-up (dataset, checkpoint, one test view with the compile): {result['warm_up_s']} s")
    print("| video | frames | size | seconds |\n|---|---|---|---|")
    for r in result["rows"]:
        print(f"| `{r['what']}` | {r['frames']} | {r['width']}x{r['height']} | {r['seconds']} |")
    c = result["renderers"]
    print(f"renderers, {c['frames_compared']} frames of the {args.orbit} orbit after each one's first: old "
          f"{c['old_s']} s ({c['old_cpu_s']} s CPU), new {c['new_s']} s ({c['new_cpu_s']} s CPU): {c['ratio']}x "
          f"(CPU {c['cpu_ratio']}x); first frames {c['old_first_s']} / {c['new_first_s']} s; PSNR new vs old min "
          f"{c['psnr_min']} dB, depth rel. diff <= {c['depth_max_rel_diff']}; load {c['load_before']} -> "
          f"{c['load_after']}")
    print(f"reading the parameters: {checkpoint_s['abstract_s']} s (abstract template), {checkpoint_s['drawn_s']} s "
          "(drawn template, its compiles included)")
    f = result["fresh_orbit"]
    print(f"render --orbit --frames {f['frames']} --width {f['width']} in a fresh process: {f['seconds']} s "
          f"({f['cpu_seconds']} s CPU; load {f['load_before']} -> {f['load_after']})")
    print(f"load average before: {result['load_before']}, after: {result['load_average']}")
    io.write_json(Path(args.out), result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
