"""train.depth: the sparse points' depth rays, their loss and schedule, and the step that uses them."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.data.formats import colmap_model
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import sparse_depth
from tests.train.test_loop import tiny_config, tiny_dataset


def rotation(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


# the model's frame: x_model = S * R x_data + T (any similarity; the loader must undo it)
S, R, T = 2.5, rotation([1, 2, 3], 0.7), np.array([4.0, -1.0, 2.0])


def ball_points(count=60, seed=0) -> np.ndarray:
    """Points on the tiny scene's ball (radius 0.7), in the data frame. [count, 3]."""
    v = np.random.default_rng(seed).normal(size=(count, 3))
    return 0.7 * v / np.linalg.norm(v, axis=1, keepdims=True)


def write_model(folder, ds, points, tracks, errors, moved_camera=None):
    """A COLMAP text model of the dataset's cameras and `points` (data frame), in the model frame;
    tracks: per point the dataset frame ids that see it."""
    images = {}
    for f in range(ds.num_frames):
        c2w = np.asarray(ds.c2w[f], np.float64)
        r_cv = c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # OpenGL -> OpenCV camera axes
        centre = S * R @ c2w[:3, 3] + T + (np.array([0.5, 0, 0]) if f == moved_camera else 0)
        r_cw = (R @ r_cv).T
        images[f + 1] = colmap_model.Image(id=f + 1, qvec=colmap_model.rotmat_to_qvec(r_cw), tvec=-r_cw @ centre,
                                           camera_id=1, name=f"frame_{f:02d}.png")
    pts = {i + 1: colmap_model.Point3D(id=i + 1, xyz=S * R @ p + T, rgb=np.zeros(3, np.uint8), error=float(e),
                                       track=np.array([[f + 1, 0] for f in track], np.int64).reshape(-1, 2))
           for i, (p, track, e) in enumerate(zip(points, tracks, errors))}
    fx, fy, cx, cy = (float(v) for v in ds.intrinsics[0])
    cameras = {1: colmap_model.Camera(id=1, model="PINHOLE", width=ds.width, height=ds.height,
                                      params=np.array([fx, fy, cx, cy]))}
    colmap_model.write_model(folder, cameras, images, pts)


def dataset_with_model(tmp_path, **kw):
    ds = dataclasses.replace(tiny_dataset(), root=tmp_path, frame_paths=[f"images/frame_{f:02d}.png" for f in range(5)])
    points = ball_points()
    tracks = [list(range(5))] * len(points)
    errors = [0.5] * len(points)
    tracks[0], tracks[1] = [0, 4], [1, 2]  # one training photo and the test photo; two training photos
    errors[2] = 3.0
    folder = sparse_depth.model_folder(tmp_path)
    folder.mkdir(parents=True)
    write_model(folder, ds, points, tracks, errors, **kw)
    return ds, points, tracks, errors


def brute_force(ds, points, tracks, errors, max_error=2.0, min_views=2) -> list[tuple]:
    """(frame, t) of every ray a loop over points and training frames finds, sorted."""
    train_ids = set(int(i) for i in ds.split["train"])
    out = []
    for p, track, e in zip(points, tracks, errors):
        seen = [f for f in track if f in train_ids]
        if e > max_error or len(seen) < min_views:
            continue
        for f in seen:
            c2w = np.asarray(ds.c2w[f], np.float64)
            x, y, z = c2w[:3, :3].T @ (p - c2w[:3, 3])
            fx, fy, cx, cy = ds.intrinsics[f]
            u, v = cx + fx * x / -z, cy - fy * y / -z
            if z < 0 and 0 <= u < ds.width and 0 <= v < ds.height:
                out.append((f, round(float(np.linalg.norm(p - c2w[:3, 3])), 4)))
    return sorted(out)


