"""Density-only proposal field (mip-NeRF 360's proposal MLP, here a small hash grid).

It only has to say where along a ray the main field's weights may be, so it is a grid field
without a colour branch: `init(key, cfg) -> params`, `density(params, cfg, x) -> sigma`.
cfg is a grid.Config (its colour settings are unused); x: [..., 3] in [-1, 1].
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxnerf_grid.nerf.fields import grid, layers


def check(cfg: grid.Config) -> None:
    if not isinstance(cfg, grid.Config) or cfg.kind != grid.KIND:
        raise ValueError(f"proposal field: kind must be 'grid', got {cfg.kind!r}")
    grid.check(cfg)


def init(key, cfg: grid.Config) -> dict:
    """{"encoding", "trunk", "density": [width, 1]}."""
    check(cfg)
    return grid.init_trunk(key, cfg, 1)


def density(params: dict, cfg: grid.Config, x: jnp.ndarray) -> jnp.ndarray:
    """x: [..., 3] -> sigma [...] >= 0."""
    return layers.activate_density(grid.apply_trunk(params, cfg, x)[..., 0], cfg.density_activation,
                                   cfg.density_bias)
