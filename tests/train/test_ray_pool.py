"""ray_pool.py: the 8-bit pool split over devices draws the same batches as the float32 pool.

The reference is `train.build_pool` + `train.gather_batch` (today's float32 pool: a list of flat
pixel ids, a copy of every frame per device) with the same key; the datasets' pixels are
k / 255 (8-bit photos), so the values must be equal, not close.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.data import working
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import ray_pool
from jaxnerf_grid.util import parallel
from jaxnerf_grid.util.io import DataError
from tests.train.test_loop import tiny_config, tiny_dataset

BATCH = 64


def eight_bit(ds: Dataset, weights=None, frame_buffer: bool = False) -> Dataset:
    """ds with its pixels rounded to k / 255 (as float32, or uint8 in a working.frame_buffer) and
    `weights` ([N, H, W], None: the dataset's)."""
    codes = working.to_uint8(ds.images)
    if frame_buffer:
        images = working.frame_buffer(*codes.shape[:3])
        images[...] = codes
    else:
        images = codes.astype(np.float32) / 255.0
    return dataclasses.replace(ds, images=images, weights=ds.weights if weights is None else weights)


def reference_batch(ds: Dataset, cfg, key) -> dict:
    """The float32 pool's global batch for `key`: build_pool, its draw, gather_batch."""
    pool = train.build_pool(ds, cfg)
    ids = jax.random.randint(key, (BATCH,), 0, pool["pixels"].shape[0])
    return jax.device_get(train.gather_batch({k: jnp.asarray(v) for k, v in pool.items()},
                                             jnp.asarray(pool["pixels"])[ids]))


def sharded_batch(ds: Dataset, cfg, key, n: int) -> dict:
    """The 8-bit pool's global batch for `key` on n devices: each device's share, joined."""
    pool = ray_pool.upload(ray_pool.build(ds, cfg), n)
    keys = jnp.stack([key] * n)
    step = jax.pmap(lambda p, k: ray_pool.device_batch(p, k, BATCH, BATCH // n), axis_name=parallel.AXIS,
                    devices=parallel.devices(n))
    return parallel.unshard(jax.device_get(step(pool, keys)))


def two_devices():
    if jax.local_device_count() < 2:
        pytest.skip("needs XLA_FLAGS=--xla_force_host_platform_device_count=2 (set by .ci/run)")


def soft_weights(ds: Dataset, seed: int = 0) -> np.ndarray:
    """More than 256 distinct weights in (0, 1], a few zeros (the float32 fallback)."""
    w = np.random.default_rng(seed).uniform(0.01, 1.0, ds.images.shape[:3]).astype(np.float32)
    w[:, :2, :5] = 0.0
    return w


CASES = {
    "binary masks": lambda ds: eight_bit(ds),                                    # corner of weight 0
    "no masks": lambda ds: eight_bit(ds, weights=np.ones(ds.images.shape[:3], np.float32)),
    "uint8 frame buffer": lambda ds: eight_bit(ds, frame_buffer=True),
    "soft weights": lambda ds: eight_bit(ds, weights=soft_weights(ds)),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("n", [1, 2])
def test_sharded_uint8_batch_equals_the_float32_pools(case, n):
    if n == 2:
        two_devices()
    ds = CASES[case](tiny_dataset(frames=6))  # 5 training frames: the second device's group is padded
    cfg = train.config_lib.resolve(tiny_config(), ds)
    key = jax.random.PRNGKey(7)
    want, got = reference_batch(ds, cfg, key), sharded_batch(ds, cfg, key, n)
    for name in ("rgb", "weight", "image_index", "near", "far"):  # the targets: equal
        np.testing.assert_array_equal(np.asarray(got[name]), np.asarray(want[name]), err_msg=name)
    for name in ("origins", "directions"):  # the same pixels' rays, compiled apart: to the last bit or so
        np.testing.assert_allclose(np.asarray(got[name]), np.asarray(want[name]), rtol=0, atol=3e-7, err_msg=name)


def test_mask_floor_weights_are_coded_exactly():
    ds = eight_bit(tiny_dataset(frames=6))
    masks = np.zeros(ds.images.shape[:3], np.float32)
    masks[:, 5:, :] = 1.0
    ds = dataclasses.replace(ds, masks=masks)
    cfg = train.config_lib.resolve(tiny_config(mask_weight_floor=0.3), ds)
    pool = ray_pool.build(ds, cfg)
    assert "codes" in pool  # {0, 0.7, 1}: three levels, not k / 255, coded exactly
    assert set(np.unique(pool["levels"]).tolist()) == {0.0, np.float32(0.7), 1.0}
    key = jax.random.PRNGKey(3)
    want, got = reference_batch(ds, cfg, key), sharded_batch(ds, cfg, key, 1)
    np.testing.assert_array_equal(got["weight"], want["weight"])
    np.testing.assert_array_equal(got["rgb"], want["rgb"])


def test_pool_holds_one_byte_a_channel_and_shares_the_datasets_frames():
    ds = eight_bit(tiny_dataset(frames=6), weights=np.ones((6, 12, 16), np.float32), frame_buffer=True)
    cfg = train.config_lib.resolve(tiny_config(), ds)
    pool = ray_pool.build(ds, cfg)
    assert pool["rows"].dtype == np.uint8 and np.shares_memory(pool["rows"], ds.images)
    assert "codes" not in pool and "row_start" not in pool  # every weight 1: nothing more per pixel
    assert ray_pool.host_bytes(pool) < ds.images.nbytes + 2 * working.frame_stride(12, 16) * working.FRAME_SPARE


def test_each_device_holds_its_group_of_frames_only():
    two_devices()
    ds = eight_bit(tiny_dataset(frames=6), frame_buffer=True)
    cfg = train.config_lib.resolve(tiny_config(), ds)
    host = ray_pool.build(ds, cfg)
    pool = ray_pool.upload(host, 2)
    per = ray_pool.group_size(5, 2)  # training frames 0..4 stored at dataset frames 0..4: 3 and 2 (+ a spare)
    assert pool["rows"].shape == (2, per, host["rows"].shape[1])
    for d, shard in enumerate(pool["rows"].addressable_shards):
        np.testing.assert_array_equal(np.asarray(shard.data)[0], host["rows"][d * per:(d + 1) * per])


def test_a_pool_past_two_to_the_31_pixels_is_refused_in_one_line():
    # 150 frames of 4000 x 3600 = 2.16e9 pixels, made of one zero-stride pixel: nothing allocated
    frames, h, w = 150, 3600, 4000
    images = np.broadcast_to(np.zeros((1, 1, 1, 3), np.uint8), (frames, h, w, 3))
    ds = Dataset(root="big", images=images, c2w=np.tile(np.eye(4, dtype=np.float32), (frames, 1, 1)),
                 intrinsics=np.tile(np.array([[w, w, w / 2, h / 2]], np.float32), (frames, 1)),
                 split={"train": np.arange(frames), "test": np.arange(1)}, near=0.1, far=10.0)
    cfg = train.config_lib.resolve(tiny_config(), ds)
    with pytest.raises(DataError) as err:
        ray_pool.build(ds, cfg)
    assert "2,160,000,000 training pixels" in str(err.value) and "\n" not in str(err.value)
    last_id = np.asarray([frames * h * w - 1], np.int64)
    assert last_id.astype(np.int32)[0] < 0  # what an int32 flat id of the last pixel would have been


def test_uint8_loading_matches_the_float_load_of_8bit_photos(tmp_path):
    from jaxnerf_grid.data import formats

    ds = eight_bit(tiny_dataset(frames=4))
    formats.save_transforms_json(ds, tmp_path / "data")
    floats = formats.load_dataset(tmp_path / "data", progress=False)
    bytes_ = formats.load_dataset(tmp_path / "data", progress=False, uint8_images=True)
    assert bytes_.images.dtype == np.uint8 and working.frame_rows(bytes_.images) is not None
    np.testing.assert_array_equal(working.as_float(bytes_.images), floats.images)
    # resized working frames (16 x 12 -> 8 x 6, 2 x 2 means) are rounded to the nearest byte
    small = formats.load_dataset(tmp_path / "data", progress=False, max_side=8, cache=False)
    small_bytes = formats.load_dataset(tmp_path / "data", progress=False, max_side=8, cache=False, uint8_images=True)
    error = np.abs(working.as_float(small_bytes.images) - small.images)
    assert small.images.shape == (4, 6, 8, 3) and 0 < error.max() <= 0.5 / 255 + 1e-6
