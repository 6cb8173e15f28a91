"""What the robust weighting would ignore in whole frames of a trained run, with and without
multi-view confirmation, for a few spread bounds: a quick look before a long training run.

    python scripts/robust_offline.py RUN FRAMES [--spreads 3,2,1.5] [--confirms 0,0.01,0.02] [--views 8]
        [--quantile Q] [--disconfirms 0.08,0.04,0.02] [--breakdown]

FRAMES: comma-separated dataset indices of training frames. For each frame the run renders
it (rgb and median depth), takes the residuals of the whole frame as the batch, applies the
rule of `jaxnerf_grid/masks/robust.py` over the frame cut into train.robust.patch squares (the
inlier quantile is the run's train.robust.quantile unless --quantile says another; 0 leaves
the spread bound alone), with the confirmation of `jaxnerf_grid/masks/photo_consistency.py` against the
--views nearest training photos, and prints the share of the frame it would ignore; where
the dataset has distractor masks (the pasted-transient benchmark's), the share of the
distractor pixels and of the static pixels separately. docs/ROBUST.md quotes it.
"""

from __future__ import annotations

import argparse
import sys

import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.masks import photo_consistency, robust
from jaxnerf_grid.nerf import rays
from jaxnerf_grid.render import views
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train.runs import load_run_and_dataset


