"""robust.py: the photometric evidence against a direct NumPy computation (loops over pixels),
on hand-made residuals: random ones, a pasted square, a flat scene, a prior that is wrong."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.masks import robust

DEFAULTS = {"quantile": 0.8, "flagged_quantile": 0.5, "patch_share": 0.6, "floor": 0.0, "spread": 0.0}


def reference_inliers(res, prior, batch_res, quantile, flagged_quantile, floor, spread=0.0, confirmed=None,
                      strict=False):
    """Step 1 of the rule, one pixel at a time with np.quantile and np.median (the spread bound
    on the root residuals). res, prior, confirmed: any shape. strict: a flagged pixel (prior
    below 1/2) needs its residual within the bound and the confirmation."""
    res, prior = np.asarray(res, np.float64), np.asarray(prior, np.float64)
    batch = np.asarray(batch_res, np.float64)
    root = np.sqrt(batch)
    mad_sigma = 1.4826 * np.median(np.abs(root - np.median(root)))
    inlier = np.zeros(res.shape)
    for idx in np.ndindex(res.shape):
        q = flagged_quantile + (quantile - flagged_quantile) * prior[idx]
        bound = (np.median(root) + spread * (1 / 3 + 2 / 3 * prior[idx]) * mad_sigma) ** 2
        inlier[idx] = res[idx] <= max(np.quantile(batch, q), bound, floor)
        seen = confirmed is not None and confirmed[idx] > 0
        if strict and prior[idx] < 0.5:
            inlier[idx] = inlier[idx] and seen
        elif seen:
            inlier[idx] = 1.0
    return inlier


def reference_weights(res, prior, batch_res, quantile, flagged_quantile, patch_share, floor, spread=0.0,
                      confirmed=None, strict=False):
    """The rule of robust.py's docstring, pixel by pixel. res, prior, confirmed: [P, p, p]."""
    inlier = reference_inliers(res, prior, batch_res, quantile, flagged_quantile, floor, spread, confirmed, strict)
    count, p, _ = inlier.shape
    vote = np.zeros(res.shape)
    for k in range(count):
        for i in range(p):
            for j in range(p):
                near = [inlier[k, a, b] for a in range(i - 1, i + 2) for b in range(j - 1, j + 2)
                        if 0 <= a < p and 0 <= b < p]
                vote[k, i, j] = np.mean(near) >= 0.5
    out = np.zeros(res.shape)
    for k in range(count):
        kept = vote[k].mean() >= patch_share
        for i in range(p):
            for j in range(p):
                out[k, i, j] = vote[k, i, j] if kept else vote[k, i, j] * inlier[k, i, j]
    return out


def ours(res, prior, batch_res=None, **kw):
    args = {**DEFAULTS, **kw}
    batch_res = res.reshape(-1) if batch_res is None else batch_res
    return np.asarray(robust.robust_weights(jnp.asarray(res, jnp.float32), jnp.asarray(prior, jnp.float32),
                                            jnp.asarray(batch_res, jnp.float32), **args))


def test_random_residuals_and_priors_match_numpy():
    rng = np.random.default_rng(0)
    res = (rng.random((4, 8, 8)) ** 3).astype(np.float32)
    res[1, 2:7, 1:6] += 1.0                                   # a blob of outliers
    res[3] += 0.5                                             # a whole patch of outliers
    prior = rng.choice([0.0, 0.3, 1.0], size=res.shape).astype(np.float32)
    extra = (rng.random(64) ** 3).astype(np.float32)          # other devices' residuals
    batch = np.concatenate([res.reshape(-1), extra])
    for kw in ({}, {"floor": 0.05}, {"patch_share": 0.9, "quantile": 0.6}, {"spread": 3.0},
               {"spread": 1.0, "quantile": 0.5}):
        want = reference_weights(res, prior, batch, **{**DEFAULTS, **kw})
        np.testing.assert_array_equal(ours(res, prior, batch, **kw), want)
    assert 0 < ours(res, prior, batch).mean() < 1


