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

from jaxnerf_grid.fields import hashgrid, layers
from jaxnerf_grid.fields.base import FieldConfig


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
    keys = jax.random.split(k_view, cfg.view_depth)
    view, fan_in = [], cfg.geo_features + dirs_size(cfg) + cfg.appearance_dim
    for i in range(cfg.view_depth):
        view.append(layers.he_dense(keys[i], fan_in, cfg.view_width))
        fan_in = cfg.view_width
    params["view"] = view
    params["rgb"] = layers.glorot_dense(k_rgb, cfg.view_width, 3)
    if cfg.transient_dim > 0:
        params.update(layers.transient_init(k_tr, cfg.geo_features, cfg.transient_dim, cfg.transient_depth,
                                            cfg.transient_width))
    return params


def dirs_size(cfg: FieldConfig) -> int:
    from jaxnerf_grid import coords

    return coords.encoded_size(3, 0, cfg.dir_max_deg) if cfg.use_viewdirs else 0


def apply(params: dict, cfg: FieldConfig, x: jnp.ndarray, viewdirs: jnp.ndarray | None = None,
          appearance: jnp.ndarray | None = None, transient: jnp.ndarray | None = None) -> dict:
    """Evaluates the field at points; see fields.apply for the arguments and outputs."""
    raw = apply_trunk(params, cfg, x)
    sigma = layers.activate_density(raw[..., 0], cfg.density_activation, cfg.density_bias)
    feature = raw[..., 1:]
    v = layers.colour_inputs(feature, viewdirs, appearance, cfg.use_viewdirs, cfg.dir_max_deg, cfg.appearance_dim)
    for layer in params["view"]:
        v = jax.nn.relu(layers.dense(layer, v))
    out = {"rgb": jax.nn.sigmoid(layers.dense(params["rgb"], v)), "sigma": sigma}
    if cfg.transient_dim > 0:
        out.update(layers.transient_apply(params, feature, transient))
    return out
