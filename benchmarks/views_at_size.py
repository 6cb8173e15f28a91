"""Held-out PSNR of runs trained at different sizes, compared at one size: each run's
`report_views.png` (ground truth | render | depth per test view, `report.markdown.side_by_side`)
is cut into its views, photo and render are shrunk to --size (area averaging), and the PSNR of
each view and their mean are written.

    python -m benchmarks.views_at_size --run NAME=GRID:WxH [--run ...] --size WxH [--out OUT.json]

GRID is a run's report_views image (PNG, or a high-quality JPEG of it where the PNG is too large
to move), WxH the size of one view in it (the run's metrics.json "resolution"). A run trained at
full size and one at the working size then score the same pixels: the full-size run's finer
detail is averaged away, and what is left is what both models got right or wrong at that size.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from jaxnerf_grid.eval.metrics import psnr

GAP = 2   # report.markdown.side_by_side's white gap between tiles


def split_views(grid: np.ndarray, width: int, height: int, gap: int = GAP) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(photo, render)] per row of a side_by_side grid [R * (height + gap) - gap, >= 2 * width + gap, 3]."""
    rows = (grid.shape[0] + gap) // (height + gap)
    if rows < 1 or grid.shape[1] < 2 * width + gap:
        raise ValueError(f"a {grid.shape[1]}x{grid.shape[0]} image holds no {width}x{height} views")
    out = []
    for r in range(rows):
        top = r * (height + gap)
        out.append((grid[top:top + height, :width], grid[top:top + height, width + gap:2 * width + gap]))
    return out


def psnr_at_size(photo: np.ndarray, render: np.ndarray, width: int, height: int) -> float:
    """PSNR of photo and render [H, W, 3] in [0, 1], both shrunk to width x height by area averaging."""
    def shrink(x):
        return x if x.shape[:2] == (height, width) else cv2.resize(x, (width, height), interpolation=cv2.INTER_AREA)
    return float(psnr(shrink(render.astype(np.float32)), shrink(photo.astype(np.float32))))


def size_arg(text: str) -> tuple[int, int]:
    w, _, h = text.lower().partition("x")
    if not (w.isdigit() and h.isdigit()):
        raise argparse.ArgumentTypeError(f"{text}: expected WIDTHxHEIGHT")
    return int(w), int(h)


def run_arg(text: str) -> tuple[str, Path, tuple[int, int]]:
    name, _, rest = text.partition("=")
    path, _, size = rest.rpartition(":")
    if not (name and path):
        raise argparse.ArgumentTypeError(f"{text}: expected NAME=GRID:WxH")
    return name, Path(path), size_arg(size)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=run_arg, action="append", required=True, help="NAME=GRID:WxH")
    p.add_argument("--size", type=size_arg, required=True, help="the common size, WIDTHxHEIGHT")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    width, height = args.size
    result = {"size": [width, height], "runs": {}}
    for name, path, (vw, vh) in args.run:
        grid = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if grid is None:
            raise SystemExit(f"{path}: not an image")
        try:
            views = split_views(grid[..., ::-1].astype(np.float32) / 255.0, vw, vh)
        except ValueError as e:
            raise SystemExit(f"{path}: {e}") from None
        per_view = [psnr_at_size(photo, render, width, height) for photo, render in views]
        result["runs"][name] = {"view_size": [vw, vh], "per_view_psnr": per_view, "psnr": float(np.mean(per_view))}
        print(f"{name}: {len(views)} views at {width}x{height}: PSNR "
              f"{', '.join(f'{v:.2f}' for v in per_view)} (mean {np.mean(per_view):.2f})")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
