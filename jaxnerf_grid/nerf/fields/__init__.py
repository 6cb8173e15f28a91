"""Radiance fields behind one seam: `init(key, cfg) -> params`, `apply(params, cfg, x, ...)`.

`cfg.kind` picks the module: "mlp" (fields/mlp.py, NeRF's MLP on positional encoding) or
"grid" (fields/grid.py, a multiresolution hash encoding with small MLPs). A new kind is one
module with `init` and `apply`, added to `KINDS`. fields/proposal.py is the density-only field
of proposal sampling. Every kind takes the same inputs and returns the same outputs, so every
method (ours, nerf, nerfw; models.py) runs with every kind.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnerf_grid.nerf.fields import grid, hashgrid, mlp, proposal
from jaxnerf_grid.nerf.fields.base import FIELD_KINDS, FieldConfig, check
from jaxnerf_grid.nerf.fields.hashgrid import HashConfig
from jaxnerf_grid.nerf.fields.mlp import dir_input_size, pos_input_size

KINDS = {"mlp": mlp, "grid": grid}

__all__ = ["FIELD_KINDS", "FieldConfig", "HashConfig", "KINDS", "apply", "check", "dir_input_size", "grid",
           "hashgrid", "init", "mlp", "num_params", "pos_input_size", "proposal"]


def init(key, cfg: FieldConfig) -> dict:
    """Random parameters of a field of kind cfg.kind (a dict pytree of float32 arrays)."""
    check(cfg)
    return KINDS[cfg.kind].init(key, cfg)


def apply(params: dict, cfg: FieldConfig, x: jnp.ndarray, viewdirs: jnp.ndarray | None = None,
          appearance: jnp.ndarray | None = None, transient: jnp.ndarray | None = None) -> dict:
    """Evaluates the field at points.

    x: [..., 3] points (already contracted / scaled, |x| <= 1); viewdirs: [..., 3] unit
    directions (required when cfg.use_viewdirs); appearance: [..., appearance_dim] or None
    (zeros); transient: [..., transient_dim] (required when the field has a transient head).
    Returns dict: rgb [..., 3] in (0, 1), sigma [...] >= 0; with a transient head also
    transient_rgb [..., 3], transient_sigma [...] >= 0, beta [...] > 0 (without beta_min).
    """
    return KINDS[cfg.kind].apply(params, cfg, x, viewdirs, appearance, transient)


def num_params(params) -> int:
    """Total number of scalars in a parameter pytree."""
    return int(sum(x.size for x in jax.tree_util.tree_leaves(params)))
