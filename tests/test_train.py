"""train.py: ray pool, data-parallel equivalence, the non-finite guard, rendering, learning."""

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid import rays as rays_lib, train, views
from jaxnerf_grid.data.dataset import Dataset

TINY_FIELD = {"depth": 2, "width": 32, "skip": 1, "pos_max_deg": 4, "dir_max_deg": 2, "view_width": 16}
TINY_GRID = {"kind": "grid", "depth": 1, "width": 16, "dir_max_deg": 2, "view_width": 16, "view_depth": 2,
             "density_activation": "exp", "geo_features": 7,
             "grid": {"num_levels": 4, "features_per_level": 2, "log2_table_size": 10, "min_resolution": 4,
                      "max_resolution": 64, "init_scale": 0.1}}
TINY_PROPOSAL = {**TINY_GRID, "width": 8, "grid": {**TINY_GRID["grid"], "num_levels": 2, "max_resolution": 16}}


def tiny_dataset(width=16, height=12, frames=5, seed=0, arc=1.0) -> Dataset:
    """A ball of radius 0.7 coloured by its normal, in front of a sky gradient, seen from a ring
    of cameras (spread over `arc` of the full circle); the last frame is the test frame; a 3x3
    corner of each frame has weight 0."""
    c2w, images = [], []
    fx = 0.5 * width / np.tan(np.radians(30))
    for k in range(frames):
        a = 2 * np.pi * arc * k / frames
        m = np.asarray(rays_lib.look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0, 0, 0]))
        r = rays_lib.generate_rays(jnp.asarray(m), fx, fx, width / 2, height / 2, width, height)
        o, d = np.asarray(r.origins, np.float64), np.asarray(r.directions, np.float64)
        b = np.sum(o * d, -1)
        disc = b * b - (np.sum(o * o, -1) - 0.49)
        t = -b - np.sqrt(np.maximum(disc, 0))
        n = (o + t[..., None] * d) / 0.7
        sky = np.stack([0.4 + 0.3 * d[..., 2], 0.6 + 0.2 * d[..., 2], np.full(d.shape[:-1], 0.9)], -1)
        img = np.where((disc > 0)[..., None], 0.5 + 0.5 * n, sky)
        c2w.append(m)
        images.append(img)
    weights = np.ones((frames, height, width), np.float32)
    weights[:, :3, :3] = 0.0
    return Dataset(root=Path("tiny"), images=np.asarray(images, np.float32), c2w=np.asarray(c2w, np.float32),
                   intrinsics=np.tile(np.array([[fx, fx, width / 2, height / 2]], np.float32), (frames, 1)),
                   split={"train": np.arange(frames - 1), "test": np.array([frames - 1])},
                   near=1.0, far=8.0, weights=weights)


def tiny_config(method="ours", field="mlp", **train_kw):
    """field "mlp": the MLP with 8 + 8 hierarchical samples; "grid": a hash grid with one proposal
    round of 12 samples -> 8, and the distortion loss on."""
    model = {"field": TINY_FIELD, "sampler": {"kind": "hierarchical", "samples": [8, 8]}}
    if field == "grid":
        model.update({"field": TINY_GRID, "sampler": {"kind": "proposal", "samples": [12], "main_samples": 8,
                                                      "field": TINY_PROPOSAL}})
        train_kw.setdefault("distortion_loss_weight", 0.01)
    overrides = {"model": model,
                 "train": {"batch_rays": 64, "max_steps": 30, "checkpoint_every": 10, "log_every": 5,
                           "warmup": 5, "lr_init": 5e-3, "lr_final": 1e-3, "chunk": 256, "num_devices": 2,
                           **train_kw}}
    return train.make_config(method, overrides)


def test_pool_holds_exactly_the_weighted_pixels_and_rays_match():
    ds = tiny_dataset()
    cfg = tiny_config()
    pool = train.build_pool(ds, cfg)
    expected = [(f * 12 + r) * 16 + c for f in range(4) for r in range(12) for c in range(16)
                if ds.weights[f, r, c] > 0]
    np.testing.assert_array_equal(pool["pixels"], expected)
    ids = jnp.asarray([pool["pixels"][0], pool["pixels"][-1]])
    batch = train.gather_batch({k: jnp.asarray(v) for k, v in pool.items()}, ids)
    full = views.camera_rays(ds, 3, 1.0, 8.0)
    np.testing.assert_allclose(batch["directions"][1], full.directions[11, 15], atol=1e-6)
    np.testing.assert_allclose(batch["rgb"][1], ds.images[3, 11, 15])
    np.testing.assert_allclose(batch["rgb"][0], ds.images[0, 0, 3])
    # use_masks off (the baselines): every pixel is a target
    assert train.build_pool(ds, tiny_config("nerf"))["pixels"].size == 4 * 12 * 16


