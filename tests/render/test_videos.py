"""Fly-around videos (docs/VIDEOS.md): the orbit against its closed form, the camera-path
reader and its refusals, and `render --orbit / --path` on a tiny run read back with OpenCV."""

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.nerf import rays
from jaxnerf_grid.render import videos
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError
from tests.train.test_loop import TINY_FIELD, tiny_dataset


def test_orbit_follows_the_training_cameras_height_and_radius():
    # cameras on a third of a ring of radius 3 at height 0.5 above a target at (1, -2, 0.2), z up
    target = np.array([1.0, -2.0, 0.2])
    angles = np.radians([10, 40, 70, 100, 130])
    c2w = np.stack([np.asarray(rays.look_at(target + [3 * math.cos(a), 3 * math.sin(a), 0.5], target), np.float64)
                    for a in angles])
    frames = 8
    poses = videos.orbit_poses(c2w, frames)
    assert poses.shape == (frames, 4, 4)
    rel = poses[:, :3, 3] - target
    up = c2w[:, :3, 1].mean(0) / np.linalg.norm(c2w[:, :3, 1].mean(0))
    np.testing.assert_allclose(rel @ up, np.mean((c2w[:, :3, 3] - target) @ up), atol=1e-5)   # the mean height
    flat = rel - np.outer(rel @ up, up)
    np.testing.assert_allclose(np.linalg.norm(flat, axis=1), np.mean(np.linalg.norm(
        (c2w[:, :3, 3] - target) - np.outer((c2w[:, :3, 3] - target) @ up, up), axis=1)), atol=1e-5)
    # every camera looks at the target (-z through it), starting at the first camera's azimuth,
    # a turn of 2 pi / frames between frames
    forward = -poses[:, :3, 2]
    np.testing.assert_allclose(np.cross(forward, -rel / np.linalg.norm(rel, axis=1, keepdims=True)), 0, atol=1e-5)
    first = (c2w[0, :3, 3] - target) - ((c2w[0, :3, 3] - target) @ up) * up
    cos0 = flat[0] @ first / np.linalg.norm(flat[0]) / np.linalg.norm(first)
    assert cos0 == pytest.approx(1.0, abs=1e-6)
    turns = [math.acos(np.clip(flat[k] @ flat[k + 1] / np.linalg.norm(flat[k]) / np.linalg.norm(flat[k + 1]), -1, 1))
             for k in range(frames - 1)]
    np.testing.assert_allclose(turns, 2 * math.pi / frames, atol=1e-5)


def _path_file(tmp_path, cameras, **extra) -> Path:
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"render_width": 20, "render_height": 14, "fps": 12, "camera_path": cameras, **extra}))
    return path


def test_read_camera_path_takes_nerfstudios_fields(tmp_path):
    m = np.arange(16, dtype=float).reshape(4, 4)
    m[3] = [0, 0, 0, 1]
    spec = videos.read_camera_path(_path_file(tmp_path, [{"camera_to_world": m.ravel().tolist(), "fov": 50},
                                                         {"camera_to_world": m.tolist(), "fov": 30, "aspect": 1.4}]))
    np.testing.assert_array_equal(spec["c2w"], [m, m])
    assert spec["fov"].tolist() == [50, 30] and (spec["width"], spec["height"], spec["fps"]) == (20, 14, 12.0)


@pytest.mark.parametrize("cameras, extra, words", [
    ([], {}, "camera_path"),
    ([{"fov": 50}], {}, "camera_path[0]"),
    ([{"camera_to_world": [1, 2, 3], "fov": 50}], {}, "camera_path[0]"),
    ([{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 200}], {}, "fov"),
    ([{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 50}], {"render_width": 0}, "render_width"),
    ([{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 50}], {"fps": -1}, "fps"),
])
def test_read_camera_path_refuses_bad_files_naming_the_file_and_key(tmp_path, cameras, extra, words):
    path = _path_file(tmp_path, cameras, **extra)
    with pytest.raises(DataError) as err:
        videos.read_camera_path(path)
    assert str(path) in str(err.value) and words in str(err.value)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from jaxnerf_grid.data.formats import save_transforms_json
    from jaxnerf_grid.train import runs

    root = tmp_path_factory.mktemp("videos")
    ds = tiny_dataset(width=24, height=18, frames=6)
    save_transforms_json(ds, root / "data")
    overrides = {"model": {"field": TINY_FIELD, "num_coarse": 8, "num_fine": 8},
                 "train": {"batch_rays": 128, "max_steps": 40, "checkpoint_every": 40, "log_every": 20, "warmup": 5,
                           "lr_init": 5e-3, "lr_final": 1e-3, "chunk": 512, "num_devices": 1}}
    run, _, _ = runs.train_run(str(root / "data"), "ours", root / "run", overrides, progress=False)
    return run


