"""capture/poses.py's cameras and metric frame, model choice and COLMAP options, block by block.

Each block is checked against a reference written here, never against its own output: COLMAP
cameras (a text model written by hand in COLMAP's documented format, read back by pycolmap)
projected by hand, the smallest rotation between two directions in scipy's axis-angle form,
crop windows and pixel contents worked out by hand, an SVD similarity fit written here for
`poses_agree`'s medians, and pycolmap's own option defaults. No COLMAP run, no training.
"""

from __future__ import annotations

import re
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxnerf_grid.capture import poses
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError

FOCAL = 60.0


# ----------------------------------------------------------------------------------------
# Known cameras


def _w2c_opencv(centre, target, up=(0.0, 0.0, 1.0)):
    """World-to-camera rotation (OpenCV axes: x right, y down, z forward) looking at target."""
    forward = (np.asarray(target) - centre) / np.linalg.norm(np.asarray(target) - centre)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward])


def _rings(target=(1.0, -2.0, 3.0)):
    """Level cameras on two rings about `target` (z up): (centres [N, 3], w2c rotations [N, 3, 3])."""
    target = np.asarray(target)
    centres = [target + [r * np.cos(a), r * np.sin(a), z] for a in np.radians(np.arange(0, 360, 40))
               for r, z in ((12.0, 4.0), (9.0, 7.0))]
    return np.array(centres), np.stack([_w2c_opencv(c, target) for c in centres])


def _pixels(points, rotation, translation, fx, fy, cx, cy):
    """Pixels [P, 2] of points [P, 3] in the COLMAP camera x_cam = R X + t (pinhole, by hand)."""
    cam = points @ np.asarray(rotation).T + translation
    return np.column_stack([fx * cam[:, 0] / cam[:, 2] + cx, fy * cam[:, 1] / cam[:, 2] + cy])


def _numbers(values) -> str:
    return " ".join(f"{float(v):.17g}" for v in values)


def _write_model(folder, cameras, images, points, written=None):
    """A COLMAP text model. cameras: {id: (w, h, fx, fy, cx, cy)} (PINHOLE); images: [(name,
    camera id, w2c R, t)]; points [P, 3], each observed in every image at its projection.
    written: {image index: (R, t)} poses written in place of those the points were projected with."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text("".join(f"{cid} PINHOLE {_numbers(c)}\n" for cid, c in cameras.items()))
    lines = []
    for k, (name, cid, rot, t) in enumerate(images):
        pose_r, pose_t = (written or {}).get(k, (rot, t))
        q = Rotation.from_matrix(pose_r).as_quat()           # x, y, z, w
        lines.append(f"{k + 1} {_numbers([q[3], *q[:3]])} {_numbers(pose_t)} {cid} {name}")
        xy = _pixels(points, rot, t, *cameras[cid][2:])
        lines.append(" ".join(f"{_numbers(p)} {i + 1}" for i, p in enumerate(xy)))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    tracks = [" ".join(f"{k + 1} {i}" for k in range(len(images))) for i in range(len(points))]
    (folder / "points3D.txt").write_text("".join(f"{i + 1} {_numbers(p)} 128 128 128 0.1 {tracks[i]}\n"
                                                 for i, p in enumerate(points)))


def _pycolmap():
    return pytest.importorskip("pycolmap")


# ----------------------------------------------------------------------------------------
# c2w_gl_from_cam_from_world, model_poses


def test_c2w_gl_puts_each_camera_where_it_stands_and_projects_as_colmap():
    """COLMAP's world-to-camera [R | t] (OpenCV axes) -> camera-to-world (OpenGL axes): the
    centre is the known one, and a point's pixel worked out in OpenGL axes (x right, y up,
    looking down -z) is the pixel worked out in COLMAP's camera."""
    rng = np.random.default_rng(0)
    centres, w2cs = _rings()
    points = np.array([1.0, -2.0, 3.0]) + rng.uniform(-2, 2, (20, 3))
    for centre, rot in zip(centres, w2cs):
        t = -rot @ centre
        for given in (np.column_stack([rot, t]), np.column_stack([rot, t]).tolist()):
            c2w = poses.c2w_gl_from_cam_from_world(given)
            assert c2w.shape == (4, 4) and c2w.dtype == np.float64
            np.testing.assert_array_equal(c2w[3], [0.0, 0.0, 0.0, 1.0])
            np.testing.assert_allclose(c2w[:3, 3], centre, atol=1e-9)
            cam = (points - c2w[:3, 3]) @ c2w[:3, :3]            # OpenGL camera coordinates
            xy = np.column_stack([40 + FOCAL * cam[:, 0] / -cam[:, 2], 30 - FOCAL * cam[:, 1] / -cam[:, 2]])
            np.testing.assert_allclose(xy, _pixels(points, rot, t, FOCAL, FOCAL, 40, 30), atol=1e-9)
            # a rigid map: the rotation part is a rotation, the camera looks at the target along -z
            np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-12)
            ahead = np.array([1.0, -2.0, 3.0]) - centre
            np.testing.assert_allclose(-c2w[:3, 2], ahead / np.linalg.norm(ahead), atol=1e-12)


def test_c2w_gl_works_in_float64_whatever_it_is_given():
    """A float32 world-to-camera far from the origin gives the camera worked out in float64
    from the same float32 numbers (float32 arithmetic would be off by about 1e-4 here)."""
    rot = _w2c_opencv(np.array([4000.0, -3000.0, 120.0]), np.array([4010.0, -2990.0, 100.0]))
    given = np.column_stack([rot, -rot @ [4000.0, -3000.0, 120.0]]).astype(np.float32)
    m = given.astype(np.float64)
    centre = -m[:, :3].T @ m[:, 3]                               # by hand, in float64
    c2w = poses.c2w_gl_from_cam_from_world(given)
    assert c2w.dtype == np.float64
    np.testing.assert_allclose(c2w[:3, 3], centre, rtol=0, atol=1e-9)
    np.testing.assert_allclose(c2w[:3, :3], m[:, :3].T * [1, -1, -1], rtol=0, atol=1e-12)
    in_float32 = -given[:, :3].T @ given[:, 3]
    assert np.abs(in_float32 - centre).max() > 1e-6              # the case tells the two apart


def test_c2w_gl_of_a_homogeneous_4x4_is_that_of_its_3x4():
    """A world-to-camera given homogeneous, [4, 4] with the row (0, 0, 0, 1), is read by its top
    three rows: the camera worked out by hand from R and t (centre -R^T t, axes R^T with y and z
    turned to OpenGL's)."""
    centres, w2cs = _rings()
    for centre, rot in zip(centres[:4], w2cs[:4]):
        t = -rot @ centre
        given = np.vstack([np.column_stack([rot, t]), [0.0, 0.0, 0.0, 1.0]])
        c2w = poses.c2w_gl_from_cam_from_world(given)
        assert c2w.shape == (4, 4)
        np.testing.assert_allclose(c2w[:3, 3], centre, atol=1e-9)
        np.testing.assert_allclose(c2w[:3, :3], rot.T * [1, -1, -1], atol=1e-12)
        np.testing.assert_array_equal(c2w[3], [0.0, 0.0, 0.0, 1.0])