@pytest.mark.parametrize("field,sparse_adam", [("mlp", False), ("grid", False), ("grid", True)])
def test_two_devices_match_one_device(tmp_path, field, sparse_adam):
    assert jax.local_device_count() >= 2, "run with XLA_FLAGS=--xla_force_host_platform_device_count=2"
    ds = tiny_dataset()
    results = []
    for n in (1, 2):
        cfg = tiny_config(field=field, num_devices=n, sparse_adam=sparse_adam)
        results.append(train.train(ds, cfg, tmp_path / f"dev{n}", progress=False, stop_at=4).params)
    diffs = jax.tree_util.tree_map(lambda a, b: float(np.max(np.abs(a - b))), *results)
    cfg = tiny_config(field=field)
    initial = train.init_state(dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_images=5)))["params"]
    moved = jax.tree_util.tree_map(lambda a, b: float(np.max(np.abs(a - b))), results[0], initial)
    assert max(jax.tree_util.tree_leaves(diffs)) < 1e-5, diffs
    assert max(jax.tree_util.tree_leaves(moved)) > 1e-3  # the steps did change the parameters
    if field == "grid":  # the proposal field is trained too (by the interlevel loss)
        assert max(jax.tree_util.tree_leaves(moved["proposal"])) > 1e-3


def test_sparse_adam_leaves_untouched_table_rows_where_dense_adam_moves_them(tmp_path):
    # train.sparse_adam reaches the step: in step 4, lazy Adam keeps every table row that step's
    # batch did not touch; dense Adam also moves the rows touched in steps 1-3 (their momentum)
    ds = tiny_dataset()
    kept = {}
    for sparse in (False, True):
        cfg = tiny_config(field="grid", num_devices=1, sparse_adam=sparse)
        before = train.train(ds, cfg, tmp_path / f"sparse{sparse}", progress=False, stop_at=3).params
        after = train.train(ds, cfg, tmp_path / f"sparse{sparse}", progress=False, stop_at=4).params
        pairs = zip(jax.tree_util.tree_leaves_with_path(after), jax.tree_util.tree_leaves(before))
        kept[sparse] = sum(int(np.sum(np.all(np.asarray(a) == np.asarray(b), axis=-1)))
                           for (path, a), b in pairs if "table" in jax.tree_util.keystr(path))
    assert kept[True] > kept[False] + 10, kept


def test_grid_proposal_run_resumes_exactly(tmp_path):
    ds = tiny_dataset()
    cfg = tiny_config(field="grid", max_steps=20)
    train.train(ds, cfg, tmp_path / "resumed", progress=False, stop_at=10)   # checkpoint at step 10
    resumed = train.train(ds, cfg, tmp_path / "resumed", progress=False)
    straight = train.train(ds, cfg, tmp_path / "straight", progress=False)
    assert resumed.step == straight.step == 20
    diffs = jax.tree_util.tree_map(lambda a, b: float(np.max(np.abs(np.asarray(a) - np.asarray(b)))),
                                   resumed.params, straight.params)
    assert max(jax.tree_util.tree_leaves(diffs)) <= 1e-6, diffs


def test_non_finite_steps_are_skipped_and_logged(tmp_path, caplog):
    ds = tiny_dataset()
    ds.images[:] = np.nan
    cfg = tiny_config()
    before = train.init_state(dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_images=5)))
    with caplog.at_level("WARNING"):
        res = train.train(ds, cfg, tmp_path, progress=False, stop_at=3)
    assert res.skipped_steps == [1, 2, 3]
    assert "non-finite" in caplog.text
    same = jax.tree_util.tree_map(lambda a, b: bool(np.array_equal(a, b)), res.params, before["params"])
    assert all(jax.tree_util.tree_leaves(same))
    lines = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert lines[-1]["skipped_total"] == 3


