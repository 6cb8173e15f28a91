"""The evidence judged once on whole training frames, then frozen (train.robust.refine).

A robust run (`robust.py`) trains on square patches so that the evidence can be judged over
neighbourhoods, and patches cost accuracy by themselves: a batch of 1024 rays in 4 x 4
patches visits 64 places a step, not 1024 (docs/ROBUST.md: 0.6 dB on the pasted fountain-P11
with the ground-truth weights). With `train.robust.refine` = r > 0, after r x max_steps steps
(`robust.refine_step`) training stops once, renders every training frame with the model it
has, and applies the same rule to whole frames:

1. each pixel's residual (squared error of the rendered colour, mean over the channels)
   against the thresholds of all the training frames' residuals together (the batch is now
   every training pixel), with the pool's prior (1, or 1 - M_w for dpt+robust), the spread
   bound and the floor (`robust.pixel_inliers`);
2. with train.robust.confirm > 0, a pixel that a neighbouring photo confirms at its rendered
   median depth is an inlier (`photo_consistency.confirmed_at_ids`);
3. the 3x3 vote over the pixel's neighbours in its frame and the patch rule over the frame's
   tiles (`robust.frame_evidence`).

The resulting 0 / 1 weights replace the state's "robust_record" (so they are in every later
checkpoint, and RUN/weights/ shows them), and the rest of the run draws scattered rays among
the pixels of weight 1, as a run with masks does (`frozen_pool`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.config.run_config import RunConfig
from jaxnerf_grid.data import working
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.masks import photo_consistency
from jaxnerf_grid.masks import robust as robust_lib
from jaxnerf_grid.render import views
from jaxnerf_grid.train import ray_pool
from jaxnerf_grid.util import progress as progress_lib
from jaxnerf_grid.util.io import DataError


def render_training_frames(params, cfg: RunConfig, dataset: Dataset, frames: np.ndarray,
                           progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Renders the dataset frames `frames` [T] (deterministic samples, `views.render_view`).
    Returns (residual [T, H, W]: mean over the channels of the squared error of the clipped
    colour against the photo, points [T, H, W, 3]: each pixel's point at its rendered median
    depth, world units)."""
    residuals, points = [], []
    items = progress_lib.bar(frames, desc="refine: render training frames", unit="frame",
                             leave=False) if progress else frames
    for frame in items:
        view = views.render_view(params, cfg, dataset, int(frame))
        photo = working.as_float(dataset.images[int(frame)])
        residuals.append(np.mean((np.clip(view["rgb"], 0.0, 1.0) - photo) ** 2, axis=-1))
        r = views.camera_rays(dataset, int(frame), 1.0, 2.0)
        distance = view["depth"] / np.asarray(r.cos_to_axis)  # z-depth -> distance along the unit ray
        points.append(np.asarray(r.origins) + np.asarray(r.directions) * distance[..., None])
    return np.stack(residuals).astype(np.float32), np.stack(points).astype(np.float32)


def confirmed_frames(pool: dict, points: np.ndarray, threshold: float) -> np.ndarray:
    """[T, H, W] 1.0 where a neighbouring training photo confirms the pixel at its point.
    pool: train.robust_pool's (or build_pool's) dict (images, c2w, intrinsics, neighbours);
    points: [T, H, W, 3]."""
    frames, height, width = points.shape[:3]
    images, c2w, intrinsics, neighbours = (jnp.asarray(pool[k]) for k in ("images", "c2w", "intrinsics",
                                                                        "neighbours"))  # uploaded once
    table = ray_pool.byte_table(images)  # 8-bit frames: their float32 values
    out = []
    for k in range(frames):
        ids = jnp.arange(height * width, dtype=jnp.int32) + k * height * width
        out.append(np.asarray(photo_consistency.confirmed_at_ids(
            images, c2w, intrinsics, neighbours, ids, jnp.asarray(points[k].reshape(-1, 3)), threshold, table)))
    return np.stack(out).reshape(frames, height, width)


def refined_weights(residual: np.ndarray, prior: np.ndarray, cfg: RunConfig,
                    confirmed: np.ndarray | None = None) -> np.ndarray:
    """The rule of the module docstring on whole frames. residual, prior, confirmed (or None):
    [T, H, W]. Returns [T, H, W] float32 in {0, 1}."""
    t = cfg.train
    inlier = robust_lib.pixel_inliers(jnp.asarray(residual), jnp.asarray(prior), jnp.asarray(residual).reshape(-1),
                                      t.robust.quantile, t.robust.flagged_quantile, t.robust.floor, t.robust.spread,
                                      None if confirmed is None else jnp.asarray(confirmed),
                                      bool(t.robust.strict_readmit))
    return np.asarray(robust_lib.frame_evidence(inlier, t.robust.patch, t.robust.patch_share), np.float32)


def judge_frames(params, cfg: RunConfig, dataset: Dataset, pool: dict, progress: bool = False) -> np.ndarray:
    """Renders the pool's training frames and returns their frozen weights [T, H, W] in {0, 1}
    (`refined_weights`, confirmation included when train.robust.confirm > 0)."""
    residual, points = render_training_frames(params, cfg, dataset, pool["frame"], progress)
    confirmed = None
    if cfg.train.robust.confirm > 0 and "neighbours" in pool:
        confirmed = confirmed_frames(pool, points, cfg.train.robust.confirm)
    return refined_weights(residual, ray_pool.host_weights(pool), cfg, confirmed)


def frozen_pool(pool: dict, weights: np.ndarray) -> dict:
    """The pool of the run's last part: the robust pool with `weights` [T, H, W] as its weights and
    the pixels of weight > 0 as the ones drawn (flat ids, `train.build_pool`'s numbering), no
    neighbours, float32 weights (no "levels"). DataError when no pixel is left."""
    pixels = np.flatnonzero(np.asarray(weights).reshape(-1) > 0).astype(np.int32)
    if pixels.size == 0:
        raise DataError("train.robust.refine: the evidence ignored every training pixel; "
                        "lower train.robust.refine or raise train.robust.spread")
    out = {k: v for k, v in pool.items() if k not in ("neighbours", "levels")}
    out.update(weights=np.asarray(weights, np.float32), pixels=pixels)
    return out
