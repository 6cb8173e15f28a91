"""`jaxnerf-grid synth`: render the procedural tower benchmark to a transforms.json dataset.

The work is `data.synthetic.generate.generate_scene`; this module parses the arguments.
"""

from __future__ import annotations

import argparse
import os

from jaxnerf_grid.data.synthetic import DISTRACTOR_LEVELS, PRESETS


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid synth", description=__doc__)
    p.add_argument("--preset", default="tower-small", choices=sorted(PRESETS))
    p.add_argument("--out", required=True, help="output dataset folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--distractors", choices=list(DISTRACTOR_LEVELS), default=None,
                   help="distractor coverage level (default: the preset's)")
    p.add_argument("--mode", choices=["teleport", "jitter"], default=None,
                   help="re-place distractors anew in every view (teleport) or jitter a fixed layout")
    p.add_argument("--no-shadows", action="store_true", help="no cast shadows (sun always visible)")
    p.add_argument("--no-conductors", action="store_true", help="no power lines (the towers alone)")
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--height", type=int, default=None)
    p.add_argument("--num-train", type=int, default=None)
    p.add_argument("--num-test", type=int, default=None)
    p.add_argument("--supersample", type=int, default=None, help="N: NxN colour samples per pixel")
    p.add_argument("--workers", type=int, default=0, help="processes (0: min(2, CPU count))")
    p.add_argument("--preview", action="store_true", help="also write preview.png (a contact sheet)")
    p.add_argument("--gps-origin", default=None, metavar="LAT,LON,ALT",
                   help="also write photos_gps/ (JPEGs with EXIF GPS: true camera centres plus a consumer "
                        "receiver's error, seeded) and gps_truth.json, the tower's base at LAT,LON,ALT "
                        "(docs/GEOREFERENCE.md)")
    p.add_argument("--gcp-layout", default="ground", metavar="NAME",
                   help="with --gps-origin, the ground control points written: ground (gcp.csv, points on the "
                        "ground around the tower; default) or spread (gcp_spread.csv, control points at "
                        "different heights: the ground, a cross-arm tip, the earth-wire peak) or dense (gcp_dense.csv, "
                        "37 control points over the tower: a diagnostic)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def check_args(args) -> None:
    """Refuses (ConfigError naming the flag) sizes and counts that would write a dataset
    `train` cannot use: width / height >= 8, num-train, num-test, supersample >= 1, workers >= 0."""
    from jaxnerf_grid.config.schema import ConfigError

    for flag, value, low in (("--width", args.width, 8), ("--height", args.height, 8),
                             ("--num-train", args.num_train, 1),
                             ("--num-test", args.num_test, 1), ("--supersample", args.supersample, 1),
                             ("--workers", args.workers, 0)):
        if value is not None and value < low:
            raise ConfigError(f"{flag} = {value}: must be >= {low}")


def clear_derived_outputs(out) -> None:
    """Before `synth --overwrite` replaces a dataset synth wrote (its marker present): removes
    what later commands derived from the old photos there (mask's masks/, weights/, dpt_depth/,
    overlays/), which the generator's own clearing does not know about. Anything else, and a
    folder synth did not write, is left to the generator's rules."""
    import shutil
    from pathlib import Path

    from jaxnerf_grid.data.formats.writing import MASK_OUTPUT_DIRS
    from jaxnerf_grid.data.synthetic.generate import is_synthetic_dataset

    out = Path(out)
    if not out.is_dir() or not is_synthetic_dataset(out):
        return
    for name in MASK_OUTPUT_DIRS:
        if (out / name).is_dir() and not (out / name).is_symlink():
            shutil.rmtree(out / name)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    check_args(args)
    from jaxnerf_grid.capture.gps_photos import layout_points, parse_origin, write_gps_photos
    from jaxnerf_grid.data.synthetic.generate import contact_sheet, generate_scene

    origin = parse_origin(args.gps_origin) if args.gps_origin is not None else None
    layout_points(args.gcp_layout)  # an unknown layout refused before anything is written
    workers = args.workers or min(2, os.cpu_count() or 1)
    if args.overwrite:
        clear_derived_outputs(args.out)
    path = generate_scene(
        args.preset, args.out, seed=args.seed, distractors=args.distractors, overwrite=args.overwrite,
        progress=not args.quiet, workers=workers, width=args.width, height=args.height,
        num_train=args.num_train, num_test=args.num_test, supersample=args.supersample, mode=args.mode,
        shadows=False if args.no_shadows else None, conductors=False if args.no_conductors else None,
    )
    if args.preview:
        contact_sheet(path.parent, path.parent / "preview.png")
    if origin is not None:
        print(f"wrote {write_gps_photos(path.parent, origin, seed=args.seed, gcp_layout=args.gcp_layout)}")
    print(f"wrote {path}")
    return 0