def test_model_poses_of_a_hand_written_model_are_its_cameras(tmp_path):
    pycolmap = _pycolmap()
    centres, w2cs = _rings()
    images = [(f"v{k:02d}.png", 1, r, -r @ c) for k, (c, r) in enumerate(zip(centres, w2cs))]
    _write_model(tmp_path / "m", {1: (80, 60, FOCAL, FOCAL, 40, 30)}, images, np.array([[1.0, -2.0, 3.0]]))
    got = poses.model_poses(pycolmap.Reconstruction(tmp_path / "m"))
    assert sorted(got) == [name for name, *_ in images]
    for name, _, rot, t in images:
        np.testing.assert_allclose(got[name][:3, 3], -rot.T @ t, atol=1e-9)
        np.testing.assert_allclose(got[name][:3, :3], rot.T * [1, -1, -1], atol=1e-9)


# ----------------------------------------------------------------------------------------
# orient_z_up


def test_orient_z_up_turns_a_tilted_model_by_the_smallest_rotation_and_keeps_its_projections(tmp_path):
    """Level cameras in a world turned by a known rotation Q: the model is turned (in place, no
    scale, no shift) by the smallest rotation taking Q's +z to +z (scipy's axis-angle form),
    cameras, points and all, and every point keeps its pixel."""
    pycolmap = _pycolmap()
    q = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    centres, w2cs = _rings()
    centres, w2cs = centres @ q.T, w2cs @ q.T                  # the same cameras in the turned world
    points = (np.array([1.0, -2.0, 3.0]) + np.random.default_rng(1).uniform(-2, 2, (15, 3))) @ q.T
    cam = (80, 60, FOCAL, FOCAL, 40, 30)
    images = [(f"v{k:02d}.png", 1, r, -r @ c) for k, (c, r) in enumerate(zip(centres, w2cs))]
    _write_model(tmp_path / "m", {1: cam}, images, points)
    model = pycolmap.Reconstruction(tmp_path / "m")
    up = q[:, 2]
    axis = np.cross(up, [0.0, 0.0, 1.0])
    expected = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.arccos(up[2])).as_matrix()

    rot = poses.orient_z_up(pycolmap, model)
    np.testing.assert_allclose(rot, expected, atol=1e-9)
    np.testing.assert_allclose(rot @ up, [0.0, 0.0, 1.0], atol=1e-9)
    for pid, point in model.points3D.items():
        np.testing.assert_allclose(point.xyz, expected @ points[pid - 1], atol=1e-9)
    moved = np.stack([model.points3D[pid].xyz for pid in range(1, len(points) + 1)])
    by_name = {name: (r, t) for name, _, r, t in images}
    for image in model.images.values():
        r, t = by_name[image.name]
        m = image.cam_from_world().matrix()
        np.testing.assert_allclose(m[:, :3], r @ expected.T, atol=1e-9)      # cameras turned
        np.testing.assert_allclose(-m[:, :3].T @ m[:, 3], expected @ (-r.T @ t), atol=1e-9)   # centres turned
        np.testing.assert_allclose(_pixels(moved, m[:, :3], m[:, 3], *cam[2:]), _pixels(points, r, t, *cam[2:]),
                                   atol=1e-6)


# ----------------------------------------------------------------------------------------
# crop_to_common_size


def _pattern(h, w, k, channels=3):
    """A photo whose every pixel says where it is: [H, W, 3] uint8 (or [H, W] with channels=1)."""
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([3 * x + k, 4 * y + k, 2 * (x + y)], -1)            # smooth (JPEG), under 256 up to 70 x 53
    assert img.max() < 256
    img = img.astype(np.uint8)
    return img[..., 0] if channels == 1 else img


def _binary_model(tmp_path, cameras, names, points):
    """A PINHOLE model in COLMAP's binary format (as undistortion writes it) at tmp_path/sparse,
    one image per camera, every point observed in every image; returns (pycolmap, model_dir)."""
    pycolmap = _pycolmap()
    centres, w2cs = _rings()
    images = [(name, cid, w2cs[k], -w2cs[k] @ centres[k]) for k, (name, cid) in enumerate(zip(names, cameras))]
    _write_model(tmp_path / "text", cameras, images, points)
    (tmp_path / "sparse").mkdir()
    pycolmap.Reconstruction(tmp_path / "text").write(tmp_path / "sparse")
    return pycolmap, tmp_path / "sparse", images


