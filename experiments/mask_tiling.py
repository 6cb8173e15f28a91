"""Does `jaxnerf-grid mask --tiles N` find more of the distractors in a large photo?

Usage:
  JAX_PLATFORMS=cpu python -m experiments.mask_tiling [--width 640 --height 480 --views 12]
      [--cache experiments/.cache] [--results experiments/results/mask_tiling]

The built-in DPT (trained at a 160 px working size) masks held-out synthetic scenes (seeds
7101-7102, disjoint from its training seeds) rendered at a larger size than it was trained on,
in several ways:
  * the whole photo resized to a working size of 160 px (the default), 320 px or 480 px;
  * 2, 3 or 4 overlapping 160 px windows along the longer side of a finer copy of the photo
    (`--tiles`; each window sees 2-4x more pixels of a distractor than the whole-photo pass).
Mask M = [C > 0.5] against the ground-truth distractor mask (bit 0): IoU, precision, recall
pooled over all pixels (experiments/train_builtin_dpt.py's `evaluate`), and seconds per photo.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from experiments import runner, scenes  # noqa: E402
from experiments.train_builtin_dpt import evaluate  # noqa: E402
from jaxnerf_grid.masks.write import load_models  # noqa: E402

SEEDS = (7101, 7102)
CONDITIONS = [(160, 1), (320, 1), (480, 1), (160, 2), (160, 3), (160, 4)]  # (max_side, tiles)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--views", type=int, default=12)
    p.add_argument("--cache", default=str(ROOT / "experiments" / ".cache"))
    p.add_argument("--results", default=str(ROOT / "experiments" / "results" / "mask_tiling"))
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)

    t_start = time.time()
    command = ("JAX_PLATFORMS=cpu python -m experiments.mask_tiling "
               + " ".join(argv if argv is not None else sys.argv[1:]))
    ctx = runner.Context(setting="quick", seeds=len(SEEDS), steps=0, cache=Path(args.cache),
                         results=Path(args.results).parent, budget_s=None, lpips_weights=None,
                         progress=not args.quiet, command=command.strip())
    size = (args.width, args.height, args.views, 0, 1)  # (w, h, train views, test views, supersampling)
    roots = [scenes.scene(ctx, "tower-small", seed, size=size) for seed in SEEDS]

    model, _, _ = load_models(None, None)
    rows = []
    for max_side, tiles in CONDITIONS:
        evaluate(model, roots[:1], max_side=max_side, tiles=tiles)  # compile outside the timing
        t = time.perf_counter()
        res = evaluate(model, roots, max_side=max_side, tiles=tiles)
        per_photo = (time.perf_counter() - t) / res["num_frames"]
        rows.append({"max_side": max_side, "tiles": tiles, "seconds_per_photo": per_photo, **res})
        pm = res["pooled"]
        print(f"max_side {max_side} tiles {tiles}: IoU {pm['iou']:.3f} precision {pm['precision']:.3f} "
              f"recall {pm['recall']:.3f}; {per_photo:.2f} s/photo", flush=True)

    out = Path(args.results)
    out.parent.mkdir(parents=True, exist_ok=True)
    summary = {"command": ctx.command, "seeds": list(SEEDS), "size": [args.width, args.height],
               "views_per_scene": args.views, "wall_s": time.time() - t_start, "rows": rows}
    out.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
    lines = [
        "# Masks of large photos: one resized pass vs overlapping windows",
        "",
        f"Built-in DPT on held-out synthetic scenes (seeds {', '.join(map(str, SEEDS))}, "
        f"{args.views} views each, rendered at {args.width}x{args.height}; the model was trained at a "
        "160 px working size). M = [C > 0.5] against the ground-truth distractor mask, pooled over all pixels.",
        "",
        "| working size | windows along the longer side | IoU | precision | recall | s / photo |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        pm = r["pooled"]
        lines.append(f"| {r['max_side']} | {r['tiles']} | {pm['iou']:.3f} | {pm['precision']:.3f} | "
                     f"{pm['recall']:.3f} | {r['seconds_per_photo']:.2f} |")
    lines += ["", f"Command: `{summary['command']}`; {summary['wall_s'] / 60:.1f} min in all on this machine.", ""]
    out.with_suffix(".md").write_text("\n".join(lines))
    print(f"wrote {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    runner.cpu_defaults()
    raise SystemExit(main())