def test_the_model_is_moved_by_a_similarity_fit_that_recovers_a_known_one():
    from jaxnerf_grid.capture import georef

    src = np.random.default_rng(1).normal(size=(10, 3))
    scale, rot, shift = georef.umeyama(src, S * src @ R.T + T)
    assert scale == pytest.approx(S)
    np.testing.assert_allclose(rot, R, atol=1e-9)
    np.testing.assert_allclose(shift, T, atol=1e-9)


def test_depth_rays_are_the_points_each_training_photo_sees_in_the_datasets_frame(tmp_path):
    ds, points, tracks, errors = dataset_with_model(tmp_path)
    rays, why = sparse_depth.dataset_rays(ds, ds.split["train"], 2.0, 2)
    expected = brute_force(ds, points, tracks, errors)
    got = sorted((int(f), round(float(t), 4)) for f, t in zip(rays["camera"], rays["t"]))
    assert got == expected and len(got) > 20
    # each ray ends on a point of the ball, and starts at its camera's centre
    ends = rays["origins"] + rays["directions"] * rays["t"][:, None]
    np.testing.assert_allclose(np.linalg.norm(ends, axis=1), 0.7, atol=1e-4)
    np.testing.assert_allclose(rays["origins"], ds.c2w[rays["camera"], :3, 3], atol=1e-5)
    # the point seen by one training photo (and the test photo) and the one over the error bound are out
    assert not any(np.allclose(e, points[0], atol=1e-4) or np.allclose(e, points[2], atol=1e-4) for e in ends)
    assert str(len(got)) in why


def test_a_model_whose_cameras_are_not_the_datasets_is_not_used(tmp_path):
    ds, *_ = dataset_with_model(tmp_path, moved_camera=2)
    rays, why = sparse_depth.dataset_rays(ds, ds.split["train"], 2.0, 2)
    assert rays is None and "do not match" in why


def test_no_model_says_so(tmp_path):
    ds = dataclasses.replace(tiny_dataset(), root=tmp_path, frame_paths=[f"f{f}.png" for f in range(5)])
    rays, why = sparse_depth.dataset_rays(ds, ds.split["train"], 2.0, 2)
    assert rays is None and "no sparse model" in why


def test_ray_loss_is_the_weight_beyond_the_tolerance_in_log_distance():
    edges = jnp.array([[1.0, 2.0, 3.0, 5.0]])  # midpoints 1.5, 2.5, 4.0
    target = jnp.array([2.5])
    at = sparse_depth.ray_loss(edges, jnp.array([[0.0, 1.0, 0.0]]), target, 0.01)
    assert float(at[0]) == 0.0
    split = sparse_depth.ray_loss(edges, jnp.array([[0.3, 0.2, 0.5]]), target, 0.01)
    expected = 0.3 * (np.log(2.5 / 1.5) - 0.01) + 0.5 * (np.log(4.0 / 2.5) - 0.01)
    assert float(split[0]) == pytest.approx(expected, rel=1e-5)
    capped = sparse_depth.ray_loss(jnp.array([[1.0, 2.0, 1000.0]]), jnp.array([[0.0, 1.0]]), target, 0.01, cap=1.0)
    assert float(capped[0]) == pytest.approx(1.0)


def test_the_weight_decays_log_linearly_over_the_run():
    at = [float(sparse_depth.weight_at(s, 0.2, 0.1, 1000)) for s in (0, 500, 1000, 4000)]
    np.testing.assert_allclose(at, [0.2, 0.2 * 0.1 ** 0.5, 0.02, 0.02], rtol=1e-6)


def test_the_term_is_off_before_its_start_and_on_its_schedule_after():
    at = [float(sparse_depth.weight_at(s, 0.2, 0.1, 1000, start=0.25)) for s in (0, 249, 250, 500, 1000)]
    np.testing.assert_allclose(at, [0.0, 0.0, 0.2 * 0.1 ** 0.25, 0.2 * 0.1 ** 0.5, 0.02], rtol=1e-6)


