"""Pure MLP radiance fields: `init(key, cfg) -> params`, `apply(params, cfg, x, viewdirs, ...)`.

The field is NeRF's MLP (Mildenhall et al. 2020): a ReLU trunk on the positionally encoded
point with the encoded input concatenated again after layer `skip`, a density head, and a
view-dependent colour branch fed by the trunk's feature, the encoded direction and (NeRF-W)
an appearance embedding. NeRF-W's transient head (Martin-Brualla et al. 2021) is optional:
from the trunk feature and a per-image transient embedding it predicts a transient density,
a transient colour and an uncertainty beta.

Parameters are a plain dict pytree: {"trunk": [{"w", "b"}, ...], "density": {"w", "b"},
"feature": {...}, "view": [...], "rgb": {...}, optional "transient": [...], "transient_out"}.
Weights are initialised by hand: He-normal for ReLU layers, Glorot-uniform for output heads.

Activations: density = softplus(raw + density_bias) (mip-NeRF's shifted softplus, default
bias -1) or relu(raw) (original NeRF); colour = sigmoid; transient density = softplus;
beta = softplus (NeRF-W adds beta_min after compositing, see models.py).

Inputs: the point `x` is expected already contracted and scaled by the caller (models.py
encodes z / R for contracted points, so the encoder sees |x| < 1 inside the far sphere).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxnerf_grid import coords


@dataclasses.dataclass(frozen=True)
class FieldConfig:
    """Shape of one MLP field.

    depth, width: trunk layers and their width (NeRF: 8 x 256; CPU demo: 4 x 128).
    skip: the encoded input is concatenated to the activations after this many trunk layers
      (NeRF: 4; 0 or >= depth disables it).
    pos_min_deg, pos_max_deg: positional-encoding octaves of the point (NeRF: 0..10).
    dir_max_deg: octaves of the view direction (NeRF: 4); use_viewdirs=False drops the branch
      input (colour from the feature only).
    view_width: hidden width of the colour branch (NeRF: width / 2).
    density_activation: "softplus" (with density_bias added first) or "relu".
    appearance_dim: size of the appearance embedding fed to the colour branch (0 = none).
    transient_dim: size of the transient embedding; > 0 adds NeRF-W's transient head with
      `transient_depth` layers of `transient_width`.
    """

    depth: int = 4
    width: int = 128
    skip: int = 2
    pos_min_deg: int = 0
    pos_max_deg: int = 10
    dir_max_deg: int = 4
    use_viewdirs: bool = True
    view_width: int = 64
    density_activation: str = "softplus"
    density_bias: float = -1.0
    appearance_dim: int = 0
    transient_dim: int = 0
    transient_depth: int = 4
    transient_width: int = 64


def _check(cfg: FieldConfig) -> None:
    if cfg.depth < 1 or cfg.width < 1:
        raise ValueError(f"FieldConfig: depth ({cfg.depth}) and width ({cfg.width}) must be >= 1")
    if cfg.density_activation not in ("softplus", "relu"):
        raise ValueError(f"FieldConfig: density_activation must be 'softplus' or 'relu', "
                         f"got {cfg.density_activation!r}")


def pos_input_size(cfg: FieldConfig) -> int:
    return coords.encoded_size(3, cfg.pos_min_deg, cfg.pos_max_deg)


def dir_input_size(cfg: FieldConfig) -> int:
    return coords.encoded_size(3, 0, cfg.dir_max_deg) if cfg.use_viewdirs else 0


def _he_dense(key, fan_in: int, fan_out: int) -> dict:
    """ReLU layer: He-normal weights (std sqrt(2 / fan_in)), zero bias."""
    w = jax.random.normal(key, (fan_in, fan_out), jnp.float32) * jnp.sqrt(2.0 / fan_in)
    return {"w": w, "b": jnp.zeros((fan_out,), jnp.float32)}


def _glorot_dense(key, fan_in: int, fan_out: int) -> dict:
    """Linear output layer: Glorot-uniform weights (limit sqrt(6 / (in + out))), zero bias."""
    limit = jnp.sqrt(6.0 / (fan_in + fan_out))
    w = jax.random.uniform(key, (fan_in, fan_out), jnp.float32, -limit, limit)
    return {"w": w, "b": jnp.zeros((fan_out,), jnp.float32)}


def _dense(layer: dict, x: jnp.ndarray) -> jnp.ndarray:
    return x @ layer["w"] + layer["b"]


def init(key, cfg: FieldConfig) -> dict:
    """Random parameters of a field. Returns a dict pytree of float32 arrays."""
    _check(cfg)
    keys = iter(jax.random.split(key, cfg.depth + cfg.transient_depth + 8))
    pos_size = pos_input_size(cfg)
    trunk, fan_in = [], pos_size
    for i in range(cfg.depth):
        trunk.append(_he_dense(next(keys), fan_in, cfg.width))
        fan_in = cfg.width + (pos_size if i + 1 == cfg.skip and cfg.skip < cfg.depth else 0)
    params = {
        "trunk": trunk,
        "density": _glorot_dense(next(keys), cfg.width, 1),
        "feature": _glorot_dense(next(keys), cfg.width, cfg.width),
        "view": [_he_dense(next(keys), cfg.width + dir_input_size(cfg) + cfg.appearance_dim,
                           cfg.view_width)],
        "rgb": _glorot_dense(next(keys), cfg.view_width, 3),
    }
    if cfg.transient_dim > 0:
        layers, fan_in = [], cfg.width + cfg.transient_dim
        for _ in range(cfg.transient_depth):
            layers.append(_he_dense(next(keys), fan_in, cfg.transient_width))
            fan_in = cfg.transient_width
        params["transient"] = layers
        # outputs: transient density (1), transient colour (3), uncertainty beta (1)
        params["transient_out"] = _glorot_dense(next(keys), cfg.transient_width, 5)
    return params


def apply(params: dict, cfg: FieldConfig, x: jnp.ndarray, viewdirs: jnp.ndarray | None = None,
          appearance: jnp.ndarray | None = None, transient: jnp.ndarray | None = None) -> dict:
    """Evaluates the field at points.

    x: [..., 3] points (already contracted / scaled); viewdirs: [..., 3] unit directions
    (required when cfg.use_viewdirs); appearance: [..., appearance_dim] or None (zeros);
    transient: [..., transient_dim] (required when the field has a transient head).
    Returns dict: rgb [..., 3] in (0, 1), sigma [...] >= 0; with a transient head also
    transient_rgb [..., 3], transient_sigma [...] >= 0, beta [...] > 0 (without beta_min).
    """
    encoded = coords.positional_encoding(x, cfg.pos_min_deg, cfg.pos_max_deg)
    h = encoded
    for i, layer in enumerate(params["trunk"]):
        h = jax.nn.relu(_dense(layer, h))
        if i + 1 == cfg.skip and cfg.skip < cfg.depth:
            h = jnp.concatenate([h, encoded], axis=-1)
    raw_density = _dense(params["density"], h)[..., 0]
    if cfg.density_activation == "softplus":
        sigma = jax.nn.softplus(raw_density + cfg.density_bias)
    else:
        sigma = jax.nn.relu(raw_density)
    feature = _dense(params["feature"], h)
    branch = [feature]
    if cfg.use_viewdirs:
        if viewdirs is None:
            raise ValueError("fields.apply: this field uses view directions; pass viewdirs")
        dirs = jnp.broadcast_to(viewdirs, x.shape)
        branch.append(coords.positional_encoding(dirs, 0, cfg.dir_max_deg))
    if cfg.appearance_dim > 0:
        if appearance is None:
            appearance = jnp.zeros((cfg.appearance_dim,), x.dtype)
        branch.append(jnp.broadcast_to(appearance, (*x.shape[:-1], cfg.appearance_dim)))
    v = jnp.concatenate(branch, axis=-1)
    for layer in params["view"]:
        v = jax.nn.relu(_dense(layer, v))
    out = {"rgb": jax.nn.sigmoid(_dense(params["rgb"], v)), "sigma": sigma}
    if cfg.transient_dim > 0:
        if transient is None:
            raise ValueError("fields.apply: this field has a transient head; pass transient")
        t = jnp.concatenate([feature, jnp.broadcast_to(transient, (*x.shape[:-1], cfg.transient_dim))],
                            axis=-1)
        for layer in params["transient"]:
            t = jax.nn.relu(_dense(layer, t))
        raw = _dense(params["transient_out"], t)
        out["transient_sigma"] = jax.nn.softplus(raw[..., 0])
        out["transient_rgb"] = jax.nn.sigmoid(raw[..., 1:4])
        out["beta"] = jax.nn.softplus(raw[..., 4])
    return out


def num_params(params) -> int:
    """Total number of scalars in a parameter pytree."""
    return int(sum(x.size for x in jax.tree_util.tree_leaves(params)))
