"""error_map.py: the tiles' draw against its closed-form probabilities, the record's update
against a loop, and runs with the map: 1 and 2 devices equal, a resume exact, the draws
following the record, one-line refusals."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.train import checkpoint, error_map, ray_pool
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.util import parallel
from tests.train.test_loop import tiny_config, tiny_dataset
from tests.train.test_lowres import max_diff


def test_tiles_cover_the_frame_and_the_last_ones_are_cut_short():
    assert error_map.tile_grid(12, 16, 5) == (3, 4)
    t, row, col = np.array([0, 1, 1]), np.array([0, 11, 4]), np.array([0, 15, 5])
    # frame 1, row 11 -> tile row 2, col 15 -> tile col 3: (1 * 3 + 2) * 4 + 3
    assert error_map.tile_ids(t, row, col, 12, 16, 5).tolist() == [0, 23, 13]


def test_tiles_are_drawn_in_proportion_to_their_error_and_pixels_uniformly_inside():
    h, w, tile = 7, 9, 4                  # 2 x 3 tiles a frame, the last row and column cut short
    errors = np.zeros(2 * 2 * 3, np.float32)
    errors[[1, 5, 10]] = [1.0, 3.0, 0.5]
    t, row, col = error_map.draw(jnp.asarray(errors), jax.random.PRNGKey(3), 200_000, h, w, tile)
    t, row, col = np.asarray(t), np.asarray(row), np.asarray(col)
    assert row.max() == h - 1 and col.max() == w - 1 and row.min() == 0 and col.min() == 0
    ids = error_map.tile_ids(t, row, col, h, w, tile)
    mass = errors + error_map.FLOOR * errors.mean() + 1e-12
    np.testing.assert_allclose(np.bincount(ids, minlength=errors.size) / ids.size, mass / mass.sum(), atol=4e-3)
    # tile 5 (frame 0, tile row 1, col 2) holds rows 4-6 and columns 8: every one of its 3 pixels equally
    inside = (ids == 5)
    assert set(zip(row[inside].tolist(), col[inside].tolist())) == {(4, 8), (5, 8), (6, 8)}
    counts = np.bincount(row[inside] - 4, minlength=3) / inside.sum()
    np.testing.assert_allclose(counts, [1 / 3] * 3, atol=0.01)


def test_a_record_of_zeros_draws_every_tile_alike():
    t, row, col = error_map.draw(jnp.zeros(6, jnp.float32), jax.random.PRNGKey(0), 60_000, 8, 12, 4)
    ids = error_map.tile_ids(np.asarray(t), np.asarray(row), np.asarray(col), 8, 12, 4)
    np.testing.assert_allclose(np.bincount(ids, minlength=6) / ids.size, [1 / 6] * 6, atol=0.01)


def test_the_record_moves_half_way_to_the_mean_error_of_the_weighted_rays_in_each_tile():
    errors = np.array([0.2, 0.4, 0.6, 0.8], np.float32)
    ids = np.array([1, 1, 2, 2, 3])
    ray_errors = np.array([0.1, 0.3, 0.9, 5.0, 1.0], np.float32)
    weights = np.array([1.0, 0.5, 1.0, 0.0, 1.0], np.float32)    # ray 3 is masked: counts nothing
    expected = errors.copy()
    for tile in range(4):
        picked = [e for i, e, wt in zip(ids, ray_errors, weights) if i == tile and wt > 0]
        if picked:
            expected[tile] = 0.5 * errors[tile] + 0.5 * sum(picked) / len(picked)
    got = error_map.update(jnp.asarray(errors), jnp.asarray(ids), jnp.asarray(ray_errors), jnp.asarray(weights))
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    assert float(got[0]) == pytest.approx(0.2) and float(got[2]) == pytest.approx(0.75)


def test_the_map_refuses_the_robust_step_and_the_resolution_schedule_in_one_line():
    with pytest.raises(ConfigError, match="train.error_share needs train.robust off"):
        error_map.error_rays(tiny_config(error_share=0.5, robust="robust").train)
    with pytest.raises(ConfigError, match="train.error_share and train.lowres_share"):
        error_map.error_rays(tiny_config(error_share=0.5, lowres_share=0.3).train)
    assert error_map.error_rays(tiny_config(error_share=0.25).train) == 16   # of 64 rays
    assert error_map.error_rays(tiny_config().train) == 0


def test_the_batch_takes_its_last_share_from_the_map_with_colours_and_weights_of_those_pixels():
    assert jax.local_device_count() >= 2, "run with XLA_FLAGS=--xla_force_host_platform_device_count=2"
    ds = tiny_dataset()
    pool = ray_pool.build(ds, tiny_config())           # a 3x3 corner of weight 0: the masked pool
    assert "row_start" in pool
    errors = np.zeros(4 * 3 * 4, np.float32)              # 12 x 16 frames, tiles of 4: 3 x 4 a frame
    errors[(2 * 3 + 1) * 4 + 2] = 1.0                     # tile 30: frame 2, rows 4-7, columns 8-11
    errors[0] = 1.0                                       # frame 0's corner tile, 9 of its 16 pixels masked
    batch, from_errors = 64, 48
    for n in (1, 2):
        step = jax.pmap(lambda p, k, e, n=n: ray_pool.device_batch(p, k, batch, batch // n, errors=e,
                                                                   from_errors=from_errors, tile=4),
                        axis_name=parallel.AXIS, devices=parallel.devices(n))
        out = step(ray_pool.upload(pool, n), parallel.replicate(jax.random.PRNGKey(1), n),
                   parallel.replicate(jnp.asarray(errors), n))
        rgb = np.concatenate(list(np.asarray(out["rgb"])))
        weight = np.concatenate(list(np.asarray(out["weight"])))
        tiles = np.asarray(out["tiles"][0])
        drawn = tiles[batch - from_errors:]
        assert np.mean(np.isin(drawn, [0, 30])) > 0.9 and {0, 30} <= set(drawn.tolist())
        assert np.sum(np.isin(tiles[:batch - from_errors], [0, 30])) < 6   # the uniform share: 2 of 48 tiles
        # each drawn pixel's colour and weight are the dataset's: find them from its tile by brute force
        for k in range(batch - from_errors, batch):
            tile = tiles[k]
            f, rest = divmod(int(tile), 12)
            r0, c0 = (rest // 4) * 4, (rest % 4) * 4
            block = ds.images[f, r0:r0 + 4, c0:c0 + 4].reshape(-1, 3)
            match = np.flatnonzero(np.all(np.abs(block - rgb[k]) <= 0.5 / 255 + 1e-6, axis=1))
            assert match.size >= 1
            wblock = ds.weights[f, r0:r0 + 4, c0:c0 + 4].reshape(-1)
            assert weight[k] in set(wblock[match].tolist())
        if n == 1:
            first = (rgb, weight, tiles)
        else:
            np.testing.assert_array_equal(rgb, first[0])
            np.testing.assert_array_equal(weight, first[1])
            np.testing.assert_array_equal(tiles, first[2])
    assert 0.0 in set(weight[batch - from_errors:].tolist())   # masked pixels of the corner tile drawn, weight 0


def test_with_the_map_two_devices_and_a_resume_train_as_one_device_straight(tmp_path):
    assert jax.local_device_count() >= 2, "run with XLA_FLAGS=--xla_force_host_platform_device_count=2"
    ds = tiny_dataset()
    cfg = tiny_config(field="grid", error_share=0.5, error_tile=4)
    one = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, num_devices=1))
    straight = train.train(ds, one, tmp_path / "one", progress=False, stop_at=12)
    two = train.train(ds, cfg, tmp_path / "two", progress=False, stop_at=12)
    train.train(ds, cfg, tmp_path / "resumed", progress=False, stop_at=10)   # a checkpoint at 10
    resumed = train.train(ds, cfg, tmp_path / "resumed", progress=False, stop_at=12)
    never = train.train(ds, tiny_config(field="grid"), tmp_path / "never", progress=False, stop_at=12)
    assert max_diff(straight.params, two.params) <= 1e-6
    assert max_diff(resumed.params, two.params) <= 1e-6
    assert max_diff(two.params, never.params) > 1e-4


def test_the_record_is_checkpointed_with_the_run_and_absent_without_the_map(tmp_path):
    ds = tiny_dataset()
    cfg = tiny_config(field="grid", error_share=0.5, error_tile=4, num_devices=1, max_steps=30)
    train.train(ds, cfg, tmp_path / "r", progress=False)
    state = train.init_state(dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_images=5)),
                             train.train_frames_shape(ds))
    restored, step = checkpoint.restore_latest(tmp_path / "r", state)
    record = np.asarray(restored["error_map"])
    assert step == 30 and record.shape == (4 * 3 * 4,) and np.count_nonzero(record) > 40
    # the plain run's state has no map
    assert "error_map" not in train.init_state(dataclasses.replace(tiny_config(), model=dataclasses.replace(
        tiny_config().model, num_images=5)), train.train_frames_shape(ds))


def test_the_logged_fit_is_the_uniform_shares_mse_not_the_whole_batchs(tmp_path):
    ds = tiny_dataset()
    cfg = tiny_config(field="grid", error_share=0.5, error_tile=4, num_devices=1, log_every=1)
    train.train(ds, cfg, tmp_path / "r", progress=False, stop_at=1)
    logged = train.read_log(tmp_path / "r" / "metrics.jsonl")[0]["psnr"]
    # the first step's batch, drawn and rendered again with the initial parameters
    settled = config_lib.resolve(cfg, ds)
    state = train.init_state(settled, train.train_frames_shape(ds))
    _, k_batch, k_rays = jax.random.split(state["key"], 3)
    pool = ray_pool.upload(ray_pool.build(ds, settled), 1)
    batch = jax.pmap(lambda p, k, e: ray_pool.device_batch(p, k, 64, 64, errors=e, from_errors=32, tile=4),
                     axis_name=parallel.AXIS, devices=parallel.devices(1))(
        pool, parallel.replicate(k_batch, 1), parallel.replicate(jnp.asarray(state["error_map"]), 1))
    batch = jax.tree_util.tree_map(lambda x: x[0], batch)
    _, terms = train.batch_terms(state["params"], settled, batch, jax.random.split(k_rays, 64))
    mse, w = np.asarray(terms["mse"], np.float64), np.asarray(batch["weight"], np.float64)
    uniform = np.sum(mse[:32] * w[:32]) / np.sum(w[:32])
    whole = np.sum(mse * w) / np.sum(w)
    assert logged == pytest.approx(-10 * np.log10(uniform), abs=1e-3)
    assert abs(-10 * np.log10(whole) - logged) > 1e-2
