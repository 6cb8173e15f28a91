"""Uniform preprocessing: EXIF orientation, common size with consistent intrinsics, CLAHE,
intensity normalisation, no silent overwrites."""

import struct

import cv2
import numpy as np
import pytest
from skimage.color import rgb2lab

from jaxnerf_grid.data import formats, preprocess
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError
from tests.support.blobs import blob, centroid


def _jpeg_with_orientation(rgb, orientation):
    """JPEG bytes with a hand-written EXIF APP1 segment holding one Orientation tag."""
    ok, buf = cv2.imencode(".jpg", np.round(rgb[..., ::-1] * 255).astype(np.uint8),
                           [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    jpeg = buf.tobytes()
    # TIFF header (little endian, IFD at offset 8), one entry: tag 0x0112 SHORT count 1
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1)
    tiff += struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack("<I", 0)
    payload = b"Exif\x00\x00" + tiff
    app1 = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    assert jpeg[:2] == b"\xff\xd8"
    return jpeg[:2] + app1 + jpeg[2:]


def _quadrants(h, w):
    img = np.zeros((h, w, 3), np.float32)
    img[: h // 2, : w // 2] = [0.9, 0.1, 0.1]
    img[: h // 2, w // 2:] = [0.1, 0.9, 0.1]
    img[h // 2:, : w // 2] = [0.1, 0.1, 0.9]
    img[h // 2:, w // 2:] = [0.9, 0.9, 0.1]
    return img


def test_exif_orientation_honoured(tmp_path):
    raw = _quadrants(16, 32)
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "shot.jpg").write_bytes(_jpeg_with_orientation(raw, 6))
    loaded = io.read_image(tmp_path / "src" / "shot.jpg")
    expected = np.rot90(raw, k=-1)  # orientation 6: display = raw turned 90 degrees clockwise
    assert loaded.shape == (32, 16, 3)
    assert np.abs(loaded - expected).mean() < 0.05  # JPEG chroma subsampling at the edges
    assert np.abs(loaded - np.rot90(raw, k=1)).mean() > 0.2  # not the other way round
    ignored = io.read_image(tmp_path / "src" / "shot.jpg", honour_exif=False)
    assert ignored.shape == (16, 32, 3)  # the tag is what makes the difference
    out = preprocess.preprocess_images(tmp_path / "src", tmp_path / "out")
    written = io.read_image(out / "images" / "shot.png")
    assert written.shape == (32, 16, 3) and np.abs(written - expected).mean() < 0.05


def _project(x, c2w, fx, fy, cx, cy):
    rel = np.linalg.inv(c2w) @ np.append(x, 1.0)
    return fx * rel[0] / -rel[2] + cx, fy * -rel[1] / -rel[2] + cy


def _mixed_size_scene(root):
    """Two frames of one camera at full and half resolution, a blob at a known 3-D point."""
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, 3.0]
    x = np.array([0.3, -0.2, 0.0])
    full = (64, 48, 60.0, 60.0, 33.0, 22.0)
    half = (32, 24, 30.0, 30.0, 16.5, 11.0)
    frames = []
    for i, (w, h, fx, fy, cx, cy) in enumerate((full, half)):
        u, v = _project(x, c2w, fx, fy, cx, cy)
        io.write_png(root / f"im{i}.png", blob(u, v, w, h, sigma=w / 16), bits=16)
        io.write_png(root / f"mask{i}.png", (np.arange(w)[None].repeat(h, 0) < w // 2).astype(np.float32))
        frames.append({"file_path": f"im{i}.png", "transform_matrix": c2w.tolist(), "w": w, "h": h,
                       "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "mask_path": f"mask{i}.png",
                       "split": ["train", "test"][i]})
    io.write_json(root / "transforms.json", {
        "frames": frames, "near": 0.5, "far": 9.0,
        "scene_normalization": {"scale": 1.0, "translation": [0, 0, 0]}})
    return x, c2w


def test_dataset_with_mixed_sizes_resized_consistently(tmp_path):
    x, c2w = _mixed_size_scene(tmp_path / "src")
    with pytest.raises(DataError, match=r"im1\.png.*im0\.png"):
        formats.load_dataset(tmp_path / "src")
    out = preprocess.preprocess_images(tmp_path / "src", tmp_path / "out", size=(40, 30))
    ds = formats.load_dataset(out)
    assert ds.images.shape == (2, 30, 40, 3)
    np.testing.assert_allclose(ds.intrinsics[0], np.array([60, 60, 33, 22]) * 40 / 64, rtol=1e-6)
    np.testing.assert_allclose(ds.intrinsics[1], np.array([30, 30, 16.5, 11]) * 40 / 32, rtol=1e-6)
    for i in range(2):  # the blob still sits on the projection of x (non-integer scale 0.625, 1.25)
        u, v = _project(x, c2w, *ds.intrinsics[i])
        uc, vc = centroid(ds.images[i])
        assert np.hypot(uc - u, vc - v) < 0.1, (i, uc, vc, u, v)
    np.testing.assert_array_equal(ds.masks[:, :, :20], 1.0)  # extras resized with the images
    np.testing.assert_array_equal(ds.masks[:, :, 20:], 0.0)
    np.testing.assert_array_equal(ds.split["test"], [1])
    assert (ds.near, ds.far) == (0.5, 9.0)


def test_long_side_and_plain_folder(tmp_path):
    for name, (h, w) in (("a", (48, 64)), ("b", (24, 32))):
        io.write_png(tmp_path / "src" / f"{name}.png", np.full((h, w, 3), 0.4, np.float32))
    out = preprocess.preprocess_images(tmp_path / "src", tmp_path / "out", size=32)
    for name in "ab":
        assert io.read_image(out / "images" / f"{name}.png").shape == (24, 32, 3)
    rec = io.read_json(out / "preprocess.json")
    assert rec["output_size"] == [32, 24] and rec["images"][0]["scale"] == [0.5, 0.5]


def test_clahe_on_lightness_only():
    rng = np.random.default_rng(0)
    base = 0.45 + 0.1 * rng.uniform(size=(64, 64, 1)).astype(np.float32)  # low-contrast
    colour = np.concatenate([base * 1.1, base, base * 0.8], axis=-1)
    out = preprocess.clahe_lab(colour, clip_limit=3.0)
    lab_in, lab_out = rgb2lab(colour), rgb2lab(out)  # skimage: an independent LAB conversion
    assert lab_out[..., 0].std() > 2.0 * lab_in[..., 0].std()  # contrast of L went up
    # chroma direction kept: hue angle in the a-b plane barely moves
    hue_in = np.arctan2(lab_in[..., 2], lab_in[..., 1])
    hue_out = np.arctan2(lab_out[..., 2], lab_out[..., 1])
    assert np.abs(np.angle(np.exp(1j * (hue_out - hue_in)))).mean() < 0.1
    grey = np.repeat(base, 3, axis=-1)
    g = preprocess.clahe_lab(grey)
    assert np.abs(g - g[..., :1]).max() < 2e-3  # grey stays grey


def test_normalize_intensity():
    ramp = np.linspace(0.2, 0.6, 1000, dtype=np.float32).reshape(10, 100, 1).repeat(3, -1)
    out = preprocess.normalize_intensity(ramp)
    assert out.min() == 0.0 and out.max() == 1.0
    assert np.all(np.diff(out[..., 0].ravel()) >= 0)  # monotone
    mid = (0.4 - np.percentile(ramp, 1)) / (np.percentile(ramp, 99) - np.percentile(ramp, 1))
    assert out[..., 0].ravel()[np.argmin(np.abs(ramp[..., 0].ravel() - 0.4))] == pytest.approx(mid, abs=1e-3)


def test_no_overwrite_without_flag_and_dataset_input(tmp_path):
    x, c2w = _mixed_size_scene(tmp_path / "src")
    preprocess.preprocess_images(tmp_path / "src", tmp_path / "out", size=(32, 24))
    with pytest.raises(DataError, match=r"out.*overwrite=True"):
        preprocess.preprocess_images(tmp_path / "src", tmp_path / "out", size=(32, 24))
    assert preprocess.main([str(tmp_path / "src"), str(tmp_path / "out"), "--size", "16", "12",
                            "--clahe", "--overwrite"]) == 0
    ds = formats.load_dataset(tmp_path / "out")
    assert ds.images.shape == (2, 12, 16, 3)
    # an in-memory Dataset: resized, intrinsics scaled, extras carried
    out2 = preprocess.preprocess_images(ds, tmp_path / "out2", size=(8, 6))
    ds2 = formats.load_dataset(out2)
    np.testing.assert_allclose(ds2.intrinsics, ds.intrinsics * 0.5, rtol=1e-6)
    assert ds2.masks.shape == (2, 6, 8)