@pytest.mark.parametrize("field", ["mlp", "grid"])
def test_training_learns_and_chunked_render_is_consistent(tmp_path, field):
    ds = tiny_dataset()
    cfg = tiny_config(field=field)
    res = train.train(ds, cfg, tmp_path, progress=False)
    log = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [x["step"] for x in log] == [5, 10, 15, 20, 25, 30]
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_images=5))
    initial = train.init_state(cfg)["params"]
    err = lambda p: float(np.mean((views.render_view(p, cfg, ds, 0)["rgb"] - ds.images[0]) ** 2))  # noqa: E731
    assert err(res.params) < 0.6 * err(initial), (err(res.params), err(initial))
    small = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, chunk=50))  # not a divisor of 192
    a = views.render_view(res.params, cfg, ds, 4)
    b = views.render_view(res.params, small, ds, 4)
    assert a["rgb"].shape == (12, 16, 3) and a["depth"].shape == (12, 16)
    np.testing.assert_allclose(a["rgb"], b["rgb"], atol=1e-5)
    cos = np.asarray(views.camera_rays(ds, 4, 1.0, 8.0).cos_to_axis)
    assert np.all(a["depth"] >= 1.0 * cos - 1e-4) and np.all(a["depth"] <= 8.0 * cos + 1e-4)
    assert np.all((a["opacity"] >= 0) & (a["opacity"] <= 1 + 1e-5))
    init_test = views.render_view(initial, cfg, ds, 4)["rgb"]
    assert np.mean((a["rgb"] - ds.images[4]) ** 2) < np.mean((init_test - ds.images[4]) ** 2)


def test_nerfw_appearance_fit_reduces_error():
    ds = tiny_dataset()
    cfg = tiny_config("nerfw")
    mcfg = dataclasses.replace(cfg.model, num_images=5, appearance_dim=4, transient_dim=4)
    params = train.init_state(dataclasses.replace(cfg, model=mcfg))["params"]
    r = views.camera_rays(ds, 4, 1.0, 8.0)
    flat = rays_lib.Rays(*(jnp.reshape(x, (-1, *x.shape[2:])) for x in r))
    target = ds.images[4].reshape(-1, 3)
    tcfg = dataclasses.replace(cfg.train, appearance_steps=40, appearance_lr=0.1, appearance_rays=64)
    emb = views.fit_appearance(params, mcfg, tcfg, flat, target, jax.random.PRNGKey(0))
    before = views.render_rays_chunked(params, mcfg, r, 0, np.asarray(params["appearance"]).mean(0), 256)
    after = views.render_rays_chunked(params, mcfg, r, 0, emb, 256)
    err = lambda out: float(np.mean((out["rgb"] - ds.images[4]) ** 2))  # noqa: E731
    assert err(after) < err(before)


def test_loss_weights_floor_and_switch():
    ds = tiny_dataset()
    ds.weights = np.full(ds.images.shape[:3], 0.9, np.float32)
    ds.weights[:, 0, 0] = 0.0
    ds.masks = np.zeros(ds.images.shape[:3], np.float32)
    ds.masks[:, :2, :2] = 1.0
    w = train.loss_weights(ds, tiny_config(mask_weight_floor=0.5).train)
    assert w[0, 0, 0] == 0.0 and w[0, 1, 1] == np.float32(0.5) and w[0, 5, 5] == np.float32(0.9)
    np.testing.assert_array_equal(train.loss_weights(ds, tiny_config(use_masks=False).train), 1.0)


# --------------------------------------------------------------------------- train.robust


def last_state(run_dir, cfg, ds) -> dict:
    """The newest checkpoint's state of a run of the tiny scene (robust_record included)."""
    from jaxnerf_grid import checkpoint

    full = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_images=ds.num_frames))
    return checkpoint.restore_latest(run_dir, train.init_state(full, train.train_frames_shape(ds)))[0]


@pytest.mark.parametrize("method,mode,confirm,scattered", [
    ("ours", "dpt+robust", 0.01, 0.0), ("ours", "dpt+robust", 0.01, 0.5), ("nerfw", "robust", 0.0, 0.0),
    ("nerf", "robust", 0.0, 0.0)])
def test_robust_two_devices_match_one_device(tmp_path, method, mode, confirm, scattered):
    """Patches, scattered rays, the all-gathered quantiles, the multi-view confirmation and the
    per-pixel record do not depend on the device count, for every method."""
    assert jax.local_device_count() >= 2, "run with XLA_FLAGS=--xla_force_host_platform_device_count=2"
    ds = tiny_dataset()
    states = []
    for n in (1, 2):
        cfg = tiny_config(method, num_devices=n, robust=mode, robust_patch=4, robust_warmup=0.0,
                          robust_confirm=confirm, robust_scattered=scattered)
        train.train(ds, cfg, tmp_path / f"dev{n}", progress=False, stop_at=4)
        states.append(last_state(tmp_path / f"dev{n}", cfg, ds))
    diffs = jax.tree_util.tree_map(lambda a, b: float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b)))),
                                   states[0], states[1])
    assert max(jax.tree_util.tree_leaves(diffs)) < 1e-5, diffs
    record = states[0]["robust_record"]
    assert record.shape == (4, 12, 16) and 0 < record.min() < 1  # some drawn pixel was ignored
    assert sorted(p.name for p in (tmp_path / "dev1" / "weights").iterdir()) == [
        f"frame_{k:04d}.png" for k in range(4)]
    if mode == "dpt+robust":  # the pool holds the pixels the prior flags (weight 0) too
        assert train.build_pool(ds, cfg)["pixels"].size == 4 * 12 * 16