def test_crop_to_common_size_cuts_each_photo_centred_and_moves_the_model_with_it(tmp_path):
    """Three cameras of 70 x 50, 64 x 48 and 67 x 53 pixels: every photo is cut to 64 x 48,
    centred, i.e. (left, top) = (3, 1), (0, 0), (1, 2) (worked out by hand); each camera's
    principal point and each observation move by the same, the pixels are the window's (a PNG
    exactly, a grey PNG stays grey, a JPEG within its compression), and every point still
    projects (by hand) onto its moved observation."""
    cameras = {1: (70, 50, FOCAL, FOCAL + 1, 35.5, 24.0), 2: (64, 48, FOCAL, FOCAL, 31.0, 23.5),
               3: (67, 53, FOCAL + 2, FOCAL, 33.0, 27.0)}
    names = ["a.png", "b.png", "c.jpg"]
    points = np.array([1.0, -2.0, 3.0]) + np.random.default_rng(2).uniform(-2, 2, (12, 3))
    pycolmap, model_dir, images = _binary_model(tmp_path, cameras, names, points)
    (tmp_path / "images").mkdir()
    photos = {"a.png": _pattern(50, 70, 1), "b.png": _pattern(48, 64, 2, channels=1), "c.jpg": _pattern(53, 67, 3)}
    for name, img in photos.items():
        assert io.opencv().imwrite(str(tmp_path / "images" / name), img)
    original_jpeg = io.opencv().imread(str(tmp_path / "images" / "c.jpg"))

    assert poses.crop_to_common_size(pycolmap, model_dir, tmp_path / "images") == (64, 48)

    offsets = {1: (3, 1), 2: (0, 0), 3: (1, 2)}
    model = pycolmap.Reconstruction(model_dir)
    for cid, (_, _, fx, fy, cx, cy) in cameras.items():
        cam = model.cameras[cid]
        left, top = offsets[cid]
        assert (cam.width, cam.height) == (64, 48)
        np.testing.assert_allclose(cam.params, [fx, fy, cx - left, cy - top], atol=1e-12)
    for image in model.images.values():
        (name, cid, rot, t), = [i for i in images if i[0] == image.name]
        left, top = offsets[cid]
        seen = np.stack([p.xy for p in image.points2D])
        np.testing.assert_allclose(seen, _pixels(points, rot, t, *cameras[cid][2:]) - [left, top], atol=1e-9)
        np.testing.assert_allclose(seen, _pixels(points, rot, t, *model.cameras[cid].params), atol=1e-9)
    cv2 = io.opencv()
    a = cv2.imread(str(tmp_path / "images" / "a.png"), cv2.IMREAD_UNCHANGED)
    b = cv2.imread(str(tmp_path / "images" / "b.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(a, photos["a.png"][1:49, 3:67])
    np.testing.assert_array_equal(b, photos["b.png"])                  # grey, and not cut
    c = cv2.imread(str(tmp_path / "images" / "c.jpg"))
    assert c.shape == (48, 64, 3)
    # the JPEG's mean colour is its window's (0.02 off, measured); a window one pixel off differs by 1.8-4
    for top, left, agree in ((2, 1, True), (2, 2, False), (2, 0, False), (3, 1, False), (1, 1, False)):
        off = np.abs(c.mean((0, 1)) - original_jpeg[top:top + 48, left:left + 64].mean((0, 1))).max()
        assert off < 0.5 if agree else off > 1.5, (top, left, off)


def test_crop_to_common_size_moves_only_the_principal_point_of_a_camera_with_more_parameters(tmp_path):
    """An OPENCV camera (fx, fy, cx, cy, k1, k2, p1, p2) beside a PINHOLE one: the crop moves its
    principal point by the window's (left, top) = (3, 1), worked out by hand for 70 x 50 -> 64 x
    48, and leaves the focal lengths and the four distortion parameters as they were."""
    pycolmap = _pycolmap()
    cameras = {1: (70, 50, FOCAL, FOCAL + 1, 35.5, 24.0), 2: (64, 48, FOCAL, FOCAL, 31.0, 23.5)}
    centres, w2cs = _rings()
    images = [(name, cid, w2cs[k], -w2cs[k] @ centres[k]) for k, (name, cid) in enumerate([("a.png", 1), ("b.png", 2)])]
    _write_model(tmp_path / "text", cameras, images, np.array([[1.0, -2.0, 3.0]]))
    distortion = [0.01, -0.002, 0.0003, -0.0004]
    (tmp_path / "text" / "cameras.txt").write_text(
        f"1 OPENCV {_numbers([70, 50, FOCAL, FOCAL + 1, 35.5, 24.0, *distortion])}\n"
        f"2 PINHOLE {_numbers(cameras[2])}\n")
    (tmp_path / "sparse").mkdir()
    pycolmap.Reconstruction(tmp_path / "text").write(tmp_path / "sparse")
    (tmp_path / "images").mkdir()
    for name, (h, w) in (("a.png", (50, 70)), ("b.png", (48, 64))):
        assert io.opencv().imwrite(str(tmp_path / "images" / name), _pattern(h, w, 1))
    assert poses.crop_to_common_size(pycolmap, tmp_path / "sparse", tmp_path / "images") == (64, 48)
    model = pycolmap.Reconstruction(tmp_path / "sparse")
    assert model.cameras[1].model.name == "OPENCV" and (model.cameras[1].width, model.cameras[1].height) == (64, 48)
    np.testing.assert_allclose(model.cameras[1].params, [FOCAL, FOCAL + 1, 32.5, 23.0, *distortion], atol=1e-12)
    np.testing.assert_allclose(model.cameras[2].params, [FOCAL, FOCAL, 31.0, 23.5], atol=1e-12)


def test_crop_to_common_size_writes_jpegs_at_its_quality(tmp_path, monkeypatch):
    """A cut JPEG (.jpg or .JPEG) is the window of the decoded photo encoded by OpenCV at
    JPEG_QUALITY, byte for byte (set to 60 here, away from OpenCV's default of 95)."""
    monkeypatch.setattr(poses, "JPEG_QUALITY", 60)
    cameras = {1: (66, 50, FOCAL, FOCAL, 33, 25), 2: (68, 52, FOCAL, FOCAL, 34, 26), 3: (64, 48, FOCAL, FOCAL, 32, 24)}
    names = ["c.jpg", "d.JPEG", "e.png"]
    pycolmap, model_dir, _ = _binary_model(tmp_path, cameras, names, np.array([[1.0, -2.0, 3.0]]))
    (tmp_path / "images").mkdir()
    cv2, expected = io.opencv(), {}
    for k, (name, (w, h, *_)) in enumerate(zip(names, cameras.values())):
        assert cv2.imwrite(str(tmp_path / "images" / name), _pattern(h, w, k))
        decoded = cv2.imdecode(np.fromfile(str(tmp_path / "images" / name), np.uint8), cv2.IMREAD_UNCHANGED)
        left, top = (w - 64) // 2, (h - 48) // 2              # (1, 1), (2, 2), (0, 0)
        if name != "e.png":
            expected[name] = cv2.imencode(".jpg", decoded[top:top + 48, left:left + 64],
                                          [cv2.IMWRITE_JPEG_QUALITY, 60])[1].tobytes()
            at_95 = cv2.imencode(".jpg", decoded[top:top + 48, left:left + 64])[1].tobytes()
            assert at_95 != expected[name]
    assert poses.crop_to_common_size(pycolmap, model_dir, tmp_path / "images") == (64, 48)
    for name, payload in expected.items():
        assert (tmp_path / "images" / name).read_bytes() == payload, name


def test_crop_to_common_size_leaves_photos_of_one_size_alone(tmp_path):
    cameras = {1: (64, 48, FOCAL, FOCAL, 32, 24), 2: (64, 48, FOCAL, FOCAL, 31, 25)}
    pycolmap, model_dir, _ = _binary_model(tmp_path, cameras, ["a.jpg", "b.jpg"], np.array([[1.0, -2.0, 3.0]]))
    (tmp_path / "images").mkdir()
    raw = {}
    for k, name in enumerate(["a.jpg", "b.jpg"]):
        io.opencv().imwrite(str(tmp_path / "images" / name), _pattern(48, 64, k))
        raw[name] = (tmp_path / "images" / name).read_bytes()
    model_bytes = {p.name: p.read_bytes() for p in model_dir.iterdir()}
    assert poses.crop_to_common_size(pycolmap, model_dir, tmp_path / "images") == (64, 48)
    assert {name: (tmp_path / "images" / name).read_bytes() for name in raw} == raw   # not encoded again
    assert {p.name: p.read_bytes() for p in model_dir.iterdir()} == model_bytes


def test_crop_to_common_size_names_a_photo_it_cannot_read_or_write(tmp_path, monkeypatch):
    cameras = {1: (66, 48, FOCAL, FOCAL, 33, 24), 2: (64, 48, FOCAL, FOCAL, 32, 24)}
    pycolmap, model_dir, _ = _binary_model(tmp_path, cameras, ["a.png", "b.png"], np.array([[1.0, -2.0, 3.0]]))
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "a.png").write_bytes(b"not a photo")
    io.opencv().imwrite(str(tmp_path / "images" / "b.png"), _pattern(48, 64, 0))
    with pytest.raises(DataError, match=r"a\.png: not a readable undistorted photo"):
        poses.crop_to_common_size(pycolmap, model_dir, tmp_path / "images")
    io.opencv().imwrite(str(tmp_path / "images" / "a.png"), _pattern(48, 66, 0))
    monkeypatch.setattr(io.opencv(), "imencode", lambda *args: (False, None))
    with pytest.raises(DataError, match=r"images/[ab]\.png: could not encode the cropped photo$"):
        poses.crop_to_common_size(pycolmap, model_dir, tmp_path / "images")


# ----------------------------------------------------------------------------------------
# scene_georeference


def test_scene_georeference_maps_normalised_points_to_the_crs_by_the_documented_rule():
    """In metres: 1 / scale metres per scene unit, and scene_to_crs takes a normalised point
    x_norm = scale (x + translation) (the orbit normalisation of a local point x, in metres)
    to x + origin; the record's own keys are kept, the given record is left as it was."""
    record = {"units": "metres", "crs": "EPSG:32633", "origin": [500000.0, 4649776.0, 120.0], "method": "gps"}
    given = dict(record)
    norm = {"scale": 0.04, "translation": [-3.0, 4.5, -10.0]}
    out = poses.scene_georeference(record, norm)
    assert record == given and {k: out[k] for k in record} == record
    assert out["metres_per_scene_unit"] == pytest.approx(25.0, rel=1e-12)
    matrix = np.asarray(out["scene_to_crs"])
    assert matrix.shape == (4, 4)
    np.testing.assert_array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0])
    local = np.random.default_rng(3).uniform(-30, 30, (10, 3))
    x_norm = 0.04 * (local + [-3.0, 4.5, -10.0])
    crs = np.column_stack([x_norm, np.ones(10)]) @ matrix.T
    np.testing.assert_allclose(crs[:, :3], local + record["origin"], atol=1e-6)


