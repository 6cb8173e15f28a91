"""Seconds per photo of `foreground.predict_maps` (what `jaxnerf-grid mask` runs) with the
built-in DPT, by working size and batch size, and each batch size's speed-up over batch 1
measured in the same run: is batching photos worth it on this machine?

Usage:
  python -m benchmarks.mask_speed [--photos 8] [--size 640x480] [--max-side 160 320]
      [--batch-sizes 1 2 4 8] [--repeats 3] [--out benchmarks/results/mask_speed.json]

Random photos (the time does not depend on the content). Every (working size, batch size) is
compiled once first; then `--repeats` rounds each time all batch sizes of a working size in
turn (round-robin), so a change in the machine's load hits them alike. Reported: the median
seconds per photo, and "speedup_vs_batch1", the median over the rounds of (batch-1 time /
this batch's time) within the round. Wall time includes the resizes to and from the working
size, as in the CLI. The load average (os.getloadavg) before and after and the CPU count are
written with the results.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np


def machine_load() -> dict:
    """The 1, 5 and 15 minute load averages and the CPU count (is the machine shared right now?)."""
    return {"load_average": list(os.getloadavg()), "cpu_count": os.cpu_count()}


def seconds_per_photo(fg, model, photos, classes, max_side: int, batch_size: int) -> float:
    t = time.perf_counter()
    list(fg.predict_maps(model, model, photos, classes, max_side=max_side, batch_size=batch_size))
    return (time.perf_counter() - t) / len(photos)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--photos", type=int, default=8)
    p.add_argument("--size", default="640x480", help="photo size WxH")
    p.add_argument("--max-side", type=int, nargs="+", default=[160, 320])
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 2, 4, 8])
    p.add_argument("--repeats", type=int, default=3, help="interleaved rounds over the batch sizes")
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "mask_speed.json"))
    args = p.parse_args(argv)

    import jax

    from jaxnerf_grid.masks import foreground as fg
    from jaxnerf_grid.masks.write import default_classes, load_models

    load_before = machine_load()
    sizes = sorted(set(args.batch_sizes) | {1})    # batch 1 is the reference of the ratios
    w, h = (int(v) for v in args.size.lower().split("x"))
    model, _, wdir = load_models(None, None)
    classes = default_classes(model, wdir)
    rng = np.random.default_rng(0)
    photos = [rng.uniform(size=(h, w, 3)).astype(np.float32) for _ in range(args.photos)]
    rows = []
    for max_side in args.max_side:
        for bs in sizes:   # compile every batch shape first
            list(fg.predict_maps(model, model, photos[:bs], classes, max_side=max_side, batch_size=bs))
        times = {bs: [] for bs in sizes}
        for _ in range(args.repeats):
            for bs in sizes:
                times[bs].append(seconds_per_photo(fg, model, photos, classes, max_side, bs))
        for bs in sizes:
            speedup = statistics.median(a / b for a, b in zip(times[1], times[bs]))
            rows.append({"max_side": max_side, "batch_size": bs, "seconds_per_photo": statistics.median(times[bs]),
                         "speedup_vs_batch1": speedup, "seconds_per_photo_per_round": times[bs]})
            print(f"working size {max_side}, batch {bs}: {statistics.median(times[bs]):.3f} s per photo, "
                  f"x{speedup:.2f} against batch 1", flush=True)
    result = {"photo_size": [w, h], "photos": args.photos, "repeats": args.repeats, "backend": jax.default_backend(),
              "default_batch_size": fg.default_batch_size(), "machine": {**machine_load(), "load_before": load_before},
              "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
