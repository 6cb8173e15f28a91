"""Bad input: every case raises DataError whose message names the offending file."""

import json
import struct

import numpy as np
import pytest

from jaxnerf_grid.data import formats
from jaxnerf_grid.data.formats import colmap_model as colmap_io
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError

W, H = 16, 12
EYE_POSE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]


def _scene(root, n=3, **top_extra):
    """A minimal valid transforms.json scene; returns its top-level dict."""
    frames = []
    for i in range(n):
        io.write_png(root / "images" / f"f{i}.png", np.full((H, W, 3), 0.5, np.float32))
        pose = np.array(EYE_POSE, float)
        pose[0, 3] = i * 0.1
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": pose.tolist()})
    top = {"fl_x": 20.0, "fl_y": 20.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H, "frames": frames,
           "scene_normalization": {"scale": 1.0, "translation": [0, 0, 0]}}
    top.update(top_extra)
    io.write_json(root / "transforms.json", top)
    return top


def _rewrite(root, top):
    io.write_json(root / "transforms.json", top)


def test_valid_scene_loads(tmp_path):
    _scene(tmp_path)
    assert formats.load_dataset(tmp_path).num_frames == 3


def test_missing_image(tmp_path):
    _scene(tmp_path)
    (tmp_path / "images" / "f1.png").unlink()
    with pytest.raises(DataError, match=r"f1\.png.*not found"):
        formats.load_dataset(tmp_path)


def test_unreadable_image(tmp_path):
    _scene(tmp_path)
    (tmp_path / "images" / "f2.png").write_bytes(b"this is not a png")
    with pytest.raises(DataError, match=r"f2\.png.*not a readable image"):
        formats.load_dataset(tmp_path)


def test_sizes_differ_between_images(tmp_path):
    top = _scene(tmp_path)
    del top["w"], top["h"]
    _rewrite(tmp_path, top)
    io.write_png(tmp_path / "images" / "f2.png", np.zeros((H + 2, W, 3), np.float32))
    with pytest.raises(DataError, match=r"f2\.png.*f0\.png"):
        formats.load_dataset(tmp_path)


def test_size_mismatch_with_json(tmp_path):
    _scene(tmp_path)
    io.write_png(tmp_path / "images" / "f1.png", np.zeros((H, W + 4, 3), np.float32))
    with pytest.raises(DataError, match=r"f1\.png.*size mismatch"):
        formats.load_dataset(tmp_path)


def test_extra_size_mismatch(tmp_path):
    top = _scene(tmp_path)
    io.write_png(tmp_path / "m1.png", np.zeros((H + 1, W), np.float32))
    top["frames"][1]["mask_path"] = "m1.png"
    _rewrite(tmp_path, top)
    with pytest.raises(DataError, match=r"m1\.png.*size mismatch"):
        formats.load_dataset(tmp_path)


@pytest.mark.parametrize("bad,what", [
    (lambda p: p.__setitem__((0, 3), float("nan")), "non-finite"),
    (lambda p: p.__setitem__((slice(0, 3), slice(0, 3)), 1.1 * np.eye(3)), "not orthonormal"),
    (lambda p: p.__setitem__((slice(0, 3), 0), [-1.0, 0, 0]), "determinant"),
    (lambda p: p.__setitem__((3, 2), 0.5), "last row"),
])
def test_degenerate_pose(tmp_path, bad, what):
    top = _scene(tmp_path)
    pose = np.array(top["frames"][1]["transform_matrix"], float)
    bad(pose)
    top["frames"][1]["transform_matrix"] = pose.tolist()
    (tmp_path / "transforms.json").write_text(json.dumps(top))  # Python's json writes NaN
    with pytest.raises(DataError, match=rf"transforms\.json.*degenerate pose.*{what}"):
        formats.load_dataset(tmp_path)


def test_unknown_camera_model_json(tmp_path):
    _scene(tmp_path, camera_model="EQUIRECTANGULAR")
    with pytest.raises(DataError, match=r"transforms\.json.*EQUIRECTANGULAR"):
        formats.load_dataset(tmp_path)


def _colmap_scene(root, model_line):
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"# cameras\n{model_line}\n")
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 3 1 a.png\n\n2 1 0 0 0 0.1 0 3 1 b.png\n\n")
    for name in ("a.png", "b.png"):
        io.write_png(root / "images" / name, np.zeros((H, W, 3), np.float32))


def test_unknown_camera_model_colmap_text(tmp_path):
    _colmap_scene(tmp_path, f"1 WEIRD_LENS {W} {H} 20 8 6")
    with pytest.raises(DataError, match=r"cameras\.txt.*WEIRD_LENS"):
        formats.load_dataset(tmp_path)


def test_unsupported_camera_model_colmap_text(tmp_path):
    _colmap_scene(tmp_path, f"1 OPENCV_FISHEYE {W} {H} 20 20 8 6 0.1 0 0 0")
    with pytest.raises(DataError, match=r"cameras\.txt.*OPENCV_FISHEYE"):
        formats.load_dataset(tmp_path)


def test_unknown_camera_model_colmap_binary(tmp_path):
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.bin").write_bytes(struct.pack("<QiiQQ", 1, 1, 42, W, H) + struct.pack("<3d", 20, 8, 6))
    colmap_io.write_images_binary(sparse / "images.bin", {})
    (tmp_path / "images").mkdir()
    with pytest.raises(DataError, match=r"cameras\.bin.*unknown camera model id 42"):
        formats.load_dataset(tmp_path)


