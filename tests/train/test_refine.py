"""train.robust.refine (jaxnerf_grid/train/refine.py): the evidence judged once on whole frames, then
frozen. The frame rule against a brute-force loop, the rendered points against the cameras,
the weights of hand-made residuals, and the trainer's switch: 1 vs 2 devices, exact resume on
either side of it, the frozen weights in the record and in the log."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.masks import robust
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import refine
from jaxnerf_grid.util.io import DataError
from tests.train.test_loop import last_state, tiny_config, tiny_dataset


def brute_frame_evidence(inlier: np.ndarray, patch: int, share: float) -> np.ndarray:
    """The rule written out pixel by pixel: vote over the 3x3 neighbours inside the frame, tile
    share over the pixels of the pixel's patch x patch tile (from the top-left corner)."""
    frames, height, width = inlier.shape
    vote = np.zeros_like(inlier, dtype=float)
    for t in range(frames):
        for r in range(height):
            for c in range(width):
                nb = [inlier[t, i, j] for i in range(r - 1, r + 2) for j in range(c - 1, c + 2)
                      if 0 <= i < height and 0 <= j < width]
                vote[t, r, c] = 1.0 if sum(nb) / len(nb) >= 0.5 else 0.0
    out = np.zeros_like(vote)
    for t in range(frames):
        for r in range(height):
            for c in range(width):
                r0, c0 = (r // patch) * patch, (c // patch) * patch
                tile = vote[t, r0:r0 + patch, c0:c0 + patch]
                kept = tile.mean() >= share
                out[t, r, c] = vote[t, r, c] if (kept or inlier[t, r, c]) else 0.0
    return out


@pytest.mark.parametrize("shape,patch", [((2, 13, 18), 4), ((1, 8, 8), 4), ((3, 7, 5), 3)])
def test_frame_evidence_against_a_pixel_loop(shape, patch):
    rng = np.random.default_rng(sum(shape) + patch)
    inlier = (rng.random(shape) < 0.7).astype(np.float32)
    got = np.asarray(robust.frame_evidence(jnp.asarray(inlier), patch, 0.6))
    np.testing.assert_array_equal(got, brute_frame_evidence(inlier, patch, 0.6))


def test_frame_evidence_finds_a_square_and_keeps_a_flat_frame():
    inlier = np.ones((2, 16, 20), np.float32)
    inlier[1, 4:10, 6:13] = 0.0       # a 6 x 7 transient in frame 1
    inlier[1, 6, 8] = 1.0             # one inlier inside it (dropped by the vote)
    inlier[0, 3, 3] = 0.0             # one outlier on a static frame (re-admitted)
    got = np.asarray(robust.frame_evidence(jnp.asarray(inlier), 4, 0.6))
    assert np.all(got[0] == 1.0)
    assert np.all(got[1, 5:9, 7:12] == 0.0)  # the square's inside, its one inlier included
    assert got[1].sum() >= 16 * 20 - 6 * 7 and got[1].sum() < 16 * 20 - 20


def test_refined_weights_drop_a_pasted_square_and_readmit_a_fitted_flagged_wall():
    """Hand-made residuals: noise of 0.01^2 everywhere, a pasted 6 x 6 square with error 0.3^2
    in frame 0; the prior flags (0) a 5 x 5 region of frame 1 whose residual is as small as the
    rest (a static wall the DPT took for a person) and a 6 x 6 region of frame 2 with error
    0.3^2 (a real transient the DPT found)."""
    rng = np.random.default_rng(0)
    residual = (0.01 * (1 + rng.random((3, 16, 16)))) ** 2
    residual[0, 5:11, 5:11] = 0.3 ** 2
    residual[2, 5:11, 5:11] = 0.3 ** 2
    prior = np.ones_like(residual)
    prior[1, 8:13, 8:13] = 0.0
    prior[2, 5:11, 5:11] = 0.0
    cfg = tiny_config(robust="dpt+robust", robust_patch=4, robust_floor=0.0)
    w = refine.refined_weights(residual.astype(np.float32), prior.astype(np.float32), cfg)
    assert np.all(w[0, 5:11, 5:11] == 0) and w[0].sum() >= 256 - 36 - 12
    assert np.all(w[1, 8:13, 8:13] == 1)                  # re-admitted: the model explains it
    assert np.all(w[2, 5:11, 5:11] == 0)
    confirmed = np.zeros_like(residual)
    confirmed[0, 5:11, 5:11] = 1.0   # another photo shows the same colours there: static after all
    w = refine.refined_weights(residual.astype(np.float32), prior.astype(np.float32), cfg, confirmed)
    assert np.all(w[0] == 1)


def test_rendered_points_lie_on_their_pixels_rays_at_the_rendered_z_depth():
    """render_training_frames' points, taken back into each camera: the pixel's centre through
    the intrinsics, and the camera-frame depth the render's z-depth (not the distance)."""
    ds = tiny_dataset()
    cfg = tiny_config(num_devices=1)
    params = train.init_state(cfg)["params"]
    frames = np.asarray([0, 2])
    residual, points = refine.render_training_frames(params, cfg, ds, frames)
    assert residual.shape == (2, 12, 16) and points.shape == (2, 12, 16, 3)
    from jaxnerf_grid.render import views
    for k, frame in enumerate(frames):
        view = views.render_view(params, cfg, ds, int(frame))
        depth = view["depth"]
        c2w = np.asarray(ds.c2w[frame], np.float64)
        cam = (points[k].reshape(-1, 3) - c2w[:3, 3]) @ c2w[:3, :3]        # world -> camera (x right, y up, -z)
        z = -cam[:, 2]
        np.testing.assert_allclose(z, depth.reshape(-1), rtol=2e-4)
        fx, fy, cx, cy = ds.intrinsics[frame]
        col = cx + fx * cam[:, 0] / z
        row = cy - fy * cam[:, 1] / z
        rows, cols = np.mgrid[0:12, 0:16]
        np.testing.assert_allclose(col, cols.ravel() + 0.5, atol=1e-3)
        np.testing.assert_allclose(row, rows.ravel() + 0.5, atol=1e-3)
        photo = ds.images[frame]
        np.testing.assert_allclose(residual[k], np.mean((np.clip(view["rgb"], 0, 1) - photo) ** 2, -1), rtol=1e-5)


def test_frozen_pool_draws_only_the_kept_pixels_and_refuses_an_empty_one():
    pool = {"pixels": np.arange(24, dtype=np.int32), "weights": np.ones((2, 3, 4), np.float32),
            "neighbours": np.zeros((2, 1), np.int32), "near": 1.0}
    weights = np.zeros((2, 3, 4), np.float32)
    weights[1, 2, 3] = weights[0, 0, 1] = 1.0
    out = refine.frozen_pool(pool, weights)
    np.testing.assert_array_equal(out["pixels"], [0 * 12 + 0 * 4 + 1, 1 * 12 + 2 * 4 + 3])
    assert "neighbours" not in out and out["near"] == 1.0 and out["weights"] is not pool["weights"]
    with pytest.raises(DataError, match="robust.refine"):
        refine.frozen_pool(pool, np.zeros_like(weights))


def refine_config(n=1, **kw):
    kw = {"robust": "dpt+robust", "robust_patch": 4, "robust_warmup": 0.1, "robust_refine": 0.4,
          "max_steps": 10, "checkpoint_every": 2, "log_every": 2, **kw}
    return tiny_config(num_devices=n, **kw)


def test_refine_two_devices_match_one_and_the_record_holds_the_frozen_weights(tmp_path):
    """After step 4 (0.4 x 10) the record is the whole-frame rule of the parameters at step 4
    (recomputed here from that checkpoint), unchanged to the end, and the log's robust_weight
    is its mean; 1 and 2 devices agree."""
    assert jax.local_device_count() >= 2, "run with XLA_FLAGS=--xla_force_host_platform_device_count=2"
    ds = tiny_dataset()
    states = []
    for n in (1, 2):
        cfg = refine_config(n, keep_checkpoints=20)
        train.train(ds, cfg, tmp_path / f"dev{n}", progress=False)
        states.append(last_state(tmp_path / f"dev{n}", cfg, ds))
    diffs = jax.tree_util.tree_map(lambda a, b: float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b)))),
                                   states[0], states[1])
    assert max(jax.tree_util.tree_leaves(diffs)) < 1e-5, diffs
    cfg = refine_config(1)
    from jaxnerf_grid.train import checkpoint
    full = train.init_state(train.config_lib.resolve(cfg, ds), train.train_frames_shape(ds))
    at4 = checkpoint.load_checkpoint(checkpoint.checkpoint_path(tmp_path / "dev1", 4), full)
    pool = train.build_pool(ds, train.config_lib.resolve(cfg, ds))
    expected = refine.judge_frames(at4["params"], train.config_lib.resolve(cfg, ds), ds, pool)
    record = states[0]["robust_record"]
    np.testing.assert_array_equal(record, expected)
    assert set(np.unique(record)) <= {0.0, 1.0}
    log = train.read_log(tmp_path / "dev1" / "metrics.jsonl")
    late = [r["robust_weight"] for r in log if r["step"] > 4]
    assert late and all(abs(v - float(record.mean())) < 1e-6 for v in late)


