"""Seconds per photo of `foreground.predict_maps` (what `jaxnerf-grid mask` runs) with the
built-in DPT, by working size and batch size: is batching photos worth it on this machine?

Usage:
  python benchmarks/mask_speed.py [--photos 8] [--size 640x480] [--max-side 160 320]
      [--batch-sizes 1 2 4 8] [--out benchmarks/results/mask_speed.json]

Random photos (the time does not depend on the content); every (working size, batch size) is
compiled once on a first pass, then timed on a second. Wall time includes the resizes to and
from the working size, as in the CLI.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--photos", type=int, default=8)
    p.add_argument("--size", default="640x480", help="photo size WxH")
    p.add_argument("--max-side", type=int, nargs="+", default=[160, 320])
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 2, 4, 8])
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "mask_speed.json"))
    args = p.parse_args(argv)

    import jax

    from jaxnerf_grid import foreground as fg
    from jaxnerf_grid.masking import default_classes, load_models

    w, h = (int(v) for v in args.size.lower().split("x"))
    model, _, wdir = load_models(None, None)
    classes = default_classes(model, wdir)
    rng = np.random.default_rng(0)
    photos = [rng.uniform(size=(h, w, 3)).astype(np.float32) for _ in range(args.photos)]
    rows = []
    for max_side in args.max_side:
        for bs in args.batch_sizes:
            list(fg.predict_maps(model, model, photos[:bs], classes, max_side=max_side, batch_size=bs))
            t = time.perf_counter()
            list(fg.predict_maps(model, model, photos, classes, max_side=max_side, batch_size=bs))
            per_photo = (time.perf_counter() - t) / len(photos)
            rows.append({"max_side": max_side, "batch_size": bs, "seconds_per_photo": per_photo})
            print(f"working size {max_side}, batch {bs}: {per_photo:.3f} s per photo", flush=True)
    result = {"photo_size": [w, h], "photos": args.photos, "backend": jax.default_backend(),
              "default_batch_size": fg.default_batch_size(), "cpu_count": os.cpu_count(),
              "loadavg_after": os.getloadavg(), "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
