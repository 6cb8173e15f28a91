"""capture/poses.py's `poses_from_images` end to end, and its staging and recovery
functions (`check_out`, `make_stage`, `_siblings`, `_staged_names`, `recover`, `_finish_swap`,
`move_into_place`, `_inside`), with no COLMAP feature, matching or mapping run.

`run_colmap` is replaced by a stand-in that records what it is handed and returns a COLMAP model
written by hand (`test_poses_frames._write_model`: known cameras on two rings about a target,
points on a sphere of radius 2 about it, each seen where it projects), read by pycolmap; the
rest of the flow is the package's own, pycolmap's undistortion included (PINHOLE cameras: the
photos keep their size). Each expectation is written out here: the summary's values, the
cameras of transforms.json where the hand-made model puts them (after the smallest rotation
taking the tilted world's up to +z, scipy's axis-angle form, and the orbit normalisation,
centre the target and radius the sphere's 2), near / far by the COLMAP loader's rule on
depths worked out here, the one-line refusals, and the folders left on disk. The staging tests
build the folders by hand (an old dataset, a staging folder, a user's file) and write the
expected trees and rename orders out.
"""

from __future__ import annotations

import json
import os
import re
import socket
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from jaxnerf_grid.capture import georef, gps, poses
from jaxnerf_grid.util import io, staging
from jaxnerf_grid.util.io import DataError
from tests.capture.test_poses_cameras_and_frame import FOCAL, _rings, _write_model

pycolmap = pytest.importorskip("pycolmap")

TARGET = np.array([1.0, -2.0, 3.0])
MARKER = ".jaxnerf-grid-poses"
MARKER_TEXT = "written by jaxnerf-grid poses; --overwrite replaces its outputs\n"
TIMES = {"features": 1.0, "matching": 2.0, "mapping": 3.0}


