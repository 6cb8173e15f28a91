"""NeRF-W's transient compositing, where the transient head joins the renderer, with non-zero
transient density and colour, against a per-sample loop written here.

NeRF-W (Martin-Brualla et al. 2021, Eq. 9-10; docs: `jaxnerf_grid/nerf/models.py`'s docstring): static
and transient densities share the transmittance
    T_i = exp(-sum_{j<i} (sigma_j + sigma_t,j) delta_j),
each adds its own colour with alpha 1 - exp(-sigma delta):
    C = sum_i T_i [(1 - e^{-sigma_i delta_i}) c_i + (1 - e^{-sigma_t,i delta_i}) c_t,i] + (1 - opacity) bg
    beta_hat = sum_i T_i (1 - e^{-sigma_t,i delta_i}) beta_i + beta_min
and the static picture (`rgb_static`, what evaluation shows) is the static field alone.
"""

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.nerf import fields, models, samplers

SMALL = fields.mlp.Config(depth=2, width=16, skip=1, pos_max_deg=4, dir_max_deg=2, view_width=8)
BACKGROUND = 0.2


def _analytic_field(params, cfg, x, viewdirs=None, appearance=None, transient=None):
    """A field whose every output varies along the ray and differs between channels: static
    density and colour from the position, transient density, colour (not the complement of
    the static one) and beta from the position and the transient embedding."""
    r = jnp.linalg.norm(x, axis=-1)
    out = {"sigma": 3.0 * jnp.exp(-((r - 0.8) ** 2) / 0.1),
           "rgb": jnp.stack([0.2 + 0.6 * jax.nn.sigmoid(x[..., 0]), 0.5 + 0.4 * jnp.sin(r),
                             0.3 * jnp.ones_like(r)], -1)}
    if cfg.transient_dim > 0:
        e = transient[..., 0]
        out["transient_sigma"] = 2.0 * jnp.exp(-((r - 1.4) ** 2) / 0.2) * (1.0 + e)
        out["transient_rgb"] = jnp.stack([0.9 * jnp.ones_like(r), 0.1 + 0.05 * r, jax.nn.sigmoid(x[..., 2])], -1)
        out["beta"] = 0.5 + r
    return out


def _loop(sig, rgb, tsig, trgb, beta, t_edges, beta_min):
    """One ray, sample by sample (float64): (mixed rgb, static rgb, beta_hat, transient opacity)."""
    trans, mixed, static, trans_s = 1.0, np.zeros(3), np.zeros(3), 1.0
    opacity, beta_hat, t_opacity, s_opacity = 0.0, 0.0, 0.0, 0.0
    for i in range(len(sig)):
        delta = t_edges[i + 1] - t_edges[i]
        a_s = 1.0 - np.exp(-sig[i] * delta)
        a_t = 1.0 - np.exp(-tsig[i] * delta)
        mixed += trans * (a_s * rgb[i] + a_t * trgb[i])
        opacity += trans * (a_s + a_t)
        t_opacity += trans * a_t
        beta_hat += trans * a_t * beta[i]
        trans *= np.exp(-(sig[i] + tsig[i]) * delta)
        static += trans_s * a_s * rgb[i]          # the static field alone
        s_opacity += trans_s * a_s
        trans_s *= 1.0 - a_s
    mixed += np.clip(1.0 - opacity, 0.0, 1.0) * BACKGROUND
    static += (1.0 - s_opacity) * BACKGROUND
    return mixed, static, beta_hat + beta_min, t_opacity


def test_transient_compositing_against_a_per_sample_loop(monkeypatch):
    cfg = models.ModelConfig(**{**models.method_defaults("nerfw"), "field": SMALL,
                                "sampler": samplers.hierarchical.Config(samples=(12, 12)),
                                "num_images": 3, "appearance_dim": 4, "transient_dim": 3,
                                "background": BACKGROUND})
    params = models.init(jax.random.PRNGKey(0), cfg)
    params["transient"] = params["transient"].at[:, 0].set(jnp.array([0.0, 0.5, 1.0]))
    monkeypatch.setattr(fields, "apply", _analytic_field)
    rng = np.random.default_rng(0)
    o = rng.normal(size=(6, 3)).astype(np.float32)
    o = 3.0 * o / np.linalg.norm(o, axis=-1, keepdims=True)
    d = rng.normal(scale=0.3, size=(6, 3)).astype(np.float32) - o
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    index = np.array([0, 1, 2, 0, 1, 2], np.int32)
    out = jax.jit(lambda p: models.render_rays(p, cfg, jnp.asarray(o), jnp.asarray(d), jnp.full(6, 0.5),
                                               jnp.full(6, 6.0), image_index=jnp.asarray(index)))(params)
    fine = out["final"]
    t_edges = np.asarray(fine["t_edges"], np.float64)
    t_mid = 0.5 * (t_edges[:, 1:] + t_edges[:, :-1])
    x = o[:, None].astype(np.float64) + t_mid[..., None] * d[:, None]      # nerf: no contraction, scale 1
    emb = np.asarray(params["transient"])[index][:, None, :]
    f = {k: np.asarray(v, np.float64) for k, v in
         _analytic_field(None, models.main_field(params, cfg)[1], jnp.asarray(x), None, None,
                         jnp.asarray(np.broadcast_to(emb, (*x.shape[:-1], 3)))).items()}
    got_t_opacity = np.asarray(fine["transient_opacity"])
    for r in range(6):
        mixed, static, beta_hat, t_opacity = _loop(f["sigma"][r], f["rgb"][r], f["transient_sigma"][r],
                                                   f["transient_rgb"][r], f["beta"][r], t_edges[r], cfg.beta_min)
        np.testing.assert_allclose(fine["rgb"][r], mixed, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(fine["rgb_static"][r], static, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(fine["beta"][r], beta_hat, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(got_t_opacity[r], t_opacity, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(fine["transient_sigma_mean"], f["transient_sigma"].mean(-1), rtol=1e-5)
    # the transient part matters here: the mixed picture is clearly not the static one
    assert np.abs(np.asarray(fine["rgb"]) - np.asarray(fine["rgb_static"])).max() > 0.05
    assert got_t_opacity.min() > 0.05
    # evaluation shows the static part
    np.testing.assert_allclose(models.static_rgb(out), fine["rgb_static"])
