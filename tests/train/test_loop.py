"""train.py: ray pool, data-parallel equivalence, the non-finite guard, rendering, learning."""

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.render import views
from jaxnerf_grid.train import loop as train

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
    ds.intrinsics[:] = np.nan  # every ray non-finite (8-bit training frames cannot hold a NaN)
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


def test_the_left_half_fit_starts_from_the_training_photos_mean_appearance():
    """With no fitting step, NeRF-W's left-half fit of held-out frame 4 returns where it starts:
    the mean of the training rows 0-3, not of all five (row 4 was never trained)."""
    from jaxnerf_grid.eval import evaluate

    ds = tiny_dataset()  # frames 0-3 train, frame 4 is held out
    cfg = tiny_config("nerfw")
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_images=5, appearance_dim=4,
                                                             use_transient=False),
                              train=dataclasses.replace(cfg.train, appearance_steps=0))
    params = train.init_state(cfg)["params"]
    rows = np.arange(20, dtype=np.float32).reshape(5, 4) / 10.0
    params = dict(params, appearance=jnp.asarray(rows))
    rays = views.camera_rays(ds, 4, *config_lib.near_far(cfg.model, ds))
    emb = evaluate._fit_left_half(params, cfg, ds, 4, np.asarray(ds.images[4]), rays)
    np.testing.assert_allclose(emb, sum(rows[i] for i in range(4)) / 4, atol=1e-6)


def test_a_held_out_view_renders_with_the_training_photos_mean_appearance():
    ds = tiny_dataset()  # frames 0-3 train, frame 4 is held out
    cfg = tiny_config("nerfw")
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_images=5, appearance_dim=4,
                                                             use_transient=False))
    params = train.init_state(cfg)["params"]
    rows = np.arange(20, dtype=np.float32).reshape(5, 4) / 10.0  # distinct rows; row 4 never trained
    params = dict(params, appearance=jnp.asarray(rows))
    mean_of_training_rows = sum(rows[i] for i in range(4)) / 4
    held_out = views.render_view(params, cfg, ds, 4)["rgb"]
    r = views.camera_rays(ds, 4, *config_lib.near_far(cfg.model, ds))
    expected = views.render_rays_chunked(params, cfg.model, r, 0, mean_of_training_rows, 256)["rgb"]
    np.testing.assert_allclose(held_out, expected, atol=1e-6)
    own_row = views.render_rays_chunked(params, cfg.model, r, 4, None, 256)["rgb"]
    assert np.max(np.abs(held_out - own_row)) > 1e-3  # the untrained row would colour it otherwise
    trained = views.render_view(params, cfg, ds, 2)["rgb"]  # a training frame keeps its own row
    r2 = views.camera_rays(ds, 2, *config_lib.near_far(cfg.model, ds))
    np.testing.assert_allclose(trained, views.render_rays_chunked(params, cfg.model, r2, 2, None, 256)["rgb"],
                               atol=1e-6)


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
    from jaxnerf_grid.train import checkpoint

    full = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_images=ds.num_frames))
    return checkpoint.restore_latest(run_dir, train.init_state(full, train.train_frames_shape(ds)))[0]