def _sphere(n=40, radius=2.0):
    """n points on the sphere of `radius` about TARGET (a Fibonacci lattice): every one at
    distance exactly `radius` (to rounding) from the point the cameras look at."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    a = np.pi * (1 + 5 ** 0.5) * k
    r = np.sqrt(1 - z * z)
    return TARGET + radius * np.column_stack([r * np.cos(a), r * np.sin(a), z])


def _write_photos(folder, names, size=(80, 60)):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(3)
    for name in names:
        io.write_png(folder / name, rng.random((size[1], size[0], 3)).astype(np.float32))


class _Colmap:
    """Stand-in for `poses.run_colmap`: records its arguments and what the staging folder holds
    when it is called, adds known seconds to `timings`, and returns (the model, relaxed, extended,
    the photos placed structure-less: `from_2d`)."""

    def __init__(self, model_dir, relaxed=False, fail=None, from_2d=()):
        self.model_dir, self.relaxed, self.fail, self.calls = model_dir, relaxed, fail, []
        self.from_2d = list(from_2d)

    def __call__(self, module, photo_dir, names, work_dir, **kwargs):
        stage = work_dir.parent
        self.calls.append({"module": module, "photo_dir": photo_dir, "names": list(names), "work_dir": work_dir,
                           "photos": sorted(p.name for p in photo_dir.iterdir()),
                           "sizes": {p.name: io.opencv().imread(str(p)).shape[1::-1] for p in photo_dir.iterdir()},
                           "owner": (stage / "OWNER").read_text(), "stage": stage, **kwargs})
        if self.fail is not None:
            raise self.fail
        kwargs["timings"].update(TIMES)
        return pycolmap.Reconstruction(self.model_dir), self.relaxed, False, self.from_2d


def _scene(tmp_path, registered=12, photos=13, turned=(5,), tilt=None, camera=(80, 60, FOCAL, FOCAL, 40, 30),
           photo_size=(80, 60)):
    """Photos v00..v{photos-1}.png (80 x 60), a broken file and a note in tmp_path/photos; a
    hand-written model of the first `registered` ring cameras in tmp_path/model, the world
    turned by `tilt` (a rotation matrix), the cameras in `turned` written turned by 20 degrees
    about their own y axis (they fail the vetting). Returns (photo folder, model folder,
    [(name, centre, w2c rotation)] of the registered cameras in the untilted world)."""
    centres, w2cs = _rings()
    q = np.eye(3) if tilt is None else tilt
    names = [f"v{k:02d}.png" for k in range(photos)]
    _write_photos(tmp_path / "photos", names, photo_size)
    (tmp_path / "photos" / "broken.png").write_bytes(b"not a png")
    (tmp_path / "photos" / "notes.txt").write_text("not a photo")
    images = [(names[k], 1, w2cs[k] @ q.T, -(w2cs[k] @ q.T) @ (q @ centres[k])) for k in range(registered)]
    turn = Rotation.from_rotvec([0.0, np.radians(20.0), 0.0]).as_matrix()
    written = {k: (turn @ images[k][2], turn @ images[k][3]) for k in turned}
    _write_model(tmp_path / "model", {1: camera}, images, _sphere() @ q.T, written=written)
    return tmp_path / "photos", tmp_path / "model", [(names[k], centres[k], w2cs[k]) for k in range(registered)]


def _smallest_rotation_to_z(up):
    axis = np.cross(up, [0.0, 0.0, 1.0])
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.arccos(up[2])).as_matrix()


def _hidden(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def _no_gps_check(*args, **kwargs):
    raise AssertionError("precheck_gps called without GPS")


# ----------------------------------------------------------------------------------------
# poses_from_images: the whole step


def test_poses_from_images_writes_the_dataset_of_the_hand_written_model(tmp_path, monkeypatch):
    """13 readable photos (and a broken file, a note), 12 in the model, v05 turned (left out by
    the vetting), the world tilted by a known rotation; out in a parent folder not made yet.
    The summary, transforms.json (cameras, intrinsics, near / far, the poses record), the
    folder written and what run_colmap was handed, all against values worked out here."""
    q = Rotation.from_rotvec([0.25, -0.4, 0.1]).as_matrix()
    photos, model_dir, cams = _scene(tmp_path, tilt=q)
    stand_in = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", stand_in)
    monkeypatch.setattr(georef, "precheck_gps", _no_gps_check)
    read = []
    real_positions_of = gps.positions_of
    monkeypatch.setattr(gps, "positions_of",
                        lambda records: read.append([r.path for _, r in records]) or real_positions_of(records))
    # the clock: start, photos in / out, writing, the last stage in, the total, the writing, out
    clock = iter([100.0, 100.2, 100.7, 103.0, 103.1, 112.34, 112.41, 115.0])
    monkeypatch.setattr(poses, "time", type("Clock", (), {"monotonic": staticmethod(lambda: next(clock))}))
    monkeypatch.setattr(pycolmap.logging, "minloglevel", 0)
    out = tmp_path / "site" / "north" / "data"
    summary = poses.poses_from_images(photos, out, progress=False)
    recorded = json.loads(json.dumps({k: v for k, v in summary.items() if k not in ("georeference", "transforms")}))

    names = [f"v{k:02d}.png" for k in range(13)]
    call, = stand_in.calls
    stage = call["stage"]
    assert stage.parent == out.parent and stage.name.startswith(".data.poses-")
    assert call["owner"] == f"{socket.gethostname()} {os.getpid()}\n"
    assert (call["module"], call["photo_dir"], call["names"], call["work_dir"], call["photos"]) == (
        pycolmap, stage / "_work" / "photos", names, stage / "_work", names)
    assert {k: call[k] for k in ("matcher", "camera_model", "single_camera", "vocab_tree", "show", "source",
                                 "keep_all", "overlap", "feature_side")} == {
        "matcher": "exhaustive", "camera_model": "SIMPLE_RADIAL", "single_camera": True, "vocab_tree": None,
        "show": False, "source": photos, "keep_all": False, "overlap": 10, "feature_side": poses.FEATURE_SIDE}
    assert call["sizes"] == {n: (80, 60) for n in names}
    assert read == [[photos / n for n in names]]
    assert pycolmap.logging.minloglevel == 3

    up_rotation = _smallest_rotation_to_z(q[:, 2])
    rows = summary.pop("vetting")
    assert (rows["keep_all"], rows["left_out"]) == (False, ["v05.png"])
    assert [(r["name"], r["kept"]) for r in rows["photos"]] == [(n, n != "v05.png") for n in names[:12]]
    np.testing.assert_allclose(summary.pop("up_rotation"), up_rotation, atol=1e-9)
    assert summary.pop("mean_reprojection_error") == pytest.approx(0.1)  # each point's error as written
    cameras = summary.pop("camera_set")   # 11 of the 13 readable kept: 85 %, at least 75 %
    assert {k: cameras[k] for k in ("photos", "kept", "arc_from", "verdict", "accepted")} == {
        "photos": 13, "kept": 11, "arc_from": "registered", "verdict": None, "accepted": False}
    assert (summary.pop("registered_left_out"), summary.pop("registered_structure_less"),
            summary.pop("gps_priors")) == (False, [], 0)
    assert summary.pop("gps_disagreed") is None   # no GPS to judge
    assert summary.pop("gps_priors_skipped") is None   # no GPS to leave out of the mapping
    assert summary.pop("unregistered_why") == {}   # no matching database from the stand-in
    assert summary == {
        "photos": 14, "registered": 12, "in_dataset": 11, "unregistered": ["v12.png"], "skipped": ["broken.png"],
        "points3d": 40, "matcher": "exhaustive", "matcher_asked": "auto",
        "matcher_reason": "auto: 13 photos, 78 pairs, at most 1225", "overlap": None, "neighbours": None,
        "camera_model": "SIMPLE_RADIAL",
        "single_camera": True, "camera_sharing": "one size, 80x60, and one camera: no EXIF camera",
        "max_side": None, "feature_side": 1200, "relaxed_mapping": False,
        "pycolmap": pycolmap.__version__, "georeference": {"units": "unknown", "source": None},
        "reconstruction_reused": False,
        "seconds": 12.3, "timings_s": {"photos": 0.5, **TIMES, "writing": 9.4},
        "transforms": str(out / "transforms.json")}
    assert list(summary["timings_s"]) == ["photos", "features", "matching", "mapping", "writing"]

    # the folder: the dataset alone beside nothing; the photos untouched
    assert sorted(p.name for p in (tmp_path / "site" / "north").iterdir()) == ["data"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [MARKER, "images", "sparse", "transforms.json", "poses_topview.png", "poses_report.md"])
    assert (out / MARKER).read_text() == MARKER_TEXT
    kept = [n for n in names[:12] if n != "v05.png"]
    assert sorted(p.name for p in (out / "images").iterdir()) == kept
    assert sorted(p.name for p in (out / "sparse").iterdir()) == ["0"]
    assert sorted(p.name for p in photos.iterdir()) == sorted(names + ["broken.png", "notes.txt"])
    for n in kept:                                              # PINHOLE: undistorted photo = the photo
        a, b = io.read_image(out / "images" / n), io.read_image(photos / n)
        assert a.shape == b.shape == (60, 80, 3) and np.abs(a - b).max() <= 1.5 / 255

    # transforms.json: each camera where the model put it, turned up and normalised by hand
    top = io.read_json(out / "transforms.json")
    assert top["poses"] == recorded                            # the summary less the georeference
    assert top["georeference"] == {"units": "unknown", "source": None}
    turn = up_rotation @ q                                      # untilted world -> dataset frame
    np.testing.assert_allclose(top["scene_normalization"]["scale"], 0.5, rtol=1e-6)   # points kept in float32
    np.testing.assert_allclose(top["scene_normalization"]["translation"], -(turn @ TARGET), atol=1e-9)
    frames = {f["file_path"]: f for f in top["frames"]}
    assert sorted(frames) == [f"images/{n}" for n in kept]
    depths = []
    for name, centre, w2c in cams:
        if name == "v05.png":
            continue
        f = frames[f"images/{name}"]
        assert (f["fl_x"], f["fl_y"], f["cx"], f["cy"], f["w"], f["h"]) == (FOCAL, FOCAL, 40.0, 30.0, 80, 60)
        c2w = np.asarray(f["transform_matrix"])
        np.testing.assert_allclose(c2w[:3, 3], turn @ (centre - TARGET) / 2.0, atol=1e-9)
        np.testing.assert_allclose(c2w[:3, :3], turn @ w2c.T @ np.diag([1.0, -1.0, -1.0]), atol=1e-9)
        depths.append((_sphere() - centre) @ w2c[2] / 2.0)      # along the viewing axis, normalised
    depths = np.concatenate(depths)
    corner = 1.0 / np.sqrt(1 + (40 / FOCAL) ** 2 + (30 / FOCAL) ** 2)
    near = 0.9 * np.percentile(depths, 0.5)
    np.testing.assert_allclose([top["near"], top["far"]], [near, max(1.1 * np.percentile(depths, 99.5) / corner,
                                                                      2 * near)], rtol=1e-6)
    assert (top["w"], top["h"]) == (80, 60)


def test_poses_from_images_hands_on_its_options_and_the_georeference(tmp_path, monkeypatch):
    """single_camera, PINHOLE, sequential with overlap 4, keep_all, max_side 40 (photos 80 x 60
    worked at 40 x 30), a CRS, a GCP file and a scale bar: run_colmap, the GPS reading and check,
    the GCP reading and the alignment each get them (sizes the photos' own, ratios 0.5); the
    alignment's similarity (scale 2, 30 degrees about z, a shift) moves the model, so the
    dataset's cameras turn by 30 degrees and its scale and georeference follow."""
    photos, model_dir, cams = _scene(tmp_path, turned=(), camera=(40, 30, FOCAL / 2, FOCAL / 2, 20, 15))
    gcp = tmp_path / "gcp.csv"
    gcp.write_text("name,x,y\n")
    stand_in = _Colmap(model_dir, relaxed=True)
    monkeypatch.setattr(poses, "run_colmap", stand_in)
    names = [f"v{k:02d}.png" for k in range(13)]
    positions = {n: {"latitude": 47.0, "longitude": 8.0, "altitude": 400.0} for n in names}
    calls = []
    monkeypatch.setattr(gps, "positions_of",
                        lambda records: calls.append(("read_all", [r.path for _, r in records])) or positions)
    monkeypatch.setattr(georef, "read_gcp_csv", lambda path, sizes: calls.append(("gcp", path, sizes)) or [])
    monkeypatch.setattr(georef, "precheck_gps", lambda *args: calls.append(("precheck", *args)))
    z30 = Rotation.from_rotvec([0.0, 0.0, np.radians(30.0)]).as_matrix()
    shift = np.array([5.0, -3.0, 1.0])
    record = {"units": "metres", "source": "gps", "crs": "EPSG:32632", "origin": [466000.0, 5247000.0, 400.0],
              "metres_per_model_unit": 2.0}

    def align(model, gps_positions, **kwargs):
        calls.append(("align", model.num_reg_images(), gps_positions, kwargs))
        return (2.0, z30, shift), dict(record)

    monkeypatch.setattr(georef, "align_model", align)
    bar = "0,0,0,0,0,1,10"
    out = tmp_path / "data"
    summary = poses.poses_from_images(photos, out, matcher="sequential", camera_model="PINHOLE", single_camera=True,
                                      max_side=40, overlap=4, progress=False, keep_all=True, crs="EPSG:32632",
                                      gcp=gcp, scale_bar=bar)
    sizes, ratios = {n: (80, 60) for n in names}, {n: (0.5, 0.5) for n in names}
    assert calls == [("read_all", [photos / n for n in names]), ("gcp", gcp, sizes),
                     ("precheck", positions, "EPSG:32632", 13, photos),
                     ("align", 12, positions, {"crs_name": "EPSG:32632", "gcp_path": gcp, "scale_bar": bar,
                                               "sizes": sizes, "ratios": ratios, "source": photos})]
    call, = stand_in.calls
    assert call["sizes"] == {n: (40, 30) for n in names}           # the working copies COLMAP reads
    assert {k: call[k] for k in ("matcher", "camera_model", "single_camera", "show", "keep_all", "overlap")} == {
        "matcher": "sequential", "camera_model": "PINHOLE", "single_camera": True, "show": False, "keep_all": True,
        "overlap": 4}
    assert {k: summary[k] for k in ("registered", "in_dataset", "matcher", "matcher_asked", "matcher_reason",
                                    "overlap", "camera_model", "single_camera", "max_side", "relaxed_mapping")} == {
        "registered": 12, "in_dataset": 12, "matcher": "sequential", "matcher_asked": "sequential",
        "matcher_reason": "asked for", "overlap": 4, "camera_model": "PINHOLE", "single_camera": True,
        "max_side": 40, "relaxed_mapping": True}
    assert summary["vetting"]["keep_all"] is True and summary["vetting"]["left_out"] == []
    assert summary["georeference"] == record
    top = io.read_json(out / "transforms.json")
    assert len(top["frames"]) == 12 and (top["w"], top["h"]) == (40, 30)
    # the model moved by (2, Rz(30), shift): its cameras' centre 2 Rz target + shift, radius 2 x 2
    norm = top["scene_normalization"]
    np.testing.assert_allclose(norm["scale"], 0.25, rtol=1e-6)
    np.testing.assert_allclose(norm["translation"], -(2.0 * z30 @ TARGET + shift), atol=1e-4)
    np.testing.assert_allclose(top["georeference"]["metres_per_scene_unit"], 4.0, rtol=1e-6)
    frames = {f["file_path"]: np.asarray(f["transform_matrix"]) for f in top["frames"]}
    for name, centre, _ in cams[:4]:
        np.testing.assert_allclose(frames[f"images/{name}"][:3, 3], z30 @ (centre - TARGET) / 2.0, atol=1e-4)


def test_keep_all_keeps_the_photo_the_vetting_would_leave_out(tmp_path, monkeypatch):
    photos, model_dir, _ = _scene(tmp_path)
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False, keep_all=True)
    assert (summary["in_dataset"], summary["vetting"]["keep_all"], summary["vetting"]["left_out"]) == (12, True, [])
    assert [r["kept"] for r in summary["vetting"]["photos"]].count(False) == 1    # v05 fails, and stays
    top = io.read_json(tmp_path / "data" / "transforms.json")
    assert "images/v05.png" in [f["file_path"] for f in top["frames"]] and len(top["frames"]) == 12