def test_truncated_colmap_binary(tmp_path):
    sparse = tmp_path / "sparse" / "0"
    cams = {1: colmap_io.Camera(1, "PINHOLE", W, H, np.array([20.0, 20, 8, 6]))}
    colmap_io.write_cameras_binary(sparse / "cameras.bin", cams)
    raw = (sparse / "cameras.bin").read_bytes()
    (sparse / "cameras.bin").write_bytes(raw[:-5])
    colmap_io.write_images_binary(sparse / "images.bin", {})
    (tmp_path / "images").mkdir()
    with pytest.raises(DataError, match=r"cameras\.bin.*truncated"):
        formats.load_dataset(tmp_path)


def test_colmap_zero_quaternion(tmp_path):
    _colmap_scene(tmp_path, f"1 PINHOLE {W} {H} 20 20 8 6")
    (tmp_path / "sparse" / "0" / "images.txt").write_text("1 0 0 0 0 0 0 3 1 a.png\n\n2 1 0 0 0 0 0 3 1 b.png\n")
    with pytest.raises(DataError, match=r"images\.txt.*a\.png.*degenerate pose"):
        formats.load_dataset(tmp_path)


def test_colmap_image_size_mismatch(tmp_path):
    _colmap_scene(tmp_path, f"1 PINHOLE {W * 2} {H * 2} 20 20 8 6")
    with pytest.raises(DataError, match=r"a\.png.*size mismatch"):
        formats.load_dataset(tmp_path)


def test_empty_split(tmp_path):
    top = _scene(tmp_path)
    _rewrite(tmp_path, {**top, "frames": []})
    with pytest.raises(DataError, match=r"transforms\.json.*empty split"):
        formats.load_dataset(tmp_path)
    for f in top["frames"]:
        f["split"] = "train"
    _rewrite(tmp_path, top)
    with pytest.raises(DataError, match=r"transforms\.json.*empty split 'test'"):
        formats.load_dataset(tmp_path)


def test_empty_blender_split(tmp_path):
    io.write_png(tmp_path / "train" / "r_0.png", np.zeros((H, W, 4), np.float32))
    io.write_json(tmp_path / "transforms_train.json", {"camera_angle_x": 0.7, "frames": [
        {"file_path": "./train/r_0", "transform_matrix": EYE_POSE}]})
    io.write_json(tmp_path / "transforms_test.json", {"camera_angle_x": 0.7, "frames": []})
    with pytest.raises(DataError, match=r"transforms_test\.json.*empty split"):
        formats.load_dataset(tmp_path)


def test_missing_extra_file(tmp_path):
    top = _scene(tmp_path)
    top["frames"][2]["depth_file_path"] = "depth/f2.exr"
    _rewrite(tmp_path, top)
    with pytest.raises(DataError, match=r"f2\.exr.*not found"):
        formats.load_dataset(tmp_path)
    # and without extras the same file is never looked at
    assert formats.load_dataset(tmp_path, load_extras=False).depth is None


def test_llff_count_mismatch(tmp_path):
    row = np.concatenate([np.array([[0, 1, 0, 0, H], [-1, 0, 0, 0, W], [0, 0, 1, 3, 20.0]]).ravel(), [1, 5]])
    np.save(tmp_path / "poses_bounds.npy", np.stack([row, row]))
    io.write_png(tmp_path / "images" / "a.png", np.zeros((H, W, 3), np.float32))
    with pytest.raises(DataError, match=r"poses_bounds\.npy.*2 poses but 1 images"):
        formats.load_dataset(tmp_path)


def test_llff_degenerate_pose(tmp_path):
    row = np.concatenate([np.array([[0, 2, 0, 0, H], [-1, 0, 0, 0, W], [0, 0, 1, 3, 20.0]]).ravel(), [1, 5]])
    np.save(tmp_path / "poses_bounds.npy", row[None])
    io.write_png(tmp_path / "images" / "a.png", np.zeros((H, W, 3), np.float32))
    with pytest.raises(DataError, match=r"poses_bounds\.npy.*a\.png.*degenerate pose"):
        formats.load_dataset(tmp_path)


def test_unknown_layout_and_invalid_json(tmp_path):
    with pytest.raises(DataError, match="unknown dataset layout"):
        formats.load_dataset(tmp_path)
    (tmp_path / "transforms.json").write_text("{not json")
    with pytest.raises(DataError, match=r"transforms\.json.*invalid JSON"):
        formats.load_dataset(tmp_path)


def test_save_refuses_to_overwrite(tmp_path):
    _scene(tmp_path / "src")
    ds = formats.load_dataset(tmp_path / "src")
    out = formats.save_transforms_json(ds, tmp_path / "out")
    with pytest.raises(DataError, match=r"out.*overwrite=True"):
        formats.save_transforms_json(ds, tmp_path / "out")
    formats.save_transforms_json(ds, tmp_path / "out", overwrite=True)
    again = formats.load_dataset(out.parent)
    np.testing.assert_allclose(again.c2w, ds.c2w)
    np.testing.assert_allclose(again.intrinsics, ds.intrinsics)
    np.testing.assert_allclose(again.images, ds.images, atol=1 / 255)
    assert again.normalization == ds.normalization