@pytest.mark.parametrize("record", [{"units": "unknown"}, {"units": "scale bar", "method": "scale_bar"}, {}])
def test_scene_georeference_outside_metres_is_the_record_alone(record):
    given = dict(record)
    out = poses.scene_georeference(record, {"scale": 0.04, "translation": [-3.0, 4.5, -10.0]})
    assert out == given and out is not record and record == given


def test_georef_report_lines_of_a_full_record_and_of_none_written_out():
    """poses_report.md's georeference section, line by line as written here, for a record with
    GPS, control and check points and a scale bar (a bent model: the GPS RMS above 6 m), for one
    without a CRS name, GPS or suspicion, and for unknown units."""
    full = {"units": "metres", "source": "gcp+gps", "crs": "EPSG:32633", "crs_name": "WGS 84 / UTM zone 33N",
            "origin": [500000.04, 4649776.96, 0.0], "metres_per_scene_unit": 23.456789, "height_from": "gcp",
            "gps": {"photos": 14, "registered": 16, "inliers": 13, "rms_m": 6.5, "rms_horizontal_m": 2.25},
            "gcp": {"control": {"rms_m": 0.012, "residuals": [{"name": "A", "error": 0.0104, "dz": -0.0021},
                                                              {"name": "B", "error": 0.01349, "dz": 0.0069}]},
                    "check": {"rms_m": 0.03, "residuals": [{"name": "C", "error": 0.03, "dz": 0.0}]}},
            "scale_bar": {"metres": 10.0, "model_length": 0.123456}}
    assert poses.georef_report_lines(full) == [
        "## Scale and georeference (docs/GEOREFERENCE.md)", "",
        "- source: gcp+gps; units: metres; CRS: EPSG:32633 (WGS 84 / UTM zone 33N)",
        "- metres per normalised scene unit: 23.46; local origin in the CRS: 500000.0, 4649777.0, 0.0",
        "- GPS: 14 of 16 registered photos, 13 inliers; residual RMS 6.5 m (horizontal 2.25 m); heights from gcp",
        "- control points: RMS 0.012 m; A 0.010 m (dz -0.002), B 0.013 m (dz +0.007)",
        "- check points: RMS 0.03 m; C 0.030 m (dz +0.000)",
        "- scale bar: 10.0 m over 0.1235 model units",
        "- **check the reconstruction**: the residuals exceed what GPS (about 3 m) or ground control points "
        "(centimetres) explain; a photo registered in the wrong place bends the model (docs/GEOREFERENCE.md)",
        ""]
    plain = {"units": "metres", "source": "scale_bar", "crs": None, "origin": [0.0, 0.0, 0.0],
             "metres_per_scene_unit": 0.5, "gcp": {"control": None}}
    assert poses.georef_report_lines(plain) == [
        "## Scale and georeference (docs/GEOREFERENCE.md)", "",
        "- source: scale_bar; units: metres; CRS: none (scale only)",
        "- metres per normalised scene unit: 0.5; local origin in the CRS: 0.0, 0.0, 0.0", ""]
    unknown = ["## Scale and georeference (docs/GEOREFERENCE.md)", "",
               "Units unknown: no GPS read from the photos, no ground control points, no scale bar; the model is "
               "in arbitrary units.", ""]
    assert poses.georef_report_lines({"units": "unknown"}) == unknown
    assert poses.georef_report_lines({}) == unknown


# ----------------------------------------------------------------------------------------
# Model choice: choose_model, poses_agree


def _c2w(centre, target):
    """Camera-to-world [4, 4] in OpenGL axes (x right, y up, z backward) looking at target, z up."""
    back = (centre - target) / np.linalg.norm(centre - target)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    out = np.eye(4)
    out[:3, :3] = np.column_stack([right, np.cross(back, right), back])
    out[:3, 3] = centre
    return out


def _similarity(src, dst):
    """(s, R, t) minimising |s R src + t - dst|^2 (Umeyama's SVD solution, written here). [N, 3] each."""
    ms, md = src.mean(0), dst.mean(0)
    xs, xd = src - ms, dst - md
    u, sig, vt = np.linalg.svd(xd.T @ xs)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = float((sig * np.diag(d)).sum() / (xs ** 2).sum())
    return scale, rot, md - scale * rot @ ms


def _noisy_copy(a, seed, centre_noise, degrees):
    """a's cameras moved by a similarity, each centre shifted and each camera turned a little."""
    rng = np.random.default_rng(seed)
    turn, scale, shift = Rotation.from_rotvec([0.4, 0.1, -0.7]).as_matrix(), 2.5, np.array([3.0, -1.0, 0.5])
    b = {}
    for name, m in a.items():
        out = np.eye(4)
        wobble = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.radians(degrees)).as_matrix()
        out[:3, :3] = turn @ wobble @ m[:3, :3]
        out[:3, 3] = scale * turn @ (m[:3, 3] + rng.normal(size=3) * centre_noise) + shift
        b[name] = out
    return b


def _medians(a, b):
    """poses_agree's two medians, worked out here: (rotation difference in degrees, centre
    distance / the spread of a's centres) after fitting b's centres to a's."""
    names = sorted(set(a) & set(b))
    pa, pb = np.stack([a[k] for k in names]), np.stack([b[k] for k in names])
    s, rot, t = _similarity(pb[:, :3, 3], pa[:, :3, 3])
    centre = [np.linalg.norm(s * rot @ cb + t - ca) for cb, ca in zip(pb[:, :3, 3], pa[:, :3, 3])]
    spread = np.median([np.linalg.norm(c - pa[:, :3, 3].mean(0)) for c in pa[:, :3, 3]])
    angle = [np.degrees(Rotation.from_matrix(ra.T @ rot @ rb).magnitude())
             for ra, rb in zip(pa[:, :3, :3], pb[:, :3, :3])]
    return float(np.median(angle)), float(np.median(centre) / spread)


def _small_orbit(count=10):
    """Cameras on a ring 0.6 units across (the spread of their centres is under 1)."""
    angles = np.radians(np.arange(count) * 360.0 / count + 10.0)
    return {f"p{k}": _c2w(np.array([0.3 * np.cos(a), 0.3 * np.sin(a), 0.1 + 0.02 * k]), np.zeros(3))
            for k, a in enumerate(angles)}


