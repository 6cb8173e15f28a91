"""NeRF's MLP field (Mildenhall et al. 2020): `Config`, `init(key, cfg)`, `apply(params, cfg, x, ...)`.

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

import dataclasses
import typing

import jax
import jax.numpy as jnp

from jaxnerf_grid.config import schema as config
from jaxnerf_grid.nerf import coords
from jaxnerf_grid.nerf.fields import base, layers

KIND = "mlp"


@dataclasses.dataclass(frozen=True)
class Config(base.FieldBase):
    """model.field = {"kind": "mlp", ...}: base.FieldBase's keys and

    skip: the encoded input is concatenated after this many trunk layers (0 or >= depth
      disables it).
    pos_min_deg, pos_max_deg: positional-encoding octaves of the point (NeRF: 0..10).
    """

    kind: str = KIND
    skip: int = 2
    pos_min_deg: int = 0
    pos_max_deg: int = 10

    RANGES: typing.ClassVar[dict] = {**base.FieldBase.RANGES, "skip": config.NONNEGATIVE,
                                     "pos_min_deg": config.NONNEGATIVE, "pos_max_deg": config.NONNEGATIVE}

    @staticmethod
    def upgrade_dict(data: dict) -> dict:
        """An older field dict (every kind's keys) as an MLP's (base.drop_other_kinds)."""
        return base.drop_other_kinds(data, KIND)


def check(cfg: Config) -> None:
    """Raises ValueError naming the setting (an MLP needs a trunk: depth >= 1)."""
    base.check_shared(cfg, 1, ("softplus", "relu"))


def pos_input_size(cfg: Config) -> int:
    return coords.encoded_size(3, cfg.pos_min_deg, cfg.pos_max_deg)


def encoding_floats(cfg: Config) -> int:
    """Floats of one sample's encoding (train.loop.field_floats): the encoded point."""
    return pos_input_size(cfg)


def describe(cfg: Config) -> str:
    """One line: the field's kind and shape (report/markdown.py)."""
    return (f"MLP {cfg.depth} x {cfg.width} (skip after {cfg.skip}), PE "
            f"{cfg.pos_max_deg} octaves, view dirs {cfg.use_viewdirs}")


dir_input_size = layers.dir_input_size


def init(key, cfg: Config) -> dict:
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


def apply(params: dict, cfg: Config, x: jnp.ndarray, viewdirs: jnp.ndarray | None = None,
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
