"""`jaxnerf-grid poses`: camera poses for a folder of photos (structure from motion with COLMAP's
Python bindings, pycolmap), written as a dataset that `mask`, `train` and `demo --data` read.

The work is `data.poses.poses_from_images`; this module parses the arguments.

    jaxnerf-grid poses --images DIR --out DATA_DIR [--matcher auto|exhaustive|spatial|sequential|vocab]
                       [--overlap K] [--neighbours K]
                       [--camera-model SIMPLE_RADIAL] [--single-camera | --camera-per-photo]
                       [--max-side N] [--feature-side N]
                       [--keep-all] [--overwrite]
                       [--accept-few-cameras]
                       [--crs EPSG:XXXX] [--gcp FILE] [--scale-bar SPEC] [--ignore-gps]

DATA_DIR gets images/ (the undistorted photos, same names), transforms.json (docs/DATASET.md,
OpenGL camera-to-world, normalised for an orbit: z up, the looked-at point in the unit
sphere, and the scene bounds), sparse/0 (the COLMAP model, z up), poses_topview.png and
poses_report.md (the vetting table: registered photos that fail it are left out unless
--keep-all). Photos with EXIF GPS put the model in metres in a projected CRS (the GPS's UTM
zone or --crs), refined by ground control points (--gcp); without GPS, --scale-bar gives the
scale; else units stay unknown (docs/GEOREFERENCE.md). Needs the `sfm` extra
(pycolmap); docs/POSES.md has the stages, the limits and measured times.
"""

from __future__ import annotations

import argparse

from jaxnerf_grid.capture.camera_set import MIN_ARC_SHARE, MIN_KEPT_SHARE
from jaxnerf_grid.capture.poses import (
    CAMERA_MODELS,
    EXHAUSTIVE_MAX_PAIRS,
    FEATURE_SIDE,
    MATCHERS,
    SEQUENTIAL_OVERLAP,
    SPATIAL_NEIGHBOURS,
)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid poses", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--images", required=True, help="folder of photos (PNG / JPEG; subfolders are ignored)")
    p.add_argument("--out", required=True, help="dataset folder to write (DATA_DIR)")
    p.add_argument("--matcher", default="auto", metavar="{" + ",".join(MATCHERS) + "}",
                   help=f"exhaustive: every pair (up to a few hundred photos); spatial: each photo with its "
                        f"--neighbours nearest by GPS; sequential: each photo with its next --overlap in "
                        f"name order (a flight's sequence), the pairs across the end that close an orbit and "
                        f"COLMAP's quadratic overlap; vocab: a vocabulary tree (needs --vocab-tree); auto "
                        f"(default): exhaustive up to {EXHAUSTIVE_MAX_PAIRS} pairs, above it spatial when every "
                        f"photo has GPS, else sequential when the names are numbered in sequence, else exhaustive")
    p.add_argument("--overlap", type=int, default=SEQUENTIAL_OVERLAP,
                   help="sequential matching: the next photos (in name order) each photo is matched with")
    p.add_argument("--neighbours", type=int, default=SPATIAL_NEIGHBOURS,
                   help=f"spatial matching: the photos nearest by GPS each photo is matched with (default "
                        f"{SPATIAL_NEIGHBOURS}; more place each camera closer at more matching time, docs/POSES.md)")
    p.add_argument("--vocab-tree", default=None, help="COLMAP vocabulary tree file for --matcher vocab")
    p.add_argument("--camera-model", choices=CAMERA_MODELS, default="SIMPLE_RADIAL",
                   help="COLMAP camera model fitted to the photos (undistorted to PINHOLE afterwards)")
    cams = p.add_mutually_exclusive_group()
    cams.add_argument("--single-camera", dest="single_camera", action="store_const", const=True, default=None,
                      help="one camera (intrinsics) shared by all photos: right for one drone camera at one zoom "
                           "(default: shared when the photos have one size and one EXIF camera and focal length)")
    cams.add_argument("--camera-per-photo", dest="single_camera", action="store_const", const=False,
                      help="each photo its own camera (intrinsics), whatever the photos' EXIF says")
    p.add_argument("--max-side", type=int, default=None,
                   help="scale the photos so the longer side is at most N pixels (the dataset keeps this size)")
    p.add_argument("--feature-side", type=int, default=FEATURE_SIDE,
                   help=f"SIFT sees the photos scaled to at most N px on the long side (default {FEATURE_SIDE}; "
                        "0: COLMAP's own 3200); the dataset keeps the photos' size")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a DATA_DIR written by poses (its outputs only; other folders are refused)")
    p.add_argument("--keep-all", action="store_true",
                   help="keep every registered photo, also those the vetting would leave out (docs/POSES.md)")
    p.add_argument("--accept-few-cameras", action="store_true",
                   help=f"write the dataset even when fewer than {MIN_KEPT_SHARE * 100:.0f} %% of the photos are "
                        f"kept or the kept cameras cover less than {MIN_ARC_SHARE * 100:.0f} %% of the flight's arc "
                        "around the scene (a NeRF trained on them renders the rest poorly; docs/POSES.md); after a "
                        "refusal, the same command with this flag reuses the refused run's reconstruction kept in "
                        "DATA_DIR.refused")
    p.add_argument("--crs", default=None,
                   help="projected CRS for the GPS alignment, e.g. EPSG:32633 (default: the GPS's UTM zone)")
    p.add_argument("--gcp", default=None,
                   help="ground control points: CSV rows image,x,y,X,Y,Z[,check] (docs/GEOREFERENCE.md)")
    p.add_argument("--scale-bar", default=None,
                   help="a known distance when the photos have no GPS: 'X1,Y1,Z1,X2,Y2,Z2,METRES' or "
                        "'IMG1:x,y;IMG2:x,y;IMG3:x,y;IMG4:x,y;METRES' (docs/GEOREFERENCE.md)")
    p.add_argument("--ignore-gps", action="store_true",
                   help="do not read the photos' GPS (e.g. when it is wrong); --scale-bar or --gcp still apply")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxnerf_grid.capture.poses import format_summary, poses_from_images

    summary = poses_from_images(args.images, args.out, matcher=args.matcher, overlap=args.overlap,
                                camera_model=args.camera_model,
                                single_camera=args.single_camera, max_side=args.max_side,
                                vocab_tree=args.vocab_tree, overwrite=args.overwrite, progress=not args.quiet,
                                keep_all=args.keep_all, crs=args.crs, gcp=args.gcp, scale_bar=args.scale_bar,
                                ignore_gps=args.ignore_gps, accept_few_cameras=args.accept_few_cameras,
                                feature_side=args.feature_side, neighbours=args.neighbours)
    print(format_summary(summary))
    print(f"wrote {summary['transforms']}")
    return 0