def test_poses_agree_thresholds_are_the_median_angle_and_the_median_centre_distance_over_the_spread():
    """Against the medians worked out here: b agrees with a exactly when both lie within the
    thresholds (a threshold 0.1 % above a median passes, 0.1 % below fails)."""
    a = _small_orbit()
    b = _noisy_copy(a, seed=5, centre_noise=0.004, degrees=1.5)
    angle, ratio = _medians(a, b)
    spread = np.median([np.linalg.norm(m[:3, 3] - np.mean([n[:3, 3] for n in a.values()], 0)) for m in a.values()])
    assert 0.2 < angle < 2.0 and 0.002 < ratio < 0.05 and spread < 0.5          # the case is what it should be
    assert poses.poses_agree(a, b, max_deg=angle * 1.001, max_centre=ratio * 1.001)
    assert not poses.poses_agree(a, b, max_deg=angle * 0.999, max_centre=ratio * 1.001)
    assert not poses.poses_agree(a, b, max_deg=angle * 1.001, max_centre=ratio * 0.999)
    assert poses.poses_agree(a, b) == (angle <= 2.0 and ratio <= 0.05)


def _tetrahedron(rotation):
    """Four cameras at alternate corners of a cube, all with one rotation: their centres' fit is
    exact in floating point (the identity, scale 1)."""
    out = {}
    for k, c in enumerate([(1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)]):
        out[f"p{k}"] = np.eye(4)
        out[f"p{k}"][:3, :3], out[f"p{k}"][:3, 3] = rotation, c
    return out


def test_poses_agree_at_its_bounds():
    """Identical poses agree with both thresholds 0 (the bounds are inclusive); three common
    photos are enough, two are not; a half turn of every camera agrees only with max_deg=180,
    also where rounding puts its cosine a hair below -1."""
    a = _tetrahedron(np.eye(3))
    assert poses.poses_agree(a, dict(a), max_deg=0.0, max_centre=0.0)
    three = {k: a[k] for k in ("p0", "p1", "p2")}
    assert poses.poses_agree(three, _noisy_copy(three, seed=0, centre_noise=0.0, degrees=0.0))
    assert not poses.poses_agree({k: a[k] for k in ("p0", "p1")}, a)
    # a half turn about an axis k: R = 2 k k^T - I, whose trace rounds below -1 for this k
    k = np.array([0.1, 0.1, 0.5])
    k /= np.linalg.norm(k)
    half = 2.0 * np.outer(k, k) - np.eye(3)
    assert (np.einsum("ij,ij->", half, np.eye(3)) - 1.0) / 2.0 < -1.0
    turned = _tetrahedron(half)
    assert poses.poses_agree(a, turned, max_deg=180.0)
    assert not poses.poses_agree(a, turned, max_deg=179.9)


class _Image:
    def __init__(self, name, c2w_gl):
        self.name, self.c2w = name, c2w_gl

    def cam_from_world(self):
        return self

    def matrix(self):
        """World-to-camera [3, 4] in OpenCV axes, from the OpenGL camera-to-world (by hand)."""
        rot = self.c2w[:3, :3] * [1, -1, -1]                  # OpenCV camera axes in the world
        return np.column_stack([rot.T, -rot.T @ self.c2w[:3, 3]])


class _Model:
    """What choose_model reads of a pycolmap.Reconstruction: registered photos and their poses."""

    def __init__(self, c2ws: dict):
        self.images = {i + 1: _Image(name, m) for i, (name, m) in enumerate(sorted(c2ws.items()))}

    def num_reg_images(self):
        return len(self.images)

    def reg_image_ids(self):
        return list(self.images)


def test_choose_model_keeps_the_relaxed_model_only_when_it_has_more_photos_and_agrees(capsys):
    """Judged by a default of at least MIN_COMPARED photos, the relaxed model is kept when it
    counts more photos and agrees (the same cameras moved by a similarity), not when its
    cameras are turned; each choice is said on stderr when asked."""
    cams = _small_orbit(12)
    default = _Model({k: cams[k] for k in list(cams)[:9]})
    agreeing = _Model(_noisy_copy(cams, seed=1, centre_noise=0.0, degrees=0.0))
    turned = _noisy_copy(cams, seed=1, centre_noise=0.0, degrees=0.0)
    turned = {k: m @ np.diag([-1.0, -1.0, 1.0, 1.0]) for k, m in turned.items()}   # every camera turned 180 degrees
    disagreeing = _Model(turned)
    assert poses.choose_model(default, agreeing) is agreeing
    assert poses.choose_model(default, disagreeing) is default
    assert capsys.readouterr().err == ""                             # quiet unless asked
    assert poses.choose_model(default, agreeing, show=True) is agreeing
    assert capsys.readouterr().err == "poses: kept the relaxed model (12 photos)\n"
    assert poses.choose_model(default, disagreeing, show=True) is default
    assert capsys.readouterr().err == ("poses: the relaxed model (12 photos) disagrees with the default one; "
                                       "kept the default (9 photos)\n")
    # a relaxed model counting no more photos than the default is not taken, agreeing or not
    assert poses.choose_model(default, agreeing, count=lambda m: 5) is default
    assert poses.choose_model(default, None) is default and poses.choose_model(None, agreeing) is agreeing
    # a default of MIN_COMPARED photos judges the relaxed model; one photo fewer is too small to
    small = _Model({k: cams[k] for k in list(cams)[:poses.MIN_COMPARED]})
    assert poses.MIN_COMPARED == 8 and poses.choose_model(small, disagreeing) is small
    smaller = _Model({k: cams[k] for k in list(cams)[:poses.MIN_COMPARED - 1]})
    assert poses.choose_model(smaller, disagreeing) is disagreeing


def test_vetted_count_counts_the_photos_that_pass_the_vetting(tmp_path):
    """18 cameras that saw 40 points where they project: all 18 pass; the same model with one
    camera's written pose turned by 20 degrees about its own y axis (its observations kept): 17."""
    pycolmap = _pycolmap()
    centres, w2cs = _rings()
    points = np.array([1.0, -2.0, 3.0]) + np.random.default_rng(6).uniform(-2, 2, (40, 3))
    images = [(f"v{k:02d}.png", 1, r, -r @ c) for k, (c, r) in enumerate(zip(centres, w2cs))]
    cam = {1: (80, 60, FOCAL, FOCAL, 40, 30)}
    _write_model(tmp_path / "good", cam, images, points)
    assert poses.vetted_count(pycolmap.Reconstruction(tmp_path / "good")) == 18
    turn = Rotation.from_rotvec([0.0, np.radians(20.0), 0.0]).as_matrix() @ w2cs[5]
    _write_model(tmp_path / "turned", cam, images, points, written={5: (turn, -turn @ centres[5])})
    model = pycolmap.Reconstruction(tmp_path / "turned")
    assert model.num_reg_images() == 18 and poses.vetted_count(model) == 17


# ----------------------------------------------------------------------------------------
# The COLMAP options: check_options, mapper_options