def test_a_pasted_square_is_found_and_the_background_kept():
    rng = np.random.default_rng(1)
    res = (1e-4 * rng.random((4, 16, 16))).astype(np.float32)   # a static scene fitted to noise
    res[2, 5:11, 4:10] = 0.1 + 0.05 * rng.random((6, 6))         # a pasted 6 x 6 transient
    prior = np.ones_like(res)
    got = ours(res, prior)
    np.testing.assert_array_equal(got, reference_weights(res, prior, res.reshape(-1), **DEFAULTS))
    assert np.all(got[2, 6:10, 5:9] == 0)                       # the square's inside is ignored
    background = np.ones(res.shape, bool)
    background[2, 4:12, 3:11] = False
    # the quantile makes 20 % of the noise outliers; the 3x3 vote re-admits nearly all of them
    assert got[background].mean() > 0.95
    # with the default floor (noise far below it) the background is kept whole
    floored = ours(res, prior, floor=1e-3)
    assert np.all(floored[background] == 1) and np.all(floored[2, 6:10, 5:9] == 0)


def test_the_spread_bound_keeps_a_static_scene_and_still_finds_a_transient():
    """Residuals of a static scene fitted to noise (RMS errors |N(0, 0.02)|, a few 3-sigma
    ones among them): the quantile alone drops a fifth of the pixels before the vote, the spread
    bound (k = 3) almost none; a pasted square (RMS error 0.3) is dropped either way."""
    rng = np.random.default_rng(4)
    res = (np.abs(rng.normal(0.0, 0.02, (8, 8, 8))) ** 2).astype(np.float32)
    res[5, 2:6, 2:6] = 0.09
    prior = np.ones_like(res)
    plain, spread = ours(res, prior), ours(res, prior, spread=3.0)
    np.testing.assert_array_equal(spread, reference_weights(res, prior, res.reshape(-1), **{**DEFAULTS, "spread": 3.0}))
    static = np.ones(res.shape, bool)
    static[5, 1:7, 1:7] = False
    q80 = robust.quantile_of(jnp.asarray(res), jnp.asarray(0.8))
    inlier_plain = np.asarray(robust.inliers(jnp.asarray(res), q80, 0))
    assert inlier_plain[static].mean() < 0.85                  # the quantile cuts its share
    assert spread[static].mean() > 0.99
    assert np.all(spread[5, 3:5, 3:5] == 0) and np.all(plain[5, 3:5, 3:5] == 0)


def test_spread_thresholds_against_numpy():
    rng = np.random.default_rng(5)
    batch = (rng.random(101) ** 4).astype(np.float32)
    prior = np.array([0.0, 0.5, 1.0], np.float32)
    root = np.sqrt(batch.astype(np.float64))
    sigma = 1.4826 * np.median(np.abs(root - np.median(root)))
    want = (np.median(root) + 2.5 * (1 / 3 + 2 / 3 * prior) * sigma) ** 2
    got = np.asarray(robust.spread_thresholds(jnp.asarray(batch), jnp.asarray(prior), 2.5))
    np.testing.assert_allclose(got, want, rtol=1e-5)


@pytest.mark.parametrize("spread", [0.3, 1.5, 3.0])
def test_flagged_quantile_never_binds_with_a_spread(spread):
    """For a fully flagged pixel the quantile is the batch median of the squared residuals, m^2,
    and the spread bound (m + k/3 1.4826 MAD)^2 is never below it (docs/ROBUST.md): any flagged
    quantile up to 0.5 gives the same inliers as the spread bound alone (checked against the
    NumPy reference, which computes both figures)."""
    rng = np.random.default_rng(11)
    batch = (rng.random(257) ** 3).astype(np.float32)
    res = batch[:64].reshape(4, 4, 4)
    prior = np.zeros_like(res)
    args = dict(quantile=0.8, floor=0.0, spread=spread)
    alone = reference_inliers(res, prior, batch, flagged_quantile=0.0, **args)
    for q in (0.0, 0.25, 0.5):
        got = np.asarray(robust.pixel_inliers(jnp.asarray(res), jnp.asarray(prior), jnp.asarray(batch),
                                              flagged_quantile=q, **args))
        np.testing.assert_array_equal(got, alone)
    # without a spread the quantile is the only bar, and it does bind
    no_spread = reference_inliers(res, prior, batch, flagged_quantile=0.5, quantile=0.8, floor=0.0, spread=0.0)
    assert 0 < no_spread.mean() < 1


