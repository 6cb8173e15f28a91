"""Rays drawn where the model is still wrong: a per-tile error map of the training frames.

`train.error_share` of each batch (0 = off) is drawn from square tiles of `train.error_tile`
working pixels, a tile with probability proportional to its recent error (plus a small floor),
a pixel uniformly within it; the rest of the batch is drawn uniformly from the training pixels
as without it. After each step the tiles the batch reached take the mean squared error of its
rays there into their record (an exponential average, ERROR_RATE), so the map follows the fit.
Instant-NGP samples its training pixels from such an error map; this one is per tile so that
the map is small (1 / tile^2 of the pixels) and its cumulative sum cheap in every step.

The loss is not re-weighted: the drawn share over-weights the tiles still in error, the uniform
share keeps every pixel in the objective. The PSNR the run logs is the uniform share's, an
unbiased sample of the training pixels' fit. Masked pixels (loss weight 0) drawn in a tile count
nothing and update nothing. The map is part of the training state (checkpointed: a resumed run
draws what the straight run draws) and replicated: every device draws the same global batch
from it, so 1 and 2 devices train the same.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.config.schema import ConfigError

ERROR_RATE = 0.5   # a reached tile's record moves half-way to the batch's error there
FLOOR = 1e-3       # every tile keeps this share of the mean record, so none is starved
ERROR_FOLD = 0x45  # the error draws' key is folded off the batch key


def tile_grid(h: int, w: int, tile: int) -> tuple[int, int]:
    """(tile rows, tile columns) covering an h x w frame with tile x tile squares (the last row
    and column of tiles may be cut short)."""
    return math.ceil(h / tile), math.ceil(w / tile)


def error_rays(tcfg) -> int:
    """Rays of each batch drawn from the error map: round(error_share x batch_rays). Refused in
    one line with the resolution schedule or the robust step, whose frames it does not tile.
    tcfg: a TrainConfig."""
    if tcfg.error_share <= 0:
        return 0
    if tcfg.robust.mode != "off":
        raise ConfigError("train.error_share needs train.robust off: the robust step draws patches of its own "
                          "(set train.error_share=0 or train.robust.mode=off)")
    if tcfg.lowres_share > 0 and tcfg.lowres_factor > 1:
        raise ConfigError("train.error_share and train.lowres_share cannot both be on: the map tiles the "
                          "working frames (set one of them to 0)")
    return int(round(tcfg.error_share * tcfg.batch_rays))


def init(frames: int, h: int, w: int, tile: int) -> np.ndarray:
    """The record before any step: [frames * tile rows * tile columns] float32 zeros (every tile
    equally likely: each holds only the floor)."""
    ty, tx = tile_grid(h, w, tile)
    return np.zeros(frames * ty * tx, np.float32)


def tile_ids(t, row, col, h: int, w: int, tile: int):
    """Flat tile ids [B] int32 of pixels (training frame t, row, col), each [B] int32."""
    ty, tx = tile_grid(h, w, tile)
    return (t * ty + row // tile) * tx + col // tile


def draw(errors, key, count: int, h: int, w: int, tile: int):
    """`count` pixels drawn from the record `errors` ([tiles] float32): a tile with probability
    proportional to errors + FLOOR x their mean (uniform over tiles while all are 0), by the
    inverse of the cumulative sum, then a pixel uniformly within it. Returns (t, row, col), each
    [count] int32."""
    ty, tx = tile_grid(h, w, tile)
    k_tile, k_row, k_col = jax.random.split(key, 3)
    mass = errors + FLOOR * jnp.mean(errors) + 1e-12
    cdf = jnp.cumsum(mass)
    u = jax.random.uniform(k_tile, (count,), jnp.float32) * cdf[-1]
    ids = jnp.minimum(jnp.searchsorted(cdf, u, side="right"), errors.shape[0] - 1).astype(jnp.int32)
    t, rest = ids // (ty * tx), ids % (ty * tx)
    top, left = (rest // tx) * tile, (rest % tx) * tile
    row = top + jax.random.randint(k_row, (count,), 0, jnp.minimum(tile, h - top))
    col = left + jax.random.randint(k_col, (count,), 0, jnp.minimum(tile, w - left))
    return t.astype(jnp.int32), row.astype(jnp.int32), col.astype(jnp.int32)


def update(errors, ids, ray_errors, weights):
    """The record after a step: each tile the batch reached with a weighted ray moves ERROR_RATE
    of the way to the mean error of those rays. errors: [tiles]; ids: [B] tile ids; ray_errors:
    [B] squared errors; weights: [B] loss weights (0: not counted). Returns [tiles] float32."""
    counted = (weights > 0).astype(jnp.float32)
    sums = jnp.zeros_like(errors).at[ids].add(ray_errors * counted)
    counts = jnp.zeros_like(errors).at[ids].add(counted)
    mean = sums / jnp.maximum(counts, 1.0)
    return jnp.where(counts > 0, (1.0 - ERROR_RATE) * errors + ERROR_RATE * mean, errors)