def test_the_photos_placed_from_2d_matches_alone_are_named_in_summary_and_report(tmp_path, monkeypatch):
    """run_colmap says v03 and v12 were placed structure-less; v12 is not in the model it hands
    back (v00-v11): the summary and poses_report.md name v03 alone."""
    photos, model_dir, _ = _scene(tmp_path)
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir, from_2d=["v03.png", "v12.png"]))
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False)
    assert summary["registered_structure_less"] == ["v03.png"]
    report = (tmp_path / "data" / "poses_report.md").read_text()
    line, = [x for x in report.splitlines() if x.startswith("placed from their 2-D matches alone")]
    assert line.startswith("placed from their 2-D matches alone (1; ") and line.endswith("): v03.png")


def test_poses_from_images_hands_on_the_vocabulary_tree(tmp_path, monkeypatch):
    photos, model_dir, _ = _scene(tmp_path, turned=())
    tree = tmp_path / "tree.bin"
    tree.write_bytes(b"tree")
    stand_in = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", stand_in)
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False, matcher="vocab", vocab_tree=tree)
    assert (stand_in.calls[0]["matcher"], stand_in.calls[0]["vocab_tree"]) == ("vocab", tree)
    assert (summary["matcher"], summary["matcher_asked"], summary["matcher_reason"], summary["overlap"]) == (
        "vocab", "vocab", "asked for", None)


