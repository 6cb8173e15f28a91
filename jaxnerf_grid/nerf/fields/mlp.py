"""NeRF's MLP field (Mildenhall et al. 2020): `init(key, cfg)`, `apply(params, cfg, x, ...)`.

A ReLU trunk on the positionally encoded point with the encoded input concatenated again after
layer `skip`, a density head, and a view-dependent colour branch fed by the trunk's feature,
the encoded direction and (NeRF-W) an appearance embedding; NeRF-W's optional transient head
(fields/layers.py) reads the trunk feature and a per-image transient embedding.

Parameters: {"trunk": [{"w", "b"}, ...], "density": {"w", "b"}, "feature": {...},
"view": [...], "rgb": {...}, optional "transient": [...], "transient_out"}.
He-normal for ReLU layers, Glorot-uniform for output heads.

Inputs: the point `x` is already contracted and scaled by the caller (models.py encodes z / R
for contracted points, so the encoder sees |x| < 1 inside the far sphere).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnerf_grid.nerf import coords
from jaxnerf_grid.nerf.fields import layers
from jaxnerf_grid.nerf.fields.base import FieldConfig


def pos_input_size(cfg: FieldConfig) -> int:
    return coords.encoded_size(3, cfg.pos_min_deg, cfg.pos_max_deg)


dir_input_size = layers.dir_input_size


def init(key, cfg: FieldConfig) -> dict:
    """Random parameters of an MLP field. Returns a dict pytree of float32 arrays."""
    keys = iter(jax.random.split(key, cfg.depth + cfg.view_depth + 8))
    pos_size = pos_input_size(cfg)
    trunk, fan_in = [], pos_size
    for i in range(cfg.depth):
        trunk.append(layers.he_dense(next(keys), fan_in, cfg.width))
        fan_in = cfg.width + (pos_size if i + 1 == cfg.skip and cfg.skip < cfg.depth else 0)
    view, fan_in = [], cfg.width + dir_input_size(cfg) + cfg.appearance_dim
    for _ in range(cfg.view_depth):
        view.append(layers.he_dense(next(keys), fan_in, cfg.view_width))
        fan_in = cfg.view_width
    params = {
        "trunk": trunk,
        "density": layers.glorot_dense(next(keys), cfg.width, 1),
        "feature": layers.glorot_dense(next(keys), cfg.width, cfg.width),
        "view": view,
        "rgb": layers.glorot_dense(next(keys), cfg.view_width, 3),
    }
    if cfg.transient_dim > 0:
        params.update(layers.transient_init(next(keys), cfg.width, cfg.transient_dim, cfg.transient_depth,
                                            cfg.transient_width))
    return params


def apply(params: dict, cfg: FieldConfig, x: jnp.ndarray, viewdirs: jnp.ndarray | None = None,
          appearance: jnp.ndarray | None = None, transient: jnp.ndarray | None = None) -> dict:
    """Evaluates the field at points; see fields.apply for the arguments and outputs."""
    encoded = coords.positional_encoding(x, cfg.pos_min_deg, cfg.pos_max_deg)
    h = encoded
    for i, layer in enumerate(params["trunk"]):
        h = jax.nn.relu(layers.dense(layer, h))
        if i + 1 == cfg.skip and cfg.skip < cfg.depth:
            h = jnp.concatenate([h, encoded], axis=-1)
    sigma = layers.activate_density(layers.dense(params["density"], h)[..., 0], cfg.density_activation,
                                    cfg.density_bias)
    return layers.radiance_outputs(params, cfg, sigma, layers.dense(params["feature"], h), viewdirs, appearance,
                                   transient)
