"""Scene bounds from the data (data/bounds.py) against the rule's closed form, and how the demo's
recipe takes them (docs/BOUNDS.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from jaxnerf_grid import demo
from jaxnerf_grid.capture import bounds
from jaxnerf_grid.config import build
from jaxnerf_grid.data.formats import colmap
from jaxnerf_grid.nerf import coords
from jaxnerf_grid.util.io import DataError


def _look_at_origin(eye) -> np.ndarray:
    """OpenGL camera-to-world [4, 4] at eye looking at the origin, z up."""
    eye = np.asarray(eye, float)
    f = -eye / np.linalg.norm(eye)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, np.cross(r, f), -f, eye
    return m


def _cloud_with_outliers(seed=0):
    """1000 points at radii k / 1000 (k = 1..1000, random directions) and 20 outliers at radius 50."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(1020, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    radii = np.concatenate([np.arange(1, 1001) / 1000.0, np.full(20, 50.0)])
    return d * radii[:, None]


def _ring(radius=3.0, n=10, closest=None):
    angles = 2 * np.pi * np.arange(n) / n
    eyes = [radius * np.array([np.cos(a), np.sin(a), 0.0]) for a in angles]
    if closest is not None:
        eyes[3] = closest * eyes[3] / radius
    return np.stack([_look_at_origin(e) for e in eyes])


def test_bounds_of_a_point_cloud_with_outliers_closed_form():
    """ROI radius: the 95th percentile of 1020 distances (linear interpolation at rank
    0.95 x 1019 = 968.05: 0.969 + 0.05 x 0.001), the 20 outliers at 50 change nothing beyond
    their share; below the camera cap (1/3 of the median camera distance 3 = 1). near: 0.9 x
    (2.5 - ROI radius), the closest camera at 2.5; far: (R - 1) / (R 5e-4) = 1000 for R = 2."""
    c2w = _ring(closest=2.5)
    got = bounds.scene_bounds(c2w, _cloud_with_outliers(), points_near=0.2)
    roi = 0.969 + 0.05 * 0.001
    assert np.allclose(got["roi_centre"], 0.0, atol=1e-9)
    assert got["roi_radius"] == pytest.approx(roi, abs=1e-9)
    assert got["near"] == pytest.approx(0.9 * (2.5 - roi), abs=1e-9)
    assert got["nearest_camera_to_roi"] == pytest.approx(2.5 - roi, abs=1e-9)
    assert got["far"] == pytest.approx(1000.0) and got["contract_radius"] == 2.0
    # the points' near wins when it is larger; the camera cap when the points spread wider
    assert bounds.scene_bounds(c2w, _cloud_with_outliers(), points_near=1.7)["near"] == 1.7
    assert bounds.scene_bounds(c2w, 5 * _cloud_with_outliers())["roi_radius"] == pytest.approx(1.0)


def test_observation_depths_are_each_photos_points_along_its_axis():
    c2w = _ring()  # camera 0 at (3, 0, 0) looking at the origin: z-depth = 3 - x
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.2], [4.0, 0.0, 0.0]])  # the last is behind camera 0
    got = colmap.observation_depths(c2w[:2], points, [np.array([0, 1, 2]), None])
    np.testing.assert_allclose(got[0], [3.0, 2.0])
    assert got[1].size == 0


def test_a_photo_whose_points_the_rois_near_cuts_off_starts_its_rays_at_the_points():
    """near by the ROI rule 0.9 x (2.5 - roi) = 1.3779; photo 3 sees 100 points, 11 of them
    nearer than that: more than NEAR_SHARE (a tenth), so near is the points' near 0.6; with 9 of
    100 nearer the ROI rule stands."""
    c2w = _ring(closest=2.5)
    roi_near = 0.9 * (2.5 - (0.969 + 0.05 * 0.001))

    def depths(nearer):
        photo = np.concatenate([np.full(nearer, 0.7), np.full(100 - nearer, 2.4)])
        return [np.full(50, 2.8)] * 3 + [photo] + [np.full(50, 2.8)] * 6

    cut = bounds.scene_bounds(c2w, _cloud_with_outliers(), points_near=0.6, depths=depths(11))
    assert cut["near"] == 0.6 and cut["observations_nearer"] == pytest.approx(0.11)
    kept = bounds.scene_bounds(c2w, _cloud_with_outliers(), points_near=0.6, depths=depths(9))
    assert kept["near"] == pytest.approx(roi_near, abs=1e-9) and kept["observations_nearer"] == pytest.approx(0.09)
    # a points' near beyond the ROI's is never taken when a photo is cut: the smaller of the two
    farther = bounds.scene_bounds(c2w, _cloud_with_outliers(), points_near=1.5, depths=depths(11))
    assert farther["near"] == pytest.approx(roi_near, abs=1e-9)
    # a photo with 99 observations, 20 of them nearer, says too little: the usual rule, the larger near
    few = [np.full(50, 2.8)] * 9 + [np.concatenate([np.full(20, 0.7), np.full(79, 2.4)])]
    assert bounds.scene_bounds(c2w, _cloud_with_outliers(), points_near=1.5, depths=few)["near"] == 1.5