def test_mapper_options_set_the_seed_the_reprojection_filter_and_the_relaxed_thresholds():
    """COLMAP's defaults (pycolmap's own) but a fixed seed and a 2 px filter; relaxed: 15 inliers
    to register a photo, 50 to start a model, an 8-degree starting angle."""
    pycolmap = _pycolmap()
    defaults = pycolmap.IncrementalPipelineOptions()
    relaxed = {"abs_pose_min_num_inliers": 15, "init_min_num_inliers": 50, "init_min_tri_angle": 8.0}
    assert defaults.random_seed != 0 and defaults.mapper.filter_max_reproj_error != 2.0
    assert all(getattr(defaults.mapper, key) != value for key, value in relaxed.items())
    for is_relaxed in (False, True):
        options = poses.mapper_options(pycolmap, is_relaxed)
        assert options.random_seed == 0 and options.mapper.filter_max_reproj_error == 2.0
        for key, value in relaxed.items():
            assert getattr(options.mapper, key) == (value if is_relaxed else getattr(defaults.mapper, key)), key
        assert options.mapper.abs_pose_max_error == defaults.mapper.abs_pose_max_error


def test_check_options_refuses_each_bad_option_and_names_the_choices(tmp_path):
    tree = tmp_path / "tree.bin"
    tree.write_bytes(b"\0")
    for matcher in ("auto", "exhaustive", "sequential"):
        for overlap in (1, 10):
            poses.check_options(matcher, "OPENCV", None, overlap)
    poses.check_options("vocab", "SIMPLE_PINHOLE", tree, 1)
    with pytest.raises(DataError) as err:
        poses.check_options("nearest", "OPENCV", None)
    assert str(err.value) == ("unknown poses.matcher 'nearest'; choose one of auto, exhaustive, spatial, sequential, "
                              "vocab")
    for overlap in (0, -3, True, 2.0, "5"):
        with pytest.raises(DataError, match=r"^poses\.overlap must be a whole number of photos, at least 1, got "):
            poses.check_options("sequential", "OPENCV", None, overlap)
        with pytest.raises(DataError, match=r"^poses\.neighbours must be a whole number of photos, at least 1, got "):
            poses.check_options("spatial", "OPENCV", None, 10, overlap)
    poses.check_options("spatial", "OPENCV", None, 10, 1)
    with pytest.raises(DataError) as err:
        poses.check_options("exhaustive", "FISHEYE", None)
    assert str(err.value) == ("unknown camera model 'FISHEYE'; choose one of SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, "
                              "RADIAL, OPENCV")
    with pytest.raises(DataError) as err:
        poses.check_options("vocab", "OPENCV", None)
    assert str(err.value) == ("poses.matcher vocab needs a vocabulary tree file (poses.vocab_tree, e.g. COLMAP's "
                              "vocab_tree_flickr100K_words32K.bin); none is downloaded: use exhaustive or sequential")
    with pytest.raises(DataError) as err:
        poses.check_options("vocab", "OPENCV", tmp_path / "missing.bin")
    assert str(err.value) == f"{tmp_path / 'missing.bin'}: vocabulary tree file not found"


# ----------------------------------------------------------------------------------------
# Stage 1 and the helpers: list_photos, working_size, check_one_size, leave_out, _link_or_copy,
# import_pycolmap


def test_list_photos_takes_png_and_jpeg_files_by_name_and_refuses_too_few(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("c.jpeg", "a.PNG", "b.jpg", "notes.txt", "d.tif"):
        (folder / name).write_bytes(b"x")
    (folder / "e.png").mkdir()                                        # a folder, not a photo
    assert poses.list_photos(folder) == [folder / "a.PNG", folder / "b.jpg", folder / "c.jpeg"]
    (folder / "c.jpeg").unlink()
    with pytest.raises(DataError) as err:
        poses.list_photos(folder)
    assert str(err.value) == f"{folder}: 2 photo(s); camera poses need at least 3"
    for name in ("a.PNG", "b.jpg"):
        (folder / name).unlink()
    with pytest.raises(DataError) as err:
        poses.list_photos(str(folder))
    assert str(err.value) == f"{folder}: no photos (PNG or JPEG) in this folder"
    with pytest.raises(DataError) as err:
        poses.list_photos(tmp_path / "missing")
    assert str(err.value) == f"{tmp_path / 'missing'}: photo folder not found"


def test_working_size_keeps_a_side_of_at_least_one_pixel():
    assert poses.working_size(4000, 3, 100) == (100, 1) and poses.working_size(3, 4000, 100) == (1, 100)
    assert poses.working_size(800, 600, 800) == (800, 600) and poses.working_size(801, 600, 800) == (800, 599)


def test_check_one_size_names_the_sizes_most_common_first(tmp_path):
    sizes = {"a.png": (32, 24), "b.png": [64, 48], "c.png": (64, 48)}
    poses.check_one_size(sizes, tmp_path, single_camera=False)               # each photo its own camera
    poses.check_one_size({"b.png": (64, 48), "c.png": [64, 48]}, tmp_path, single_camera=True)
    with pytest.raises(DataError) as err:
        poses.check_one_size(sizes, tmp_path, single_camera=True)
    assert str(err.value) == (f"{tmp_path}: poses.single_camera needs photos of one size, these have 2 (64x48: 2 "
                              "(e.g. b.png); 32x24: 1 (e.g. a.png)); leave poses.single_camera off (each photo gets "
                              "its own camera) or split the folder")


def test_leave_out_deregisters_the_named_photos_and_their_observations(tmp_path):
    pycolmap = _pycolmap()
    centres, w2cs = _rings()
    images = [(f"v{k:02d}.png", 1, r, -r @ c) for k, (c, r) in enumerate(zip(centres[:4], w2cs[:4]))]
    _write_model(tmp_path / "m", {1: (80, 60, FOCAL, FOCAL, 40, 30)}, images, np.array([[1.0, -2.0, 3.0]]))
    model = pycolmap.Reconstruction(tmp_path / "m")
    poses.leave_out(model, ["v01.png", "v03.png", "elsewhere.png"])
    assert sorted(model.images[i].name for i in model.reg_image_ids()) == ["v00.png", "v02.png"]
    assert model.points3D[1].track.length() == 2                          # seen by the 4, kept by 2


def test_link_or_copy_links_and_copies_when_it_cannot(tmp_path, monkeypatch):
    src = tmp_path / "src.jpg"
    src.write_bytes(b"photo bytes")
    poses._link_or_copy(src, tmp_path / "linked.jpg")
    assert (tmp_path / "linked.jpg").read_bytes() == b"photo bytes"
    assert (tmp_path / "linked.jpg").stat().st_ino == src.stat().st_ino

    def refuse(*args):
        raise OSError("cross-device link")

    monkeypatch.setattr(poses.os, "link", refuse)
    poses._link_or_copy(src, tmp_path / "copied.jpg")
    assert (tmp_path / "copied.jpg").read_bytes() == b"photo bytes"
    assert (tmp_path / "copied.jpg").stat().st_ino != src.stat().st_ino


def test_import_pycolmap_without_it_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)                    # import pycolmap raises ImportError
    with pytest.raises(DataError) as err:
        poses.import_pycolmap()
    assert str(err.value) == ("pycolmap is not installed (jaxnerf-grid poses needs it): pip install -e '.[sfm]' "
                              "(or: bash scripts/setup.sh)")