def test_poses_from_images_says_unknown_for_a_pycolmap_without_a_version(tmp_path, monkeypatch):
    photos, model_dir, _ = _scene(tmp_path, turned=())
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    monkeypatch.delattr(pycolmap, "__version__")
    assert poses.poses_from_images(photos, tmp_path / "data", progress=False)["pycolmap"] == "unknown"


@pytest.mark.parametrize("ignore_gps", [True, False])
def test_poses_from_images_reads_no_gps_when_told_and_reads_it_else(tmp_path, monkeypatch, ignore_gps):
    photos, model_dir, _ = _scene(tmp_path, turned=())
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    read, aligned = [], []
    monkeypatch.setattr(gps, "positions_of", lambda records: read.append(1) or {})
    real_align = georef.align_model
    monkeypatch.setattr(georef, "align_model", lambda model, positions, **kw: aligned.append(positions)
                        or real_align(model, positions, **kw))
    poses.poses_from_images(photos, tmp_path / "data", progress=False, ignore_gps=ignore_gps)
    assert (read, aligned) == ([] if ignore_gps else [1], [{}])


def test_poses_from_images_opens_each_photo_once_for_its_exif(tmp_path, monkeypatch):
    """The cameras, the GPS and the upright sizes come from one opening of each readable photo's
    header (`photo_headers`), not one per reader: PIL's Image.open is called once per photo (the
    pixels are decoded by OpenCV), and not at all for the broken file."""
    photos, model_dir, _ = _scene(tmp_path, turned=())
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    opened = []
    real_open = Image.open

    def counting_open(fp, *args, **kwargs):
        opened.append(Path(getattr(fp, "name", fp)).name)
        return real_open(fp, *args, **kwargs)

    monkeypatch.setattr(Image, "open", counting_open)
    poses.poses_from_images(photos, tmp_path / "data", progress=False)
    assert sorted(opened) == [f"v{k:02d}.png" for k in range(13)]


def test_poses_from_images_with_a_scale_bar_is_in_metres(tmp_path, monkeypatch):
    """No GPS, a scale bar of 10 m between two model points 2 units apart (the target and 2
    above it, in the frame the bar is read in: the world is level, so the turn is none): 5 m
    per model unit, the sphere's radius 10 m, 10 m per normalised scene unit."""
    photos, model_dir, _ = _scene(tmp_path, turned=())
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False,
                                      scale_bar="1,-2,3,1,-2,5,10")
    geo = summary["georeference"]
    assert (geo["units"], geo["source"], geo["crs"]) == ("metres", "scale_bar", None)
    np.testing.assert_allclose(geo["metres_per_model_unit"], 5.0, rtol=1e-9)
    top = io.read_json(tmp_path / "data" / "transforms.json")
    np.testing.assert_allclose(top["georeference"]["metres_per_scene_unit"], 10.0, rtol=1e-6)
    np.testing.assert_allclose(top["scene_normalization"]["scale"], 0.1, rtol=1e-6)


def test_poses_from_images_is_quiet_or_says_its_stages(tmp_path, monkeypatch, capsys):
    photos, model_dir, _ = _scene(tmp_path, turned=())
    stand_in = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", stand_in)
    poses.poses_from_images(photos, tmp_path / "quiet", progress=False)
    assert capsys.readouterr().err == "poses: skipping " + str(photos / "broken.png") + ": not a readable image\n"
    poses.poses_from_images(photos, tmp_path / "loud")
    err = capsys.readouterr().err.splitlines()
    assert stand_in.calls[1]["show"] is True
    assert "poses: undistortion to PINHOLE, orientation, transforms.json ..." in err
    assert any(line.startswith("poses: undistortion to PINHOLE, orientation, transforms.json done in ")
               for line in err)
    assert not any(line.startswith("poses: photos") and "done in" in line for line in err)  # the photos stage is quiet
    assert len([line for line in err if re.fullmatch(r"poses: photos: 14/14 photos \(100%\), \d+\.\d s", line)]) == 1


# ----------------------------------------------------------------------------------------
# poses_from_images: refusals, and what a failure leaves


def _refused(tmp_path, monkeypatch, photos, out, **kwargs) -> str:
    """The one-line DataError of a refused run; run_colmap never called, `out` not made, nothing
    hidden left beside it."""
    stand_in = _Colmap(tmp_path / "model")
    monkeypatch.setattr(poses, "run_colmap", stand_in)
    existed = out.exists()
    with pytest.raises(DataError) as err:
        poses.poses_from_images(photos, out, progress=False, **kwargs)
    assert stand_in.calls == [] and out.exists() == existed
    assert not [n for n in _hidden(out.parent) if n.startswith(f".{out.name}.")] and "\n" not in str(err.value)
    return str(err.value)


