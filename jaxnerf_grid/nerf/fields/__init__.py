"""Radiance fields behind one seam: `init(key, cfg) -> params`, `apply(params, cfg, x, ...)`.

`model.field` is a tagged choice (config/schema.py, "Tagged unions"): a `Config` of one field
module, chosen by its `kind`, each with only its own keys:

  {"kind": "mlp", ...}   fields/mlp.py, NeRF's MLP on positional encoding
  {"kind": "grid", ...}  fields/grid.py, a multiresolution hash encoding with small MLPs

Each kind's module has the same functions, called here through `KINDS[cfg.kind]`: `Config`,
`check(cfg)`, `init(key, cfg)`, `apply(params, cfg, x, ...)`, `encoding_floats(cfg)`,
`describe(cfg)`. A new kind is one module, added to KINDS and to `FieldConfig`. The keys every
kind shares, and the reading of older configs' single field layout, are in fields/base.py.
fields/proposal.py is the density-only field of proposal sampling. Every kind takes the same
inputs and returns the same outputs, so every method (ours, nerf, nerfw; models.py) runs with
every kind.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnerf_grid.nerf.fields import grid, hashgrid, mlp, proposal
from jaxnerf_grid.nerf.fields.hashgrid import HashConfig
from jaxnerf_grid.nerf.fields.mlp import dir_input_size, pos_input_size

KINDS = {mlp.KIND: mlp, grid.KIND: grid}
FIELD_KINDS = tuple(KINDS)

FieldConfig = mlp.Config | grid.Config

__all__ = ["FIELD_KINDS", "FieldConfig", "HashConfig", "KINDS", "apply", "check", "describe", "dir_input_size",
           "encoding_floats", "grid", "hashgrid", "init", "mlp", "module", "num_params", "pos_input_size",
           "proposal"]


def module(cfg: FieldConfig):
    """The module of a field config's kind."""
    if cfg.kind not in KINDS:
        raise ValueError(f"FieldConfig: unknown kind {cfg.kind!r}; choose from {list(KINDS)}")
    return KINDS[cfg.kind]


def check(cfg: FieldConfig) -> None:
    """Checks a field config (the hash encoding too, for kind "grid"); raises ValueError
    naming the setting."""
    module(cfg).check(cfg)


def encoding_floats(cfg: FieldConfig) -> int:
    """Floats of one sample's encoding (the encoded point, or a grid's gathered features)."""
    return module(cfg).encoding_floats(cfg)


def describe(cfg: FieldConfig) -> str:
    """One line: the field's kind and shape."""
    return module(cfg).describe(cfg)


def init(key, cfg: FieldConfig) -> dict:
    """Random parameters of a field of kind cfg.kind (a dict pytree of float32 arrays)."""
    check(cfg)
    return module(cfg).init(key, cfg)


def apply(params: dict, cfg: FieldConfig, x: jnp.ndarray, viewdirs: jnp.ndarray | None = None,
          appearance: jnp.ndarray | None = None, transient: jnp.ndarray | None = None) -> dict:
    """Evaluates the field at points.

    x: [..., 3] points (already contracted / scaled, |x| <= 1); viewdirs: [..., 3] unit
    directions (required when cfg.use_viewdirs); appearance: [..., appearance_dim] or None
    (zeros); transient: [..., transient_dim] (required when the field has a transient head).
    Returns dict: rgb [..., 3] in (0, 1), sigma [...] >= 0; with a transient head also
    transient_rgb [..., 3], transient_sigma [...] >= 0, beta [...] > 0 (without beta_min).
    """
    return module(cfg).apply(params, cfg, x, viewdirs, appearance, transient)


def num_params(params) -> int:
    """Total number of scalars in a parameter pytree."""
    return int(sum(x.size for x in jax.tree_util.tree_leaves(params)))
