"""The robust step's lean pool (`train.robust_pool`) trains on the float32 pool's values.

The reference is `train.build_pool` (float32 frames and weights, a list of every pixel id): the
batch (rgb, weight), the multi-view confirmation, refine.py's reads and a few robust training
steps must be bit-identical from either pool; the lean one holds 8-bit frames as uint8 and
the weights as uint8 codes into a table where one exists.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.data import working
from jaxnerf_grid.masks import photo_consistency
from jaxnerf_grid.masks import robust as robust_lib
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import ray_pool, refine
from jaxnerf_grid.util import parallel
from tests.train.test_loop import tiny_config, tiny_dataset
from tests.train.test_ray_pool import soft_weights


def eight_bit(ds, weights=None):
    """ds with uint8 frames and `weights` ([N, H, W]; None: the dataset's binary corner)."""
    return dataclasses.replace(ds, images=working.to_uint8(ds.images),
                               weights=ds.weights if weights is None else weights)


def three_levels(ds):
    """Weights in {0, 0.3, 1}: not k / 255, so the table is the distinct values."""
    w = np.ones(ds.images.shape[:3], np.float32)
    w[:, 4:8, 2:9] = 0.3
    w[:, :3, :3] = 0.0
    return w


# (dataset, train.robust mode, the lean pool's image and weight dtypes)
CASES = {
    "no weights": (lambda ds: eight_bit(ds), "robust", np.uint8, np.uint8),
    "binary weights": (lambda ds: eight_bit(ds), "dpt+robust", np.uint8, np.uint8),
    "three levels": (lambda ds: eight_bit(ds, three_levels(ds)), "dpt+robust", np.uint8, np.uint8),
    "soft weights": (lambda ds: eight_bit(ds, soft_weights(ds)), "dpt+robust", np.uint8, np.float32),
    "float frames": (lambda ds: ds, "dpt+robust", np.float32, np.uint8),
}


def case(name, **kw):
    """(dataset, resolved config, lean pool, float32 pool) of a CASES entry."""
    make, mode, _, _ = CASES[name]
    ds = make(tiny_dataset(arc=0.1))
    cfg = train.config_lib.resolve(tiny_config(num_devices=1, robust=mode, robust_patch=4, robust_confirm=0.01,
                                               **kw), ds)
    return ds, cfg, train.robust_pool(ds, cfg), train.build_pool(ds, cfg)


def on_device(pool):
    return {k: jnp.asarray(v) for k, v in pool.items()}


def drawn_ids(pool, key):
    """Four 4x4 patches and 64 scattered pixels over the pool's frames, [128] flat ids."""
    frames, height, width = pool["weights"].shape
    return jnp.concatenate([robust_lib.draw_patches(key, 4, frames, height, width, 4),
                            robust_lib.draw_pixels(jax.random.fold_in(key, 1), 64, frames, height, width)])


@pytest.mark.parametrize("name", sorted(CASES))
def test_lean_pool_batch_and_confirmation_equal_the_float32_pools(name):
    _, _, image_dtype, weight_dtype = CASES[name]
    ds, cfg, lean, full = case(name)
    assert lean["images"].dtype == image_dtype and lean["weights"].dtype == weight_dtype
    assert ("levels" in lean) == (weight_dtype == np.uint8) and "pixels" not in lean
    for seed in range(3):
        ids = drawn_ids(lean, jax.random.PRNGKey(seed))
        got, want = (jax.device_get(train.gather_batch(on_device(p), ids)) for p in (lean, full))
        assert got.keys() == want.keys()
        for k in want:
            assert got[k].dtype == want[k].dtype, k
            np.testing.assert_array_equal(got[k], want[k], err_msg=k)
        points = jnp.asarray(want["origins"] + want["directions"] * 3.0)
        errors = []
        for p in (lean, full):
            d = on_device(p)
            frames, height, width = p["weights"].shape
            frame, pix = ids // (height * width), ids % (height * width)
            errors.append(np.asarray(photo_consistency.confirmation_errors(
                d["images"], d["c2w"], d["intrinsics"], d["neighbours"], frame, pix // width, pix % width,
                points, ray_pool.byte_table(d["images"]))))
        np.testing.assert_array_equal(errors[0], errors[1])
        finite = errors[1][np.isfinite(errors[1])]
        assert finite.size > 10
        threshold = float(np.median(finite))
        flags = [np.asarray(photo_consistency.confirmed_at_ids(
            d["images"], d["c2w"], d["intrinsics"], d["neighbours"], ids, points, threshold,
            ray_pool.byte_table(d["images"]))) for d in map(on_device, (lean, full))]
        np.testing.assert_array_equal(flags[0], flags[1])
        assert 0 < flags[1].sum() < flags[1].size


@pytest.mark.parametrize("name", ["binary weights", "soft weights"])
def test_refine_reads_the_same_weights_and_confirmation_from_the_lean_pool(name):
    ds, cfg, lean, full = case(name)
    np.testing.assert_array_equal(ray_pool.host_weights(lean), full["weights"])
    assert ray_pool.host_weights(lean).dtype == np.float32
    frames, height, width = full["weights"].shape
    rng = np.random.default_rng(0)
    points = (full["c2w"][:, None, None, :3, 3] * rng.uniform(0.0, 0.3, (frames, height, width, 1))).astype(np.float32)
    np.testing.assert_array_equal(refine.confirmed_frames(lean, points, 0.01),
                                  refine.confirmed_frames(full, points, 0.01))
    residual = rng.uniform(0, 0.05, (frames, height, width)).astype(np.float32)
    np.testing.assert_array_equal(refine.refined_weights(residual, ray_pool.host_weights(lean), cfg),
                                  refine.refined_weights(residual, full["weights"], cfg))
    frozen = refine.frozen_pool(lean, full["weights"])
    assert "levels" not in frozen and frozen["weights"].dtype == np.float32


@pytest.mark.parametrize("name", ["binary weights", "three levels"])
def test_robust_steps_on_the_lean_pool_give_the_float32_pools_params(name):
    """Three robust steps (evidence from the first, patches and scattered pixels, the
    confirmation on) from either pool: the same parameters, record and stats, bit for bit."""
    ds, cfg, lean, full = case(name, robust_warmup=0.0, robust_scattered=0.5)
    step = train.make_train_step(cfg, 1)
    ends = []
    for pool in (lean, full):
        state = parallel.replicate(train.init_state(cfg, train.train_frames_shape(ds)), 1)
        pool_r = parallel.replicate(pool, 1)
        for _ in range(3):
            state, stats = step(state, pool_r)
        ends.append(jax.device_get((state, stats)))
    leaves = [jax.tree_util.tree_leaves(e) for e in ends]
    assert len(leaves[0]) == len(leaves[1])
    for a, b in zip(*leaves):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert 0 < float(ends[1][1]["robust_weight"][0]) < 1


def test_lean_pool_host_bytes_against_the_float32_pools():
    """uint8 frames (3 bytes a pixel) and weight codes (1, + a 1 KiB table) against float32
    frames, weights and pixel ids (20 bytes a pixel); soft weights stay 4 bytes a pixel."""
    for name, weight_bytes, table in (("binary weights", 1, 256 * 4), ("soft weights", 4, 0)):
        ds, cfg, lean, full = case(name)
        frames, height, width = full["weights"].shape
        k = full["neighbours"].shape[1]
        small = frames * (16 * 4 + 4 * 4 + 4 + k * 4)  # c2w, intrinsics, frame, neighbours
        pixels = frames * height * width
        assert ray_pool.host_bytes(full) == pixels * (12 + 4 + 4) + small
        assert ray_pool.host_bytes(lean) == pixels * (3 + weight_bytes) + table + small
