"""benchmarks/strecha_dataset.py: a Strecha .camera file (K, distortion, R camera-to-world in
OpenCV axes, centre C, size) to a transforms.json frame, checked by projecting a world point by
hand with Strecha's own model x ~ K R^T (X - C) and casting the loaded camera's ray through it."""

import numpy as np
import pytest

from benchmarks import strecha_dataset
from jaxnerf_grid.data.formats import load_dataset
from jaxnerf_grid.data.normalize import apply_normalization_to_points
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.util.io import DataError, write_png


def _rotation(axis, angle):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _write_scene(root, cams):
    (root / "images").mkdir(parents=True)
    (root / "gt_dense_cameras").mkdir()
    for i, (k, r, c) in enumerate(cams):
        write_png(root / "images" / f"{i:04d}.png", np.full((24, 32, 3), 0.5, np.float32))
        rows = [k[0], k[1], k[2], [0, 0, 0], r[0], r[1], r[2], c, [32, 24]]
        (root / "gt_dense_cameras" / f"{i:04d}.png.camera").write_text(
            "\n".join(" ".join(f"{v:.12g}" for v in row) for row in rows) + "\n")


def test_a_surveyed_camera_sees_the_point_it_projects(tmp_path):
    k = np.array([[30.0, 0, 15.5], [0, 31.0, 11.0], [0, 0, 1]])
    target = np.array([0.5, 1.0, 0.2])
    cams = []
    for i in range(6):  # cameras on a ring, each looking roughly at the target (OpenCV axes)
        c = target + 8 * np.array([np.cos(i), np.sin(i), 0.3])
        z = (target - c) / np.linalg.norm(target - c)
        x = np.cross(z, [0, 0, -1.0])
        x /= np.linalg.norm(x)
        r = np.stack([x, np.cross(z, x), z], axis=1) @ _rotation([1, 2, 3], 0.05)  # columns: camera axes in world
        cams.append((k, r, c))
    _write_scene(tmp_path / "scene", cams)
    strecha_dataset.strecha_dataset(tmp_path / "scene", tmp_path / "out")
    ds = load_dataset(tmp_path / "out", progress=False)
    assert (ds.width, ds.height) == (32, 24) and ds.num_frames == 6
    point = target + np.array([0.3, -0.2, 0.1])
    for i, (kk, r, c) in enumerate(cams):
        x = kk @ r.T @ (point - c)
        u, v = x[0] / x[2], x[1] / x[2]
        ray = rays_lib.rays_for_pixels(ds.c2w[i], *ds.intrinsics[i], np.float32(u), np.float32(v))
        p = apply_normalization_to_points(point, ds.normalization)
        o, d = np.asarray(ray.origins, np.float64), np.asarray(ray.directions, np.float64)
        off = (p - o) - np.dot(p - o, d) * d
        assert np.linalg.norm(off) < 1e-4 and np.dot(p - o, d) > 0


def test_a_camera_file_of_the_wrong_length_is_one_line_naming_it(tmp_path):
    _write_scene(tmp_path / "scene", [(np.eye(3), np.eye(3), np.zeros(3))])
    bad = tmp_path / "scene" / "gt_dense_cameras" / "0000.png.camera"
    bad.write_text("1 2 3\n")
    with pytest.raises(DataError, match="0000.png.camera.*26 numbers"):
        strecha_dataset.strecha_dataset(tmp_path / "scene", tmp_path / "out")


def test_poses_accuracy_scores_a_dataset_against_the_surveyed_cameras(tmp_path):
    """benchmarks.poses_accuracy.strecha_errors on the dataset strecha_dataset wrote (the same
    cameras, normalised: scaled, turned, moved) finds 0 degrees; a frame turned 2 degrees in the
    dataset reports 2 degrees, the others still about 0."""
    import json

    from benchmarks import poses_accuracy

    k = np.array([[30.0, 0, 15.5], [0, 31.0, 11.0], [0, 0, 1]])
    cams = []
    for i in range(5):
        c = 6 * np.array([np.cos(0.4 * i), np.sin(0.4 * i), 0.2])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, -1.0])
        x /= np.linalg.norm(x)
        cams.append((k, np.stack([x, np.cross(z, x), z], axis=1), c))
    _write_scene(tmp_path / "scene", cams)
    strecha_dataset.strecha_dataset(tmp_path / "scene", tmp_path / "out")
    row = poses_accuracy.strecha_errors(tmp_path / "scene", tmp_path / "out")
    assert row["rotation_deg_max"] < 1e-3
    meta = json.loads((tmp_path / "out" / "transforms.json").read_text())
    m = np.asarray(meta["frames"][3]["transform_matrix"])
    m[:3, :3] = _rotation([0.3, 1, 0.2], np.radians(2.0)) @ m[:3, :3]
    meta["frames"][3]["transform_matrix"] = m.tolist()
    (tmp_path / "out" / "transforms.json").write_text(json.dumps(meta))
    per_photo = poses_accuracy.strecha_errors(tmp_path / "scene", tmp_path / "out")["per_photo"]
    assert per_photo["0003.png"]["rotation_deg"] == pytest.approx(2.0, abs=1e-3)
    assert max(v["rotation_deg"] for n, v in per_photo.items() if n != "0003.png") < 1e-3