def test_poses_from_images_refuses_bad_input_before_any_work(tmp_path, monkeypatch):
    photos, _, _ = _scene(tmp_path)
    out = tmp_path / "data"
    assert _refused(tmp_path, monkeypatch, photos, out, max_side=15) == (
        "poses.max_side must be at least 16 pixels, got 15")
    assert _refused(tmp_path, monkeypatch, photos, out, matcher="nearest").startswith("unknown poses.matcher 'nearest'")
    assert _refused(tmp_path, monkeypatch, photos, out, gcp=tmp_path / "no.csv") == (
        f"{tmp_path / 'no.csv'}: ground control point file not found")
    assert _refused(tmp_path, monkeypatch, photos, out, scale_bar="ten metres").startswith("poses.scale_bar: expected")
    assert "poses.crs" in _refused(tmp_path, monkeypatch, photos, out, crs="EPSG:4326")
    for inside in (tmp_path, photos):                            # the photos' folder, or one holding it
        assert _refused(tmp_path, monkeypatch, photos, inside, overwrite=True) == (
            f"{inside}: the output folder holds the input photos ({photos}); choose another poses.out")
    out.mkdir()
    (out / "thesis.tex").write_text("years of work")
    assert _refused(tmp_path, monkeypatch, photos, out) == (
        f"{out}: already exists and is not empty; pass overwrite=True to replace it")
    assert [p.name for p in out.iterdir()] == ["thesis.tex"]
    monkeypatch.setitem(sys.modules, "pycolmap", None)
    assert _refused(tmp_path, monkeypatch, photos, tmp_path / "other").startswith("pycolmap is not installed")


def test_poses_from_images_takes_max_side_16(tmp_path, monkeypatch):
    """The smallest working size allowed: 80 x 60 photos worked at 16 x 12 (the model's cameras
    at that size)."""
    photos, model_dir, _ = _scene(tmp_path, turned=(), camera=(16, 12, FOCAL / 5, FOCAL / 5, 8, 6))
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False, max_side=16)
    assert summary["max_side"] == 16 and io.read_json(tmp_path / "data" / "transforms.json")["w"] == 16


def test_poses_from_images_refuses_single_camera_over_photos_of_two_sizes(tmp_path, monkeypatch):
    """Only the readable photos count: a broken file does not make a size of its own."""
    photos, model_dir, _ = _scene(tmp_path, turned=())
    _write_photos(photos, ["v13.png"], (60, 80))
    err = _refused(tmp_path, monkeypatch, photos, tmp_path / "data", single_camera=True)
    assert err.startswith(f"{photos}: poses.single_camera needs photos of one size, these have 2 (80x60: 13 (e.g. "
                          "v00.png); 60x80: 1 (e.g. v13.png))")


def _old_dataset(out):
    out.mkdir(parents=True)
    (out / MARKER).write_text("")
    (out / "transforms.json").write_text("old transforms")
    (out / "notes.txt").write_text("mine")
    return {p.name: p.read_text() for p in out.iterdir()}


@pytest.mark.parametrize("photos, registered, turned, message", [
    (13, 4, (1,), "only 3 of 13 photos registered and passed the vetting (a dataset needs 4; not registered or "
                  "left out: v04.png, v05.png, v06.png, v07.png, v08.png, ...)"),
    (8, 3, (1,), "only 2 of 8 photos registered and passed the vetting (a dataset needs 3; not registered or left "
                 "out: v03.png, v04.png, v05.png, v06.png, v07.png, ...)"),
    (7, 3, (1,), "only 2 of 7 photos registered and passed the vetting (a dataset needs 3; not registered or left "
                 "out: v03.png, v04.png, v05.png, v06.png, v01.png)")])
def test_poses_from_images_refuses_too_few_registered_and_keeps_the_old_dataset(
        tmp_path, monkeypatch, photos, registered, turned, message):
    """Too few photos registered and vetted (a quarter of the readable ones, at least 3): the
    refusal names the photos (five at most, unregistered first), the old dataset and the user's
    file stay as they were and the staging folder is gone."""
    folder, model_dir, _ = _scene(tmp_path, registered=registered, photos=photos, turned=turned)
    before = _old_dataset(tmp_path / "data")
    stand_in = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", stand_in)
    with pytest.raises(DataError) as err:
        poses.poses_from_images(folder, tmp_path / "data", progress=False, overwrite=True)
    assert str(err.value) == (f"{folder}: {message}; more overlap and texture between photos help "
                              "(docs/POSES.md)")
    assert {p.name: p.read_text() for p in (tmp_path / "data").iterdir()} == before
    assert len(stand_in.calls) == 1 and not stand_in.calls[0]["stage"].exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "model", "photos"]


def test_poses_from_images_writes_a_dataset_at_exactly_enough_registered(tmp_path, monkeypatch):
    """4 of 13 registered and vetted: a quarter of 13 rounded up, enough for a model; too few to
    train on (under 75 %): refused in one line naming the count, written with
    accept_few_cameras, and the record says so."""
    folder, model_dir, _ = _scene(tmp_path, registered=5, photos=13, turned=(1,))
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    with pytest.raises(DataError, match=r": only 4 of 13 photos kept \(31 %; training needs 10, 75%\); not written"):
        poses.poses_from_images(folder, tmp_path / "data", progress=False)
    assert not (tmp_path / "data").exists()
    summary = poses.poses_from_images(folder, tmp_path / "data", progress=False, accept_few_cameras=True)
    assert (summary["registered"], summary["in_dataset"]) == (5, 4)
    assert len(io.read_json(tmp_path / "data" / "transforms.json")["frames"]) == 4
    assert summary["camera_set"]["accepted"] is True and summary["camera_set"]["verdict"].startswith("only 4 of 13")


class Killed(BaseException):
    pass


@pytest.mark.parametrize("failure", [RuntimeError("COLMAP failed"), Killed()])
def test_a_failure_before_the_swap_removes_the_stage_and_keeps_the_old_dataset(tmp_path, monkeypatch, failure):
    """An error, or a BaseException (Ctrl-C), while COLMAP runs: raised out as it is, the old
    dataset as it was, no staging folder left."""
    folder, model_dir, _ = _scene(tmp_path)
    before = _old_dataset(tmp_path / "data")
    stand_in = _Colmap(model_dir, fail=failure)
    monkeypatch.setattr(poses, "run_colmap", stand_in)
    with pytest.raises(type(failure)):
        poses.poses_from_images(folder, tmp_path / "data", progress=False, overwrite=True)
    assert {p.name: p.read_text() for p in (tmp_path / "data").iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "model", "photos"]


