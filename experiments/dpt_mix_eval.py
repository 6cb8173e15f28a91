"""Score DPT weights on frames drawn from a data cache (`experiments/dpt_data.py`): synthetic
frames of held-out seeds, distractors pasted on real photos, static real photos with empty masks.

    python -m experiments.dpt_mix_eval --weights DIR [DIR ...] --cache VAL.npz [--sprites-from OTHER.npz]
        [--frames 96] [--seed 12345] [--out RESULTS.json]

Every model is scored on the same frames (one draw, fixed seed; `train_dpt_mix.val_set`) at the
working size its config asks for (extra.max_side): IoU / precision / recall of M = [C > 0.5],
recall per class and per distractor size (`mask_scores`), and the share masked on the empty
real photos. A cache with no synthetic frames (real photos only, e.g. a scene kept out of
training) takes its sprites from --sprites-from.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from experiments import dpt_data, mask_scores, train_dpt_mix


def score(weights: Path, cache: dict, sprites: list, frames: int, seed: int) -> dict:
    """`train_dpt_mix.val_scores` of the DPT in `weights` on `frames` frames drawn from the cache."""
    from jaxnerf_grid.masks import dpt
    from jaxnerf_grid.util import io

    model = dpt.load_pretrained(weights)
    max_side = int(io.read_json(weights / "config.json").get("extra", {}).get("max_side", 160))
    hw = (cache["syn_x"] if len(cache["syn_x"]) else cache["real_x"]).shape[1:3]
    out_hw = train_dpt_mix.working_hw(*hw, max_side, model.config.patch_size)
    val = train_dpt_mix.val_set(cache, sprites, out_hw, frames, seed)
    return train_dpt_mix.val_scores(model.params, model.config, val)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", nargs="+", required=True)
    p.add_argument("--cache", required=True)
    p.add_argument("--sprites-from", default=None)
    p.add_argument("--frames", type=int, default=96)
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    cache = dpt_data.load_cache(args.cache)
    sprites = dpt_data.unpack_sprites(dpt_data.load_cache(args.sprites_from) if args.sprites_from else cache)
    rows = {w: score(Path(w), cache, sprites, args.frames, args.seed) for w in args.weights}
    lines = mask_scores.markdown(rows)
    lines += ["", "share masked on the empty real photos: " +
              ", ".join(f"{w}: {s['static_share']:.3f}" if s["static_share"] is not None else f"{w}: -"
                        for w, s in rows.items())]
    print("\n".join(lines))
    if args.out:
        Path(args.out).write_text(json.dumps({"cache": args.cache, "frames": args.frames, "seed": args.seed,
                                              "scores": rows}, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
