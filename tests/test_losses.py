"""losses.py against closed forms and NumPy."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid import losses


def test_weighted_mean_normalised_by_weight_sum():
    rng = np.random.default_rng(0)
    per_ray = rng.uniform(size=10)
    w = rng.uniform(size=10)
    w[3] = 0.0
    np.testing.assert_allclose(losses.weighted_mean(jnp.asarray(per_ray), jnp.asarray(w)),
                               (per_ray * w).sum() / w.sum(), rtol=1e-6)
    # split over two "devices" with the global total: the parts add up to the whole
    total = w.sum()
    parts = [losses.weighted_mean(jnp.asarray(per_ray[i:i + 5]), jnp.asarray(w[i:i + 5]), total) for i in (0, 5)]
    np.testing.assert_allclose(sum(parts), (per_ray * w).sum() / total, rtol=1e-6)
    assert float(losses.weighted_mean(jnp.ones(3), jnp.zeros(3))) == 0.0


def test_masked_pixel_has_no_gradient():
    target = jnp.array([[1.0, 0, 0], [0, 1.0, 0]])
    w = jnp.array([1.0, 0.0])
    g = jax.grad(lambda rgb: losses.weighted_mean(losses.squared_error(rgb, target), w))(jnp.zeros((2, 3)))
    np.testing.assert_allclose(g[1], 0.0)
    np.testing.assert_allclose(g[0], [-2.0 / 3.0, 0, 0], rtol=1e-6)


def test_nerfw_loss_closed_form():
    rgb = jnp.array([[0.5, 0.5, 0.5]])
    target = jnp.array([[0.8, 0.5, 0.2]])
    beta = jnp.array([0.4])
    sigma_t = jnp.array([2.0])
    mse = (0.09 + 0 + 0.09) / 3
    expected = mse / (2 * 0.16) + np.log(0.16) / 2 + 0.01 * 2.0
    np.testing.assert_allclose(losses.nerfw_ray_loss(rgb, target, beta, sigma_t, 0.01), [expected], rtol=1e-5)


def test_per_ray_loss_combines_passes_and_psnr():
    target = jnp.zeros((2, 3))
    out = {"coarse": {"rgb": jnp.full((2, 3), 0.1)}, "fine": {"rgb": jnp.full((2, 3), 0.2)}}
    res = losses.per_ray_loss(out, target)
    np.testing.assert_allclose(res["loss"], [0.01 + 0.04] * 2, rtol=1e-5)
    np.testing.assert_allclose(losses.mse_to_psnr(0.01), 20.0, rtol=1e-6)
    out["fine"].update(beta=jnp.full((2,), 1.0), transient_sigma_mean=jnp.zeros(2))
    res = losses.per_ray_loss(out, target, use_transient=True)
    np.testing.assert_allclose(res["loss"], [0.01 + 0.04 / 2] * 2, rtol=1e-5)