def test_prepare_photos_links_or_scales_each_readable_photo_and_names_the_unreadable(tmp_path, capsys):
    """Photos used as they are are linked into the work folder (the same file), scaled ones are
    written there at the working size; an unreadable one is skipped with its reason, and said
    on stderr even when quiet; fewer than 3 readable photos are refused, naming the unreadable."""
    cv2 = io.opencv()
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("a.png", "b.jpg", "d.png"):
        assert cv2.imwrite(str(folder / name), _pattern(50, 70, 1))
    (folder / "c.png").write_bytes(b"not a photo")
    photos = sorted(folder.iterdir())
    work, names, skipped, sizes = poses.prepare_photos(photos, tmp_path / "work" / "photos", None, show=False)
    assert work == tmp_path / "work" / "photos" and names == ["a.png", "b.jpg", "d.png"]
    assert skipped == {"c.png": f"{folder / 'c.png'}: not a readable photo (corrupt or unsupported format)"}
    assert sizes == {"a.png": (70, 50), "b.jpg": (70, 50), "d.png": (70, 50)}
    for name in names:
        assert (work / name).stat().st_ino == (folder / name).stat().st_ino                 # linked
    assert capsys.readouterr().err == f"poses: skipping {folder / 'c.png'}: not a readable image\n"
    work, names, skipped, sizes = poses.prepare_photos(photos, tmp_path / "small", 40, show=True)
    assert names == ["a.png", "b.jpg", "d.png"] and set(sizes.values()) == {(40, 29)}
    for name in names:
        assert cv2.imread(str(work / name)).shape == (29, 40, 3)
        assert (work / name).stat().st_ino != (folder / name).stat().st_ino
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f"poses: skipping {folder / 'c.png'}: not a readable image"
    assert re.fullmatch(r"poses: photos: 4/4 photos \(100%\), \d+\.\d s", err[1]) and len(err) == 2
    (folder / "e.png").write_bytes(b"")
    with pytest.raises(DataError) as err:
        poses.prepare_photos([folder / "a.png", folder / "c.png", folder / "e.png"], tmp_path / "w3", None,
                             show=False)
    assert str(err.value) == (f"{folder}: only 1 readable photo(s) of 3 (unreadable: c.png, e.png); camera poses "
                              "need at least 3")
    with pytest.raises(DataError, match=r"only 2 readable photo\(s\) of 2 \(unreadable: none\); camera poses need"):
        poses.prepare_photos([folder / "a.png", folder / "d.png"], tmp_path / "w4", None, show=False)


def test_prepare_photos_into_an_existing_work_folder_and_a_refusal_names_the_first_photos_folder(tmp_path):
    """The work folder may exist already (empty): the photos are linked into it. Too few
    readable photos from two folders are refused naming the first photo's folder."""
    cv2 = io.opencv()
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir()
    second.mkdir()
    for name in ("a.png", "b.png", "c.png"):
        assert cv2.imwrite(str(first / name), _pattern(50, 70, 1))
    (tmp_path / "work").mkdir()
    photos = sorted(first.iterdir())
    work, names, skipped, sizes = poses.prepare_photos(photos, tmp_path / "work", None, show=False)
    assert (work, names, skipped) == (tmp_path / "work", ["a.png", "b.png", "c.png"], {})
    assert sorted(p.name for p in work.iterdir()) == names
    (second / "d.png").write_bytes(b"not a photo")
    with pytest.raises(DataError) as err:
        poses.prepare_photos([first / "a.png", second / "d.png"], tmp_path / "w2", None, show=False)
    assert str(err.value) == (f"{first}: only 1 readable photo(s) of 2 (unreadable: d.png); camera poses "
                              "need at least 3")


def test_prepare_photo_writes_scaled_jpegs_at_its_quality_and_names_a_copy_it_cannot_write(tmp_path, monkeypatch,
                                                                                           capsys):
    """A scaled JPEG copy (.jpg or .JPEG) is OpenCV's encoding of the area-scaled photo at
    JPEG_QUALITY, byte for byte (60 here, away from OpenCV's default of 95); an encoder failure
    is a DataError naming the photo. And prepare_photos shows its progress by default."""
    monkeypatch.setattr(poses, "JPEG_QUALITY", 60)
    cv2 = io.opencv()
    for name in ("a.jpg", "b.JPEG"):
        src = tmp_path / name
        assert cv2.imwrite(str(src), _pattern(50, 70, 2), [cv2.IMWRITE_JPEG_QUALITY, 95])
        decoded = cv2.imdecode(np.fromfile(str(src), np.uint8), cv2.IMREAD_COLOR)
        scaled = cv2.resize(decoded, (40, 29), interpolation=cv2.INTER_AREA)
        expected = cv2.imencode(".jpg", scaled, [cv2.IMWRITE_JPEG_QUALITY, 60])[1].tobytes()
        assert expected != cv2.imencode(".jpg", scaled)[1].tobytes()
        used, size = poses.prepare_photo(src, tmp_path / "work", 40)
        assert (used, size) == (tmp_path / "work" / name, (40, 29)) and used.read_bytes() == expected, name
    (tmp_path / "work" / "b.JPEG").rename(tmp_path / "work" / "c.jpg")    # three names, as list_photos gives
    photos = [tmp_path / "a.jpg", tmp_path / "b.JPEG", tmp_path / "work" / "c.jpg"]
    capsys.readouterr()
    poses.prepare_photos(photos, tmp_path / "again", None)
    assert re.fullmatch(r"poses: photos: 3/3 photos \(100%\), \d+\.\d s\n", capsys.readouterr().err)
    monkeypatch.setattr(cv2, "imencode", lambda *args: (False, None))
    with pytest.raises(DataError) as err:
        poses.prepare_photo(tmp_path / "a.jpg", tmp_path / "work", 40)
    assert str(err.value) == f"{tmp_path / 'a.jpg'}: could not encode a working copy"


# ----------------------------------------------------------------------------------------
# the top view and the summary, pixel for pixel and word for word


