"""Multiresolution hash encoding (Instant-NGP, Müller et al. 2022) as pure functions.

A point u in the unit cube is looked up on L grids whose resolutions grow geometrically from
`min_resolution` to `max_resolution`. On level l with resolution N_l the point sits in the cell
with lower corner c = floor(u N_l) (clipped to N_l - 1), and its feature is the trilinear mix of
the F-vectors stored at the cell's 8 corners:

    f_l(u) = sum_k w_k(u) table_l[index_l(c + b_k)],   b_k in {0, 1}^3, sum_k w_k = 1

A level whose (N_l + 1)^3 vertices fit in its table (`2^log2_table_size` rows) is dense:
index = x + y (N_l + 1) + z (N_l + 1)^2, and the table holds exactly that many rows. Finer
levels are hashed: index = (x * 1 XOR y * 2654435761 XOR z * 805459861) mod 2^log2_table_size
(uint32 arithmetic, Instant-NGP's primes), so distinct vertices may collide.

All levels live in one table [sum of level sizes, F] with per-level row offsets, so the whole
encoding is one gather (and its gradient one scatter-add), the fastest layout on XLA:CPU.
The encoding of a point is the levels' features concatenated: [L * F].

Coordinates: the fields feed points x in [-1, 1]^3 (a contracted point divided by the far
radius R, see models.field_inputs); `encode` maps them to u = (x + 1) / 2.
"""

from __future__ import annotations

import dataclasses
import math
import typing

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.config import schema as config

PRIMES = (1, 2654435761, 805459861)


@dataclasses.dataclass(frozen=True)
class HashConfig:
    """num_levels L, features_per_level F, log2_table_size (rows per level at most 2^this),
    min_resolution, max_resolution: cells per axis of the coarsest and finest level (over the
    cube [-1, 1]^3), init_scale: table entries start U(-init_scale, init_scale)."""

    num_levels: int = 12
    features_per_level: int = 2
    log2_table_size: int = 17
    min_resolution: int = 16
    max_resolution: int = 1024
    init_scale: float = 1e-4

    # allowed values, checked by config.validate (docs/RELIABILITY.md)
    RANGES: typing.ClassVar[dict] = {
        "num_levels": config.AT_LEAST_ONE, "features_per_level": config.AT_LEAST_ONE,
        "log2_table_size": config.Range(1, 26), "min_resolution": config.AT_LEAST_ONE,
        "max_resolution": config.AT_LEAST_ONE, "init_scale": config.NONNEGATIVE}


def check(cfg: HashConfig, where: str = "grid") -> None:
    """Raises ValueError naming the bad setting."""
    if cfg.num_levels < 1 or cfg.features_per_level < 1:
        raise ValueError(f"{where}: num_levels and features_per_level must be >= 1")
    if not 1 <= cfg.log2_table_size <= 26:
        raise ValueError(f"{where}: log2_table_size must be in 1..26, got {cfg.log2_table_size}")
    if not 1 <= cfg.min_resolution <= cfg.max_resolution:
        raise ValueError(f"{where}: need 1 <= min_resolution <= max_resolution, got "
                         f"{cfg.min_resolution}, {cfg.max_resolution}")


def level_resolutions(cfg: HashConfig) -> list[int]:
    """Cells per axis of each level: floor(N_min * b^l), b = (N_max / N_min)^(1 / (L - 1))."""
    if cfg.num_levels == 1:
        return [int(cfg.min_resolution)]
    growth = math.exp((math.log(cfg.max_resolution) - math.log(cfg.min_resolution)) / (cfg.num_levels - 1))
    return [int(math.floor(cfg.min_resolution * growth ** level + 1e-6)) for level in range(cfg.num_levels)]


@dataclasses.dataclass(frozen=True)
class Layout:
    """Static description of the table: per level its resolution, whether it is dense, its
    number of rows and its first row in the shared table."""

    resolutions: tuple
    dense: tuple
    sizes: tuple
    offsets: tuple

    @property
    def total(self) -> int:
        return int(self.offsets[-1] + self.sizes[-1])


def layout(cfg: HashConfig) -> Layout:
    table = 2 ** cfg.log2_table_size
    res = level_resolutions(cfg)
    dense = tuple((r + 1) ** 3 <= table for r in res)
    sizes = tuple((r + 1) ** 3 if d else table for r, d in zip(res, dense))
    offsets = tuple(int(v) for v in np.concatenate([[0], np.cumsum(sizes)[:-1]]))
    return Layout(tuple(res), dense, sizes, offsets)


