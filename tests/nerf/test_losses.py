"""losses.py against closed forms and NumPy."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.nerf import losses


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


def test_weighted_mean_with_weights_summing_below_one():
    """The total's guard (1e-12) only stops a division by zero: weights summing to 0.3, given or
    summed, still divide by 0.3 (a guard of ~1 passed the tests above)."""
    per_ray = np.array([2.0, 5.0, 1.0], np.float32)
    w = np.array([0.1, 0.0, 0.2], np.float32)
    want = (2.0 * 0.1 + 1.0 * 0.2) / 0.3
    np.testing.assert_allclose(losses.weighted_mean(jnp.asarray(per_ray), jnp.asarray(w)), want, rtol=1e-6)
    np.testing.assert_allclose(losses.weighted_mean(jnp.asarray(per_ray), jnp.asarray(w), 0.3), want, rtol=1e-6)


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
    first, last = {"rgb": jnp.full((2, 3), 0.1)}, {"rgb": jnp.full((2, 3), 0.2)}
    out = {"levels": [first, last], "final": last}
    res = losses.per_ray_loss(out, target, level_weight=0.5)
    np.testing.assert_allclose(res["loss"], [0.5 * 0.01 + 0.04] * 2, rtol=1e-5)
    np.testing.assert_allclose(res["mse"], [0.04] * 2, rtol=1e-5)
    np.testing.assert_allclose(res["mse_levels"], [[0.01] * 2], rtol=1e-5)
    np.testing.assert_allclose(losses.mse_to_psnr(0.01), 20.0, rtol=1e-6)
    last.update(beta=jnp.full((2,), 1.0), transient_sigma_mean=jnp.zeros(2))
    res = losses.per_ray_loss(out, target, use_transient=True)
    np.testing.assert_allclose(res["loss"], [0.01 + 0.04 / 2] * 2, rtol=1e-5)
    # one pass: its own colour term only (no level before it)
    res = losses.per_ray_loss({"levels": [first], "final": first}, target, level_weight=0.5)
    np.testing.assert_allclose(res["loss"], [0.01] * 2, rtol=1e-5)
    assert res["mse_levels"] == []


# --------------------------------------------------------------------------- proposal / distortion


def _random_step(rng, n, lo=0.0, hi=1.0):
    edges = np.sort(np.concatenate([[lo, hi], rng.uniform(lo, hi, n - 1)]))
    w = rng.uniform(size=n) ** 3
    return edges, w / w.sum() * rng.uniform(0.3, 1.0)


def _interlevel_brute(e_main, w_main, e_prop, w_prop, eps=1e-7):
    total = 0.0
    for i in range(len(w_main)):
        a, b = e_main[i], e_main[i + 1]
        bound = sum(w_prop[j] for j in range(len(w_prop)) if e_prop[j] < b and e_prop[j + 1] > a)
        total += max(0.0, w_main[i] - bound) ** 2 / (w_main[i] + eps)
    return total


def _distortion_brute(edges, w):
    mid = 0.5 * (edges[1:] + edges[:-1])
    inter = sum(w[i] * w[j] * abs(mid[i] - mid[j]) for i in range(len(w)) for j in range(len(w)))
    return inter + sum(w[i] ** 2 * (edges[i + 1] - edges[i]) for i in range(len(w))) / 3.0


def test_interlevel_loss_matches_per_interval_loop():
    rng = np.random.default_rng(3)
    rows = [(_random_step(rng, 12), _random_step(rng, 7)) for _ in range(6)]
    # shared edges (proposal edges that coincide with main ones) exercise the boundary rule
    e, w = _random_step(rng, 8)
    rows.append(((e, w), (e[::2], rng.uniform(size=4) * 0.2)))
    for (e_m, w_m), (e_p, w_p) in rows:
        got = losses.interlevel_ray_loss(jnp.asarray(e_m, jnp.float32), jnp.asarray(w_m, jnp.float32),
                                         jnp.asarray(e_p, jnp.float32), jnp.asarray(w_p, jnp.float32))
        np.testing.assert_allclose(got, _interlevel_brute(e_m, w_m, e_p, w_p), rtol=2e-4, atol=1e-6)


def test_interlevel_loss_batched_zero_when_bounded_and_only_proposal_learns():
    rng = np.random.default_rng(4)
    e_m, w_m = _random_step(rng, 10)
    # a proposal equal to the main step function bounds it: loss 0
    batch = lambda a: jnp.asarray(np.stack([a, a]), jnp.float32)  # noqa: E731
    got = losses.interlevel_ray_loss(batch(e_m), batch(w_m), batch(e_m), batch(w_m))
    assert got.shape == (2,)
    np.testing.assert_allclose(got, 0.0, atol=1e-7)
    # gradient flows to the proposal weights, never to the main ones
    e_p, w_p = _random_step(rng, 5)
    args = [jnp.asarray(a, jnp.float32) for a in (e_m, w_m, e_p, w_p * 0.1)]
    g_main, g_prop = jax.grad(lambda wm, wp: losses.interlevel_ray_loss(args[0], wm, args[2], wp),
                              argnums=(0, 1))(args[1], args[3])
    np.testing.assert_allclose(g_main, 0.0)
    assert np.all(np.asarray(g_prop) <= 0) and np.any(np.asarray(g_prop) < 0)


def test_interlevel_loss_of_a_main_weight_as_small_as_eps_is_finite():
    """A main interval of weight 1e-7 (eps) with no proposal mass over it: w^2 / (w + eps) =
    5e-8, not a division by zero (w - eps passed the tests above)."""
    edges = jnp.asarray([0.0, 0.5, 1.0], jnp.float32)
    got = losses.interlevel_ray_loss(edges, jnp.asarray([1e-7, 0.5], jnp.float32), edges,
                                     jnp.asarray([0.0, 0.5], jnp.float32))
    np.testing.assert_allclose(got, _interlevel_brute(np.asarray(edges), [1e-7, 0.5], np.asarray(edges), [0.0, 0.5]),
                               rtol=1e-3)
    np.testing.assert_allclose(got, 5e-8, rtol=1e-3)


def test_distortion_loss_matches_quadratic_sum_and_prefers_one_narrow_interval():
    rng = np.random.default_rng(5)
    for n in (1, 2, 9, 33):
        e, w = _random_step(rng, n)
        got = losses.distortion_ray_loss(jnp.asarray(e, jnp.float32), jnp.asarray(w, jnp.float32))
        np.testing.assert_allclose(got, _distortion_brute(e, w), rtol=1e-4, atol=1e-7)
    # all mass in one narrow interval beats the same mass spread (or split in two far apart)
    edges = jnp.linspace(0.0, 1.0, 33)
    narrow = jnp.zeros(32).at[10].set(1.0)
    spread = jnp.full(32, 1.0 / 32)
    split = jnp.zeros(32).at[3].set(0.5).at[28].set(0.5)
    values = [float(losses.distortion_ray_loss(edges, w)) for w in (narrow, spread, split)]
    assert values[0] < values[1] and values[0] < values[2], values
    np.testing.assert_allclose(values[0], (1.0 / 32) / 3.0, rtol=1e-5)


def test_squared_error_and_distortion_per_ray_of_a_batch():
    """[..., 3] colours and [..., n] weights of a batch of rays: one value per ray, each the
    NumPy mean / the quadratic sum of its own row (the last axis, not axis
    1 or all of them)."""
    rng = np.random.default_rng(7)
    rgb, target = rng.uniform(size=(2, 4, 3)), rng.uniform(size=(2, 4, 3))
    np.testing.assert_allclose(losses.squared_error(jnp.asarray(rgb), jnp.asarray(target)),
                               np.mean((rgb - target) ** 2, axis=-1), rtol=1e-5)
    rows = [_random_step(rng, 6) for _ in range(3)]
    edges, w = (np.stack([r[i] for r in rows]) for i in (0, 1))
    got = losses.distortion_ray_loss(jnp.asarray(edges, jnp.float32), jnp.asarray(w, jnp.float32))
    np.testing.assert_allclose(got, [_distortion_brute(e, x) for e, x in rows], rtol=1e-4, atol=1e-7)


def test_per_ray_loss_adds_interlevel_and_distortion_terms():
    rng = np.random.default_rng(6)
    e_m, w_m = _random_step(rng, 6)
    e_p, w_p = _random_step(rng, 4)
    final = {"rgb": jnp.full((1, 3), 0.1), "s_edges": jnp.asarray(e_m[None], jnp.float32),
             "weights": jnp.asarray(w_m[None], jnp.float32)}
    prop = {"s_edges": jnp.asarray(e_p[None], jnp.float32), "weights": jnp.asarray(w_p[None], jnp.float32)}
    out = {"levels": [prop, prop, final], "final": final}
    res = losses.per_ray_loss(out, jnp.zeros((1, 3)), interlevel_weight=0.5, distortion_weight=0.25)
    expected = (0.01 + 0.5 * 2 * _interlevel_brute(e_m, w_m, e_p, w_p) + 0.25 * _distortion_brute(e_m, w_m))
    np.testing.assert_allclose(res["loss"], [expected], rtol=1e-4)
    assert res["mse_levels"] == []  # proposal levels render no colour
    # the terms as logged, unweighted (two proposal levels: twice the loop's value)
    np.testing.assert_allclose(res["interlevel"], [2 * _interlevel_brute(e_m, w_m, e_p, w_p)], rtol=1e-4)
    np.testing.assert_allclose(res["distortion"], [_distortion_brute(e_m, w_m)], rtol=1e-4)
