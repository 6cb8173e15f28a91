"""Dense layers and heads shared by every field kind (plain dict pytrees).

`he_dense` / `glorot_dense` initialise one layer {"w": [in, out], "b": [out]}; `dense` applies
it. `transient_init` / `transient_apply` are NeRF-W's transient head (Martin-Brualla et al.
2021): from a field's feature and a per-image transient embedding, a transient density, a
transient colour and an uncertainty beta. `activate_density` is the density activation of
every field.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnerf_grid.nerf import coords

DENSITY_ACTIVATIONS = ("softplus", "relu", "exp")


def he_dense(key, fan_in: int, fan_out: int) -> dict:
    """ReLU layer: He-normal weights (std sqrt(2 / fan_in)), zero bias."""
    w = jax.random.normal(key, (fan_in, fan_out), jnp.float32) * jnp.sqrt(2.0 / fan_in)
    return {"w": w, "b": jnp.zeros((fan_out,), jnp.float32)}


def glorot_dense(key, fan_in: int, fan_out: int) -> dict:
    """Linear output layer: Glorot-uniform weights (limit sqrt(6 / (in + out))), zero bias."""
    limit = jnp.sqrt(6.0 / (fan_in + fan_out))
    w = jax.random.uniform(key, (fan_in, fan_out), jnp.float32, -limit, limit)
    return {"w": w, "b": jnp.zeros((fan_out,), jnp.float32)}


def dense(layer: dict, x: jnp.ndarray) -> jnp.ndarray:
    """x: [..., in] -> [..., out]."""
    return x @ layer["w"] + layer["b"]


@jax.custom_jvp
def trunc_exp(x: jnp.ndarray) -> jnp.ndarray:
    """exp(x) whose derivative is exp(clip(x, -15, 15)) (Instant-NGP's density activation:
    large densities without exploding gradients)."""
    return jnp.exp(x)


@trunc_exp.defjvp
def _trunc_exp_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return jnp.exp(x), dx * jnp.exp(jnp.clip(x, -15.0, 15.0))


def activate_density(raw: jnp.ndarray, activation: str, bias: float) -> jnp.ndarray:
    """raw: [...] -> sigma [...] >= 0: softplus(raw + bias), relu(raw) or trunc_exp(raw + bias)."""
    if activation == "softplus":
        return jax.nn.softplus(raw + bias)
    if activation == "exp":
        return trunc_exp(jnp.minimum(raw + bias, 30.0))
    return jax.nn.relu(raw)


def transient_init(key, feature_dim: int, transient_dim: int, depth: int, width: int) -> dict:
    """{"transient": [depth layers], "transient_out": {w: [width, 5], b}}."""
    keys = jax.random.split(key, depth + 1)
    layers, fan_in = [], feature_dim + transient_dim
    for i in range(depth):
        layers.append(he_dense(keys[i], fan_in, width))
        fan_in = width
    # outputs: transient density (1), transient colour (3), uncertainty beta (1)
    return {"transient": layers, "transient_out": glorot_dense(keys[-1], width, 5)}


def transient_apply(params: dict, feature: jnp.ndarray, transient: jnp.ndarray | None) -> dict:
    """feature: [..., C]; transient: [..., T] (broadcast). Returns transient_sigma [...] >= 0,
    transient_rgb [..., 3] in (0, 1), beta [...] > 0 (without beta_min)."""
    if transient is None:
        raise ValueError("fields.apply: this field has a transient head; pass transient")
    size = params["transient"][0]["w"].shape[0] - feature.shape[-1]
    t = jnp.concatenate([feature, jnp.broadcast_to(transient, (*feature.shape[:-1], size))], axis=-1)
    for layer in params["transient"]:
        t = jax.nn.relu(dense(layer, t))
    raw = dense(params["transient_out"], t)
    return {"transient_sigma": jax.nn.softplus(raw[..., 0]), "transient_rgb": jax.nn.sigmoid(raw[..., 1:4]),
            "beta": jax.nn.softplus(raw[..., 4])}


def dir_input_size(cfg) -> int:
    """Width of the encoded view direction in the colour branch's input (0 without viewdirs)."""
    return coords.encoded_size(3, 0, cfg.dir_max_deg) if cfg.use_viewdirs else 0


def first_colour_layer(layer: dict, feature: jnp.ndarray, viewdirs, appearance, cfg) -> jnp.ndarray:
    """The colour branch's first layer before its activation: `dense(layer, [feature, encoded
    direction, appearance embedding (zeros without)])`, with the direction's and the
    appearance's parts computed at their own shape and broadcast.

    The layer's weight rows are [feature C | encoded direction D | appearance A], so
    W [f, d, a] + b = W_f f + W_d d + W_a a + b. A ray's direction (viewdirs [rays, 1, 3]
    against feature [rays, samples, C]) is encoded and multiplied once per ray instead of once
    per sample (the sines and cosines and D x width of the layer's multiply-adds per
    sample). Same value up to float rounding. viewdirs and appearance broadcast against feature's
    leading shape.
    feature: [..., C] -> [..., width]."""
    w = layer["w"]
    c = feature.shape[-1]
    d = dir_input_size(cfg)
    out = feature @ w[:c] + layer["b"]
    if cfg.use_viewdirs:
        if viewdirs is None:
            raise ValueError("fields.apply: this field uses view directions; pass viewdirs")
        out = out + coords.positional_encoding(viewdirs, 0, cfg.dir_max_deg) @ w[c:c + d]
    if cfg.appearance_dim > 0 and appearance is not None:
        out = out + appearance @ w[c + d:]
    return jnp.broadcast_to(out, (*feature.shape[:-1], w.shape[-1]))


def init_colour_branch(view_key, rgb_key, fan_in: int, depth: int, width: int) -> dict:
    """{"view": [depth ReLU layers of width], "rgb": {w: [width, 3], b}} on a [..., fan_in]
    input; the view layers from split(view_key, depth), the output layer from rgb_key."""
    keys = jax.random.split(view_key, depth)
    view = []
    for i in range(depth):
        view.append(he_dense(keys[i], fan_in, width))
        fan_in = width
    return {"view": view, "rgb": glorot_dense(rgb_key, width, 3)}


def radiance_outputs(params: dict, cfg, sigma: jnp.ndarray, feature: jnp.ndarray, viewdirs, appearance,
                     transient) -> dict:
    """What every field kind returns, from its density and feature: the colour branch
    (`first_colour_layer` -> "view" layers -> sigmoid "rgb") and, with cfg.transient_dim > 0,
    NeRF-W's transient head. sigma: [...]; feature: [..., C]. Returns fields.apply's dict."""
    colour_layers = [*params["view"], params["rgb"]]
    v = first_colour_layer(colour_layers[0], feature, viewdirs, appearance, cfg)
    for layer in colour_layers[1:]:
        v = dense(layer, jax.nn.relu(v))
    out = {"rgb": jax.nn.sigmoid(v), "sigma": sigma}
    if cfg.transient_dim > 0:
        out.update(transient_apply(params, feature, transient))
    return out
