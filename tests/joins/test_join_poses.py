"""`poses`' dataset stage (`data.poses.write_dataset`) against the cameras it was given.

A COLMAP text model is written by hand (COLMAP's documented format: cameras.txt, images.txt,
points3D.txt) from known metric cameras on an orbit and points projected into them; the
transforms.json that `write_dataset` makes from it must give back those cameras (through its
normalisation record), near / far from the points' depths by the documented rule (in
normalised units: metric times the scale), and, loaded as a dataset, put every point on the
pixel COLMAP observed it at.
"""

from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid.capture import bounds as bounds_lib
from jaxnerf_grid.capture import poses
from jaxnerf_grid.data.formats import load_dataset
from jaxnerf_grid.util import io

WIDTH, HEIGHT, FOCAL = 64, 48, 60.0
TARGET = np.array([5.0, -3.0, 10.0])


def _w2c_opencv(centre, target):
    """World-to-camera rotation (OpenCV axes: x right, y down, z forward) looking at target, z up."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward])


def _quaternion(r):
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method, w > 0 branch)."""
    w = 0.5 * np.sqrt(1.0 + np.trace(r))
    return np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)])


def _orbit(count=8):
    """Known cameras: (centres [N, 3], w2c rotations [N, 3, 3]) on a 30 m ring, 8 m above TARGET."""
    angles = 2 * np.pi * (np.arange(count) + 0.3) / count
    centres = TARGET + np.column_stack([30 * np.cos(angles), 30 * np.sin(angles), np.full(count, 8.0)])
    return centres, np.stack([_w2c_opencv(c, TARGET) for c in centres])


def _project(points, centre, w2c):
    """Pixel (x, y) (COLMAP: the top-left corner of the image is (0, 0)) and z-depth of points [P, 3]."""
    cam = (points - centre) @ w2c.T
    return np.column_stack([FOCAL * cam[:, 0] / cam[:, 2] + WIDTH / 2,
                            FOCAL * cam[:, 1] / cam[:, 2] + HEIGHT / 2]), cam[:, 2]


def _numbers(values) -> str:
    return " ".join(f"{float(v):.17g}" for v in values)


@pytest.fixture
def stage(tmp_path):
    """A stage folder (sparse/0 in COLMAP's text format, images/) and the known scene. Built per
    test (0.1 s): mutmut credits a function to the tests whose own setup calls it."""
    root = tmp_path
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (root / "images").mkdir()
    rng = np.random.default_rng(4)
    points = TARGET + rng.uniform(-5, 5, (300, 3))
    centres, w2cs = _orbit()
    (model / "cameras.txt").write_text(f"1 PINHOLE {WIDTH} {HEIGHT} {FOCAL} {FOCAL} {WIDTH / 2} {HEIGHT / 2}\n")
    lines, tracks, depths, pixels = [], {i: [] for i in range(len(points))}, [], []
    for k, (c, r) in enumerate(zip(centres, w2cs)):
        xy, z = _project(points, c, r)
        assert np.all((xy >= 0) & (xy < [WIDTH, HEIGHT])) and np.all(z > 0)     # every point seen
        q, t = _quaternion(r), -r @ c
        name = f"photo_{k:02d}.png"
        io.write_png(root / "images" / name, np.zeros((HEIGHT, WIDTH, 3), np.float32))
        lines.append(f"{k + 1} {_numbers(q)} {_numbers(t)} 1 {name}")
        lines.append(" ".join(f"{_numbers(p)} {i + 1}" for i, p in enumerate(xy)))
        for i in range(len(points)):
            tracks[i].append(f"{k + 1} {i}")
        depths.append(z)
        pixels.append(xy)
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    (model / "points3D.txt").write_text("".join(f"{i + 1} {_numbers(p)} 128 128 128 0.1 "
                                                f"{' '.join(tracks[i])}\n" for i, p in enumerate(points)))
    summary = {"registered": len(centres), "photos": len(centres), "points3d": len(points),
               "mean_reprojection_error": 0.0, "unregistered": [], "skipped": []}
    top = poses.write_dataset(root, summary)
    return {"root": root, "top": top, "points": points, "centres": centres, "w2cs": w2cs,
            "depths": np.concatenate(depths), "pixels": pixels}


def _to_metric(x, record):
    """x_norm -> metres: R^T x_norm / s - t (R the identity without a rotation)."""
    rotation = np.asarray(record.get("rotation", np.eye(3)), np.float64)
    return np.asarray(x, np.float64) @ rotation / record["scale"] - np.asarray(record["translation"])


