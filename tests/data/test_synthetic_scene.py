"""The synthetic tower benchmark end to end, on tiny images: layout, determinism, exact masks."""

import json
import math

import numpy as np
import pytest

from jaxnerf_grid.data.synthetic import CLASSES
from jaxnerf_grid.data.synthetic.generate import generate_scene
from jaxnerf_grid.util import io

TINY = dict(width=40, height=30, num_train=3, num_test=1, supersample=1)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth") / "a"
    generate_scene("tower-small", root, seed=3, distractors="high", progress=False, **TINY)
    return root


def _frames(root, split=None):
    meta = io.read_json(root / "transforms.json")
    return meta, [f for f in meta["frames"] if split is None or f["split"] == split]


def test_layout_matches_dataset_contract(tiny):
    meta, frames = _frames(tiny)
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "near", "far", "scene_normalization", "generator", "tower_ply"):
        assert key in meta
    assert (meta["w"], meta["h"]) == (40, 30)
    assert meta["generator"]["preset"] == "tower-small" and meta["generator"]["seed"] == 3
    assert [f["split"] for f in frames].count("test") == 1 and len(frames) == 4
    for f in frames:
        for key in ("file_path", "clean_file_path", "depth_file_path", "semantic_file_path",
                    "distractor_mask_path", "shadow_mask_path"):
            assert (tiny / f[key]).is_file(), f[key]
        c2w = np.array(f["transform_matrix"])
        assert c2w.shape == (4, 4)
        np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-5)
        assert 1.5 < np.linalg.norm(c2w[:3, 3]) < 4.5           # drone orbit, normalised units
    pts = io.read_ply_points(tiny / meta["tower_ply"])
    assert len(pts) > 1000 and np.linalg.norm(pts, axis=-1).max() < 1.0   # tower in the unit sphere


def test_depth_and_semantics_against_ground_plane(tiny):
    """Ground pixels: z-depth equals the analytic pinhole ray / plane z = 0 intersection."""
    meta, frames = _frames(tiny)
    s, tr = meta["scene_normalization"]["scale"], meta["scene_normalization"]["translation"]
    ground_z = s * (0.0 + tr[2])
    checked = 0
    for f in frames:
        depth = io.read_exr(tiny / f["depth_file_path"])
        sem = np.round(io.read_mask(tiny / f["semantic_file_path"]) * 255).astype(int)
        assert sem.max() < len(CLASSES)
        np.testing.assert_array_equal(np.isinf(depth), sem == CLASSES.index("sky"))
        assert np.all(depth[np.isfinite(depth)] > meta["near"])
        c2w = np.array(f["transform_matrix"])
        j, i = np.nonzero(sem == CLASSES.index("ground"))
        cam = np.stack([(i + 0.5 - meta["cx"]) / meta["fl_x"], -(j + 0.5 - meta["cy"]) / meta["fl_y"],
                        -np.ones(len(i))], -1)                    # z-depth 1 along -z
        world = cam @ c2w[:3, :3].T
        z_depth = (ground_z - c2w[2, 3]) / world[:, 2]
        np.testing.assert_allclose(depth[j, i], z_depth, rtol=1e-4)
        checked += len(i)
    assert checked > 100


def test_distractor_mask_is_exactly_where_images_differ(tiny):
    _, train = _frames(tiny, "train")
    total_cov = 0.0
    for f in train:
        img, clean = io.read_image(tiny / f["file_path"]), io.read_image(tiny / f["clean_file_path"])
        dmask = io.read_mask(tiny / f["distractor_mask_path"]) > 0.5
        smask = io.read_mask(tiny / f["shadow_mask_path"]) > 0.5
        differ = np.any(img != clean, axis=-1)
        assert not np.any(differ & ~dmask & ~smask), "images differ outside the distractor/shadow masks"
        assert not np.any(dmask & smask)
        # A covered pixel changes unless the distractor happens to match the background to 8 bits.
        assert differ[dmask].mean() > 0.97
        # supersample=1: the only colour sample is the pixel centre, which sets the semantic class.
        sem = np.round(io.read_mask(tiny / f["semantic_file_path"]) * 255).astype(int)
        is_distractor = np.isin(sem, [CLASSES.index(c) for c in ("person", "vehicle", "bird")])
        np.testing.assert_array_equal(is_distractor, dmask)
        total_cov += dmask.mean()
    assert total_cov / len(train) > 0.15                      # "high" clutter at this size


def test_test_frames_are_clean(tiny):
    _, test = _frames(tiny, "test")
    for f in test:
        np.testing.assert_array_equal(io.read_image(tiny / f["file_path"]), io.read_image(tiny / f["clean_file_path"]))
        assert io.read_mask(tiny / f["distractor_mask_path"]).max() == 0


def test_same_seed_same_output_and_overwrite_guard(tiny, tmp_path):
    other = tmp_path / "b"
    generate_scene("tower-small", other, seed=3, distractors="high", progress=False, **TINY)
    meta_a, frames = _frames(tiny)
    meta_b = io.read_json(other / "transforms.json")
    assert json.dumps(meta_a, sort_keys=True) == json.dumps(meta_b, sort_keys=True)
    for f in frames:
        for key in ("file_path", "clean_file_path", "semantic_file_path", "distractor_mask_path", "shadow_mask_path"):
            assert (tiny / f[key]).read_bytes() == (other / f[key]).read_bytes(), f[key]
        a, b = io.read_exr(tiny / f["depth_file_path"]), io.read_exr(other / f["depth_file_path"])
        np.testing.assert_array_equal(a, b)
    with pytest.raises(io.DataError, match="overwrite"):
        generate_scene("tower-small", other, seed=3, progress=False, **TINY)


