"""contract / inv_contract / positional_encoding against closed forms written in NumPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.nerf import coords
from jaxnerf_grid.nerf.samplers import s_space as sampling


def contract_reference(x, radius):
    """Eq. 9 (corrected) point by point in float64."""
    out = np.empty_like(x, dtype=np.float64)
    for i, p in enumerate(x.astype(np.float64)):
        n = np.linalg.norm(p)
        out[i] = p if n <= 1 else (radius - (radius - 1) / n) * p / n
    return out


@pytest.mark.parametrize("radius", [2.0, 3.5, 1.25])
def test_contract_matches_closed_form(radius):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(500, 3)) * rng.choice([0.3, 3.0, 300.0], size=(500, 1))
    got = np.asarray(coords.contract(jnp.asarray(x, jnp.float32), radius))
    np.testing.assert_allclose(got, contract_reference(x, radius), rtol=2e-6, atol=2e-6)


@pytest.mark.parametrize("radius", [2.0, 4.0])
def test_inverse_round_trip(radius):
    rng = np.random.default_rng(1)
    x = rng.normal(size=(400, 3)) * rng.choice([0.5, 2.0, 20.0], size=(400, 1))
    z = coords.contract(jnp.asarray(x, jnp.float32), radius)
    np.testing.assert_allclose(np.asarray(coords.inv_contract(z, radius)), x, rtol=2e-4, atol=1e-5)
    # and the other way round, from contracted space
    zs = rng.uniform(-1, 1, size=(400, 3))
    zs = zs / np.linalg.norm(zs, axis=-1, keepdims=True) * rng.uniform(0, radius * 0.999, (400, 1))
    back = coords.contract(coords.inv_contract(jnp.asarray(zs, jnp.float32), radius), radius)
    np.testing.assert_allclose(np.asarray(back), zs, rtol=1e-4, atol=1e-5)


def test_continuity_monotonicity_and_bound():
    radius = 2.0
    direction = np.array([0.36, -0.48, 0.8])
    norms = np.concatenate([np.linspace(0.0, 2.0, 2001), np.geomspace(2.0, 1e8, 500)])
    z = np.asarray(coords.contract(jnp.asarray(norms[:, None] * direction, jnp.float32), radius))
    radii = np.linalg.norm(z, axis=-1)
    assert np.all(np.diff(radii) >= -1e-6), "contracted radius must not decrease"
    assert np.all(radii < radius + 1e-6)
    # continuity at |x| = 1: neighbouring samples 1e-3 apart map within ~1e-3
    i = np.searchsorted(norms, 1.0)
    assert abs(radii[i + 1] - radii[i - 1]) < 3e-3
    # directions preserved
    np.testing.assert_allclose(z[1:] / radii[1:, None], np.broadcast_to(direction, z[1:].shape), atol=1e-5)


def test_gradients_finite_at_origin_and_across_unit_sphere():
    grad = jax.jacfwd(lambda x: coords.contract(x, 2.0))
    for point in ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0 - 1e-7, 0.0], [0.0, 0.0, 1.0 + 1e-6]):
        jac = np.asarray(grad(jnp.asarray(point, jnp.float32)))
        assert np.all(np.isfinite(jac))
    # inside: identity; just outside: radial derivative is (R - 1) / |x|^2 -> 1 at |x| = 1
    np.testing.assert_allclose(np.asarray(grad(jnp.zeros(3))), np.eye(3), atol=1e-6)
    jac_out = np.asarray(grad(jnp.asarray([1.0 + 1e-3, 0.0, 0.0])))
    np.testing.assert_allclose(jac_out[0, 0], (2.0 - 1.0) / (1.0 + 1e-3) ** 2, rtol=1e-3)
    grad_sum = jax.grad(lambda x: jnp.sum(coords.inv_contract(x, 2.0)))(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(grad_sum)))


def test_radius_must_exceed_one():
    with pytest.raises(ValueError, match="radius must be > 1"):
        coords.contract(jnp.ones(3), radius=1.0)
    with pytest.raises(ValueError, match="radius must be > 1"):
        coords.inv_contract(jnp.ones(3), radius=0.5)


def test_disparity_warp_gives_linear_contracted_radius():
    """From t = 1 to far on a ray through the origin, uniform s gives |z| = 1 + (R - 1) s."""
    radius, far = 2.0, 1e9
    s_edges = sampling.stratified_s(None, (), 64)
    t_edges = sampling.ray_warp("disparity", 1.0, far)[1](s_edges)
    direction = jnp.asarray([0.6, 0.0, 0.8])
    z = coords.contract(t_edges[:, None] * direction, radius)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(z), axis=-1),
                               1.0 + (radius - 1.0) * np.asarray(s_edges), atol=2e-5)


def test_positional_encoding_closed_form():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(7, 3)).astype(np.float32)
    got = np.asarray(coords.positional_encoding(jnp.asarray(x), 1, 4, append_identity=True))
    expected = []
    for p in x:
        sins = [np.sin(2.0 ** k * p[d]) for k in range(1, 4) for d in range(3)]
        coss = [np.cos(2.0 ** k * p[d]) for k in range(1, 4) for d in range(3)]
        expected.append(sins + coss + list(p))
    np.testing.assert_allclose(got, np.array(expected), atol=2e-5)
    assert got.shape[-1] == coords.encoded_size(3, 1, 4)