def test_warmup_steps_are_a_fraction_of_the_run():
    assert robust.warmup_steps(0.2, 2400) == 480
    assert robust.warmup_steps(0.0, 2400) == 0
    assert robust.warmup_steps(1.0, 7) == 7


def test_a_flat_scene_has_no_outliers():
    res = np.full((3, 8, 8), 0.02, np.float32)                 # every residual the same
    assert np.all(ours(res, np.ones_like(res)) == 1)
    noisy = (np.random.default_rng(2).random((3, 8, 8)) * 5e-4).astype(np.float32)
    assert np.all(ours(noisy, np.ones_like(noisy), floor=1e-3) == 1)


def test_the_prior_sets_how_strict_the_evidence_is():
    """A flagged pixel is re-admitted only below the flagged quantile (the batch median); an
    unflagged one is kept up to the 0.8 quantile; a transient the prior missed is dropped."""
    res = np.zeros((4, 4, 4), np.float32)
    res[0] = 0.01                           # fitted well, flagged by a wrong prior
    res[1] = 0.03                           # fitted so-so: between the median and the 0.8 quantile
    res[2] = 0.03
    res[3] = 0.5                            # a transient the prior missed
    batch = np.concatenate([res.reshape(-1), np.full(32, 0.005, np.float32)])  # median 0.02, 0.8 quantile 0.03
    prior = np.ones_like(res)
    prior[0] = 0.0
    prior[1] = 0.0
    got = ours(res, prior, batch)
    np.testing.assert_array_equal(got, reference_weights(res, prior, batch, **DEFAULTS))
    assert np.all(got[0] == 1)              # re-admitted
    assert np.all(got[1] == 0)              # flagged and not fitted well enough: stays out
    assert np.all(got[2] == 1)              # the same residual, unflagged: kept
    assert np.all(got[3] == 0)              # missed transient: down-weighted


def test_smoothing_counts_only_neighbours_inside_the_patch():
    x = np.random.default_rng(3).random((2, 5, 5)).astype(np.float32)
    want = np.zeros_like(x)
    for k in range(2):
        for i in range(5):
            for j in range(5):
                want[k, i, j] = x[k, max(i - 1, 0):i + 2, max(j - 1, 0):j + 2].mean()
    np.testing.assert_allclose(np.asarray(robust.smooth_3x3(jnp.asarray(x))), want, rtol=1e-6)


def test_scattered_rays_are_judged_alone_against_numpy():
    """robust.pixel_inliers (a scattered ray's weight, train.robust.scattered): the threshold,
    floor and confirmation of each pixel with no vote, against the loop."""
    rng = np.random.default_rng(1)
    res = (rng.random(200) ** 3).astype(np.float32)
    res[:20] += 1.0
    prior = rng.choice([0.0, 0.5, 1.0], size=200).astype(np.float32)
    confirmed = (rng.random(200) < 0.2).astype(np.float32)
    batch = np.concatenate([res, (rng.random(100) ** 3).astype(np.float32)])
    for kw in ({"floor": 0.0, "spread": 0.0}, {"floor": 0.05, "spread": 1.5}, {"floor": 0.0, "spread": 3.0}):
        for conf in (None, confirmed):
            got = robust.pixel_inliers(jnp.asarray(res), jnp.asarray(prior), jnp.asarray(batch), 0.8, 0.5,
                                       confirmed=None if conf is None else jnp.asarray(conf), **kw)
            want = reference_inliers(res, prior, batch, 0.8, 0.5, confirmed=conf, **kw)
            np.testing.assert_array_equal(np.asarray(got), want)
    assert 0 < want.mean() < 1 and want[confirmed > 0].min() == 1.0


