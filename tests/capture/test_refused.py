"""A refused `poses` run keeps its reconstruction beside DATA_DIR (capture/refused.py), and the
same run with `accept_few_cameras` writes the dataset from it without running COLMAP again.

COLMAP is the stand-in of tests/capture/test_poses_from_images.py (a hand-written model of 9
ring cameras of 13 photos, one turned so the vetting leaves it out: 8 of 13 kept, 62 %, under
the camera-set rule's 75 %); the expected datasets are those of a fresh run with the flag.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from jaxnerf_grid.capture import poses, refused
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError
from tests.capture.test_poses_from_images import _Colmap, _scene

pycolmap = pytest.importorskip("pycolmap")


def _refused_run(tmp_path, monkeypatch):
    """The scene, the stand-in COLMAP and the refusal's message of a first run on tmp_path/data."""
    photos, model_dir, _ = _scene(tmp_path, registered=9, photos=13, turned=(5,))
    colmap = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", colmap)
    with pytest.raises(DataError) as err:
        poses.poses_from_images(photos, tmp_path / "data", progress=False)
    return photos, model_dir, colmap, str(err.value)


def test_a_refused_run_keeps_its_reconstruction_and_a_report_naming_the_photos_left_out(tmp_path, monkeypatch):
    photos, _, colmap, message = _refused_run(tmp_path, monkeypatch)
    kept = tmp_path / "data.refused"
    assert message == (f"{photos}: only 8 of 13 photos kept (62 %; training needs 10, 75%); not written (a NeRF "
                       "trained on them renders the rest as a ghost); which photos and why: "
                       f"{kept / 'poses_report.md'}; accept_few_cameras=True writes it anyway, reusing this run's "
                       "reconstruction (docs/POSES.md)")
    assert not (tmp_path / "data").exists() and len(colmap.calls) == 1
    assert sorted(p.name for p in kept.iterdir()) == [refused.MARKER, "model", "poses_report.md",
                                                      "poses_topview.png", "run.json"]
    report = (kept / "poses_report.md").read_text()
    assert report.startswith("**Refused: only 8 of 13 photos kept")
    assert "left out by the vetting (1; " in report and "v05.png (" in report
    assert "not registered (4): v09.png, v10.png, v11.png, v12.png" in report
    model = pycolmap.Reconstruction(str(kept / "model"))
    assert model.num_reg_images() == 9   # as COLMAP returned it, the photo the vetting left out included


def test_the_same_run_with_the_flag_writes_the_fresh_runs_dataset_without_colmap(tmp_path, monkeypatch):
    photos, model_dir, colmap, _ = _refused_run(tmp_path, monkeypatch)
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False, accept_few_cameras=True)
    assert len(colmap.calls) == 1 and summary["reconstruction_reused"] is True
    assert not (tmp_path / "data.refused").exists()
    assert "features" not in summary["timings_s"]

    fresh_colmap = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", fresh_colmap)
    fresh = poses.poses_from_images(photos, tmp_path / "fresh", progress=False, accept_few_cameras=True)
    assert len(fresh_colmap.calls) == 1 and fresh["reconstruction_reused"] is False
    got, want = (io.read_json(tmp_path / d / "transforms.json") for d in ("data", "fresh"))
    assert [f["file_path"] for f in got["frames"]] == [f["file_path"] for f in want["frames"]]
    np.testing.assert_allclose([f["transform_matrix"] for f in got["frames"]],
                               [f["transform_matrix"] for f in want["frames"]], atol=1e-9)
    assert (summary["in_dataset"], summary["vetting"]["left_out"]) == (fresh["in_dataset"], ["v05.png"])
    assert "features, matching and mapping: taken from the refused run" in (tmp_path / "data" /
                                                                           "poses_report.md").read_text()


@pytest.mark.parametrize("change", ["photo touched", "other option"])
def test_a_changed_photo_or_option_runs_colmap_again(tmp_path, monkeypatch, change):
    photos, _, colmap, _ = _refused_run(tmp_path, monkeypatch)
    options = {"accept_few_cameras": True}
    if change == "photo touched":
        stat = (photos / "v03.png").stat()
        os.utime(photos / "v03.png", ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    else:
        options["feature_side"] = 800
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False, **options)
    assert len(colmap.calls) == 2 and summary["reconstruction_reused"] is False
    assert not (tmp_path / "data.refused").exists()   # a dataset written: the stale reconstruction goes


def test_run_key_follows_the_photos_and_the_options(tmp_path):
    for name, data in (("a.png", b"123"), ("b.png", b"4567")):
        (tmp_path / name).write_bytes(data)
    photos = [tmp_path / "a.png", tmp_path / "b.png"]
    key = refused.run_key(photos, {"matcher": "exhaustive", "priors": {"a.png": [1.0, 2.0, 3.0]}})
    assert key == refused.run_key(photos, {"priors": {"a.png": [1.0, 2.0, 3.0]}, "matcher": "exhaustive"})
    assert key != refused.run_key(photos, {"matcher": "exhaustive", "priors": {"a.png": [1.0, 2.0, 3.5]}})
    assert key != refused.run_key(photos[:1], {"matcher": "exhaustive", "priors": {"a.png": [1.0, 2.0, 3.0]}})
    (tmp_path / "b.png").write_bytes(b"4568")   # the same size: the modification time tells
    os.utime(tmp_path / "b.png", ns=(0, 10**18))
    assert key != refused.run_key(photos, {"matcher": "exhaustive", "priors": {"a.png": [1.0, 2.0, 3.0]}})


def test_a_users_folder_of_that_name_is_neither_read_nor_removed(tmp_path, monkeypatch):
    photos, model_dir, _ = _scene(tmp_path, registered=9, photos=13, turned=(5,))
    users = tmp_path / "data.refused"
    users.mkdir()
    (users / "run.json").write_text('{"key": "anything"}')
    colmap = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", colmap)
    poses.poses_from_images(photos, tmp_path / "data", progress=False, accept_few_cameras=True)
    assert len(colmap.calls) == 1 and (users / "run.json").read_text() == '{"key": "anything"}'