def test_a_failure_whose_stage_is_already_gone_raises_its_own_error(tmp_path, monkeypatch):
    """The clean-up never hides the error: a staging folder already gone (removed under the
    run) is passed over and the run's own one-line error comes out."""
    folder, model_dir, _ = _scene(tmp_path)

    class _Vanishing(_Colmap):
        def __call__(self, module, photo_dir, names, work_dir, **kwargs):
            import shutil

            shutil.rmtree(work_dir.parent)
            raise DataError("the stage went away")

    monkeypatch.setattr(poses, "run_colmap", _Vanishing(model_dir))
    with pytest.raises(DataError, match="^the stage went away$"):
        poses.poses_from_images(folder, tmp_path / "data", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model", "photos"]


def test_a_kill_during_the_swap_leaves_the_committed_stage_for_recover(tmp_path, monkeypatch):
    """A kill after the commit point (COMPLETE written, two renames of the swap done): the
    staging folder stays, so `recover` rolls the new dataset forward; the user's file stays."""
    folder, model_dir, _ = _scene(tmp_path)
    _old_dataset(tmp_path / "data")
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    real, done = staging.move, []

    def dying(src, dst):
        if len(done) == 2:
            raise Killed()
        done.append(dst)
        real(src, dst)

    monkeypatch.setattr(staging, "move", dying)
    with pytest.raises(Killed):
        poses.poses_from_images(folder, tmp_path / "data", progress=False, overwrite=True)
    monkeypatch.setattr(staging, "move", real)
    stage, = [p for p in tmp_path.iterdir() if p.name.startswith(".data.poses-")]
    assert (stage / "COMPLETE").is_file()
    assert poses.recover(tmp_path / "data") == "rolled forward"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "model", "photos"]
    assert sorted(p.name for p in (tmp_path / "data").iterdir()) == sorted(
        [MARKER, "images", "sparse", "transforms.json", "poses_topview.png", "poses_report.md", "notes.txt"])
    assert len(io.read_json(tmp_path / "data" / "transforms.json")["frames"]) == 11
    assert (tmp_path / "data" / MARKER).read_text() == MARKER_TEXT


def test_overwrite_replaces_its_outputs_and_the_stale_masks_and_keeps_the_rest(tmp_path, monkeypatch):
    folder, model_dir, _ = _scene(tmp_path)
    out = tmp_path / "data"
    _old_dataset(out)
    (out / "images").mkdir()
    (out / "images" / "old.png").write_bytes(b"old")
    (out / "masks").mkdir()
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    poses.poses_from_images(folder, out, progress=False, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [MARKER, "images", "sparse", "transforms.json", "poses_topview.png", "poses_report.md", "notes.txt"])
    assert "old.png" not in [p.name for p in (out / "images").iterdir()]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "model", "photos"]


def test_poses_from_images_finishes_an_interrupted_swap_first(tmp_path, monkeypatch):
    """A committed staging folder left by a killed run is rolled forward before the new run
    checks its output folder, so the new run may replace it."""
    folder, model_dir, _ = _scene(tmp_path)
    out = tmp_path / "data"
    out.mkdir()
    stage = tmp_path / ".data.poses-left"
    stage.mkdir()
    (stage / MARKER).write_text("")
    (stage / "transforms.json").write_text("left")
    staging.write_complete(stage, "COMPLETE", [MARKER, "transforms.json"])
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    poses.poses_from_images(folder, out, progress=False, overwrite=True)
    assert len(io.read_json(out / "transforms.json")["frames"]) == 11
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "model", "photos"]


# ----------------------------------------------------------------------------------------
# The staging and recovery functions, on folders made by hand


def _tree(root):
    return {p.relative_to(root).as_posix(): ("dir" if p.is_dir() else p.read_text()) for p in sorted(root.rglob("*"))}


def _write(root, files):
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)


def test_inside_is_the_folder_itself_or_below_it_links_resolved(tmp_path):
    (tmp_path / "scene" / "images").mkdir(parents=True)
    (tmp_path / "alias").symlink_to(tmp_path / "scene", target_is_directory=True)
    assert poses._inside(tmp_path / "scene", tmp_path / "scene")
    assert poses._inside(tmp_path / "scene" / "images", tmp_path / "scene")
    assert poses._inside(tmp_path / "alias" / "images", tmp_path / "scene")
    assert not poses._inside(tmp_path / "scene", tmp_path / "scene" / "images")
    assert not poses._inside(tmp_path / "scene2", tmp_path / "scene")


def test_check_out_rules(tmp_path, monkeypatch):
    """Absent, empty, or with overwrite a folder holding the marker: accepted; a file, a
    non-empty folder without overwrite, one without the marker, a linked output, or a parent
    this user may not write: refused with its one line."""
    poses.check_out(tmp_path / "new", False)
    (tmp_path / "empty").mkdir()
    poses.check_out(tmp_path / "empty", False)
    (tmp_path / "file").write_text("x")
    with pytest.raises(DataError) as err:
        poses.check_out(tmp_path / "file", True)
    assert str(err.value) == f"{tmp_path / 'file'}: is a file; poses.out must be a folder"
    with pytest.raises(DataError) as err:
        poses.check_out(tmp_path / "file" / "data", True)
    assert str(err.value).startswith(f"{tmp_path / 'file' / 'data'}: poses.out cannot be made there")
    marked = tmp_path / "marked"
    _write(marked, {MARKER: "", "notes.txt": "mine"})
    with pytest.raises(DataError) as err:
        poses.check_out(marked, False)
    assert str(err.value) == f"{marked}: already exists and is not empty; pass overwrite=True to replace it"
    poses.check_out(marked, True)
    _write(tmp_path / "foreign", {"thesis.tex": "years"})
    with pytest.raises(DataError, match="not written by jaxnerf-grid poses .no .jaxnerf-grid-poses.; nothing was "
                                        "changed: choose another poses.out"):
        poses.check_out(tmp_path / "foreign", True)
    for name in ("masks", "poses_report.md"):                   # an output of its own or a stale mask output
        linked = tmp_path / f"linked-{name}"
        _write(linked, {MARKER: ""})
        (linked / name).symlink_to(tmp_path / "empty")
        with pytest.raises(DataError, match="is a symbolic link"):
            poses.check_out(linked, True)
    # the parent (where the staging folder goes) not writable, the folder itself writable
    real = os.access
    monkeypatch.setattr(os, "access", lambda path, mode: False if str(path) == str(tmp_path) else real(path, mode))
    with pytest.raises(DataError) as err:
        poses.check_out(marked, True)
    assert str(err.value).startswith(f"{tmp_path}: poses.out is not writable by this user ({tmp_path}: ")