def test_poses_accuracy_scores_a_dataset_against_a_captures_own_transforms(tmp_path):
    """`--reference`: a dataset whose cameras are the reference's scaled, turned and moved scores
    0 degrees, a frame turned 2 degrees scores 2, and a photo missing from the dataset is listed
    as left out (the reference's frames named by their file_path, as nerfstudio writes them)."""
    import json

    from benchmarks import poses_accuracy

    turn = _rotation([0.2, -0.4, 1.0], 0.7)
    ref, found = [], []
    for i in range(6):
        c = 5 * np.array([np.cos(0.5 * i), np.sin(0.5 * i), 0.3])
        z = c / np.linalg.norm(c)   # OpenGL: the camera looks along -z, away from c
        x = np.cross([0, 0, 1.0], z)
        x /= np.linalg.norm(x)
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = np.stack([x, np.cross(z, x), z], axis=1), c
        ref.append({"file_path": f"images/frame_{i:05d}.png", "transform_matrix": m.tolist()})
        if i == 5:
            continue   # not registered
        g = np.eye(4)
        g[:3, :3], g[:3, 3] = turn @ m[:3, :3], 0.3 * turn @ c + np.array([1.0, -2.0, 0.5])
        if i == 2:
            g[:3, :3] = _rotation([1.0, 0.3, 0.1], np.radians(2.0)) @ g[:3, :3]
        found.append({"file_path": f"images/frame_{i:05d}.png", "transform_matrix": g.tolist()})
    (tmp_path / "ref.json").write_text(json.dumps({"frames": ref}))
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "transforms.json").write_text(json.dumps({"frames": found}))
    (tmp_path / "photos").mkdir()
    for i in range(6):
        (tmp_path / "photos" / f"frame_{i:05d}.png").write_bytes(b"")
    out = tmp_path / "acc.json"
    assert poses_accuracy.main(["--reference", str(tmp_path / "ref.json"), "--photos", str(tmp_path / "photos"),
                                "--dataset", str(tmp_path / "data"), "--out", str(out)]) == 0
    row = json.loads(out.read_text())["rows"][0]
    assert (row["photos"], row["in_dataset"], row["left_out"]) == (6, 5, ["frame_00005.png"])
    assert row["per_photo"]["frame_00002.png"]["rotation_deg"] == pytest.approx(2.0, abs=0.05)
    assert max(v["rotation_deg"] for n, v in row["per_photo"].items() if n != "frame_00002.png") < 0.1
    assert row["per_photo"]["frame_00002.png"]["rotation_deg_oriented"] == pytest.approx(2.0, abs=0.5)
    assert row["rotation_deg_oriented_median"] < 0.5


def test_reference_cameras_named_png_match_a_datasets_jpegs_by_their_stem(tmp_path):
    """The generator names its frames .png, the photos `poses` was given are .jpg: the cameras pair
    by the name's stem, a frame turned 2 degrees scores 2, the others 0."""
    import json

    from benchmarks import poses_accuracy

    ref, found = {}, []
    for i in range(5):
        c = 4 * np.array([np.cos(0.6 * i), np.sin(0.6 * i), 0.4])
        z = c / np.linalg.norm(c)
        x = np.cross([0, 0, 1.0], z)
        x /= np.linalg.norm(x)
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = np.stack([x, np.cross(z, x), z], axis=1), c
        ref[f"train_{i:03d}.png"] = m.copy()
        if i == 1:
            m[:3, :3] = _rotation([0.0, 1.0, 0.2], np.radians(2.0)) @ m[:3, :3]
        found.append({"file_path": f"images/train_{i:03d}.jpg", "transform_matrix": m.tolist()})
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": found}))
    per_photo = poses_accuracy.reference_errors(ref, tmp_path)["per_photo"]
    assert sorted(per_photo) == [f"train_{i:03d}" for i in range(5)]
    assert per_photo["train_001"]["rotation_deg"] == pytest.approx(2.0, abs=0.05)
    assert max(v["rotation_deg"] for n, v in per_photo.items() if n != "train_001") < 0.1
