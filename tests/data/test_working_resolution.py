"""The working resolution (data/working.py): the size rule and the intrinsics against hand-computed
values, rays of a working pixel against the full-size rays through the same point, loading at
the working size against block means in NumPy, the cache of working frames, and eval / render
at the training resolution by default and at full size with --full-size."""

import os
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid.cli import eval as cli_eval
from jaxnerf_grid.cli import render as cli_render
from jaxnerf_grid.data import working
from jaxnerf_grid.data.formats import frames as frames_lib
from jaxnerf_grid.data.formats import load_dataset, save_transforms_json
from jaxnerf_grid.eval import evaluate
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.train import runs
from jaxnerf_grid.util import io
from tests.train.test_loop import TINY_FIELD, tiny_dataset


@pytest.mark.parametrize("size, max_side, expected", [
    ((3072, 2048), 640, (614, 410)),   # k = ceil(3072 / 640) = 5: 614.4 -> 614, 409.6 -> 410
    ((1920, 1080), 640, (640, 360)),   # k = 3
    ((1080, 1920), 640, (360, 640)),   # portrait: the long side is the height
    ((1000, 750), 640, (500, 375)),    # k = 2
    ((640, 480), 640, (640, 480)),     # already within the budget
    ((160, 120), 640, (160, 120)),     # the synthetic demo: unchanged
    ((3072, 2048), 0, (3072, 2048)),   # 0 = full size
    ((96, 72), 32, (32, 24)),          # k = 3
])
def test_working_size_by_hand(size, max_side, expected):
    assert working.working_size(*size, max_side) == expected


def test_working_factor_refuses_negative_budgets():
    with pytest.raises(ValueError, match="max_side"):
        working.working_factor(100, 100, -1)


def _ray_point_distance(ray, point):
    o, d = np.asarray(ray.origins, np.float64), np.asarray(ray.directions, np.float64)
    v = np.asarray(point, np.float64) - o
    return float(np.linalg.norm(v - np.dot(v, d) * d))


def test_a_working_pixel_sees_the_same_point_as_the_full_size_pixel():
    """A 3-D point projected by hand (pinhole, OpenGL axes, pixel centres at +0.5) into the full
    3072x2048 photo at (u, v) lies on the working camera's ray through (u W'/W, v H'/H)."""
    w, h = 3072, 2048
    k_full = np.array([2400.0, 2410.0, 1536.3, 1023.7])
    ww, hh = working.working_size(w, h, 640)
    k_work = frames_lib.scale_intrinsics(k_full, ww / w, hh / h)
    np.testing.assert_allclose(k_work, [2400 * 614 / 3072, 2410 * 410 / 2048, 1536.3 * 614 / 3072,
                                        1023.7 * 410 / 2048])
    c2w = np.asarray(rays_lib.look_at([4.0, -3.0, 1.5], [0.2, 0.1, 0.3]), np.float64)
    rng = np.random.default_rng(0)
    for _ in range(5):
        point = rng.uniform(-0.8, 0.8, 3)
        cam = c2w[:3, :3].T @ (point - c2w[:3, 3])        # camera frame, looking down -z
        u = k_full[2] + k_full[0] * cam[0] / -cam[2]
        v = k_full[3] - k_full[1] * cam[1] / -cam[2]
        full = rays_lib.rays_for_pixels(c2w, *k_full, np.float32(u), np.float32(v))
        small = rays_lib.rays_for_pixels(c2w, *k_work, np.float32(u * ww / w), np.float32(v * hh / h))
        assert _ray_point_distance(full, point) < 1e-4
        assert _ray_point_distance(small, point) < 1e-4


def test_a_working_pixel_centre_is_its_block_centre():
    """k = 3 divides 1920x1080: working pixel (i, j) is the mean of the 3x3 block whose centre is
    the centre of full-size pixel (3i + 1, 3j + 1), so their rays are the same."""
    w, h = 1920, 1080
    k_full = np.array([1500.0, 1500.0, 960.0, 540.0])
    ww, hh = working.working_size(w, h, 640)
    k_work = frames_lib.scale_intrinsics(k_full, ww / w, hh / h)
    c2w = np.eye(4)
    full = rays_lib.generate_rays(c2w, *k_full, w, h)
    small = rays_lib.generate_rays(c2w, *k_work, ww, hh)
    for i, j in [(0, 0), (17, 203), (639, 359), (320, 180)]:
        np.testing.assert_allclose(np.asarray(small.directions[j, i]),
                                   np.asarray(full.directions[3 * j + 1, 3 * i + 1]), atol=1e-6)


# --------------------------------------------------------------------------- loading and the cache


def _dataset_on_disk(root: Path, width=48, height=36, frames=5):
    ds = tiny_dataset(width=width, height=height, frames=frames)
    rng = np.random.default_rng(1)
    ds.images = np.round(rng.uniform(0, 1, ds.images.shape) * 255).astype(np.float32) / 255
    ds.masks = (rng.uniform(0, 1, ds.images.shape[:3]) > 0.6).astype(np.float32)
    ds.weights = np.round(rng.uniform(0, 1, ds.images.shape[:3]), 3).astype(np.float32)
    save_transforms_json(ds, root)
    return load_dataset(root, progress=False)  # full size, as written