@pytest.mark.parametrize("mode", ["robust", "dpt+robust"])
def test_robust_warmup_trains_on_the_prior_alone(tmp_path, mode):
    """During the warm-up (the first robust_warmup x max_steps steps) the weights used are the
    prior: all ones in mode robust, the dataset's 1 - M_w in dpt+robust (the record of each
    drawn pixel moves to it); without warm-up the evidence drops some pixel within 4 steps."""
    ds = tiny_dataset()
    prior = train.prior_weights(ds, tiny_config(robust=mode, robust_patch=4).train)[ds.split["train"]]
    records = {}
    for warmup in (0.0, 0.5):
        cfg = tiny_config(num_devices=1, robust=mode, robust_patch=4, robust_warmup=warmup, robust_spread=0.0)
        train.train(ds, cfg, tmp_path / f"w{warmup}", progress=False, stop_at=4)
        records[warmup] = last_state(tmp_path / f"w{warmup}", cfg, ds)["robust_record"]
    drawn = records[0.5] != 1.0
    if mode == "robust":
        assert np.all(records[0.5] == 1.0)
    else:  # every drawn pixel moved towards its prior, never towards anything else
        assert drawn.any()
        assert np.all(np.abs(records[0.5][drawn] - 1.0) <= np.abs(prior[drawn] - 1.0) + 1e-6)
        assert np.all(prior[drawn] < 1)
    assert np.any(records[0.0][prior == 1.0] < 1.0)  # the evidence at work: a pixel the prior keeps dropped


def test_multiview_confirmation_keeps_pixels_the_other_photos_confirm(tmp_path):
    """train.robust_confirm joined into the loss weights: with the quantile alone (no spread
    bound, no warm-up) the evidence drops a fifth of each batch; with a confirmation threshold
    no colour difference exceeds, every pixel some neighbour photo sees is kept, so far fewer
    are dropped; with one that nothing passes, as many as without."""
    ds = tiny_dataset(arc=0.1)
    dropped = {}
    for confirm in (0.0, 1e-12, 10.0):
        cfg = tiny_config(num_devices=1, robust="robust", robust_patch=4, robust_warmup=0.0, robust_spread=0.0,
                          robust_confirm=confirm)
        train.train(ds, cfg, tmp_path / f"c{confirm}", progress=False, stop_at=4)
        dropped[confirm] = int(np.sum(last_state(tmp_path / f"c{confirm}", cfg, ds)["robust_record"] < 1.0))
    assert dropped[0.0] > 20, dropped
    assert dropped[10.0] < 0.25 * dropped[0.0], dropped
    assert dropped[1e-12] >= 0.75 * dropped[0.0], dropped


def test_robust_readmits_a_wrong_prior_and_drops_a_missed_transient(tmp_path):
    """dpt+robust on the tiny scene seen from nearby cameras: sky that a wrong prior flags in
    frame 0 (the other frames see it unflagged, so the model explains it) is used again by the
    end; a magenta square pasted on the ball in frame 1, which the prior misses, is ignored."""
    ds = tiny_dataset(arc=0.1)
    ds.weights[0, 0:4, 10:16] = 0.0
    ds.images[1, 4:8, 6:10] = [1.0, 0.0, 1.0]
    cfg = tiny_config(num_devices=1, robust="dpt+robust", robust_patch=4, max_steps=200, checkpoint_every=200,
                      log_every=50)
    train.train(ds, cfg, tmp_path, progress=False)
    record = last_state(tmp_path, cfg, ds)["robust_record"]
    assert record[0, 0:4, 10:16].mean() > 0.8, record[0]
    assert record[1, 5:7, 7:9].mean() < 0.2, record[1]
    assert record[2:].mean() > 0.8  # frames with nothing wrong stay mostly used
    from jaxnerf_grid import io
    png = io.read_image(tmp_path / "weights" / "frame_0001.png")  # what a user looks at
    assert png.shape[:2] == (12, 16)
    np.testing.assert_allclose(png[..., 0] if png.ndim == 3 else png, record[1], atol=1 / 255 + 1e-6)
