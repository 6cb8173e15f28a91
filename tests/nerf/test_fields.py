"""fields.py against a NumPy MLP written here from NeRF's description."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.nerf import fields
from jaxnerf_grid.nerf.fields import layers


def _np_encode(x, lo, hi):
    feats_sin, feats_cos = [], []
    for k in range(lo, hi):
        feats_sin.append(np.sin(2.0 ** k * x))
        feats_cos.append(np.cos(2.0 ** k * x))
    # order: all (k, d) sines, then all cosines, then identity
    return np.concatenate(feats_sin + feats_cos + [x], axis=-1)


def _np_softplus(x):
    return np.log1p(np.exp(-np.abs(x))) + np.maximum(x, 0)


def _np_field(p, cfg, x, d, app=None, tr=None):
    p = jax.tree_util.tree_map(np.asarray, p)
    enc = _np_encode(x, cfg.pos_min_deg, cfg.pos_max_deg)
    h = enc
    for i, layer in enumerate(p["trunk"]):
        h = np.maximum(h @ layer["w"] + layer["b"], 0)
        if i + 1 == cfg.skip:
            h = np.concatenate([h, enc], -1)
    raw = (h @ p["density"]["w"] + p["density"]["b"])[..., 0]
    sigma = _np_softplus(raw + cfg.density_bias) if cfg.density_activation == "softplus" else np.maximum(raw, 0)
    feat = h @ p["feature"]["w"] + p["feature"]["b"]
    parts = [feat, _np_encode(d, 0, cfg.dir_max_deg)]
    if app is not None:
        parts.append(np.broadcast_to(app, (*x.shape[:-1], app.shape[-1])))
    v = np.maximum(np.concatenate(parts, -1) @ p["view"][0]["w"] + p["view"][0]["b"], 0)
    rgb = 1 / (1 + np.exp(-(v @ p["rgb"]["w"] + p["rgb"]["b"])))
    out = {"rgb": rgb, "sigma": sigma}
    if tr is not None:
        t = np.concatenate([feat, np.broadcast_to(tr, (*x.shape[:-1], tr.shape[-1]))], -1)
        for layer in p["transient"]:
            t = np.maximum(t @ layer["w"] + layer["b"], 0)
        raw = t @ p["transient_out"]["w"] + p["transient_out"]["b"]
        out["transient_sigma"] = _np_softplus(raw[..., 0])
        out["beta"] = _np_softplus(raw[..., 4])
        out["transient_rgb"] = 1 / (1 + np.exp(-raw[..., 1:4]))
    return out


@pytest.mark.parametrize("activation", ["softplus", "relu"])
def test_apply_matches_numpy_mlp(activation):
    cfg = fields.mlp.Config(depth=4, width=32, skip=2, pos_max_deg=6, dir_max_deg=3,
                             view_width=16, density_activation=activation)
    params = fields.init(jax.random.PRNGKey(0), cfg)
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (5, 7, 3)).astype(np.float32)
    d = rng.normal(size=(5, 7, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    out = fields.apply(params, cfg, jnp.asarray(x), jnp.asarray(d))
    ref = _np_field(params, cfg, x.astype(np.float64), d.astype(np.float64))
    assert out["rgb"].shape == (5, 7, 3) and out["sigma"].shape == (5, 7)
    np.testing.assert_allclose(out["rgb"], ref["rgb"], atol=2e-5)
    np.testing.assert_allclose(out["sigma"], ref["sigma"], rtol=1e-4, atol=1e-5)
    assert np.all(np.asarray(out["sigma"]) >= 0)


def test_transient_and_appearance_heads_match_numpy():
    cfg = fields.mlp.Config(depth=3, width=16, skip=1, pos_max_deg=4, dir_max_deg=2, view_width=8,
                             appearance_dim=5, transient_dim=4, transient_depth=2, transient_width=8)
    params = fields.init(jax.random.PRNGKey(1), cfg)
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (6, 3)).astype(np.float32)
    d = np.tile(np.array([[0, 0, 1.0]], np.float32), (6, 1))
    app = rng.normal(size=(5,)).astype(np.float32)
    tr = rng.normal(size=(4,)).astype(np.float32)
    out = fields.apply(params, cfg, jnp.asarray(x), jnp.asarray(d), jnp.asarray(app), jnp.asarray(tr))
    ref = _np_field(params, cfg, x.astype(np.float64), d.astype(np.float64), app, tr)
    for name in ("rgb", "sigma", "transient_sigma", "transient_rgb", "beta"):
        np.testing.assert_allclose(out[name], ref[name], rtol=1e-4, atol=2e-5, err_msg=name)
    assert np.all(np.asarray(out["beta"]) > 0)


def test_parameter_count_closed_form():
    cfg = fields.mlp.Config(depth=4, width=64, skip=2, pos_max_deg=10, dir_max_deg=4, view_width=32)
    pos, dirs = 3 + 3 * 2 * 10, 3 + 3 * 2 * 4
    expected = ((pos * 64 + 64) + (64 * 64 + 64) + ((64 + pos) * 64 + 64) + (64 * 64 + 64)
                + (64 + 1) + (64 * 64 + 64) + ((64 + dirs) * 32 + 32) + (32 * 3 + 3))
    assert fields.num_params(fields.init(jax.random.PRNGKey(0), cfg)) == expected


def test_init_scales_he_and_glorot():
    cfg = fields.mlp.Config(depth=2, width=256, skip=0, pos_max_deg=10)
    params = fields.init(jax.random.PRNGKey(3), cfg)
    w = np.asarray(params["trunk"][1]["w"])
    assert abs(w.std() - np.sqrt(2.0 / 256)) < 0.05 * np.sqrt(2.0 / 256)
    g = np.asarray(params["feature"]["w"])
    limit = np.sqrt(6.0 / 512)
    assert g.max() <= limit and g.min() >= -limit and abs(g.std() - limit / np.sqrt(3)) < 0.05 * limit


def test_gradients_finite_and_errors():
    cfg = fields.mlp.Config(depth=2, width=8, skip=1, pos_max_deg=3, view_width=8)
    params = fields.init(jax.random.PRNGKey(0), cfg)
    x = jnp.ones((4, 3)) * 0.3
    d = jnp.tile(jnp.array([[1.0, 0, 0]]), (4, 1))
    g = jax.grad(lambda p: jnp.sum(fields.apply(p, cfg, x, d)["rgb"]))(params)
    assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(g))
    with pytest.raises(ValueError, match="viewdirs"):
        fields.apply(params, cfg, x)
    with pytest.raises(ValueError, match="density_activation"):
        fields.init(jax.random.PRNGKey(0), dataclasses.replace(cfg, density_activation="exp"))


@pytest.mark.parametrize("view_depth,use_viewdirs,app_shape", [(1, True, None), (2, True, (5,)),
                                                                 (3, True, (4, 1, 5)), (2, False, (5,))])
def test_colour_branch_with_one_direction_per_ray_matches_the_concatenated_input(view_depth, use_viewdirs, app_shape):
    """A ray's direction [rays, 1, 3] against its samples' features [rays, samples, C], as
    models.render_rays passes it (and an appearance code per ray or one for all): the colour
    branch equals NumPy's MLP on the input concatenated at every sample."""
    cfg = fields.grid.Config(view_depth=view_depth, view_width=16, dir_max_deg=3,
                             use_viewdirs=use_viewdirs, appearance_dim=5 if app_shape else 0, geo_features=6)
    params = fields.init(jax.random.PRNGKey(2), cfg)
    rng = np.random.default_rng(2)
    feature = rng.normal(size=(4, 7, 6)).astype(np.float32)
    d = rng.normal(size=(4, 1, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    app = rng.normal(size=app_shape).astype(np.float32) if app_shape else None
    out = layers.radiance_outputs(params, cfg, jnp.zeros((4, 7)), jnp.asarray(feature), jnp.asarray(d),
                                  None if app is None else jnp.asarray(app), None)
    p = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), params)
    parts = [feature.astype(np.float64)]
    if use_viewdirs:
        parts.append(_np_encode(np.broadcast_to(d, (4, 7, 3)).astype(np.float64), 0, 3))
    if app is not None:
        parts.append(np.broadcast_to(app, (4, 7, 5)).astype(np.float64))
    v = np.concatenate(parts, -1)
    assert v.shape[-1] == p["view"][0]["w"].shape[0]
    for layer in p["view"]:
        v = np.maximum(v @ layer["w"] + layer["b"], 0)
    rgb = 1 / (1 + np.exp(-(v @ p["rgb"]["w"] + p["rgb"]["b"])))
    assert out["rgb"].shape == (4, 7, 3)
    np.testing.assert_allclose(out["rgb"], rgb, atol=2e-6)
