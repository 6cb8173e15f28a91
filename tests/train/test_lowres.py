"""lowres.py: the resolution schedule's shrunk frames against brute-force loops, and a run whose
first steps train on them: all of its steps equal to a run on frames shrunk by hand, and across
the switch the same on 1 and 2 devices and after a resume."""

import dataclasses

import jax
import numpy as np
import pytest

from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data import working
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import lowres
from tests.train.test_loop import tiny_config, tiny_dataset


def loop_block_mean(image: np.ndarray, f: int) -> np.ndarray:
    """Each whole f x f block's mean of the 8-bit codes, rounded half up, one pixel at a time."""
    codes = working.to_uint8(image).astype(np.int64)
    h, w = image.shape[0] // f, image.shape[1] // f
    out = np.zeros((h, w, image.shape[2]), np.uint8)
    for i in range(h):
        for j in range(w):
            for c in range(image.shape[2]):
                s = sum(int(codes[f * i + a, f * j + b, c]) for a in range(f) for b in range(f))
                out[i, j, c] = int(np.floor(s / (f * f) + 0.5))
    return out


@pytest.mark.parametrize("f", [2, 3])
def test_block_means_round_half_up_and_drop_the_partial_blocks(f):
    image = np.random.default_rng(f).integers(0, 256, (7, 11, 3)).astype(np.uint8)
    np.testing.assert_array_equal(lowres.block_mean_uint8(image, f), loop_block_mean(image, f))
    # a block of 1, 2, 2, 2 means 1.75 -> 2; of 1, 1, 2, 2 means 1.5 -> 2 (half up); of 0, 0, 0, 1 -> 0
    tie = np.array([[1, 2, 1, 2, 0, 0], [2, 2, 1, 2, 0, 1]], np.uint8)[..., None]
    assert lowres.block_mean_uint8(tie, 2)[0, :, 0].tolist() == [2, 2, 0]


def test_a_block_touching_a_zero_weight_is_not_drawn_and_the_mask_floor_comes_first():
    ds = tiny_dataset()
    masks = np.zeros(ds.weights.shape, np.float32)
    masks[:, 6:8, 6:8] = 1.0       # one whole 2x2 block masked, with weight 1: the floor makes it 0.7
    cfg = tiny_config(lowres_share=0.5, mask_weight_floor=0.3)
    small = lowres.lowres_dataset(dataclasses.replace(ds, masks=masks), cfg)
    h, w = ds.height // 2, ds.width // 2
    expected = np.zeros((ds.num_frames, h, w), np.float32)
    for n in ds.split["train"]:        # the held-out frame is not shrunk: the pool never reads it
        for i in range(h):
            for j in range(w):
                block = ds.weights[n, 2 * i:2 * i + 2, 2 * j:2 * j + 2].copy()
                block[masks[n, 2 * i:2 * i + 2, 2 * j:2 * j + 2] > 0.5] = np.minimum(
                    block[masks[n, 2 * i:2 * i + 2, 2 * j:2 * j + 2] > 0.5], 0.7)
                expected[n, i, j] = block.min()
    np.testing.assert_allclose(small.weights, expected)
    assert not small.images[ds.split["test"]].any()
    np.testing.assert_array_equal(small.images[1], loop_block_mean(ds.images[1], 2))
    assert small.weights[0, 1, 1] == 0.0 and small.weights[0, 2, 2] == 1.0   # the 3x3 zero corner reaches block (1, 1)
    np.testing.assert_allclose(small.weights[0, 3, 3], 0.7, rtol=1e-6)
    assert small.masks is None
    assert lowres.lowres_dataset(ds, tiny_config(lowres_share=0.5, use_masks=False)).weights is None