def test_make_stage_is_a_hidden_sibling_holding_its_owner(tmp_path):
    out = tmp_path / "Mast Nord"
    a, b = poses.make_stage(out), poses.make_stage(out)
    assert a != b and a.parent == b.parent == tmp_path
    for stage in (a, b):
        assert stage.is_dir() and stage.name.startswith(".Mast Nord.poses-") and len(stage.name) > 17
        assert sorted(p.name for p in stage.iterdir()) == ["OWNER"]
        assert (stage / "OWNER").read_text() == f"{socket.gethostname()} {os.getpid()}\n"
    assert not out.exists()


def test_siblings_are_the_hidden_folders_of_that_name_and_tag(tmp_path):
    for name in (".d.poses-b", ".d.poses-a", ".d.old-a", ".dd.poses-a", "d.poses-a", ".e.poses-a"):
        (tmp_path / name).mkdir()
    (tmp_path / ".d.poses-file").write_text("not a folder")
    out = tmp_path / "d"
    assert poses._siblings(out, ".poses-") == [tmp_path / ".d.poses-a", tmp_path / ".d.poses-b"]
    assert poses._siblings(out, ".old-") == [tmp_path / ".d.old-a"]
    assert poses._siblings(tmp_path / "missing" / "d", ".poses-") == []


def test_staged_names(tmp_path):
    """COMPLETE's list; an older version's folder (no OWNER, no COMPLETE) holding the marker:
    every output; else (no marker, or an OWNER: a run that had not finished) none."""
    complete = tmp_path / "complete"
    complete.mkdir()
    staging.write_complete(complete, "COMPLETE", ["images", "transforms.json"])
    (complete / MARKER).write_text("")
    assert poses._staged_names(complete) == ["images", "transforms.json"]
    old = tmp_path / "old"
    _write(old, {MARKER: ""})
    assert poses._staged_names(old) == ["images", "sparse", "transforms.json", "poses_topview.png",
                                        "poses_report.md", MARKER]
    running = tmp_path / "running"
    _write(running, {MARKER: "", "OWNER": "host 1\n"})
    assert poses._staged_names(running) is None
    unmarked = tmp_path / "unmarked"
    _write(unmarked, {"images/a.png": "a"})
    assert poses._staged_names(unmarked) is None
    marker_folder = tmp_path / "marker-folder"
    (marker_folder / MARKER).mkdir(parents=True)
    assert poses._staged_names(marker_folder) is None


OLD = {"images/a.png": "old a", "sparse/0/cameras.bin": "old cams", "transforms.json": "old transforms",
       "poses_report.md": "old report", MARKER: "", "masks/a.png": "old mask", "dpt_depth/a.exr": "old depth",
       "notes.txt": "mine"}
NEW = {"images/a.png": "new a", "images/c.png": "new c", "sparse/0/cameras.bin": "new cams",
       "transforms.json": "new transforms", "poses_topview.png": "new top", "poses_report.md": "new report",
       MARKER: ""}
AFTER = {"images": "dir", "images/a.png": "new a", "images/c.png": "new c", "sparse": "dir", "sparse/0": "dir",
         "sparse/0/cameras.bin": "new cams", "transforms.json": "new transforms", "poses_topview.png": "new top",
         "poses_report.md": "new report", MARKER: "", "notes.txt": "mine"}


def test_move_into_place_into_no_folder_is_one_rename(tmp_path, monkeypatch):
    out = tmp_path / "data"
    stage = poses.make_stage(out)
    _write(stage, NEW)
    moved, real = [], staging.move
    monkeypatch.setattr(staging, "move", lambda src, dst: moved.append(dst))
    poses.move_into_place(stage, out)
    assert moved == [] and not stage.exists()
    monkeypatch.setattr(staging, "move", real)
    assert _tree(out) == {k: v for k, v in AFTER.items() if k != "notes.txt"}       # OWNER gone, no COMPLETE
    # a staging folder without OWNER (made by hand) moves in as well, into no folder or a dataset
    for target in (tmp_path / "data2", out):
        stage = tmp_path / f".{target.name}.poses-hand"
        _write(stage, {"transforms.json": "by hand"})
        poses.move_into_place(stage, target)
        assert (target / "transforms.json").read_text() == "by hand" and not stage.exists()


def test_move_into_place_swaps_entry_by_entry_transforms_last(tmp_path, monkeypatch):
    """Into an old dataset: COMPLETE (the staged names, in output order) written before the
    first rename, the old outputs and stale mask outputs retired to `.data.old-XXXX` (the
    stage's XXXX), the new ones moved in, transforms.json last; the user's file stays."""
    out = tmp_path / "data"
    _write(out, OLD)
    stage = poses.make_stage(out)
    _write(stage, NEW)
    suffix = stage.name[len(".data.poses-"):]
    real, moves, seen = staging.move, [], []

    def recording(src, dst):
        if not moves:
            seen.append(((stage / "COMPLETE").read_text(), (stage / "OWNER").exists()))
        moves.append((src.parent.name, dst.parent.name, dst.name))
        real(src, dst)

    monkeypatch.setattr(staging, "move", recording)
    poses.move_into_place(stage, out)
    assert seen == [("images\nsparse\ntransforms.json\nposes_topview.png\nposes_report.md\n" + MARKER + "\n", False)]
    retired, st = f".data.old-{suffix}", stage.name
    assert moves == [("data", retired, "images"), (st, "data", "images"), ("data", retired, "sparse"),
                     (st, "data", "sparse"), (st, "data", "poses_topview.png"),
                     ("data", retired, "poses_report.md"), (st, "data", "poses_report.md"),
                     ("data", retired, MARKER), (st, "data", MARKER),
                     ("data", retired, "masks"), ("data", retired, "dpt_depth"),
                     (st, "data", "transforms.json")]
    assert _tree(out) == AFTER
    assert _hidden(tmp_path) == []