def test_the_depth_step_matches_on_one_and_two_devices_and_moves_the_parameters(tmp_path):
    assert jax.local_device_count() >= 2, "run with XLA_FLAGS=--xla_force_host_platform_device_count=2"
    ds, *_ = dataset_with_model(tmp_path)
    results = {}
    for name, n, weight in (("one", 1, 1.0), ("two", 2, 1.0), ("off", 1, 0.0)):
        cfg = tiny_config(num_devices=n, depth={"weight": weight, "rays": 16})
        results[name] = train.train(ds, cfg, tmp_path / name, progress=False, stop_at=4).params
    gap = lambda a, b: max(jax.tree_util.tree_leaves(  # noqa: E731
        jax.tree_util.tree_map(lambda x, y: float(np.max(np.abs(x - y))), a, b)))
    assert gap(results["one"], results["two"]) < 1e-5
    assert gap(results["one"], results["off"]) > 1e-4  # the term reaches the gradient
    record = json.loads((tmp_path / "one" / train.DEPTH_RECORD).read_text())
    assert record["used"] and record["rays"] > 20
    logged = [json.loads(line) for line in (tmp_path / "two" / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["depth_loss"]) for r in logged)


def test_a_late_start_leaves_the_first_steps_to_the_colours(tmp_path):
    ds, *_ = dataset_with_model(tmp_path)
    runs = {}
    for name, depth in (("late", {"weight": 1.0, "rays": 16, "start": 0.5}), ("off", {"weight": 0.0}),
                        ("early", {"weight": 1.0, "rays": 16})):
        cfg = tiny_config(num_devices=1, depth=depth)  # max_steps 30: steps 0-14 before the start
        runs[name] = train.train(ds, cfg, tmp_path / name, progress=False, stop_at=4).params
    gap = lambda a, b: max(jax.tree_util.tree_leaves(  # noqa: E731
        jax.tree_util.tree_map(lambda x, y: float(np.max(np.abs(x - y))), a, b)))
    assert gap(runs["late"], runs["off"]) == 0.0
    assert gap(runs["early"], runs["off"]) > 1e-4


def test_depth_on_without_a_model_trains_without_it_and_says_why(tmp_path):
    ds = dataclasses.replace(tiny_dataset(), root=tmp_path, frame_paths=[f"f{f}.png" for f in range(5)])
    cfg = tiny_config(num_devices=1, depth={"weight": 1.0, "rays": 16})
    train.train(ds, cfg, tmp_path / "run", progress=False, stop_at=2)
    record = json.loads((tmp_path / "run" / train.DEPTH_RECORD).read_text())
    assert not record["used"] and "no sparse model" in record["why"]


def test_the_robust_step_takes_the_depth_term_too(tmp_path):
    ds, *_ = dataset_with_model(tmp_path)
    params = []
    for weight in (1.0, 0.0):
        cfg = tiny_config(num_devices=1, depth={"weight": weight, "rays": 16}, robust={"mode": "robust"})
        params.append(train.train(ds, cfg, tmp_path / f"w{weight}", progress=False, stop_at=3).params)
    gap = jax.tree_util.tree_map(lambda x, y: float(np.max(np.abs(x - y))), *params)
    assert max(jax.tree_util.tree_leaves(gap)) > 1e-4


def test_the_report_says_whether_the_depth_prior_trained_and_why(tmp_path):
    from jaxnerf_grid.eval import evaluate

    assert evaluate.read_depth_prior(tmp_path) is None
    (tmp_path / train.DEPTH_RECORD).write_text(json.dumps({"used": True, "why": "120 depth rays from 40 points",
                                                           "rays": 120}))
    cfg = tiny_config(depth={"weight": 0.1, "rays": 16}).train
    note = evaluate.depth_prior_note(evaluate.read_depth_prior(tmp_path), cfg)
    assert "120 depth rays from 40 points" in note and "0.1" in note and "16 of them" in note
    (tmp_path / train.DEPTH_RECORD).write_text(json.dumps({"used": False, "why": "no sparse model in X"}))
    assert "not used: no sparse model in X" in evaluate.depth_prior_note(evaluate.read_depth_prior(tmp_path), cfg)
