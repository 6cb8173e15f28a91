"""Hash-grid radiance field (Instant-NGP style): `Config`, `init(key, cfg)`, `apply(params, cfg, x, ...)`.

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

import dataclasses
import typing

import jax
import jax.numpy as jnp

from jaxnerf_grid.config import schema as config
from jaxnerf_grid.nerf.fields import base, hashgrid, layers
from jaxnerf_grid.nerf.fields.hashgrid import HashConfig

KIND = "grid"


@dataclasses.dataclass(frozen=True)
class Config(base.FieldBase):
    """model.field = {"kind": "grid", ...}: base.FieldBase's keys and

    grid: the hash encoding (fields/hashgrid.py); geo_features: width of the feature the
      density trunk hands to the colour branch.
    """

    kind: str = KIND
    grid: HashConfig = HashConfig()
    geo_features: int = 15

    RANGES: typing.ClassVar[dict] = {**base.FieldBase.RANGES, "geo_features": config.AT_LEAST_ONE}

    @staticmethod
    def upgrade_dict(data: dict) -> dict:
        """An older field dict (every kind's keys) as a grid's (base.drop_other_kinds)."""
        return base.drop_other_kinds(data, KIND)


def check(cfg: Config) -> None:
    """Raises ValueError naming the setting (the hash encoding's too; a grid may have no hidden
    trunk layer: depth >= 0)."""
    base.check_shared(cfg, 0, ("softplus", "relu", "exp"))
    hashgrid.check(cfg.grid, "grid")


def encoding_floats(cfg: Config) -> int:
    """Floats of one sample's encoding (train.loop.field_floats): the features and the 8 corners
    gathered per level."""
    return 9 * hashgrid.encoded_size(cfg.grid)


def describe(cfg: Config) -> str:
    """One line: the field's kind and shape (report/markdown.py)."""
    grid = cfg.grid
    return (f"hash grid, {grid.num_levels} levels x {grid.features_per_level} features, "
            f"table 2^{grid.log2_table_size}, resolution {grid.min_resolution}-"
            f"{grid.max_resolution}; MLPs {cfg.depth} x {cfg.width} (density), "
            f"{cfg.view_depth} x {cfg.view_width} (colour)")


def init_trunk(key, cfg: Config, outputs: int) -> dict:
    """Hash table and density trunk: {"encoding", "trunk": [depth layers], "density": [.., outputs]}."""
    keys = jax.random.split(key, cfg.depth + 2)
    trunk, fan_in = [], hashgrid.encoded_size(cfg.grid)
    for i in range(cfg.depth):
        trunk.append(layers.he_dense(keys[i], fan_in, cfg.width))
        fan_in = cfg.width
    return {"encoding": hashgrid.init(keys[-2], cfg.grid), "trunk": trunk,
            "density": layers.glorot_dense(keys[-1], fan_in, outputs)}


def apply_trunk(params: dict, cfg: Config, x: jnp.ndarray) -> jnp.ndarray:
    """x: [..., 3] -> the trunk's raw outputs [..., outputs] (density logit first)."""
    h = hashgrid.encode(params["encoding"], cfg.grid, x)
    for layer in params["trunk"]:
        h = jax.nn.relu(layers.dense(layer, h))
    return layers.dense(params["density"], h)


def init(key, cfg: Config) -> dict:
    """Random parameters of a grid field."""
    k_trunk, k_view, k_rgb, k_tr = jax.random.split(key, 4)
    params = init_trunk(k_trunk, cfg, 1 + cfg.geo_features)
    colour_inputs = cfg.geo_features + layers.dir_input_size(cfg) + cfg.appearance_dim
    params.update(layers.init_colour_branch(k_view, k_rgb, colour_inputs, cfg.view_depth, cfg.view_width))
    if cfg.transient_dim > 0:
        params.update(layers.transient_init(k_tr, cfg.geo_features, cfg.transient_dim, cfg.transient_depth,
                                            cfg.transient_width))
    return params


def apply(params: dict, cfg: Config, x: jnp.ndarray, viewdirs: jnp.ndarray | None = None,
          appearance: jnp.ndarray | None = None, transient: jnp.ndarray | None = None) -> dict:
    """Evaluates the field at points; see fields.apply for the arguments and outputs."""
    raw = apply_trunk(params, cfg, x)
    sigma = layers.activate_density(raw[..., 0], cfg.density_activation, cfg.density_bias)
    return layers.radiance_outputs(params, cfg, sigma, raw[..., 1:], viewdirs, appearance, transient)
