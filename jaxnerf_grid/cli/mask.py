"""`jaxnerf-grid mask`: foreground masks M, training weights 1 - M_w, depth and overlays for a dataset.

The work is `masking.write_masks`; this module parses the arguments.

    jaxnerf-grid mask --data DIR [--weights DIR] [--depth-weights DIR] [--source dpt|gt] ...

Per frame (stem = the image's file name without extension) it writes, inside the dataset:
  masks/<stem>.png      binary foreground mask M (after optional dilation)
  weights/<stem>.exr    per-pixel training weights 1 - M_w (0 = pixel ignored)
  dpt_depth/<stem>.exr  the depth D used by Eq. 7 (DPT: relative depth 1 / inverse depth, up to
                        scale; --source gt: the ground-truth z-depth)
  overlays/<stem>.png   the photo with M_w tinted red and M outlined | Eq. 8's filtered image
                        (longest side at most 1600 px per panel)
and rewrites transforms.json atomically, every other key preserved: each frame gains
`mask_path`, `weight_path`, `dpt_depth_path`, `overlay_path`, `masked_share` and (DPT)
`dpt_confidence`; the top level gains `mask_source` ("dpt" or "ground-truth"), `mask_params`
and (DPT) `mask_domain`, the out-of-domain rule's verdict, also printed in one line: when more
than half of the frames have more than 40 % of their pixels masked, the model is out of its
domain and its masks should not be trusted (`demo --masks auto` then trains without them;
docs/MASKS.md).

--source dpt (default) runs DPT: `--weights` is a folder in the HF layout (e.g. a copy of
Intel/dpt-large-ade) or the native format; default: the built-in model shipped in
jaxnerf_grid/masks/assets/dpt_builtin (if present). An HF segmentation checkpoint has no depth head:
pass `--depth-weights` (e.g. a copy of Intel/dpt-large) for Eq. 7, else M_w = M (floor 1).
--source gt builds M from the synthetic ground truth `distractor_mask_path` and D from
`depth_file_path` (so training can run without any DPT model).
"""

from __future__ import annotations

import argparse


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid mask", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="dataset folder with transforms.json")
    p.add_argument("--source", choices=["dpt", "gt"], default="dpt",
                   help="dpt: run DPT; gt: synthetic ground-truth distractor masks and depth")
    p.add_argument("--weights", default=None, help="DPT folder (HF layout or native); default: built-in")
    p.add_argument("--depth-weights", default=None, help="separate DPT depth model (HF layout or native)")
    p.add_argument("--classes", default=None,
                   help="comma-separated dynamic class ids for Eq. 6 (default: ADE20K set for 150-label "
                        "models, the model's own set for the built-in model)")
    p.add_argument("--threshold", type=float, default=0.5, help="T in M = [C > T]")
    p.add_argument("--floor", type=float, default=0.0,
                   help="M_w = M * max(floor, (Dmax - D)/Dmax); 0 = Eq. 7 exactly, 1 = exclude fully")
    p.add_argument("--dilate", type=int, default=0, help="dilate M and M_w by this many pixels")
    p.add_argument("--max-side", type=int, default=None,
                   help="DPT working size (longest side, px); default: the model's training size "
                        "(160 for the built-in model) or 384")
    p.add_argument("--tiles", type=int, default=1,
                   help="C from this many overlapping windows along each photo's longer side, each at the "
                        "working size (small distractors keep more pixels; costs about tiles^2 x aspect "
                        "more DPT runs); depth still from the whole photo. 1 = the whole photo at once")
    p.add_argument("--tile-overlap", type=float, default=0.25,
                   help="fraction of a window shared with each neighbour, cross-faded (0 to 0.75)")
    p.add_argument("--batch-size", type=int, default=None,
                   help="images (or windows) per DPT call; default 1 on CPU (batching was slower there), 4 on a GPU")
    p.add_argument("--overwrite", action="store_true", help="replace existing mask outputs")
    p.add_argument("--quiet", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxnerf_grid.masks import write as masking

    classes = masking.parse_classes(args.classes)
    masking.write_masks(args.data, source=args.source, weights=args.weights, depth_weights=args.depth_weights,
                        classes=classes, threshold=args.threshold, floor=args.floor, dilate=args.dilate,
                        max_side=args.max_side, tiles=args.tiles, tile_overlap=args.tile_overlap,
                        batch_size=args.batch_size, overwrite=args.overwrite, progress=not args.quiet)
    return 0