def _read_video(path: Path) -> tuple[np.ndarray, float]:
    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS)
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame[..., ::-1] / 255.0)
    cap.release()
    return np.asarray(frames), fps


def test_render_orbit_writes_colour_and_depth_videos(tiny_run, capsys):
    assert cli.main(["render", "--run", str(tiny_run), "--orbit", "--frames", "10", "--fps", "5", "--width", "32",
                     "--quiet"]) == 0
    for name in ("orbit.mp4", "orbit_depth.mp4"):
        frames, fps = _read_video(tiny_run / "videos" / name)
        assert frames.shape == (10, 24, 32, 3) and fps == pytest.approx(5)   # 32 wide, the photos' 4:3
    assert "10 frames" in capsys.readouterr().out


def test_render_path_follows_the_given_cameras(tiny_run, tmp_path):
    """A path through the test camera renders what `render` renders for the test view."""
    from jaxnerf_grid.train import runs

    cfg, data = runs.load_run(tiny_run)
    ds = runs.load_dataset(data, progress=False)
    i = int(ds.split["test"][0])
    fov = math.degrees(2 * math.atan(0.5 * ds.height / float(ds.intrinsics[i][1])))
    path = tmp_path / "cams.json"
    path.write_text(json.dumps({"render_width": ds.width, "render_height": ds.height, "fps": 8,
                                "camera_path": [{"camera_to_world": np.asarray(ds.c2w[i]).ravel().tolist(),
                                                 "fov": fov}] * 3}))
    assert cli.main(["render", "--run", str(tiny_run), "--path", str(path), "--out", str(tmp_path / "v"),
                     "--quiet"]) == 0
    frames, fps = _read_video(tmp_path / "v.mp4")
    assert frames.shape == (3, ds.height, ds.width, 3) and fps == pytest.approx(8)
    assert cli.main(["render", "--run", str(tiny_run), "--quiet"]) == 0
    still = io.read_image(tiny_run / "renders" / f"{runs.frame_name(ds, i)}.png")
    assert np.mean(np.abs(frames[1] - still)) < 0.03          # mp4v's loss only


def test_a_frame_has_the_rays_of_its_camera(tiny_run):
    """`_render_frame` of a dataset camera's pose and vertical fov casts that camera's rays (the
    renderer one that returns the ray directions)."""
    from jaxnerf_grid.render import views
    from jaxnerf_grid.train import runs

    cfg, data = runs.load_run(tiny_run)
    ds = runs.load_dataset(data, progress=False)
    i = int(ds.split["test"][0])
    fov = math.degrees(2 * math.atan(0.5 * ds.height / float(ds.intrinsics[i][1])))
    echo = lambda r: {"rgb": np.asarray(r.directions), "depth": np.asarray(r.near)}  # noqa: E731
    got = videos._render_frame(echo, np.asarray(ds.c2w[i]), fov, ds.width, ds.height, 1.0, 8.0)
    want = views.camera_rays(ds, i, 1.0, 8.0)
    np.testing.assert_allclose(got["rgb"], np.asarray(want.directions), atol=1e-5)