@pytest.mark.parametrize("stop", [4, 5])
def test_refine_resumes_exactly_on_either_side_of_the_switch(tmp_path, stop):
    """Killed at the switch's step (its checkpoint holds the moving record: the switch is redone
    on resume) or one step after (the checkpoint holds the frozen weights): the resumed run
    ends where the straight one does."""
    ds = tiny_dataset()
    cfg = refine_config(1, checkpoint_every=1)
    straight = train.train(ds, cfg, tmp_path / "straight", progress=False)
    train.train(ds, cfg, tmp_path / "resumed", progress=False, stop_at=stop)
    resumed = train.train(ds, cfg, tmp_path / "resumed", progress=False)
    assert resumed.step == straight.step == 10
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)),
                           resumed.params, straight.params)
    np.testing.assert_array_equal(last_state(tmp_path / "resumed", cfg, ds)["robust_record"],
                                  last_state(tmp_path / "straight", cfg, ds)["robust_record"])


def test_grown_prior_flags_the_pixels_within_the_disc_of_a_masked_pixel():
    """train.robust.prior_grow: the prior is 0 wherever a masked pixel lies within the disc of
    radius g (OpenCV's elliptical element: offsets (dr, dc) with (dr/g)^2 + (dc/g)^2 <= 1 up to its
    rasterisation, checked here against cv2's own element written out as offsets), else the
    ungrown prior; without binary masks it is refused."""
    import cv2

    ds = tiny_dataset()
    masks = np.zeros(ds.images.shape[:3], np.float32)
    masks[0, 5, 7] = masks[1, 0, 0] = masks[2, 9:11, 12:15] = 1.0
    ds.masks = masks
    base = train.prior_weights(ds, tiny_config(robust="dpt+robust", robust_patch=4).train)
    for grow in (1, 2):
        got = train.prior_weights(ds, tiny_config(robust="dpt+robust", robust_patch=4, robust_prior_grow=grow).train)
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))
        offsets = [(r - grow, c - grow) for r in range(2 * grow + 1) for c in range(2 * grow + 1) if disc[r, c]]
        near = np.zeros(masks.shape, bool)
        for f, r, c in zip(*np.nonzero(masks > 0.5)):
            for dr, dc in offsets:
                if 0 <= r + dr < masks.shape[1] and 0 <= c + dc < masks.shape[2]:
                    near[f, r + dr, c + dc] = True
        np.testing.assert_array_equal(got, np.where(near, 0.0, base))
        assert near.sum() > (masks > 0.5).sum()
    ds.masks = None
    with pytest.raises(DataError, match="robust.prior_grow"):
        train.prior_weights(ds, tiny_config(robust="dpt+robust", robust_patch=4, robust_prior_grow=1).train)
