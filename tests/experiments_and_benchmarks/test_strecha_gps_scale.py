"""benchmarks/strecha_gps_scale.py on a made-up Strecha scene: surveyed cameras (z down, as the
benchmark's) and a dataset whose centres are a known similarity of them (z up, 1/10 scale)."""

import numpy as np

from benchmarks import strecha_gps_scale
from jaxnerf_grid.util import io


def write_scene(tmp_path, count=9):
    """A Strecha folder with `count` .camera files on an 12 m arc, and a transforms.json of the
    same cameras at 1/10 scale, z up, turned 30 degrees about z. Returns (scene, dataset)."""
    scene, data = tmp_path / "scene", tmp_path / "data"
    (scene / "gt_dense_cameras").mkdir(parents=True)
    data.mkdir()
    angle = np.radians(30.0)
    turn = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    frames = []
    for k in range(count):
        a = np.radians(-40 + 80 * k / (count - 1))
        centre_down = np.array([12 * np.sin(a), -12 * np.cos(a), -0.3 * k])  # z down: rising cameras
        numbers = [1000, 0, 500, 0, 1000, 400, 0, 0, 1] + [0, 0, 0] + list(np.eye(3).reshape(-1)) + \
            list(centre_down) + [1000, 800]
        (scene / "gt_dense_cameras" / f"{k:04d}.jpg.camera").write_text(" ".join(f"{v:.9g}" for v in numbers))
        up = np.array([centre_down[0], -centre_down[1], -centre_down[2]])
        c2w = np.eye(4)
        c2w[:3, 3] = turn @ up / 10.0 + [1.0, 2.0, 0.5]
        frames.append({"file_path": f"images/{k:04d}.jpg", "transform_matrix": c2w.tolist()})
    io.write_json(data / "transforms.json", {"frames": frames})
    return scene, data


def test_the_known_scale_is_found_and_noise_moves_it_by_about_sigma_over_the_baseline(tmp_path):
    scene, data = write_scene(tmp_path)
    result = strecha_gps_scale.run(scene, data, [0.0, 1.0], draws=60)
    assert abs(result["metres_per_unit_noise_free"] - 10.0) < 1e-6
    assert result["noise_free_rms_m"] < 1e-6  # z down turned up: the yaw-only fit is exact
    no_noise, one_metre = result["rows"]
    assert no_noise["median_pct"] < 1e-6
    ratio = 100 * 1.0 / result["baseline_m"]  # sigma over the baseline, in per cent
    assert 0.2 * ratio < one_metre["median_pct"] < 3 * ratio, (one_metre, ratio)
    assert one_metre["p95_pct"] > one_metre["median_pct"]
    assert strecha_gps_scale.main([str(scene), str(tmp_path / "missing")]) == 2  # one line, no traceback