def _topview_by_hand(c2w, points, size):
    """The top view drawn here from its description (docs/POSES.md, draw_topview's docstring):
    white, half-width e = max(1.2, 1.1 x the farthest camera x or y); (x, y) at ((x / e + 1) s / 2,
    (1 - y / e) s / 2) rounded; the unit circle grey (200) 1 px; each point with |x|, |y| < e a
    2 x 2 grey (120) block from its pixel; each camera a line (0, 0, 200 in BGR) from its centre
    0.08 e along its horizontal viewing direction, then a filled dot of radius 3 (0, 0, 220);
    the caption in black at (8, 18); every line anti-aliased. Returns RGB uint8."""
    cv2 = io.opencv()
    centres = np.asarray(c2w)[:, :3, 3]
    e = max(1.2, 1.1 * float(np.abs(centres[:, :2]).max())) if len(centres) else 1.2
    img = np.full((size, size, 3), 255, np.uint8)

    def at(x, y):
        return int(round((x / e + 1) * size / 2)), int(round((1 - y / e) * size / 2))

    cv2.circle(img, at(0.0, 0.0), int(round(size / 2 / e)), (200, 200, 200), 1, cv2.LINE_AA)
    for x, y, _ in points:
        if abs(x) < e and abs(y) < e:
            u, v = at(x, y)
            img[max(v, 0):v + 2, max(u, 0):u + 2] = 120
    for m in c2w:
        look = -m[:2, 2] / np.linalg.norm(m[:2, 2])
        tip = at(*(m[:2, 3] + 0.08 * e * look))
        cv2.line(img, at(*m[:2, 3]), tip, (0, 0, 200), 1, cv2.LINE_AA)
        cv2.circle(img, at(*m[:2, 3]), 3, (0, 0, 220), -1, cv2.LINE_AA)
    cv2.putText(img, "top view (+z up): cameras red, points grey, unit circle", (8, 18), cv2.FONT_HERSHEY_SIMPLEX,
                0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return img[..., ::-1]


def _looking_down(centre, target):
    """c2w (OpenGL: looking along -z) at centre looking at target, z up."""
    c2w = np.eye(4)
    c2w[:3, :3] = _w2c_opencv(np.asarray(centre, np.float64), target).T * [1, -1, -1]
    c2w[:3, 3] = centre
    return c2w


@pytest.mark.parametrize("case", ["far", "near"])
def test_draw_topview_is_the_picture_described_pixel_for_pixel(tmp_path, case):
    """Cameras looking down at the origin (their horizontal direction shorter than 1: drawn at
    0.08 e all the same), one of them high above the others (its z ignored for the extent);
    points inside, one exactly on the edge x = e (left out), one beyond, one at the picture's
    left and top edges (its block cut there). "far": the farthest camera coordinate 2 sets e =
    2.2; "near": cameras within 1, e = 1.2 (the floor). The written PNG equals the picture drawn
    here (_topview_by_hand) exactly; the default size is 640."""
    scale = 1.0 if case == "far" else 0.45
    centres = np.array([[2.0, 0.5, 0.3], [-0.5, -1.0, 0.2], [0.3, 1.1, 4.0]]) * [scale, scale, 1.0]
    c2w = np.stack([_looking_down(c, [0.0, 0.0, -0.5]) for c in centres])
    assert all(np.linalg.norm(m[:2, 2]) < 0.99 for m in c2w)
    e = 2.2 if case == "far" else 1.2
    points = np.array([[0.3, 0.8, 0.1], [e, 0.0, 0.0], [5.0, 0.0, 0.0], [-e + 1e-3, e - 1e-3, 0.0], [-0.2, -0.6, 1.0],
                       [-1.01 * e, 0.0, 0.0], [0.0, e, 0.0], [0.5, -0.3, 5.0]])
    # (-1.01 e, 0): column -1, outside (a block there would show its second column); (0, e): on the
    # top edge, outside (row 0 would show it); (0.5, -0.3, 5): its height does not matter
    path = tmp_path / "top.png"
    poses.draw_topview(path, c2w, points, size=200)
    got = np.round(io.read_image(path) * 255).astype(np.uint8)
    np.testing.assert_array_equal(got, _topview_by_hand(c2w, points, 200))
    poses.draw_topview(tmp_path / "default.png", c2w, points)
    assert io.read_image(tmp_path / "default.png").shape == (640, 640, 3)
    poses.draw_topview(tmp_path / "none.png", np.zeros((0, 4, 4)), points, size=200)    # no camera: e = 1.2
    got = np.round(io.read_image(tmp_path / "none.png") * 255).astype(np.uint8)
    np.testing.assert_array_equal(got, _topview_by_hand(np.zeros((0, 4, 4)), points, 200))


def test_summary_and_report_lines_word_for_word_with_several_names():
    """format_summary and report_lines with two of each list (unregistered, unreadable, left out:
    joined by ", "), a left-out photo without a table row ("?"), a GPS scale without a GPS
    residual, and the report's blank lines, every line written out here."""
    summary = {"registered": 4, "photos": 8, "points3d": 40, "mean_reprojection_error": 0.25,
               "unregistered": ["d.png", "f.png"], "skipped": ["e.jpg", "g.jpg"],
               "vetting": {"left_out": ["b.png", "c.png"],
                           "photos": [{"name": "b.png", "reasons": ["reprojection 3.2 px", "track 1.5"]}]},
               "georeference": {"units": "metres", "source": "control points", "crs": "EPSG:32632",
                                "metres_per_model_unit": 2.5}}
    assert poses.format_summary(summary).splitlines() == [
        "registered 4/8 photos, 40 3-D points, mean reprojection error 0.250 px",
        "not registered (2): d.png, f.png",
        f"left out by the vetting (2; table in {poses.REPORT}, --keep-all keeps them): "
        "b.png (reprojection 3.2 px; track 1.5), c.png (?)",
        "unreadable, skipped (2): e.jpg, g.jpg",
        "scale and georeference from control points: EPSG:32632, 2.5 m per model unit"]
    bounds = {"near": 0.125, "far": 4.5, "contract_radius": 2.0, "roi_radius": 1.0, "nearest_camera_to_roi": 2.25,
              "roi_centre": [0.5, -0.25, 0.0]}
    plain = {k: v for k, v in summary.items() if k not in ("vetting", "georeference")}
    lines = poses.report_lines(plain, bounds)
    from jaxnerf_grid.capture import vetting

    assert lines == ["# Camera poses", "", "registered 4/8 photos, 40 3-D points, mean reprojection error 0.250 px",
                     "not registered (2): d.png, f.png", "unreadable, skipped (2): e.jpg, g.jpg", "",
                     "## Vetting (docs/POSES.md)", "", *vetting.format_table([]), "",
                     "## Scene bounds (docs/BOUNDS.md)", "", "| bound | value (normalised units) |", "|---|---|",
                     "| near | 0.125 |", "| far | 4.5 |", "| contract_radius | 2 |", "| roi_radius | 1 |",
                     "| nearest_camera_to_roi | 2.25 |", "| roi_centre | 0.5, -0.25, 0 |", ""]
    no_rows = {**plain, "vetting": {"left_out": ["b.png"]}}                 # no table rows at all
    assert poses.format_summary(no_rows).splitlines()[2] == (
        f"left out by the vetting (1; table in {poses.REPORT}, --keep-all keeps them): b.png (?)")
    keep = poses.report_lines({**plain, "vetting": {"keep_all": True}}, bounds)
    assert keep[keep.index("## Vetting (docs/POSES.md)"):][:4] == [
        "## Vetting (docs/POSES.md)", "", "`--keep-all`: every registered photo kept, whatever its scores.", ""]


def test_summary_names_the_spatial_neighbours_and_the_sequential_overlap_of_the_matcher_that_ran():
    """The matcher line says each photo's nearest by GPS for spatial matching and its next photos for
    sequential matching, from the summary's counts."""
    base = {"registered": 3, "photos": 3, "points3d": 9, "mean_reprojection_error": 0.5, "unregistered": [],
            "skipped": []}
    spatial = {**base, "matcher": "spatial", "matcher_reason": "auto: 60 photos, 1770 pairs, more than 1225; every "
               "photo has GPS", "neighbours": 40, "overlap": None}
    assert poses.format_summary(spatial).splitlines()[1] == (
        "matcher: spatial (auto: 60 photos, 1770 pairs, more than 1225; every photo has GPS, each photo with its 40 "
        "nearest by GPS)")
    sequential = {**spatial, "matcher": "sequential", "matcher_reason": "asked for", "neighbours": None, "overlap": 7}
    assert poses.format_summary(sequential).splitlines()[1] == (
        "matcher: sequential (asked for, each photo with its next 7)")