def _kill_after_one_move(monkeypatch):
    """staging.move does its first rename and then the process is 'killed' (Killed raised);
    returns the real move, to put back."""
    real = staging.move

    def once(src, dst):
        real(src, dst)
        raise Killed()

    monkeypatch.setattr(staging, "move", once)
    return real


def test_move_into_place_stopped_leaves_the_retired_folder_named_after_the_stage(tmp_path, monkeypatch):
    out = tmp_path / "data"
    _write(out, OLD)
    stage = poses.make_stage(out)
    _write(stage, {k: v for k, v in NEW.items() if k != "poses_topview.png"})
    real = _kill_after_one_move(monkeypatch)
    with pytest.raises(Killed):
        poses.move_into_place(stage, out)
    suffix = stage.name[len(".data.poses-"):]
    assert _hidden(tmp_path) == sorted([stage.name, f".data.old-{suffix}"])
    assert (stage / "COMPLETE").read_text() == f"images\nsparse\ntransforms.json\nposes_report.md\n{MARKER}\n"
    assert not (stage / "OWNER").exists()
    monkeypatch.setattr(staging, "move", real)
    assert poses.recover(out) == "rolled forward"
    assert _tree(out) == {k: v for k, v in AFTER.items() if k != "poses_topview.png"}
    assert _hidden(tmp_path) == []


def test_recover_rolls_a_complete_stage_forward_even_without_the_folder(tmp_path, monkeypatch):
    """A committed staging folder whose swap had not started, the dataset folder itself gone:
    the folder is made and the staged outputs (COMPLETE's list only) moved in; a stopped
    recovery retires into `.data.old-XXXX` of the stage's XXXX."""
    stage = tmp_path / ".data.poses-k3y"
    _write(stage, {**NEW, "junk.txt": "not staged"})
    staging.write_complete(stage, "COMPLETE", ["images", "transforms.json", MARKER])
    assert poses.recover(tmp_path / "data") == "rolled forward"
    assert _tree(tmp_path / "data") == {"images": "dir", "images/a.png": "new a", "images/c.png": "new c",
                                        "transforms.json": "new transforms", MARKER: ""}
    assert _hidden(tmp_path) == []
    # stopped after its first rename: the old images retired under the stage's key
    _write(tmp_path / "data2", OLD)
    stage = tmp_path / ".data2.poses-k3y"
    _write(stage, NEW)
    staging.write_complete(stage, "COMPLETE", ["images", "sparse", "transforms.json"])
    _kill_after_one_move(monkeypatch)
    with pytest.raises(Killed):
        poses.recover(tmp_path / "data2")
    assert _hidden(tmp_path) == [".data2.old-k3y", ".data2.poses-k3y"]
    assert (tmp_path / ".data2.old-k3y" / "images" / "a.png").read_text() == "old a"


def test_recover_says_what_it_did_and_leaves_a_live_owners_stage(tmp_path):
    out = tmp_path / "d"
    _write(out, {"transforms.json": "old", "notes.txt": "mine"})
    assert poses.recover(out) is None
    assert poses.recover(tmp_path / "nowhere" / "d") is None
    host = socket.gethostname()
    # a dead run's stage and a retired folder: cleaned; a live process's (this one's parent, and
    # one of another host): left alone
    _write(tmp_path / ".d.poses-dead", {"_work/a.png": "copy", "OWNER": f"{host} 999999999\n"})
    _write(tmp_path / ".d.poses-live", {"_work/a.png": "copy", "OWNER": f"{host} {os.getppid()}\n"})
    _write(tmp_path / ".d.poses-away", {"_work/a.png": "copy", "OWNER": "another-host 12\n"})
    _write(tmp_path / ".d.poses-noowner", {"_work/a.png": "copy"})
    _write(tmp_path / ".d.old-gone", {"images/a.png": "old"})
    assert poses.recover(out) == "cleaned"
    assert _hidden(tmp_path) == [".d.poses-away", ".d.poses-live"]
    assert _tree(out) == {"transforms.json": "old", "notes.txt": "mine"}
    _write(tmp_path / ".d.old-gone", {"images/a.png": "old"})
    assert poses.recover(out) == "cleaned"                      # a retired folder alone
    assert _hidden(tmp_path) == [".d.poses-away", ".d.poses-live"]


@pytest.mark.parametrize("dead, complete", [(".d.poses-a", ".d.poses-b"), (".d.poses-b", ".d.poses-a")])
def test_recover_rolled_forward_wins_over_cleaned_in_either_order(tmp_path, dead, complete):
    out = tmp_path / "d"
    _write(out, {"transforms.json": "old"})
    _write(tmp_path / dead, {"_work/a.png": "copy", "OWNER": f"{socket.gethostname()} 999999999\n"})
    _write(tmp_path / complete, {"transforms.json": "new"})
    staging.write_complete(tmp_path / complete, "COMPLETE", ["transforms.json"])
    assert poses.recover(out) == "rolled forward"
    assert _tree(out) == {"transforms.json": "new"} and _hidden(tmp_path) == []


def test_two_recovers_at_once_pass_over_what_the_other_removed(tmp_path, monkeypatch):
    """`train` and `poses` started together on one dataset both run `recover`: a dead run's
    staging folder or a retired folder the other removed between the listing and the removal
    is passed over, not an error."""
    import shutil

    out = tmp_path / "d"
    _write(out, {"transforms.json": "old"})
    _write(tmp_path / ".d.poses-dead", {"_work/a.png": "copy", "OWNER": f"{socket.gethostname()} 999999999\n"})
    _write(tmp_path / ".d.old-gone", {"images/a.png": "old"})
    real = poses._siblings

    def listed_then_removed(folder, tag):
        found = real(folder, tag)
        for path in found:
            shutil.rmtree(path)                                  # the other process, just after the listing
        return found

    monkeypatch.setattr(poses, "_siblings", listed_then_removed)
    monkeypatch.setattr(staging, "owner_alive", lambda stage: False)
    assert poses.recover(out) == "cleaned"
    assert _hidden(tmp_path) == [] and _tree(out) == {"transforms.json": "old"}
