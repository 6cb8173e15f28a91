"""Peak host memory of `jaxnerf-grid train` against the number of working pixels.

Usage:
    python -m benchmarks.train_memory --work /tmp/train_memory [--frames 20 60 120 240]
        [--size 800x600] [--devices 1 2] [--big] [--out benchmarks/results/train_memory.json]

For each frame count a transforms.json dataset of generated photos (smooth random content, a
ring of cameras looking at the origin) is written under --work, and `jaxnerf-grid train` runs
a few steps on it in a fresh process (`--measure`: the CLI in-process, then its own peak
resident memory, getrusage ru_maxrss) on 1 and 2 CPU devices
(XLA_FLAGS=--xla_force_host_platform_device_count=2, train.num_devices). The peaks are fitted
as constant + bytes_per_pixel x working pixels (least squares, per device count) and compared
with the target: at most 1.5 x the uint8 bytes of the working frames (4.5 bytes a pixel) plus
the constant.

--big: a 300-photo capture of 20 MP photos (5472 x 3648 JPEGs) trained at --max-side 1600 (the
working rule's integer factor ceil(5472 / 1600) = 4 gives 1368 x 912 working frames), a few
steps, its peak and wall time recorded; the photos are deleted afterwards.

Results (JSON) go to --out. The photos are generated, never downloaded; --work should be a
scratch folder (it is emptied of what this script wrote).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

TARGET_BYTES_PER_PIXEL = 1.5 * 3  # 1.5 x the uint8 bytes of a working pixel
STEPS = 3
# a small batch and model: the per-pixel cost is what is measured, the step's is part of the constant
TRAIN_SETS = ["train.batch_rays=256", "train.checkpoint_every=1000", "train.log_every=1"]


def ring_c2w(count: int, radius: float = 4.0) -> np.ndarray:
    """[count, 4, 4] OpenGL camera-to-world poses on a ring at height 1, looking at the origin."""
    poses = []
    for k in range(count):
        a = 2 * math.pi * k / count
        centre = np.array([radius * math.cos(a), radius * math.sin(a), 1.0])
        back = centre / np.linalg.norm(centre)  # +z of a GL camera points away from what it sees
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, centre
        poses.append(m)
    return np.asarray(poses)


def write_photos(folder: Path, count: int, width: int, height: int, seed: int = 0, ext: str = ".png") -> Path:
    """`count` photos of smooth random content (noise at 1/16 the size, bilinearly enlarged) and
    a transforms.json (a ring of cameras, 60 degrees across) in `folder`. Returns the folder."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "images").mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    fl = 0.5 * width / math.tan(math.radians(30))
    frames = []
    for k, c2w in enumerate(ring_c2w(count)):
        small = rng.integers(0, 256, (max(2, height // 16), max(2, width // 16), 3), dtype=np.uint8)
        name = f"images/photo_{k:04d}{ext}"
        cv2.imwrite(str(folder / name), cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR))
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    meta = {"fl_x": fl, "fl_y": fl, "cx": width / 2, "cy": height / 2, "w": width, "h": height, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def measure(data: str, out: str, devices: int, max_side: int, steps: int) -> dict:
    """Trains as `jaxnerf-grid train` does (the config builder, then `runs.train_run`) in this process
    and returns its peak resident memory (bytes) and wall time. Called in a fresh process
    (--measure) so each peak is one run's."""
    from jaxnerf_grid.config import build
    from jaxnerf_grid.train import runs

    sets = (f"train.num_devices={devices}",) + tuple(TRAIN_SETS)
    built = build.build(build.Request(sets=sets, max_side=max_side, steps=steps), data=data)
    start = time.perf_counter()
    runs.train_run(data, built.method, out, built.overrides, None, overwrite=True, progress=False)
    seconds = time.perf_counter() - start
    return {"exit": 0, "peak_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
            "seconds": seconds}


def run_measure(data: Path, out: Path, devices: int, max_side: int, steps: int = STEPS) -> dict:
    """`measure` in a fresh Python process with `devices` CPU devices. Returns its dict."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[1]), env.get("PYTHONPATH", "")])
    cmd = [sys.executable, "-m", "benchmarks.train_memory", "--measure", str(data), str(out), str(devices),
           str(max_side), str(steps)]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def fit(pixels: list[int], peaks: list[int]) -> dict:
    """Least-squares peak = constant + bytes_per_pixel x pixels."""
    a = np.stack([np.ones(len(pixels)), np.asarray(pixels, np.float64)], 1)
    (const, slope), *_ = np.linalg.lstsq(a, np.asarray(peaks, np.float64), rcond=None)
    return {"constant_bytes": float(const), "bytes_per_pixel": float(slope),
            "ratio_to_uint8": float(slope / 3.0), "target_bytes_per_pixel": TARGET_BYTES_PER_PIXEL,
            "meets_target": bool(slope <= TARGET_BYTES_PER_PIXEL)}


def sweep(work: Path, frame_counts: list[int], width: int, height: int, devices: list[int]) -> dict:
    """The peaks for each frame count and device count, and the fits."""
    rows = []
    for count in frame_counts:
        data = write_photos(work / f"data_{count}", count, width, height, seed=count)
        for n in devices:
            t = time.perf_counter()
            got = run_measure(data, work / f"run_{count}_{n}", n, max(width, height))
            rows.append({"frames": count, "width": width, "height": height, "working_pixels": count * width * height,
                         "uint8_bytes": 3 * count * width * height, "devices": n, **got})
            print(f"{count} frames {width}x{height} on {n} device(s): peak {got['peak_bytes'] / 2**30:.2f} GiB "
                  f"({time.perf_counter() - t:.0f} s)", flush=True)
        shutil.rmtree(data, ignore_errors=True)
    fits = {}
    for n in devices:
        mine = [r for r in rows if r["devices"] == n]
        fits[str(n)] = fit([r["working_pixels"] for r in mine], [r["peak_bytes"] for r in mine])
    return {"rows": rows, "fits": fits}


def big_capture(work: Path, devices: int, photos: int = 300, size=(5472, 3648), max_side: int = 1600) -> dict:
    """A `photos`-photo capture of 20 MP JPEGs trained a few steps at `max_side`; deleted after."""
    data = work / "capture_20mp"
    t = time.perf_counter()
    write_photos(data, photos, size[0], size[1], seed=1, ext=".jpg")
    made = time.perf_counter() - t
    disk = sum(p.stat().st_size for p in (data / "images").iterdir())
    print(f"{photos} photos of {size[0]}x{size[1]} written in {made:.0f} s ({disk / 2**30:.1f} GiB)", flush=True)
    try:
        got = run_measure(data, work / "run_20mp", devices, max_side)
    finally:
        shutil.rmtree(data, ignore_errors=True)
    k = math.ceil(max(size) / max_side)
    w, h = round(size[0] / k), round(size[1] / k)
    return {"photos": photos, "photo_size": list(size), "max_side": max_side, "working_size": [w, h],
            "working_pixels": photos * w * h, "uint8_bytes": 3 * photos * w * h, "devices": devices,
            "photos_seconds": made, "photos_bytes_on_disk": disk, **got}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--measure", nargs=5, metavar=("DATA", "OUT", "DEVICES", "MAX_SIDE", "STEPS"),
                   help="(internal) one run in this process; prints its JSON")
    p.add_argument("--work", type=Path, help="scratch folder for the generated photos and runs")
    p.add_argument("--frames", type=int, nargs="+", default=[20, 60, 120, 240])
    p.add_argument("--size", default="800x600", help="working frame size WxH of the sweep's photos")
    p.add_argument("--devices", type=int, nargs="+", default=[1, 2])
    p.add_argument("--big", action="store_true", help="also the 300-photo 20 MP capture at --max-side 1600")
    p.add_argument("--big-only", action="store_true", help="only the 300-photo capture")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/train_memory.json"))
    args = p.parse_args(argv)
    if args.measure:
        data, out, devices, max_side, steps = args.measure
        print(json.dumps(measure(data, out, int(devices), int(max_side), int(steps))))
        return 0
    if args.work is None:
        p.error("--work is required")
    args.work.mkdir(parents=True, exist_ok=True)
    result = json.loads(args.out.read_text()) if args.out.is_file() else {}
    words = [("WORK" if w == str(args.work) else w) for w in (sys.argv[1:] if argv is None else argv)]
    result.update({"command": "python -m benchmarks.train_memory " + " ".join(words),  # no machine path
                   "steps": STEPS, "train_sets": TRAIN_SETS, "cpus": os.cpu_count(),
                   "load_average_start": os.getloadavg()[0]})
    if not args.big_only:
        width, height = (int(v) for v in args.size.split("x"))
        result["sweep"] = dict(sweep(args.work, args.frames, width, height, args.devices), command=result["command"])
    if args.big or args.big_only:
        result["big_capture"] = dict(big_capture(args.work, max(args.devices)), command=result["command"])
    result["load_average_end"] = os.getloadavg()[0]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result.get("sweep", {}).get("fits", {}), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
