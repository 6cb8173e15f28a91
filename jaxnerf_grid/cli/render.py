"""`jaxnerf-grid render`: render views of a trained run into renders/, depth/, opacity/ (`runs.render_split`).

    jaxnerf-grid render --run RUN [--split test|train|all] [--full-size]
"""

from __future__ import annotations

import argparse
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid render", description="render views of a trained run")
    p.add_argument("--run", required=True, help="run directory")
    p.add_argument("--split", choices=["test", "train", "all"], default="test")
    p.add_argument("--allow-other-data", action="store_true",
                   help="render even though the run's dataset has changed (its fingerprint differs)")
    p.add_argument("--full-size", action="store_true",
                   help="render at the photos' full size (default: the run's working resolution, train.max_side)")
    p.add_argument("--quiet", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxnerf_grid import runs

    views = runs.render_split(args.run, args.split, not args.quiet, allow_other_data=args.allow_other_data,
                              full_size=args.full_size)
    print(f"rendered {len(views)} views into {Path(args.run) / 'renders'} (depth/, opacity/ alongside)")
    return 0