def test_strict_readmission_needs_the_residual_and_the_confirmation_of_a_flagged_pixel():
    """train.robust.strict_readmit: a flagged pixel (prior < 1/2) is an inlier only when its
    residual passes *and* another photo confirms it (never without confirmation); a pixel with
    prior 1/2 or more keeps the usual either-or. robust.pixel_inliers and robust.batch_weights
    (patches and scattered rays) against the loops, and the cases by hand."""
    rng = np.random.default_rng(7)
    res = (rng.random(3 * 16 + 40) ** 3).astype(np.float32)
    res[::7] += 1.0
    prior = rng.choice([0.0, 0.3, 0.5, 1.0], size=res.shape).astype(np.float32)
    conf = (rng.random(res.shape) < 0.4).astype(np.float32)
    batch = np.concatenate([res, (rng.random(50) ** 3).astype(np.float32)])
    for confirmed in (conf, None):
        got = robust.pixel_inliers(jnp.asarray(res), jnp.asarray(prior), jnp.asarray(batch), 0.8, 0.5, 0.0, 1.5,
                                   None if confirmed is None else jnp.asarray(confirmed), strict_readmit=True)
        want = reference_inliers(res, prior, batch, 0.8, 0.5, 0.0, 1.5, confirmed, strict=True)
        np.testing.assert_array_equal(np.asarray(got), want)
    loose = reference_inliers(res, prior, batch, 0.8, 0.5, 0.0, 1.5, conf)
    strict = reference_inliers(res, prior, batch, 0.8, 0.5, 0.0, 1.5, conf, strict=True)
    flagged = prior < 0.5
    assert np.array_equal(strict[~flagged], loose[~flagged]) and (strict[flagged] < loose[flagged]).any()
    assert want[flagged].max() == 0.0 and want[~flagged].max() == 1.0   # no confirmation: none re-admitted
    got = np.asarray(robust.batch_weights(jnp.asarray(res), jnp.asarray(prior), jnp.asarray(batch), 48, 4,
                                          0.8, 0.5, 0.6, 0.0, 1.5, jnp.asarray(conf), strict_readmit=True))
    want_p = reference_weights(res[:48].reshape(3, 4, 4), prior[:48].reshape(3, 4, 4), batch, 0.8, 0.5, 0.6, 0.0,
                               1.5, conf[:48].reshape(3, 4, 4), strict=True)
    np.testing.assert_array_equal(got[:48], want_p.reshape(-1))
    np.testing.assert_array_equal(got[48:], strict[48:])
    # by hand: residual 0 (an inlier) flagged and unconfirmed -> out; confirmed -> in; unflagged -> in
    one = lambda r, p, c: float(robust.pixel_inliers(jnp.asarray([r, 0.5, 0.5], jnp.float32),  # noqa: E731
                                                     jnp.asarray([p, 1.0, 1.0], jnp.float32),
                                                     jnp.asarray([r, 0.5, 0.5], jnp.float32), 0.8, 0.5, 0.0, 0.0,
                                                     jnp.asarray([c, 0.0, 0.0], jnp.float32), True)[0])
    assert (one(0.0, 0.0, 0.0), one(0.0, 0.0, 1.0), one(0.0, 1.0, 0.0), one(9.0, 0.0, 1.0)) == (0.0, 1.0, 1.0, 0.0)