def test_poses_gives_back_the_cameras_it_was_given(stage):
    top, record = stage["top"], stage["top"]["scene_normalization"]
    assert record["scale"] != 1.0 and np.linalg.norm(record["translation"]) > 1.0      # not the identity
    rotation = np.asarray(record.get("rotation", np.eye(3)), np.float64)
    frames = sorted(top["frames"], key=lambda f: f["file_path"])
    for frame, centre, w2c in zip(frames, stage["centres"], stage["w2cs"]):
        c2w = np.asarray(frame["transform_matrix"], np.float64)
        np.testing.assert_allclose(_to_metric(c2w[:3, 3], record), centre, atol=1e-6)
        # OpenGL axes (x right, y up, z backward) are OpenCV's with y and z negated
        np.testing.assert_allclose(rotation.T @ c2w[:3, :3], w2c.T * [1, -1, -1], atol=1e-9)
        assert (frame["fl_x"], frame["fl_y"], frame["cx"], frame["cy"]) == (FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2)


def test_poses_near_and_far_are_the_points_depths_in_normalised_units(stage):
    top, scale = stage["top"], stage["top"]["scene_normalization"]["scale"]
    z = stage["depths"]                                        # metres, every observation
    min_cos = 1.0 / np.sqrt(1.0 + (WIDTH / 2 / FOCAL) ** 2 + (HEIGHT / 2 / FOCAL) ** 2)   # the corner ray
    near = 0.9 * np.percentile(z, 0.5) * scale
    far = max(1.1 * np.percentile(z, 99.5) / min_cos * scale, 2 * near)
    assert top["near"] == pytest.approx(near, rel=1e-6)
    assert top["far"] == pytest.approx(far, rel=1e-6)
    # the depth of the target (the orbit's centre) in normalised units lies between them
    target_depth = np.linalg.norm(stage["centres"][0] - TARGET) * scale
    assert top["near"] < target_depth < top["far"]


def test_the_written_dataset_puts_each_point_on_the_pixel_colmap_saw_it(stage):
    ds = load_dataset(Path(stage["root"]), progress=False)
    record = stage["top"]["scene_normalization"]
    rotation = np.asarray(record.get("rotation", np.eye(3)), np.float64)
    scene_points = (stage["points"] + np.asarray(record["translation"])) @ rotation.T * record["scale"]
    assert ds.near == pytest.approx(stage["top"]["near"]) and ds.far == pytest.approx(stage["top"]["far"])
    for k in range(ds.num_frames):
        c2w = np.asarray(ds.c2w[k], np.float64)
        cam = (scene_points - c2w[:3, 3]) @ c2w[:3, :3]        # OpenGL camera coordinates
        fx, fy, cx, cy = (float(v) for v in ds.intrinsics[k])
        xy = np.column_stack([cx + fx * cam[:, 0] / -cam[:, 2], cy - fy * cam[:, 1] / -cam[:, 2]])
        np.testing.assert_allclose(xy, stage["pixels"][k], atol=1e-3)


def test_poses_scene_bounds_are_the_known_orbit_in_normalised_units(stage):
    """The region of interest (docs/BOUNDS.md): centred where the cameras look (TARGET), its
    radius the ROI_PERCENTILE-th percentile of the points' distances to it (under the cap of
    ROI_CAMERA_FRACTION camera distances), both in normalised units."""
    top = stage["top"]
    record, bounds = top["scene_normalization"], top["scene_bounds"]
    scale, translation = record["scale"], np.asarray(record["translation"])
    assert "rotation" not in record                       # the stage's model is z-up already
    np.testing.assert_allclose(bounds["roi_centre"], scale * (TARGET + translation), atol=1e-6)
    distances = np.linalg.norm(stage["points"] - TARGET, axis=1) * scale
    camera_distance = np.linalg.norm(stage["centres"][0] - TARGET) * scale
    radius = np.percentile(distances, bounds_lib.ROI_PERCENTILE)
    assert radius < bounds_lib.ROI_CAMERA_FRACTION * camera_distance        # the cap does not decide
    assert bounds["roi_radius"] == pytest.approx(radius, rel=1e-6)
    assert bounds["nearest_camera_to_roi"] == pytest.approx(camera_distance - radius, rel=1e-6)