def test_render_video_refuses_bad_settings_in_one_line(tiny_run, tmp_path, capsys):
    before = sorted((tiny_run / "videos").iterdir()) if (tiny_run / "videos").is_dir() else []
    assert cli.main(["render", "--run", str(tiny_run), "--orbit", "--frames", "0", "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert "--frames" in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert cli.main(["render", "--run", str(tiny_run), "--path", str(tmp_path / "none.json"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert "none.json" in err and "--path" in err and len(err.splitlines()) == 1
    after = sorted((tiny_run / "videos").iterdir()) if (tiny_run / "videos").is_dir() else []
    assert after == before                                   # nothing written


def test_a_failed_render_keeps_the_earlier_video_and_leaves_no_partial_file(tmp_path):
    from jaxnerf_grid.util import progress

    video, depth = tmp_path / "orbit.mp4", tmp_path / "orbit_depth.mp4"
    video.write_bytes(b"the earlier video")

    def render(k):
        if k == 2:
            raise RuntimeError("killed")
        return {"rgb": np.full((6, 8, 3), 0.5), "depth": np.full((6, 8), 2.0)}

    with pytest.raises(RuntimeError):
        videos.write_videos(video, depth, [(k,) for k in range(4)], render, 5.0, 8, 6, progress.bar(enabled=False))
    assert video.read_bytes() == b"the earlier video" and not depth.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["orbit.mp4"]
    assert videos.write_videos(video, depth, [(k,) for k in range(2)], render, 5.0, 8, 6,
                               progress.bar(enabled=False)) == 2
    assert _read_video(video)[0].shape == (2, 6, 8, 3)


@pytest.mark.parametrize("devices", [1, 2])
def test_the_frame_renderer_renders_what_eval_renders_with_one_compile(tiny_run, devices, monkeypatch):
    """`views.frame_renderer` (the videos' renderer: blocks of rays in one call a frame) against
    the evaluation's `render_rays_chunked` on three orbit frames: the same pixels up to float
    rounding, one compiled function for all three (padding: 24 x 18 rays are not a multiple of
    the block)."""
    import jax

    from jaxnerf_grid.config import schema as config_lib
    from jaxnerf_grid.render import views
    from jaxnerf_grid.train import loop as train
    from jaxnerf_grid.train import runs

    if jax.local_device_count() < devices:
        pytest.skip(f"needs {devices} local devices")
    cfg, data = runs.load_run(tiny_run)
    ds = runs.load_dataset(data, progress=False)
    params, _ = train.load_params(tiny_run, cfg, ds)
    near, far = config_lib.near_far(cfg.model, ds)
    w, h, fov = videos.orbit_size(ds, 24)
    focal = 0.5 * h / math.tan(math.radians(fov) / 2)
    frames = [rays.generate_rays(pose.astype(np.float32), focal, focal, w / 2, h / 2, w, h, near, far)
              for pose in videos.orbit_poses(np.asarray(ds.c2w), 3)]
    wanted = [views.render_rays_chunked(params, cfg.model, r, 0, None, 4096, 1) for r in frames]
    traces = []
    real = views.models.render_rays
    monkeypatch.setattr(views.models, "render_rays", lambda *a, **k: traces.append(1) or real(*a, **k))
    views._render_frame_fn.cache_clear()
    render = views.frame_renderer(params, cfg.model, devices, block=40)
    for r, want in zip(frames, wanted):
        got = render(r)
        assert got["rgb"].shape == (h, w, 3) and got["depth"].shape == (h, w)
        np.testing.assert_allclose(got["rgb"], want["rgb"], atol=1e-4)
        np.testing.assert_allclose(got["depth"], want["depth"], rtol=1e-3, atol=1e-4)
    assert len(traces) == 1                                   # one trace (one compile) for the three frames


def test_load_params_reads_the_checkpoint_without_drawing_parameters(tiny_run, monkeypatch):
    """`train.load_params` returns the newest checkpoint's parameters, bit for bit as restored
    into a concretely drawn `init_state` (the reference), with an abstract template: `models.init`
    only traced (its leaves tracers: nothing drawn, nothing compiled for it)."""
    import jax

    from jaxnerf_grid.config import schema as config_lib
    from jaxnerf_grid.nerf import models
    from jaxnerf_grid.train import checkpoint, runs
    from jaxnerf_grid.train import loop as train

    cfg, data = runs.load_run(tiny_run)
    ds = runs.load_dataset(data, progress=False)
    concrete = train.init_state(config_lib.resolve(cfg, ds, bounds=False), train.train_frames_shape(ds))
    want, want_step = checkpoint.restore_latest(tiny_run, concrete)
    drawn = []
    real = models.init
    monkeypatch.setattr(models, "init", lambda *a: drawn.append(real(*a)) or drawn[-1])
    params, step = train.load_params(tiny_run, cfg, ds)
    assert step == want_step and drawn
    assert all(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(drawn))
    got, ref = jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(want["params"])
    assert jax.tree_util.tree_structure(params) == jax.tree_util.tree_structure(want["params"])
    for a, b in zip(got, ref):
        assert type(a) is type(b) and a.dtype == b.dtype
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_render_uses_every_cpu_core_unless_the_user_chose_a_device_count():
    """`render --orbit` asks XLA for one CPU device per core (the frame renderer splits a frame
    over them); a device count the user set in XLA_FLAGS is kept, other flags too."""
    from jaxnerf_grid.cli.render import DEVICE_COUNT_FLAG, use_every_cpu_core

    env = {}
    use_every_cpu_core(env, cores=2)
    assert env["XLA_FLAGS"] == f"{DEVICE_COUNT_FLAG}=2"
    env = {"XLA_FLAGS": "--xla_cpu_enable_fast_math=false"}
    use_every_cpu_core(env, cores=4)
    assert env["XLA_FLAGS"] == f"--xla_cpu_enable_fast_math=false {DEVICE_COUNT_FLAG}=4"
    env = {"XLA_FLAGS": f"{DEVICE_COUNT_FLAG}=1"}
    use_every_cpu_core(env, cores=8)
    assert env["XLA_FLAGS"] == f"{DEVICE_COUNT_FLAG}=1"
    env = {}
    use_every_cpu_core(env)
    assert env["XLA_FLAGS"] == f"{DEVICE_COUNT_FLAG}={len(os.sched_getaffinity(0))}"