def _blocks(arr, k):
    """Means of k x k blocks of [N, H, W(, C)] (H, W divisible by k): the area resize by hand."""
    n, h, w = arr.shape[:3]
    return arr.reshape(n, h // k, k, w // k, k, *arr.shape[3:]).mean(axis=(2, 4))


def test_loading_at_max_side_is_the_block_mean_with_scaled_intrinsics(tmp_path):
    full = _dataset_on_disk(tmp_path / "data")
    ds = load_dataset(tmp_path / "data", max_side=16, progress=False)   # 48x36 -> k = 3 -> 16x12
    assert (ds.width, ds.height) == (16, 12) and ds.meta["native_size"] == [48, 36]
    np.testing.assert_allclose(ds.images, _blocks(full.images, 3), atol=1e-5)
    np.testing.assert_allclose(ds.weights, _blocks(full.weights, 3), atol=1e-5)  # area: the mean weight
    np.testing.assert_array_equal(ds.masks, (_blocks(full.masks, 3) > 0.5).astype(np.float32))  # majority
    np.testing.assert_allclose(ds.intrinsics, full.intrinsics / 3, rtol=1e-6)
    # the in-memory path (a dataset handed to train_run / evaluate_run) gives the same
    mem = frames_lib.working_dataset(full, 16)
    np.testing.assert_allclose(mem.images, ds.images, atol=1e-6)
    np.testing.assert_array_equal(mem.masks, ds.masks)
    np.testing.assert_allclose(mem.intrinsics, ds.intrinsics, rtol=1e-6)


def test_the_cache_is_read_back_and_misses_when_a_file_changes(tmp_path, monkeypatch):
    root = tmp_path / "data"
    _dataset_on_disk(root)
    first = load_dataset(root, max_side=16, progress=False)
    cached = sorted(working.cache_folder(root).glob("*.npz"))
    assert len(cached) == first.num_frames
    real = frames_lib.read_frame
    decoded = []
    monkeypatch.setattr(frames_lib, "read_frame", lambda scene, i, *a: decoded.append(i) or real(scene, i, *a))
    again = load_dataset(root, max_side=16, progress=False)
    assert decoded == []                                          # every frame from the cache
    for name in ("images", "weights", "masks", "intrinsics"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))
    # a frame whose weights file changes is decoded again; its stale entry is replaced
    weight_file = root / io.read_json(root / "transforms.json")["frames"][2]["weight_path"]
    arr = io.read_exr(weight_file)
    io.write_exr(weight_file, np.zeros_like(arr))
    os.utime(weight_file, ns=(1, 1))
    third = load_dataset(root, max_side=16, progress=False)
    assert decoded == [2] and not third.weights[2].any() and third.weights[1].any()
    assert len(list(working.cache_folder(root).glob("*.npz"))) == first.num_frames
    # another budget is another level of the pyramid, kept beside the first
    load_dataset(root, max_side=24, progress=False)
    assert len(list(working.cache_folder(root).glob("*.npz"))) == 2 * first.num_frames


def test_a_torn_cache_entry_is_a_miss_not_an_error(tmp_path):
    root = tmp_path / "data"
    _dataset_on_disk(root)
    first = load_dataset(root, max_side=16, progress=False)
    entry = sorted(working.cache_folder(root).glob("*.npz"))[0]
    entry.write_bytes(entry.read_bytes()[:100])                 # what a kill mid-write could leave
    again = load_dataset(root, max_side=16, progress=False)
    np.testing.assert_array_equal(again.images, first.images)


# --------------------------------------------------------------------------- eval and render


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("working_run")
    save_transforms_json(tiny_dataset(width=48, height=36), root / "data")
    overrides = {"model": {"field": TINY_FIELD, "num_coarse": 8, "num_fine": 8},
                 "train": {"batch_rays": 64, "max_steps": 2, "checkpoint_every": 2, "log_every": 1, "warmup": 1,
                           "chunk": 512, "num_devices": 1, "max_side": 24}}
    run, cfg, _ = runs.train_run(str(root / "data"), "ours", root / "run", overrides, progress=False)
    return Path(run)


def test_a_run_trains_at_its_working_resolution_and_records_it(small_run):
    assert io.read_json(small_run / "config.json")["train"]["max_side"] == 24
    assert (io.read_json(small_run / "dataset.json")["width"], io.read_json(small_run / "dataset.json")["height"]) \
        == (24, 18)


def test_eval_renders_at_the_training_resolution_unless_full_size(small_run, capsys):
    assert cli_eval.main(["--run", str(small_run), "--quiet", "--distractor-views", "0"]) == 0
    m = io.read_json(small_run / "metrics.json")
    png = next((small_run / "renders").glob("*.png"))
    assert io.read_image(png).shape[:2] == (18, 24)
    assert m["resolution"] == {"width": 24, "height": 18, "native_width": 48, "native_height": 36,
                               "max_side": 24, "full_size": False}
    assert evaluate.resolution_note(m["resolution"]) in (small_run / "report.md").read_text()
    assert cli_eval.main(["--run", str(small_run), "--quiet", "--distractor-views", "0", "--full-size"]) == 0
    assert io.read_image(png).shape[:2] == (36, 48)
    assert io.read_json(small_run / "metrics.json")["resolution"]["full_size"] is True


def test_render_at_the_training_resolution_unless_full_size(small_run):
    assert cli_render.main(["--run", str(small_run), "--quiet"]) == 0
    png = next((small_run / "renders").glob("*.png"))
    assert io.read_image(png).shape[:2] == (18, 24)
    assert cli_render.main(["--run", str(small_run), "--quiet", "--full-size"]) == 0
    assert io.read_image(png).shape[:2] == (36, 48)


def test_a_run_made_before_max_side_reads_as_full_size(small_run, tmp_path):
    raw = io.read_json(small_run / "config.json")
    del raw["train"]["max_side"]
    (tmp_path / "old").mkdir()
    io.write_json(tmp_path / "old" / "config.json", raw)
    cfg, _ = runs.load_run(tmp_path / "old")
    assert cfg.train.max_side == 0