def test_poses_scale_near_and_files_by_the_rules(stage):
    """The orbit's scale (1 / the region's radius: the 95th percentile of the points' distances to
    the target, under a third of the camera distance; docs/POSES.md), the bounds' near (the
    larger of 0.9 x the gap from the cameras to the region and the points' near), the summary
    kept, and the files as written."""
    top, root = stage["top"], stage["root"]
    distances = np.linalg.norm(stage["points"] - TARGET, axis=1)
    camera_distance = np.linalg.norm(stage["centres"][0] - TARGET)
    radius = min(np.percentile(distances, 95.0), camera_distance / 3.0)
    assert top["scene_normalization"]["scale"] == pytest.approx(1.0 / radius, rel=1e-6)
    gap = top["scene_bounds"]["nearest_camera_to_roi"]
    assert top["scene_bounds"]["near"] == pytest.approx(max(bounds_lib.NEAR_FACTOR * gap, top["near"]), rel=1e-9)
    assert top["poses"]["registered"] == 8 and top["poses"]["points3d"] == 300
    assert io.read_json(root / "transforms.json") == top
    report = (root / poses.REPORT).read_text().splitlines()
    assert report[0] == "# Camera poses" and any(line.startswith("| near |") for line in report)


def _vetting_row(name, kept, reasons):
    return {"name": name, "observations": 12, "reprojection_px": 3.2, "track_length": 1.5, "neighbour_ratio": None,
            "covisible": 2, "kept": kept, "reasons": reasons}


def test_poses_report_names_each_left_out_photo_with_its_reasons_in_the_summary_and_the_table():
    """poses_report.md from a summary written by hand (no COLMAP run): the left-out photo with its
    reasons in the summary line and its table row, the --keep-all note, the unregistered and
    unreadable photos, and the bounds table, each line as docs/POSES.md states it."""
    summary = {"registered": 3, "photos": 5, "points3d": 40, "mean_reprojection_error": 0.25,
               "unregistered": ["d.png"], "skipped": ["e.jpg"],
               "vetting": {"keep_all": True, "left_out": ["b.png"],
                           "photos": [_vetting_row("a.png", True, []),
                                      _vetting_row("b.png", False, ["reprojection 3.2 px", "track 1.5"])]}}
    bounds = {"near": 0.125, "far": 4.5, "contract_radius": 2.0, "roi_radius": 1.0, "nearest_camera_to_roi": 2.25,
              "roi_centre": [0.5, -0.25, 0.0]}
    lines = poses.report_lines(summary, bounds)
    assert lines[:3] == ["# Camera poses", "", "registered 3/5 photos, 40 3-D points, mean reprojection error 0.250 px"]
    assert "not registered (1): d.png" in lines and "unreadable, skipped (1): e.jpg" in lines
    assert (f"left out by the vetting (1; table in {poses.REPORT}, --keep-all keeps them): "
            "b.png (reprojection 3.2 px; track 1.5)") in lines
    vet = lines.index("## Vetting (docs/POSES.md)")
    assert lines[vet + 2] == "`--keep-all`: every registered photo kept, whatever its scores."
    assert "| b.png | 12 | 3.20 | 1.50 | - | 2 | no | reprojection 3.2 px; track 1.5 |" in lines[vet:]
    assert "| a.png | 12 | 3.20 | 1.50 | - | 2 | yes |  |" in lines[vet:]
    table = lines.index("## Scene bounds (docs/BOUNDS.md)")
    assert lines[table:] == ["## Scene bounds (docs/BOUNDS.md)", "", "| bound | value (normalised units) |",
                             "|---|---|", "| near | 0.125 |", "| far | 4.5 |", "| contract_radius | 2 |",
                             "| roi_radius | 1 |",
                             "| nearest_camera_to_roi | 2.25 |", "| roi_centre | 0.5, -0.25, 0 |", ""]
    # without the vetting record: no left-out line, no keep-all note, an empty table
    plain = poses.report_lines({k: v for k, v in summary.items() if k != "vetting"}, bounds)
    assert not any(line.startswith(("left out", "`--keep-all`", "| b.png")) for line in plain)