def tiles(x: np.ndarray, p: int) -> np.ndarray:
    """[H, W] -> [P, p, p] squares (the frame cropped to multiples of p)."""
    h, w = (x.shape[0] // p) * p, (x.shape[1] // p) * p
    return x[:h, :w].reshape(h // p, p, w // p, p).transpose(0, 2, 1, 3).reshape(-1, p, p)


def untile(x: np.ndarray, h: int, w: int, p: int) -> np.ndarray:
    """[P, p, p] -> [h // p * p, w // p * p]."""
    hh, ww = h // p, w // p
    return x.reshape(hh, ww, p, p).transpose(0, 2, 1, 3).reshape(hh * p, ww * p)


def frame_confirmation(ds, params_view: dict, index: int, train_ids: np.ndarray, views_count: int) -> np.ndarray:
    """[H, W] confirmation errors of a training frame at its rendered median depth."""
    height, width = ds.images.shape[1:3]
    fx, fy, cx, cy = ds.intrinsics[index]
    r = rays.generate_rays(jnp.asarray(ds.c2w[index]), fx, fy, cx, cy, width, height)
    points = np.asarray(r.origins + r.directions * jnp.asarray(params_view["depth"])[..., None]).reshape(-1, 3)
    neighbours = photo_consistency.neighbour_frames(ds.c2w[train_ids], views_count)
    local = int(np.flatnonzero(train_ids == index)[0])
    rows, cols = np.mgrid[0:height, 0:width]
    err = photo_consistency.confirmation_errors(
        jnp.asarray(ds.images[train_ids]), jnp.asarray(ds.c2w[train_ids]), jnp.asarray(ds.intrinsics[train_ids]),
        jnp.asarray(neighbours), jnp.full(height * width, local, jnp.int32), jnp.asarray(rows.ravel()),
        jnp.asarray(cols.ravel()), jnp.asarray(points))
    return np.asarray(err).reshape(height, width)


def print_breakdown(index: int, res_t, err_t, residual, truth, tcfg, patch: int) -> None:
    """--breakdown (run's spread and confirmation): the share of distractor / static pixels that
    the residual test alone marks as outliers, that the confirmation confirms, and the share of
    the distractors' insides (eroded by 3x3) the whole rule ignores."""
    import cv2

    ones = jnp.ones_like(jnp.asarray(res_t))
    args = (jnp.asarray(res_t), ones, jnp.asarray(residual.ravel()), tcfg.robust.quantile,
            tcfg.robust.flagged_quantile, tcfg.robust.floor, tcfg.robust.spread)
    confirmed = jnp.asarray(err_t <= tcfg.robust.confirm, jnp.float32)
    h, w = residual.shape
    t = truth[:h // patch * patch, :w // patch * patch]
    alone = untile(np.asarray(robust.pixel_inliers(*args)), h, w, patch) < 0.5
    conf = untile(np.asarray(confirmed), h, w, patch) > 0.5
    final = untile(np.asarray(robust.evidence(robust.pixel_inliers(*args, confirmed), tcfg.robust.patch_share)),
                   h, w, patch) < 0.5
    inside = cv2.erode(t.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    print(f"frame {index} breakdown: residual test alone marks distractor {alone[t].mean():.1%} / static "
          f"{alone[~t].mean():.1%}; confirmed distractor {conf[t].mean():.1%} / static {conf[~t].mean():.1%}; "
          f"distractor insides ignored {final[inside].mean():.1%}", flush=True)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run")
    p.add_argument("frames")
    p.add_argument("--spreads", default="3,2,1.5")
    p.add_argument("--confirms", default="0,0.01,0.02")
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--quantile", type=float, default=None)
    p.add_argument("--breakdown", action="store_true",
                   help="with distractor masks: what the residual test and the confirmation do to each kind of pixel")
    p.add_argument("--disconfirms", default="",
                   help="also try these: a pixel whose confirmation error exceeds D (every neighbour that sees "
                        "its point disagrees) is an outlier whatever its residual, before the vote")
    args = p.parse_args(argv)
    cfg, _, ds = load_run_and_dataset(args.run, None, False, False, False)
    params, _ = train.load_params(args.run, cfg, ds)
    tcfg = cfg.train
    patch = tcfg.robust.patch
    train_ids = np.asarray(ds.split["train"])
    for index in (int(a) for a in args.frames.split(",")):
        view = views.render_view(params, cfg, ds, index)
        photo = ds.images[index]
        height, width = photo.shape[:2]
        residual = np.mean((np.clip(view["rgb"], 0, 1) - photo) ** 2, axis=-1)
        error = frame_confirmation(ds, view, index, train_ids, args.views)
        truth = None if ds.distractor_masks is None else np.asarray(ds.distractor_masks[index], bool)
        res_t, err_t = tiles(residual, patch), tiles(error, patch)
        if truth is not None and args.breakdown:
            print_breakdown(index, res_t, err_t, residual, truth, tcfg, patch)
        for k in (float(a) for a in args.spreads.split(",")):
            quantile = tcfg.robust.quantile if args.quantile is None else args.quantile
            for confirm in (float(a) for a in args.confirms.split(",")):
                confirmed = jnp.asarray(err_t <= confirm, jnp.float32) if confirm > 0 else None
                inlier = robust.pixel_inliers(jnp.asarray(res_t), jnp.ones_like(jnp.asarray(res_t)),
                                              jnp.asarray(residual.ravel()), quantile, tcfg.robust.flagged_quantile,
                                              tcfg.robust.floor, k, confirmed)
                for disconfirm in [None, *(float(a) for a in args.disconfirms.split(",") if a)]:
                    kept = inlier if disconfirm is None else jnp.where(
                        jnp.asarray(np.isfinite(err_t) & (err_t > disconfirm)), 0.0, inlier)
                    w = robust.evidence(kept, tcfg.robust.patch_share)
                    ignored = untile(np.asarray(w), height, width, patch) < 0.5
                    line = (f"frame {index} quantile {quantile:g} spread {k:g} confirm {confirm:g}"
                            + ("" if disconfirm is None else f" disconfirm {disconfirm:g}")
                            + f": ignored {ignored.mean():.1%}")
                    if truth is not None:
                        t = truth[:ignored.shape[0], :ignored.shape[1]]
                        line += (f" | distractor pixels ignored {ignored[t].mean():.1%}, "
                                 f"static {ignored[~t].mean():.1%}")
                    print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