def test_far_is_where_contraction_stops_changing():
    """contract(far) lies within FAR_GAP of the outer radius, for any radius R > 1."""
    for r in (1.5, 2.0, 4.0):
        far = bounds.far_for_radius(r)
        z = float(np.linalg.norm(coords.contract(np.array([far, 0.0, 0.0]), r)))
        assert (r - z) / r == pytest.approx(bounds.FAR_GAP, rel=1e-3)  # float32 contraction


def test_no_positive_near_is_a_data_error():
    c2w = _ring(closest=0.5)
    with pytest.raises(DataError, match="scene_bounds: no positive near"):
        bounds.scene_bounds(c2w, _cloud_with_outliers())


def test_the_demo_recipe_without_recorded_bounds_is_unchanged():
    """tower-small records no scene_bounds: DEMO_CONFIG's near 1, far 1000, radius 2 stay."""
    assert bounds.read_bounds({"near": 0.5, "far": 40.0}, "transforms.json") is None
    assert bounds.recipe_with_bounds(demo.DEMO_CONFIG, None) is demo.DEMO_CONFIG
    model = demo.DEMO_CONFIG["model"]
    assert (model["near"], model["far"], model["contract_radius"]) == (1.0, 1000.0, 2.0)


def test_recorded_bounds_replace_the_recipe_and_sets_win():

    recorded = {"near": 0.7, "far": 1000.0, "contract_radius": 2.0, "roi_radius": 1.0, "roi_centre": [0, 0, 0]}
    got = bounds.read_bounds({"scene_bounds": recorded}, "t.json")
    recipe = bounds.recipe_with_bounds(demo.DEMO_CONFIG, got)
    assert recipe["model"]["near"] == 0.7 and recipe["model"]["far"] == 1000.0
    assert recipe["model"]["field"] == demo.DEMO_CONFIG["model"]["field"]
    assert demo.DEMO_CONFIG["model"]["near"] == 1.0  # not changed in place
    with_set = build.with_sets(recipe, ["model.near=1.5"])
    assert with_set["model"]["near"] == 1.5 and with_set["model"]["far"] == 1000.0
    assert "near 0.7" in bounds.bounds_line(got) and "constants" in bounds.bounds_line(None)


@pytest.mark.parametrize("bad, key", [({"near": "x"}, "scene_bounds.near"), ({"near": 2000.0}, "near < far"),
                                      ({"roi_centre": [0, 0]}, "scene_bounds.roi_centre"),
                                      ({"contract_radius": 1.0}, "contract_radius > 1")])
def test_bad_recorded_bounds_name_the_file_and_key(bad, key):
    recorded = {"near": 0.7, "far": 1000.0, "contract_radius": 2.0, "roi_radius": 1.0, "roi_centre": [0, 0, 0]}
    with pytest.raises(DataError, match=f"^data/t.json: .*{key}"):
        bounds.read_bounds({"scene_bounds": {**recorded, **bad}}, "data/t.json")
    with pytest.raises(DataError, match="^data/t.json: 'scene_bounds' must be an object"):
        bounds.read_bounds({"scene_bounds": [1, 2]}, "data/t.json")