def test_a_mixed_batch_votes_in_its_patches_and_judges_its_scattered_rays_alone():
    """robust.batch_weights (train's join): the first rays are patches (the whole rule), the
    rest scattered pixels (the inlier test alone), against the loops."""
    rng = np.random.default_rng(2)
    res = (rng.random(3 * 16 + 40) ** 3).astype(np.float32)
    res[5:9] += 1.0                                       # outliers inside a patch
    res[60:64] += 1.0                                     # scattered outliers
    res[70] = 1e-4                                        # a lone scattered inlier among outliers
    res[71:74] += 1.0
    prior = rng.choice([0.0, 1.0], size=res.shape).astype(np.float32)
    conf = (rng.random(res.shape) < 0.1).astype(np.float32)
    batch = np.concatenate([res, (rng.random(50) ** 3).astype(np.float32)])
    args = (0.8, 0.5, 0.6, 0.0, 1.5)
    for confirmed in (None, conf):
        got = np.asarray(robust.batch_weights(jnp.asarray(res), jnp.asarray(prior), jnp.asarray(batch), 48, 4,
                                              *args, None if confirmed is None else jnp.asarray(confirmed)))
        want_p = reference_weights(res[:48].reshape(3, 4, 4), prior[:48].reshape(3, 4, 4), batch, 0.8, 0.5, 0.6,
                                   0.0, 1.5) if confirmed is None else None
        want_s = reference_inliers(res[48:], prior[48:], batch, 0.8, 0.5, 0.0, 1.5,
                                   None if confirmed is None else confirmed[48:])
        np.testing.assert_array_equal(got[48:], want_s)
        if want_p is not None:
            np.testing.assert_array_equal(got[:48], want_p.reshape(-1))
    assert got[48:].min() == 0.0 and got[70] == 1.0  # scattered outliers dropped, a lone inlier kept
    np.testing.assert_array_equal(
        np.asarray(robust.batch_weights(jnp.asarray(res[:48]), jnp.asarray(prior[:48]), jnp.asarray(batch), 48, 4,
                                        *args)), reference_weights(res[:48].reshape(3, 4, 4),
                                                                   prior[:48].reshape(3, 4, 4), batch, 0.8, 0.5, 0.6,
                                                                   0.0, 1.5).reshape(-1))


def test_the_devices_take_their_patches_then_their_scattered_rays():
    """robust.device_layout: 2 devices, 8 patch rays and 4 scattered ones."""
    np.testing.assert_array_equal(np.asarray(robust.device_layout(8, 4, 2)), [0, 1, 2, 3, 8, 9, 4, 5, 6, 7, 10, 11])
    np.testing.assert_array_equal(np.asarray(robust.device_layout(8, 4, 1)), np.arange(12))
    np.testing.assert_array_equal(np.asarray(robust.device_layout(8, 0, 2)), np.arange(8))
    ids = np.asarray(robust.draw_pixels(jax.random.PRNGKey(0), 5000, 3, 7, 9))
    assert ids.min() >= 0 and ids.max() < 3 * 7 * 9 and len(np.unique(ids)) > 150  # spread over every frame


def test_patches_are_squares_inside_the_frames():
    ids = np.asarray(robust.draw_patches(jax.random.PRNGKey(0), 50, 3, 7, 9, 4)).reshape(50, 4, 4)
    frame, pix = ids // 63, ids % 63
    row, col = pix // 9, pix % 9
    for k in range(50):
        assert np.all(frame[k] == frame[k, 0, 0]) and 0 <= frame[k, 0, 0] < 3
        np.testing.assert_array_equal(row[k], row[k, 0, 0] + np.arange(4)[:, None] + 0 * np.arange(4))
        np.testing.assert_array_equal(col[k], col[k, 0, 0] + np.arange(4)[None, :] + 0 * np.arange(4)[:, None])
        assert row[k].max() < 7 and col[k].max() < 9


def test_strided_patches_are_grids_inside_the_frames():
    """train.robust.patch_stride: a patch's pixels `stride` apart along rows and columns, the
    whole grid, (p - 1) stride + 1 pixels across, inside the frame (every start reachable)."""
    assert robust.patch_span(4, 1) == 4 and robust.patch_span(4, 3) == 10 and robust.patch_span(1, 5) == 1
    ids = np.asarray(robust.draw_patches(jax.random.PRNGKey(1), 400, 2, 12, 11, 4, 3)).reshape(400, 4, 4)
    frame, pix = ids // 132, ids % 132
    row, col = pix // 11, pix % 11
    for k in range(400):
        assert np.all(frame[k] == frame[k, 0, 0])
        np.testing.assert_array_equal(row[k], row[k, 0, 0] + 3 * np.arange(4)[:, None] + 0 * np.arange(4))
        np.testing.assert_array_equal(col[k], col[k, 0, 0] + 3 * np.arange(4)[None, :] + 0 * np.arange(4)[:, None])
    assert row.max() == 11 and col.max() == 10                     # the last rows and columns are reached
    assert set(row[:, 0, 0].tolist()) == {0, 1, 2} and set(col[:, 0, 0].tolist()) == {0, 1}


