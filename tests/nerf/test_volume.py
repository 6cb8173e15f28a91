"""Alpha compositing against a brute-force Python loop of Eq. 1's quadrature."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.nerf import volume as render


def brute_force(density, t_edges, rgb, dir_norm=1.0):
    """NeRF's quadrature one sample at a time, in float64."""
    transmittance, colour, weights = 1.0, np.zeros(3), []
    for i in range(len(density)):
        delta = (t_edges[i + 1] - t_edges[i]) * dir_norm
        alpha = 1.0 - np.exp(-density[i] * delta)
        weights.append(transmittance * alpha)
        colour += transmittance * alpha * rgb[i]
        transmittance *= 1.0 - alpha
    return np.array(weights), colour


def test_weights_and_colour_match_loop():
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = 16
        t_edges = np.sort(rng.uniform(0.5, 6.0, n + 1))
        density = rng.exponential(2.0, n) * rng.integers(0, 2, n)
        rgb = rng.uniform(size=(n, 3))
        dirs = rng.normal(size=3)
        w_ref, c_ref = brute_force(density, t_edges, rgb, np.linalg.norm(dirs))
        w = render.alpha_weights(jnp.asarray(density, jnp.float32), jnp.asarray(t_edges, jnp.float32),
                                 jnp.asarray(dirs, jnp.float32))
        out = render.composite(w, jnp.asarray(rgb, jnp.float32), jnp.asarray(t_edges, jnp.float32))
        np.testing.assert_allclose(np.asarray(w), w_ref, atol=2e-6)
        np.testing.assert_allclose(np.asarray(out["rgb"]), c_ref, atol=2e-6)
        np.testing.assert_allclose(float(out["opacity"]), w_ref.sum(), atol=2e-6)
        assert float(out["opacity"]) <= 1.0 + 1e-6
        mids = 0.5 * (t_edges[1:] + t_edges[:-1])
        if w_ref.sum() > 1e-6:
            np.testing.assert_allclose(float(out["depth"]), (w_ref * mids).sum() / w_ref.sum(), rtol=1e-5)


def test_median_depth_brute_force():
    rng = np.random.default_rng(1)
    for _ in range(20):
        n = 12
        t_edges = np.sort(rng.uniform(0.0, 10.0, n + 1))
        weights = rng.uniform(size=n) * (rng.uniform(size=n) > 0.4)
        weights = weights / (weights.sum() + 1e-3) * rng.uniform(0.2, 1.0)
        # brute force: walk along the ray in small steps of the piecewise-constant density of w
        fine = np.linspace(t_edges[0], t_edges[-1], 200001)
        idx = np.clip(np.searchsorted(t_edges, fine, side="right") - 1, 0, n - 1)
        width = np.diff(t_edges)[idx]
        cumulative = np.cumsum(weights[idx] / width) * (fine[1] - fine[0])
        expected = fine[np.searchsorted(cumulative, 0.5 * weights.sum())]
        got = float(render.median_depth(jnp.asarray(weights, jnp.float32), jnp.asarray(t_edges, jnp.float32)))
        np.testing.assert_allclose(got, expected, atol=2e-3 * (t_edges[-1] - t_edges[0]) + 1e-3)


def test_background_and_empty_ray():
    t_edges = jnp.linspace(1.0, 2.0, 5)
    w = render.alpha_weights(jnp.zeros(4), t_edges)
    out = render.composite(w, jnp.ones((4, 3)), t_edges, background=jnp.asarray([0.2, 0.4, 0.6]))
    np.testing.assert_allclose(np.asarray(out["rgb"]), [0.2, 0.4, 0.6], atol=1e-7)
    assert float(out["depth"]) == 2.0 and float(out["median_depth"]) == 2.0


def test_gradients_finite_at_extreme_densities():
    t_edges = jnp.linspace(0.5, 3.0, 9)
    rgb = jnp.linspace(0.0, 1.0, 24).reshape(8, 3)

    def loss(density):
        w = render.alpha_weights(density, t_edges, jnp.asarray([0.0, 0.0, -1.0]))
        out = render.composite(w, rgb, t_edges, background=1.0)
        return jnp.sum(out["rgb"]) + out["depth"] + out["opacity"]

    for density in (jnp.zeros(8), jnp.full(8, 1e6), jnp.asarray([0, 1e6, 0, 1, 0, 1e6, 0, 0], jnp.float32)):
        grad = np.asarray(jax.grad(loss)(density))
        assert np.all(np.isfinite(grad)), density
    w = np.asarray(render.alpha_weights(jnp.full(8, 1e6), t_edges))
    np.testing.assert_allclose(w, np.eye(8)[0], atol=1e-7)