def test_a_shrunk_pixels_ray_passes_through_the_centre_of_its_block():
    ds = tiny_dataset()
    for f in (2, 3):
        k = lowres.scaled_intrinsics(ds.intrinsics, f)[1]
        c2w = ds.c2w[1][None]
        small = rays_lib.rays_for_pixels(c2w, k[0:1], k[1:2], k[2:3], k[3:4], np.float32([2.5]), np.float32([1.5]),
                                         1.0, 8.0)
        big = ds.intrinsics[1]
        full = rays_lib.rays_for_pixels(c2w, big[0:1], big[1:2], big[2:3], big[3:4], np.float32([f * 2.5]),
                                        np.float32([f * 1.5]), 1.0, 8.0)
        np.testing.assert_allclose(small.directions, full.directions, atol=1e-6)
        np.testing.assert_allclose(small.origins, full.origins, atol=1e-6)


def test_the_switch_step_rounds_the_share_and_needs_the_plain_step():
    assert lowres.end_step(tiny_config(lowres_share=0.25).train) == 8          # 7.5 of 30 -> 8
    assert lowres.end_step(tiny_config(lowres_share=0.0).train) == 0
    assert lowres.end_step(tiny_config(lowres_share=0.5, lowres_factor=1).train) == 0
    with pytest.raises(ConfigError, match="train.lowres_share needs train.robust off"):
        lowres.end_step(tiny_config(lowres_share=0.5, robust="robust").train)


def max_diff(a, b) -> float:
    diffs = jax.tree_util.tree_map(lambda x, y: float(np.max(np.abs(np.asarray(x) - np.asarray(y)))), a, b)
    return max(jax.tree_util.tree_leaves(diffs))


def shrunk_by_hand(ds):
    """ds with its frames' 2x2 block means (8-bit), block minimum weights and halved intrinsics."""
    return dataclasses.replace(
        ds, images=np.stack([loop_block_mean(im, 2) for im in ds.images]).astype(np.float32) / np.float32(255),
        weights=np.stack([[[ds.weights[n, 2 * i:2 * i + 2, 2 * j:2 * j + 2].min() for j in range(ds.width // 2)]
                           for i in range(ds.height // 2)] for n in range(ds.num_frames)]).astype(np.float32),
        intrinsics=ds.intrinsics / 2)


def test_the_scheduled_run_equals_a_run_on_frames_shrunk_by_hand_resumed_on_the_working_frames(tmp_path):
    ds = tiny_dataset()
    scheduled = train.train(ds, tiny_config(lowres_share=0.2, num_devices=1), tmp_path / "s", progress=False,
                            stop_at=10)
    train.train(shrunk_by_hand(ds), tiny_config(num_devices=1), tmp_path / "r", progress=False, stop_at=6)
    reference = train.train(ds, tiny_config(num_devices=1), tmp_path / "r", progress=False, stop_at=10)
    plain = train.train(ds, tiny_config(num_devices=1), tmp_path / "p", progress=False, stop_at=10)
    assert max_diff(scheduled.params, reference.params) <= 1e-6
    assert max_diff(scheduled.params, plain.params) > 1e-4       # the shrunk frames changed the run


def test_across_the_switch_two_devices_and_a_resume_train_as_one_device_straight(tmp_path):
    assert jax.local_device_count() >= 2, "run with XLA_FLAGS=--xla_force_host_platform_device_count=2"
    ds = tiny_dataset()
    cfg = tiny_config(lowres_share=0.2)          # steps 0-5 shrunk, 6 on at the working size
    straight = train.train(ds, dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, num_devices=1)),
                           tmp_path / "one", progress=False, stop_at=10)
    two = train.train(ds, cfg, tmp_path / "two", progress=False, stop_at=10)
    train.train(ds, cfg, tmp_path / "resumed", progress=False, stop_at=4)    # before the switch
    train.train(ds, cfg, tmp_path / "resumed", progress=False, stop_at=8)    # resumed across it, then after it
    resumed = train.train(ds, cfg, tmp_path / "resumed", progress=False, stop_at=10)
    never = train.train(ds, tiny_config(), tmp_path / "never", progress=False, stop_at=10)
    assert max_diff(straight.params, two.params) <= 1e-6
    assert max_diff(resumed.params, two.params) <= 1e-6
    assert max_diff(two.params, never.params) > 1e-4