def test_poses_summary_lines_of_the_matcher_timings_georeference_and_relaxed_mapping():
    """The end-of-run summary (docs/POSES.md) from summaries written by hand: the matcher with its
    reason and overlap, the seconds of each stage, the scale and georeference with its GPS
    residual (flagged above georef.SUSPECT_GPS_RMS), units unknown, relaxed thresholds."""
    base = {"registered": 8, "photos": 8, "points3d": 300, "mean_reprojection_error": 0.5, "unregistered": [],
            "skipped": []}
    full = {**base, "matcher": "sequential", "matcher_reason": "auto: 40 photos, numbered", "overlap": 10,
            "seconds": 61.2, "timings_s": {"features": 20.4, "matching": 30.6},
            "georeference": {"units": "metres", "source": "GPS", "crs": "EPSG:32632",
                             "metres_per_model_unit": 3.14159, "gps": {"rms_m": 0.5}},
            "relaxed_mapping": True}
    assert poses.format_summary(full).splitlines()[1:] == [
        "matcher: sequential (auto: 40 photos, numbered, each photo with its next 10)",
        "time: 61 s in all; features 20 s, matching 31 s",
        "scale and georeference from GPS: EPSG:32632, 3.142 m per model unit, GPS residual RMS 0.5 m",
        f"registered with relaxed mapper thresholds: check the cameras in {poses.TOPVIEW} (a ring around the "
        "tower) before training (docs/POSES.md)"]
    far = {**full, "overlap": None, "timings_s": {}, "relaxed_mapping": False,
           "georeference": {"units": "metres", "source": "GPS", "crs": None, "metres_per_model_unit": 2.0,
                            "gps": {"rms_m": 1e6}}}
    assert poses.format_summary(far).splitlines()[1:] == [
        "matcher: sequential (auto: 40 photos, numbered)",
        "scale and georeference from GPS: no CRS, 2 m per model unit, GPS residual RMS 1000000.0 m; residuals too "
        "large: check the reconstruction (poses_report.md)"]
    unknown = {**base, "georeference": {"units": "unknown"}}
    assert poses.format_summary(unknown).splitlines()[1:] == [
        "units unknown (no GPS read from the photos, no ground control points, no scale bar)"]
    assert poses.format_summary(base).splitlines()[1:] == []


def test_poses_topview_puts_each_camera_and_point_where_it_stands_seen_from_above(tmp_path):
    """poses_topview.png: +x to the right, +y up the picture, the half-width the larger of 1.2 and
    1.1 x the farthest camera coordinate; each camera a red dot, each point a grey 2 x 2 block,
    the unit circle grey. The pixel of (x, y) by hand: ((x / e + 1) s / 2, (1 - y / e) s / 2)."""
    size = 200
    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[:, :3, 3] = [[2.0, 0.5, 0.3], [-0.5, -1.0, 0.2]]       # farthest coordinate 2: e = 2.2
    c2w[:, :3, 2] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]         # looking along -x and -y
    points = np.array([[0.3, 0.8, 0.1], [5.0, 0.0, 0.0]])      # the second outside the picture
    path = tmp_path / poses.TOPVIEW
    poses.draw_topview(path, c2w, points, size=size)
    img = np.round(io.read_image(path) * 255).astype(int)
    extent = 2.2

    def pixel(x, y):
        return (x / extent + 1) * size / 2, (1 - y / extent) * size / 2

    dot = (img[..., 0] == 220) & (img[..., 1] == 0) & (img[..., 2] == 0)
    rows, cols = np.nonzero(dot)
    for x, y in c2w[:, :2, 3]:
        u, v = pixel(x, y)
        near = (np.abs(cols - u) <= 4) & (np.abs(rows - v) <= 4)
        assert near.sum() >= 9, (x, y)                          # a filled dot of radius 3 there
        assert abs(cols[near].mean() - u) <= 0.6 and abs(rows[near].mean() - v) <= 0.6
    at_a_camera = [(np.abs(cols - pixel(x, y)[0]) <= 4) & (np.abs(rows - pixel(x, y)[1]) <= 4)
                   for x, y in c2w[:, :2, 3]]
    assert np.logical_or(*at_a_camera).all()                    # no red dot anywhere else
    # each camera's viewing direction (-z of its c2w), 0.08 e long, drawn red from its dot
    for (x, y), look in zip(c2w[:, :2, 3], -c2w[:, :2, 2]):
        u, v = (int(round(c)) for c in pixel(*((x, y) + 0.06 * extent * look)))
        assert img[v, u, 0] >= 180 and img[v, u, 1:].max() <= 80, (x, y)   # red (antialiased)
    u, v = (int(round(c)) for c in pixel(0.3, 0.8))
    assert (img[v:v + 2, u:u + 2] == 120).all()                 # the point inside, its 2 x 2 block
    radius = size / 2 / extent                                  # the unit circle, grey where it crosses +x
    assert (img[size // 2, int(round(size / 2 + radius))] < 255).all()
    assert (img[size // 2, int(round(size / 2 + radius)) + 3] == 255).all()
