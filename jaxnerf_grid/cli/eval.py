"""`jaxnerf-grid eval`: evaluate a trained run on its test views (`evaluate.evaluate_run`).

    jaxnerf-grid eval --run RUN [--lpips-weights FILE] [--reference-ply FILE] [--distractor-views N] [--full-size]

Writes metrics.json, report.md and tower_points.ply into the run; the evaluation protocol is
in evaluate.py's docstring.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid eval", description="evaluate a trained run on its test views")
    p.add_argument("--run", required=True, help="run directory")
    p.add_argument("--lpips-weights", default=None, help="LPIPS weights .npz (else LPIPS is unavailable)")
    p.add_argument("--distractor-views", type=int, default=4)
    p.add_argument("--reference-ply", default=None,
                   help="reference tower point cloud (PLY, the dataset's normalised scene units) to score "
                        "tower_points.ply against (default: the dataset's tower_ply, if any)")
    p.add_argument("--allow-other-data", action="store_true",
                   help="score the run on a dataset other than the one it was trained on (its fingerprint differs)")
    p.add_argument("--full-size", action="store_true",
                   help="render and score the test views at the photos' full size (default: the run's "
                        "working resolution, train.max_side)")
    p.add_argument("--appearance-steps", type=int, default=None,
                   help="a model with the appearance embedding: the test-time fit's steps (default: the run's "
                        "train.appearance_steps); 0 renders held-out views with the training photos' mean "
                        "embedding and scores whole views, more fits it on each view's left half (NeRF-W)")
    p.add_argument("--quiet", action="store_true")
    return p


def geometry_line(geo: dict) -> str:
    """One line of metrics["geometry"]: F-score per threshold and the Chamfer distance."""
    return ("tower geometry: " + ", ".join(f"F@{tau} {row['fscore']:.3f}" for tau, row in geo["thresholds"].items())
            + (f", Chamfer {geo['chamfer']:.4f}" if geo["chamfer"] is not None else ", Chamfer n/a")
            + " (normalised scene units)")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxnerf_grid.eval import evaluate

    m = evaluate.evaluate_run(args.run, args.lpips_weights, not args.quiet, distractor_views=args.distractor_views,
                              reference_ply=args.reference_ply, allow_other_data=args.allow_other_data,
                              full_size=args.full_size, appearance_steps=args.appearance_steps)
    ssim = m["mean"]["ssim"]  # None when every view is smaller than the SSIM window
    print(f"test PSNR {m['mean']['psnr']:.2f} dB, SSIM {'n/a' if ssim is None else f'{ssim:.4f}'}; "
          f"report: {Path(args.run) / 'report.md'}")
    if m.get("geometry"):
        print(geometry_line(m["geometry"]))
    return 0