def test_without_recorded_bounds_the_recipes_near_holds_for_an_orbit_and_drops_for_a_nearer_camera():
    ring = np.stack([_look_at_origin([3 * np.cos(a), 3 * np.sin(a), 0.5]) for a in np.linspace(0, 6, 8)])
    assert bounds.unrecorded_bounds(ring, 0.05, 1.0, 1000.0, 2.0) is None          # 0.9 x (3.04 - 1) > 1
    near_ring = ring.copy()
    near_ring[0, :3, 3] = [1.5, 0.0, 0.0]                                            # 0.5 from the unit sphere
    got = bounds.unrecorded_bounds(near_ring, 0.05, 1.0, 1000.0, 2.0)
    assert got["near"] == pytest.approx(0.9 * 0.5) and got["nearest_camera_to_roi"] == pytest.approx(0.5)
    assert (got["far"], got["contract_radius"], got["source"]) == (1000.0, 2.0, "cameras")
    assert bounds.unrecorded_bounds(near_ring, 0.6, 1.0, 1000.0, 2.0)["near"] == 0.6  # never below the dataset's
    inside = ring.copy()
    inside[0, :3, 3] = [0.3, 0.0, 0.0]                                               # inside the sphere: a walk
    got = bounds.unrecorded_bounds(inside, 0.05, 1.0, 1000.0, 2.0)
    assert got["near"] == 0.05 and got["nearest_camera_to_roi"] == pytest.approx(-0.7)
    assert "inside the region of interest" in bounds.bounds_line(got)
    assert bounds.unrecorded_bounds(inside, 0.05, None, 1000.0, 2.0) is None        # the dataset's near is used


def _normalised_folder(tmp_path, eyes, near=0.05):
    """A transforms.json dataset, taken as normalised, of 16x12 black photos at `eyes`."""
    folder = tmp_path / "walk"
    (folder / "images").mkdir(parents=True)
    frames = []
    for k, eye in enumerate(eyes):
        Image.new("RGB", (16, 12)).save(folder / "images" / f"{k}.png")
        frames.append({"file_path": f"images/{k}.png", "transform_matrix": _look_at_origin(eye).tolist()})
    meta = {"w": 16, "h": 12, "fl_x": 14.0, "fl_y": 14.0, "cx": 8.0, "cy": 6.0, "near": near, "far": 100.0,
            "scene_normalization": {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def test_the_config_of_a_capture_walking_through_its_scene_starts_the_rays_at_the_datasets_near(tmp_path):
    walk = _normalised_folder(tmp_path, [[0.3, 0.0, 0.1], [2.0, 1.0, 0.3], [-2.5, 0.5, 0.2]])
    built = build.build(build.Request(recipe="ours-lean"), data=walk)
    assert built.overrides["model"]["near"] == pytest.approx(0.05) and built.bounds["source"] == "cameras"
    orbit = _normalised_folder(tmp_path / "o", [[3.0, 0.0, 0.5], [0.0, 3.0, 0.5], [-3.0, 0.0, 0.5]])
    assert build.build(build.Request(recipe="ours-lean"), data=orbit).bounds is None


def test_near_never_drops_below_the_floor_where_one_point_lies_at_a_camera(tmp_path):
    ring = np.stack([_look_at_origin([3 * np.cos(a), 3 * np.sin(a), 0.5]) for a in np.linspace(0, 6, 8)])
    inside = ring.copy()
    inside[0, :3, 3] = [0.3, 0.0, 0.0]
    # a camera inside the region of interest: near is the points' own, here 0.001, floored at 0.05
    assert bounds.scene_bounds(inside, None, points_near=0.001)["near"] == bounds.NEAR_FLOOR == 0.05
    assert bounds.scene_bounds(inside, None, points_near=0.2)["near"] == pytest.approx(0.2)
    assert bounds.unrecorded_bounds(inside, 0.001, 1.0, 1000.0, 2.0)["near"] == 0.05
    # a dataset that recorded a smaller near runs with the floor
    walk = _normalised_folder(tmp_path, [[0.3, 0.0, 0.1], [2.0, 1.0, 0.3]])
    meta = json.loads((walk / "transforms.json").read_text())
    meta["scene_bounds"] = {"near": 0.0009, "far": 1000.0, "contract_radius": 2.0, "roi_centre": [0, 0, 0],
                            "roi_radius": 1.0}
    (walk / "transforms.json").write_text(json.dumps(meta))
    assert bounds.folder_bounds(walk)["near"] == 0.05
    assert build.build(build.Request(recipe="ours-lean"), data=walk).overrides["model"]["near"] == 0.05


def test_a_camera_inside_the_region_of_interest_is_warned_of_before_training():
    assert bounds.bounds_warning(None) is None
    assert bounds.bounds_warning({"nearest_camera_to_roi": 0.4}) is None          # an orbit outside the sphere
    line = bounds.bounds_warning({"nearest_camera_to_roi": -0.903})
    assert line.startswith("warning: a camera lies 0.903 inside the region of interest") and "\n" not in line
