"""models.py: the renderer against a brute-force loop and an analytic sphere scene."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.nerf import fields, models
from jaxnerf_grid.nerf.samplers import hierarchical, proposal

SMALL = fields.mlp.Config(depth=2, width=16, skip=1, pos_max_deg=4, dir_max_deg=2, view_width=8)


@functools.cache
def _jitted(cfg):
    return jax.jit(lambda p, a, k: models.render_rays(p, cfg, *a, **k))


@pytest.fixture(autouse=True)
def _fresh_jit_cache():
    yield
    _jitted.cache_clear()  # a test may have traced a monkeypatched field


def _render(params, cfg, *args, **kw):
    """models.render_rays, jitted once per config (eager dispatch of the renderer is slow)."""
    return _jitted(cfg)(params, args, kw)


def _cfg(method="ours", **kw):
    base = dict(models.method_defaults(method))
    base.update(field=SMALL, sampler=hierarchical.Config(samples=(16, 16)))
    base.update(kw)
    return models.ModelConfig(**base)


def _rays(n=6, seed=0):
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3)).astype(np.float32)
    o = 3.0 * o / np.linalg.norm(o, axis=-1, keepdims=True)
    target = rng.normal(scale=0.2, size=(n, 3)).astype(np.float32)
    d = target - o
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return o, d


def _contract_np(x, r):
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.where(n <= 1, x, (r - (r - 1) / np.maximum(n, 1)) * x / np.maximum(n, 1e-12))


def test_coarse_render_matches_bruteforce_loop():
    """Deterministic coarse pass vs a per-ray Python loop (disparity bins, contraction, Eq. 1)."""
    cfg = _cfg("ours", sampler=hierarchical.Config(samples=(16,)), background=0.25)
    params = models.init(jax.random.PRNGKey(0), cfg)
    o, d = _rays()
    near, far = 0.5, 40.0
    out = _render(params, cfg, jnp.asarray(o), jnp.asarray(d), jnp.full(6, near), jnp.full(6, far))
    s = np.linspace(0, 1, cfg.sampler.samples[0] + 1)
    t = 1.0 / (s / far + (1 - s) / near)          # uniform in disparity
    tm = 0.5 * (t[1:] + t[:-1])
    x = o[:, None] + tm[None, :, None] * d[:, None]
    z = _contract_np(x, 2.0) / 2.0
    f = jax.jit(fields.apply, static_argnums=1)(models.main_field(params, cfg)[0], SMALL, jnp.asarray(z, jnp.float32),
                                                jnp.asarray(np.broadcast_to(d[:, None], x.shape)))
    for r in range(6):
        sigma, rgb = np.asarray(f["sigma"][r], np.float64), np.asarray(f["rgb"][r], np.float64)
        trans, colour, acc = 1.0, np.zeros(3), 0.0
        for i in range(len(tm)):
            a = 1 - np.exp(-sigma[i] * (t[i + 1] - t[i]))
            colour += trans * a * rgb[i]
            acc += trans * a
            trans *= 1 - a
        colour += (1 - acc) * 0.25
        np.testing.assert_allclose(out["final"]["rgb"][r], colour, rtol=2e-4, atol=2e-5)
        np.testing.assert_allclose(out["final"]["opacity"][r], acc, rtol=2e-4, atol=2e-5)
    assert len(out["levels"]) == 1


def test_field_inputs_contraction_closed_form():
    cfg = _cfg("ours", contract_radius=3.0)
    t_edges = jnp.array([[9.0, 11.0]])
    z = models.field_inputs(cfg, jnp.zeros((1, 3)), jnp.array([[0.0, 0.0, 1.0]]), t_edges)
    # |x| = 10 -> |z| = 3 - 2/10 = 2.8, divided by R = 3
    np.testing.assert_allclose(z[0, 0], [0, 0, 2.8 / 3.0], rtol=1e-6)
    nerf = _cfg("nerf")
    z = models.field_inputs(nerf, jnp.zeros((1, 3)), jnp.array([[0.0, 0.0, 1.0]]), t_edges)
    np.testing.assert_allclose(z[0, 0], [0, 0, 10.0])


def _sphere_field(params, cfg, x, viewdirs=None, appearance=None, transient=None):
    """Analytic field: dense red ball of radius 0.5 in model input units, empty elsewhere."""
    inside = jnp.linalg.norm(x, axis=-1) < 0.5  # ours: inputs are z / R with R = 2
    shape = x.shape[:-1]
    out = {"sigma": jnp.where(inside, 200.0, 0.0),
           "rgb": jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0]), (*shape, 3))}
    if cfg.transient_dim > 0:
        out["transient_sigma"] = jnp.zeros(shape)
        out["transient_rgb"] = jnp.zeros((*shape, 3))
        out["beta"] = jnp.ones(shape)
    return out


def nbins_of(union):
    return 32 + 64 if union else 64


@pytest.mark.parametrize("method,union", [("ours", True), ("ours", False), ("nerf", True)])
def test_hierarchical_sampling_finds_sphere_surface(monkeypatch, method, union):
    monkeypatch.setattr(fields, "apply", _sphere_field)
    _jitted.cache_clear()
    radius = 1.0  # ours: |z / 2| < 0.5 is the unit ball (contraction is the identity there)
    cfg = _cfg(method, sampler=hierarchical.Config(samples=(32, 64), union=union))
    if method == "nerf":  # nerf inputs are not divided by R: ball radius 0.5 in world units
        radius = 0.5
    params = models.init(jax.random.PRNGKey(0), cfg)
    o, d = _rays(8, seed=2)
    d = -o / np.linalg.norm(o, axis=-1, keepdims=True)  # aim at the centre
    out = _render(params, cfg, jnp.asarray(o), jnp.asarray(d), jnp.full(8, 0.5),
                             jnp.full(8, 20.0), keys=jax.random.split(jax.random.PRNGKey(1), 8))
    truth = 3.0 - radius
    (coarse, fine), final = out["levels"], out["final"]
    assert np.array_equal(fine["rgb"], final["rgb"]) and np.array_equal(fine["s_edges"], final["s_edges"])
    np.testing.assert_allclose(fine["opacity"], 1.0, atol=1e-3)
    np.testing.assert_allclose(fine["rgb"], np.tile([1.0, 0, 0], (8, 1)), atol=1e-3)
    fine_err = np.abs(np.asarray(fine["depth"]) - truth).max()
    coarse_err = np.abs(np.asarray(coarse["depth"]) - truth).max()
    # point sampling at bin midpoints leaves an error of up to about half a coarse bin; the
    # fine pass must still clearly beat the coarse one, with its samples at the surface
    assert fine_err < 0.6 * coarse_err, (fine_err, coarse_err)
    t = np.asarray(fine["t_edges"])
    t_mid = 0.5 * (t[:, 1:] + t[:, :-1])
    near_surface = np.mean(np.abs(t_mid - truth) < 0.7, axis=-1)
    assert np.all(near_surface > (0.5 * 64 / nbins_of(union))), near_surface
    nbins = nbins_of(union)
    assert fine["s_edges"].shape == (8, nbins + 1)
    assert np.all(np.diff(np.asarray(fine["s_edges"]), axis=-1) >= 0)


def test_per_ray_keys_make_batches_consistent():
    cfg = _cfg("ours")
    params = models.init(jax.random.PRNGKey(0), cfg)
    o, d = _rays(6)
    keys = jax.random.split(jax.random.PRNGKey(5), 6)
    args = (jnp.full(6, 0.5), jnp.full(6, 30.0))
    full = _render(params, cfg, jnp.asarray(o), jnp.asarray(d), *args, keys=keys)
    half = _render(params, cfg, jnp.asarray(o[3:]), jnp.asarray(d[3:]), args[0][3:], args[1][3:],
                              keys=keys[3:])
    np.testing.assert_allclose(full["final"]["rgb"][3:], half["final"]["rgb"], rtol=1e-5, atol=1e-6)


def test_nerfw_embeddings_and_static_part(monkeypatch):
    cfg = _cfg("nerfw", num_images=3, appearance_dim=4, transient_dim=3)
    params = models.init(jax.random.PRNGKey(0), cfg)
    assert params["appearance"].shape == (3, 4) and params["transient"].shape == (3, 3)
    params["appearance"] = params["appearance"].at[1].set(5.0)
    o, d = _rays(4)
    run = lambda idx: _render(params, cfg, jnp.asarray(o), jnp.asarray(d), jnp.full(4, 0.5),  # noqa: E731
                                         jnp.full(4, 6.0), image_index=jnp.full(4, idx, jnp.int32))
    a, b = run(0), run(1)
    assert np.abs(np.asarray(a["final"]["rgb_static"]) - np.asarray(b["final"]["rgb_static"])).max() > 1e-4
    assert np.all(np.asarray(a["final"]["beta"]) >= cfg.beta_min)
    # with no transient density the mixed picture is the static one and beta = beta_min
    monkeypatch.setattr(fields, "apply", _sphere_field)
    _jitted.cache_clear()
    out = _render(params, cfg, jnp.asarray(o), jnp.asarray(d), jnp.full(4, 0.5), jnp.full(4, 6.0),
                             image_index=jnp.zeros(4, jnp.int32))
    np.testing.assert_allclose(out["final"]["rgb"], out["final"]["rgb_static"], atol=1e-6)
    np.testing.assert_allclose(out["final"]["beta"], cfg.beta_min, atol=1e-6)


def test_validation_errors():
    with pytest.raises(ConfigError, match="warp"):
        models.init(jax.random.PRNGKey(0), _cfg(warp="cubic"))
    with pytest.raises(ConfigError, match="num_images"):
        models.init(jax.random.PRNGKey(0), _cfg("nerfw"))
    with pytest.raises(ConfigError, match="method"):
        models.method_defaults("mipnerf")
    assert dataclasses.asdict(_cfg("nerf"))["use_contraction"] is False


def _sphere_density(params, cfg, x):
    return jnp.where(jnp.linalg.norm(x, axis=-1) < 0.5, 200.0, 0.0)


def _sphere_and_sky_field(params, cfg, x, viewdirs=None, appearance=None, transient=None):
    """The red ball of _sphere_field, and blue everywhere outside (the colour the far bin shows)."""
    out = _sphere_field(params, cfg, x, viewdirs, appearance, transient)
    inside = (jnp.linalg.norm(x, axis=-1) < 0.5)[..., None]
    out["rgb"] = jnp.where(inside, out["rgb"], jnp.array([0.0, 0.0, 1.0]))
    return out


@pytest.mark.parametrize("opaque_far", [False, True])
def test_proposal_sampling_finds_sphere_surface_and_opaque_far_shows_the_far_colour(monkeypatch, opaque_far):
    monkeypatch.setattr(fields, "apply", _sphere_and_sky_field)
    monkeypatch.setattr(fields.proposal, "density", _sphere_density)
    grid = fields.grid.Config(depth=1, width=8, density_activation="exp",
                              grid=fields.HashConfig(num_levels=2, log2_table_size=8, min_resolution=4,
                                                     max_resolution=8))
    cfg = _cfg("ours", sampler=proposal.Config(samples=(64,), main_samples=16, field=grid), field=grid,
               opaque_far=opaque_far)
    params = models.init(jax.random.PRNGKey(0), cfg)
    o, _ = _rays(8, seed=2)
    d_hit = -o / np.linalg.norm(o, axis=-1, keepdims=True)   # through the centre: surface at t = 2
    d_miss = o / np.linalg.norm(o, axis=-1, keepdims=True)   # straight away from the ball
    d = np.concatenate([d_hit, d_miss])
    o = np.concatenate([o, o])
    out = _render(params, cfg, jnp.asarray(o), jnp.asarray(d), jnp.full(16, 0.5), jnp.full(16, 20.0),
                  keys=jax.random.split(jax.random.PRNGKey(1), 16))
    fine = out["final"]
    assert len(out["levels"]) == 2 and "rgb" not in out["levels"][0] \
        and np.array_equal(out["levels"][1]["weights"], fine["weights"])
    np.testing.assert_allclose(fine["opacity"][:8], 1.0, atol=1e-3)
    np.testing.assert_allclose(fine["rgb"][:8], np.tile([1.0, 0, 0], (8, 1)), atol=1e-3)
    # 16 main samples resampled from the proposal: the surface bin is found to within a
    # fraction of a proposal bin, and most main samples sit at the surface
    assert np.abs(np.asarray(fine["depth"][:8]) - 2.0).max() < 0.1
    t = np.asarray(fine["t_edges"][:8])
    near_surface = np.mean(np.abs(0.5 * (t[:, 1:] + t[:, :-1]) - 2.0) < 0.3, axis=-1)
    assert np.all(near_surface > 0.5), near_surface
    # rays that miss: empty (background black) unless the far bin is opaque, then its colour
    if opaque_far:
        np.testing.assert_allclose(fine["opacity"][8:], 1.0, atol=1e-6)
        np.testing.assert_allclose(fine["rgb"][8:], np.tile([0, 0, 1.0], (8, 1)), atol=1e-6)
        np.testing.assert_allclose(np.asarray(out["levels"][0]["weights"][8:]).sum(-1), 1.0, atol=1e-6)
    else:
        np.testing.assert_allclose(fine["opacity"][8:], 0.0, atol=1e-6)
        np.testing.assert_allclose(fine["rgb"][8:], 0.0, atol=1e-6)