def test_the_record_moves_halfway_to_each_new_weight():
    record = np.ones((2, 3, 4), np.float32)
    ids = np.array([0, 5, 23])
    got = np.asarray(robust.ema_update(jnp.asarray(record), jnp.asarray(ids), jnp.asarray([0.0, 1.0, 0.0])))
    want = record.reshape(-1).copy()
    want[[0, 23]] = 0.5
    np.testing.assert_array_equal(got.reshape(-1), want)


@pytest.mark.parametrize("mode", ["off", "robust", "dpt+robust", "bad"])
def test_modes_are_checked(mode):
    from jaxnerf_grid.config.schema import ConfigError
    from jaxnerf_grid.train import loop as train

    if mode == "bad":
        with pytest.raises(ConfigError, match="train.robust"):
            train.make_config("ours", {"train": {"robust": mode}})
        return
    cfg = train.make_config("ours", {"train": {"robust": mode, "batch_rays": 128, "robust_patch": 8}})
    train.check_robust(cfg.train, 2)
    if mode != "off":
        with pytest.raises(ConfigError, match="train.batch_rays"):
            train.check_robust(cfg.train, 4)


def test_the_switch_is_settable_with_set():
    from jaxnerf_grid.config import schema as config
    from jaxnerf_grid.train import loop as train

    overrides = config.parse_sets(["train.robust=dpt+robust", "train.robust.patch=16"], train.RunConfig)
    cfg = train.make_config("nerf", overrides)
    assert cfg.train.robust.mode == "dpt+robust" and cfg.train.robust.patch == 16
    assert train.make_config("nerf").train.robust.mode == "off"


def test_bad_settings_are_one_line_errors_naming_the_key_or_folder():

    from jaxnerf_grid.config.schema import ConfigError
    from jaxnerf_grid.train import loop as train
    from jaxnerf_grid.util.io import DataError
    from tests.train.test_loop import tiny_config, tiny_dataset

    ds = tiny_dataset()                                    # 16 x 12 frames
    with pytest.raises(ConfigError, match="train.robust.patch = 16"):
        train.build_pool(ds, tiny_config(robust="robust", robust_patch=16, batch_rays=512))
    ds.weights = None
    with pytest.raises(DataError, match="tiny: train.robust = dpt\\+robust needs the dataset's masks"):
        train.build_pool(ds, tiny_config(robust="dpt+robust", robust_patch=4))
    assert train.build_pool(ds, tiny_config(robust="robust", robust_patch=4))["weights"].min() == 1
    from jaxnerf_grid.train import runs  # refused before a run folder is written
    with pytest.raises(DataError, match="needs the dataset's masks"):
        runs.check_run(tiny_config(robust="dpt+robust", robust_patch=4), ds, num_devices=2)


def test_late_ignored_share_averages_the_batches_of_the_last_quarter():
    log = [{"step": 10, "robust_weight": 0.2}, {"step": 80, "robust_weight": 0.9}, {"step": 90},
           {"step": 100, "robust_weight": 0.7}, {"step": 60, "robust_weight": 0.0}]
    assert robust.late_ignored_share(log, 100) == pytest.approx(1 - (0.9 + 0.7) / 2)
    assert robust.late_ignored_share(log, 100, tail=0.5) == pytest.approx(1 - (0.0 + 0.9 + 0.7) / 3)
    assert robust.late_ignored_share(log, 100, tail=0.95) == pytest.approx(1 - (0.2 + 0.9 + 0.7 + 0.0) / 4)
    assert robust.late_ignored_share([{"step": 5, "loss": 1.0}], 100) is None