def init(key, cfg: HashConfig) -> dict:
    """{"table": [rows of all levels, F]} with entries U(-init_scale, init_scale)."""
    check(cfg)
    rows = layout(cfg).total
    return {"table": jax.random.uniform(key, (rows, cfg.features_per_level), jnp.float32,
                                        -cfg.init_scale, cfg.init_scale)}


CORNER_BITS = np.array([[(k >> axis) & 1 for axis in range(3)] for k in range(8)], np.int32)  # [8, 3]


def corners(cfg: HashConfig, u: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Table rows and trilinear weights of the 8 corners on every level.

    u: [..., 3] in [0, 1] (clipped). Returns (rows [..., L, 8] int32 into the shared table,
    weights [..., L, 8] summing to 1 over the corners). Corner k has offset bits
    (k & 1, (k >> 1) & 1, (k >> 2) & 1) on (x, y, z).
    """
    lay = layout(cfg)
    res = jnp.asarray(lay.resolutions, jnp.float32)                       # [L]
    u = jnp.clip(u, 0.0, 1.0)
    pos = u[..., None, :] * res[:, None]                                  # [..., L, 3]
    low = jnp.minimum(jnp.floor(pos), res[:, None] - 1.0)
    frac = pos - low                                                      # [..., L, 3] in [0, 1]
    bits = jnp.asarray(CORNER_BITS)                                       # [8, 3]
    vertex = (low[..., None, :].astype(jnp.int32) + bits).astype(jnp.uint32)  # [..., L, 8, 3]
    # Trilinear weights: prod over axes of frac (bit 1) or 1 - frac (bit 0).
    per_axis = jnp.where(bits == 1, frac[..., None, :], 1.0 - frac[..., None, :])
    weights = jnp.prod(per_axis, axis=-1)                                 # [..., L, 8]
    side = np.asarray(lay.resolutions, np.uint64) + 1
    strides = np.stack([np.ones_like(side), side, side * side], axis=-1)  # [L, 3]
    strides = jnp.asarray((strides % 2 ** 32).astype(np.uint32))
    dense_row = jnp.sum(vertex * strides[:, None, :], axis=-1, dtype=jnp.uint32)
    hashed = vertex * jnp.asarray(PRIMES, jnp.uint32)
    hashed_row = (hashed[..., 0] ^ hashed[..., 1] ^ hashed[..., 2]) & jnp.uint32(2 ** cfg.log2_table_size - 1)
    row = jnp.where(jnp.asarray(lay.dense)[:, None], dense_row, hashed_row)
    row = row.astype(jnp.int32) + jnp.asarray(lay.offsets, jnp.int32)[:, None]
    return row, weights


def _mix(weights: jnp.ndarray, feats: jnp.ndarray) -> jnp.ndarray:
    """weights: [..., L, 8]; feats: [..., L, 8, F] -> [..., L, F]."""
    return jnp.einsum("...lk,...lkf->...lf", weights, feats)


def computed_once(x: jnp.ndarray) -> jnp.ndarray:
    """x [..., D], unchanged in value (a matmul by the identity at full precision: exact for
    finite x), but materialised once.

    XLA:CPU fuses the elementwise chain that made the points (the ray warp's g^-1, the
    contraction, the PDF resampling's interpolation) into the fusions that compute the L x 8
    corner rows and weights, so that chain runs once per corner instead of once per point. For
    a cheap-looking chain such as the piecewise warp's (a select and a division) that made the
    whole training step 1.9x slower than with the log warp; a dot is not fused into its
    consumers, so it stops the recomputation. Measured side by side, with and without it, by
    `python -m benchmarks.throughput --configs demo-piecewise,demo-piecewise-fused,...`
    (a "-fused" case traces encode without this function; benchmarks/results/throughput_warps.json).
    """
    eye = jnp.eye(x.shape[-1], dtype=x.dtype)
    return jnp.einsum("...i,ij->...j", x, eye, precision=jax.lax.Precision.HIGHEST)


def encode(params: dict, cfg: HashConfig, x: jnp.ndarray) -> jnp.ndarray:
    """Hash-grid features of points. x: [..., 3] in [-1, 1] -> [..., L * F]."""
    rows, weights = corners(cfg, 0.5 * (computed_once(x) + 1.0))
    # One gather for all levels and corners; the einsum (not a broadcast product and a sum)
    # keeps XLA:CPU from fusing the gather into the reduction, which is 3x slower.
    mixed = _mix(weights, params["table"].at[rows].get(mode="promise_in_bounds"))
    return mixed.reshape(*x.shape[:-1], cfg.num_levels * cfg.features_per_level)


def encoded_size(cfg: HashConfig) -> int:
    return cfg.num_levels * cfg.features_per_level
