"""Warps (Eq. 10-11), stratified sampling and PDF resampling against closed forms and statistics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxnerf_grid.nerf.samplers import s_space as sampling

KINDS = ["linear", "disparity", "log", "piecewise"]


@pytest.mark.parametrize("kind", KINDS)
def test_warp_endpoints_inverse_and_monotone(kind):
    t_near, t_far = 0.2, 500.0
    t_to_s, s_to_t = sampling.ray_warp(kind, t_near, t_far)
    np.testing.assert_allclose(float(t_to_s(jnp.asarray(t_near))), 0.0, atol=1e-6)
    np.testing.assert_allclose(float(t_to_s(jnp.asarray(t_far))), 1.0, atol=1e-6)
    t = jnp.asarray(np.geomspace(t_near, t_far, 300), jnp.float32)
    s = np.asarray(t_to_s(t))
    assert np.all(np.diff(s) > 0)
    # float32: t is ill-conditioned in s near the far end of the disparity warp, so check both ways
    np.testing.assert_allclose(np.asarray(s_to_t(jnp.asarray(s))), np.asarray(t), rtol=1e-3)
    s_grid = jnp.linspace(0.0, 1.0, 101)
    np.testing.assert_allclose(np.asarray(t_to_s(s_to_t(s_grid))), np.asarray(s_grid), atol=2e-6)


def test_warp_closed_forms():
    """Eq. 10 written out by hand for the disparity and piecewise warps."""
    t_near, t_far = 0.5, 40.0
    t = np.array([0.5, 0.7, 1.0, 3.0, 40.0])
    to_s, _ = sampling.ray_warp("disparity", t_near, t_far)
    expected = (1 / t - 1 / t_near) / (1 / t_far - 1 / t_near)
    np.testing.assert_allclose(np.asarray(to_s(jnp.asarray(t, jnp.float32))), expected, rtol=1e-5, atol=1e-6)

    g = lambda x: np.where(x < 1, x / 2, 1 - 1 / (2 * x))  # noqa: E731
    to_s, _ = sampling.ray_warp("piecewise", t_near, t_far)
    expected = (g(t) - g(t_near)) / (g(t_far) - g(t_near))
    np.testing.assert_allclose(np.asarray(to_s(jnp.asarray(t, jnp.float32))), expected, rtol=1e-5, atol=1e-6)


def test_custom_warp_and_bad_kind():
    to_s, to_t = sampling.ray_warp((jnp.sqrt, jnp.square), 1.0, 9.0)
    np.testing.assert_allclose(float(to_s(jnp.asarray(4.0))), 0.5, rtol=1e-6)
    np.testing.assert_allclose(float(to_t(jnp.asarray(0.5))), 4.0, rtol=1e-6)
    with pytest.raises(ValueError, match="unknown warp"):
        sampling.ray_warp("cubic", 1.0, 2.0)


def _edges_in_t(key, near, far, num_samples, warp="disparity"):
    """Stratified s edges mapped to metric t with Eq. 11, as models.render_ray does."""
    s_edges = sampling.stratified_s(key, near.shape, num_samples)
    _, s_to_t = sampling.ray_warp(warp, near[..., None], far[..., None])
    return s_to_t(s_edges), s_edges


def test_stratified_deterministic_and_jittered():
    near = jnp.asarray([0.5, 1.0])
    far = jnp.asarray([10.0, 100.0])
    t_edges, s_edges = _edges_in_t(None, near, far, 8)
    np.testing.assert_allclose(np.asarray(s_edges), np.broadcast_to(np.linspace(0, 1, 9), (2, 9)), atol=1e-7)
    np.testing.assert_allclose(np.asarray(t_edges[:, 0]), near, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(t_edges[:, -1]), far, rtol=1e-5)
    # uniform in disparity
    disparity = 1 / np.asarray(t_edges)
    np.testing.assert_allclose(np.diff(disparity, axis=-1), np.diff(disparity, axis=-1)[:, :1] * np.ones((1, 8)),
                               rtol=1e-4)
    t_j, s_j = _edges_in_t(jax.random.PRNGKey(0), near, far, 8)
    s_j = np.asarray(s_j)
    assert np.all(np.diff(s_j, axis=-1) > 0) and np.all(s_j[:, 0] == 0) and np.all(s_j[:, -1] == 1)
    assert not np.allclose(s_j, np.asarray(s_edges))


def test_stratified_is_uniform_in_s():
    """Sample centres of jittered stratified sampling are uniform on [0, 1] (KS test)."""
    s_edges = sampling.stratified_s(jax.random.PRNGKey(3), (4000,), 4)
    s = np.asarray(s_edges)
    # centres c_i = (i + u_i) / N; the first interior edge (c_0 + c_1) / 2 = (u_0 + 1 + u_1) / (2N),
    # so 2N * edge - 1 = u_0 + u_1 follows the triangular law on [0, 2].
    u_sum = s[:, 1] * 8 - 1
    result = stats.kstest(u_sum, stats.triang(c=0.5, loc=0, scale=2).cdf)
    assert result.pvalue > 1e-3


def test_resample_pdf_matches_histogram():
    edges = jnp.asarray([0.0, 1.0, 1.5, 4.0, 5.0, 9.0])
    weights = jnp.asarray([0.1, 0.0, 0.5, 0.3, 0.1])
    num_rays, num_samples = 400, 64
    samples = sampling.resample_pdf(jax.random.PRNGKey(7), jnp.broadcast_to(edges, (num_rays, 6)),
                                    jnp.broadcast_to(weights, (num_rays, 5)), num_samples, weight_floor=0.0)
    samples = np.asarray(samples).ravel()
    counts, _ = np.histogram(samples, bins=np.asarray(edges))
    expected = np.asarray(weights, np.float64) / np.sum(np.asarray(weights, np.float64)) * samples.size
    nonzero = expected > 0
    assert counts[~nonzero].sum() == 0
    chi2 = stats.chisquare(counts[nonzero], expected[nonzero])
    assert chi2.pvalue > 1e-3
    # within a bin the density is flat: KS test inside the widest bin
    inside = samples[(samples >= 1.5) & (samples < 4.0)]
    assert stats.kstest(inside, stats.uniform(loc=1.5, scale=2.5).cdf).pvalue > 1e-3


def test_resample_pdf_sorted_and_stops_gradient():
    edges = jnp.linspace(0.0, 1.0, 9)
    def total(w):
        return jnp.sum(sampling.resample_pdf(None, edges, w, 16))
    grad = jax.grad(total)(jnp.ones(8))
    np.testing.assert_array_equal(np.asarray(grad), 0.0)
    s = np.asarray(sampling.resample_pdf(jax.random.PRNGKey(1), edges, jnp.arange(8.0), 32))
    assert np.all(np.diff(s) >= 0)


def test_intervals_from_samples_and_merge():
    samples = jnp.asarray([[1.0, 2.0, 4.0]])
    np.testing.assert_allclose(np.asarray(sampling.intervals_from_samples(samples, 0.5, 6.0)),
                               [[0.5, 1.5, 3.0, 6.0]])
    merged = sampling.merge_edges(jnp.asarray([0.0, 2.0, 4.0]), jnp.asarray([1.0, 3.0]))
    np.testing.assert_array_equal(np.asarray(merged), [0, 1, 2, 3, 4])