def test_different_views_have_different_distractors(tiny):
    _, train = _frames(tiny, "train")
    masks = [io.read_mask(tiny / f["distractor_mask_path"]) for f in train]
    assert not np.array_equal(masks[0], masks[1])


def test_low_level_stays_under_five_percent_and_cli(tmp_path):
    from jaxnerf_grid.cli import main

    out = tmp_path / "low"
    rc = main(["synth", "--preset", "tower-small", "--out", str(out), "--seed", "1", "--distractors", "low",
               "--width", "64", "--height", "48", "--num-train", "2", "--num-test", "1", "--supersample", "1",
               "--no-shadows", "--workers", "1", "--quiet"])
    assert rc == 0
    meta, train = _frames(out, "train")
    assert meta["generator"]["distractors"] == "low" and meta["generator"]["shadows"] is False
    for f in train:
        cov = (io.read_mask(out / f["distractor_mask_path"]) > 0.5).mean()
        assert 0.0 < cov < 0.05
        assert math.isclose(cov, f["distractor_coverage"], abs_tol=1e-6)
        assert io.read_mask(out / f["shadow_mask_path"]).max() == 0        # shadows off
    assert main(["synth", "--preset", "tower-small", "--out", str(out), "--quiet"]) == 1   # refuses to overwrite


def test_camera_path_looks_at_tower_and_interleaves_test_views():
    from jaxnerf_grid.data.synthetic import PRESETS
    from jaxnerf_grid.data.synthetic.cameras import camera_path, intrinsics

    cfg = PRESETS["tower-small"]
    c2w, split = camera_path(40, 8, cfg["orbits"], cfg["low_pass"], np.random.default_rng(0))
    test_idx = np.nonzero(np.array(split) == "test")[0]
    assert len(test_idx) == 8 and test_idx[0] > 0 and test_idx[-1] < len(split) - 1
    assert np.diff(test_idx).min() >= 5                           # spread along the path
    intr = intrinsics(160, 120, 60.0)
    for pose in c2w:
        eye = pose[:3, 3]
        assert 35.0 < np.hypot(eye[0], eye[1]) < 75.0 and 2.0 < eye[2] < 45.0
        cam = pose[:3, :3].T @ (np.array([0.0, 0.0, 15.0]) - eye)  # tower middle in camera axes
        assert cam[2] < 0
        u = intr["fl_x"] * cam[0] / -cam[2] + intr["cx"]
        v = -intr["fl_y"] * cam[1] / -cam[2] + intr["cy"]
        assert 0 < u < 160 and 0 < v < 120


def test_tower_point_sample_lies_on_members():
    from jaxnerf_grid.data.synthetic import intersect as ix
    from jaxnerf_grid.data.synthetic.scene import main_tower_scene, sample_tower_points

    tower = main_tower_scene(0)
    pts = sample_tower_points(tower, 500, np.random.default_rng(0))
    cap, cyl, box = tower.tables["capsule"], tower.tables["cylinder"], tower.tables["box"]
    on_surface = np.zeros(len(pts), bool)
    for a, b, r in zip(cap["a"], cap["b"], cap["r"]):
        on_surface |= ix.inside_capsule(pts, a, b, r + 1e-6) & ~ix.inside_capsule(pts, a, b, r - 1e-6)
    for a, b, r in zip(cyl["a"], cyl["b"], cyl["r"]):
        on_surface |= ix.inside_cylinder(pts, a, b, r + 1e-6, 1e-6) & ~ix.inside_cylinder(pts, a, b, r - 1e-6, -1e-6)
    for c, R, h in zip(box["c"], box["R"], box["h"]):
        on_surface |= ix.inside_box(pts, c, R, h + 1e-6) & ~ix.inside_box(pts, c, R, h - 1e-6)
    assert on_surface.all()
    assert pts[:, 2].min() >= 0.0 and 29.0 < pts[:, 2].max() < 31.5


def test_ground_scatter_covers_its_expected_share_and_fades_below_a_pixel():
    """Shrubs and stones: the share of the ground they cover against its closed form (75 % of the
    cells hold a disc of radius cell * (0.18 + 0.22 u), u uniform: 0.75 pi E[(0.18 + 0.22 u)^2]),
    no disc crosses its cell's border, and discs smaller than about a pixel fade out."""
    from jaxnerf_grid.data.synthetic import shading

    rng = np.random.default_rng(0)
    cell = shading.SCATTER_CELL
    p = np.concatenate([rng.uniform(-500, 500, (200_000, 2)), np.zeros((200_000, 1))], 1)
    cover, albedo = shading.ground_scatter(p, np.full(len(p), 1e-4), seed=3)
    expected = 0.75 * np.pi * (0.18 ** 2 + 0.18 * 0.22 + 0.22 ** 2 / 3)
    assert abs(cover.mean() - expected) < 0.01, (cover.mean(), expected)
    assert albedo.min() >= 0 and cover.min() >= 0 and cover.max() <= 1
    border = p.copy()
    border[:, 0] = np.round(border[:, 0] / cell) * cell  # points on the cells' borders
    assert shading.ground_scatter(border, np.full(len(p), 1e-4), seed=3)[0].max() <= 0.5 + 1e-9
    far = shading.ground_scatter(p, np.full(len(p), 10.0), seed=3)[0]  # a 10 m pixel: no disc shows
    assert far.max() == 0.0
