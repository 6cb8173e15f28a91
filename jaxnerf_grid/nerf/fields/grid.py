"""Hash-grid radiance field (Instant-NGP style): `init(key, cfg)`, `apply(params, cfg, x, ...)`.

    h     = hashgrid.encode(x)                       [..., L * F]   (fields/hashgrid.py)
    trunk = `depth` ReLU layers of `width` on h, then one linear layer -> 1 + geo_features
    sigma = activation(out[0] + density_bias)        ("exp": truncated exponential)
    rgb   = sigmoid(colour MLP([geo feature, encoded direction, appearance]))
            (`view_depth` ReLU layers of `view_width`)
    NeRF-W's transient head (fields/layers.py) reads the geo feature and the transient embedding.

Parameters: {"encoding": {"table"}, "trunk": [...], "density": {...}, "view": [...],
"rgb": {...}, optional "transient", "transient_out"}. The point x: [..., 3] in [-1, 1]
(models.field_inputs: contracted point / R).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnerf_grid.nerf.fields import hashgrid, layers
from jaxnerf_grid.nerf.fields.base import FieldConfig


def init_trunk(key, cfg: FieldConfig, outputs: int) -> dict:
    """Hash table and density trunk: {"encoding", "trunk": [depth layers], "density": [.., outputs]}."""
    keys = jax.random.split(key, cfg.depth + 2)
    trunk, fan_in = [], hashgrid.encoded_size(cfg.grid)
    for i in range(cfg.depth):
        trunk.append(layers.he_dense(keys[i], fan_in, cfg.width))
        fan_in = cfg.width
    return {"encoding": hashgrid.init(keys[-2], cfg.grid), "trunk": trunk,
            "density": layers.glorot_dense(keys[-1], fan_in, outputs)}


def apply_trunk(params: dict, cfg: FieldConfig, x: jnp.ndarray) -> jnp.ndarray:
    """x: [..., 3] -> the trunk's raw outputs [..., outputs] (density logit first)."""
    h = hashgrid.encode(params["encoding"], cfg.grid, x)
    for layer in params["trunk"]:
        h = jax.nn.relu(layers.dense(layer, h))
    return layers.dense(params["density"], h)


def init(key, cfg: FieldConfig) -> dict:
    """Random parameters of a grid field."""
    k_trunk, k_view, k_rgb, k_tr = jax.random.split(key, 4)
    params = init_trunk(k_trunk, cfg, 1 + cfg.geo_features)
    colour_inputs = cfg.geo_features + layers.dir_input_size(cfg) + cfg.appearance_dim
    params.update(layers.init_colour_branch(k_view, k_rgb, colour_inputs, cfg.view_depth, cfg.view_width))
    if cfg.transient_dim > 0:
        params.update(layers.transient_init(k_tr, cfg.geo_features, cfg.transient_dim, cfg.transient_depth,
                                            cfg.transient_width))
    return params


def apply(params: dict, cfg: FieldConfig, x: jnp.ndarray, viewdirs: jnp.ndarray | None = None,
          appearance: jnp.ndarray | None = None, transient: jnp.ndarray | None = None) -> dict:
    """Evaluates the field at points; see fields.apply for the arguments and outputs."""
    raw = apply_trunk(params, cfg, x)
    sigma = layers.activate_density(raw[..., 0], cfg.density_activation, cfg.density_bias)
    return layers.radiance_outputs(params, cfg, sigma, raw[..., 1:], viewdirs, appearance, transient)
