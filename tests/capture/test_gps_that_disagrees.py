"""GPS that disagrees with the photos' reconstruction (half the registered photos or more over
9 m from their fixes: a camera's receiver that lags or drifts) is not allowed to throw the
photos out: `poses` maps again without the GPS priors and, when the GPS still disagrees,
georeferences without it (units unknown), keeping every photo the vetting keeps.

COLMAP is the stand-in of tests/capture/test_poses_from_images.py (a hand-written model of 12
ring cameras of 13 photos, v05 turned so the vetting leaves it out); the second mapping and the
alignment are stand-ins that record how they were called.
"""

from __future__ import annotations

import numpy as np
import pytest

from jaxnerf_grid.capture import georef, gps, poses
from jaxnerf_grid.util.io import DataError
from tests.capture.test_poses_from_images import _Colmap, _scene

pycolmap = pytest.importorskip("pycolmap")

NAMES = [f"v{k:02d}.png" for k in range(13)]


class _Stand:
    """The GPS fixes (100 m apart, or all at one spot), the second mapping (the same model) and
    the alignment: with GPS, all but the first 3 registered photos 50 m from their fixes, or after
    the second mapping none when `agrees_after`; without GPS, no residuals."""

    def __init__(self, monkeypatch, model_dir, *, spread=True, agrees_after=False):
        self.model_dir, self.agrees_after, self.remaps, self.aligned = model_dir, agrees_after, [], []
        fixes = {n: {"latitude": 47.0 + (0.0009 * k if spread else 0.0), "longitude": 8.0, "altitude": 400.0}
                 for k, n in enumerate(NAMES)}
        monkeypatch.setattr(gps, "positions_of", lambda records: fixes)
        monkeypatch.setattr(georef, "precheck_gps", lambda *args: None)
        monkeypatch.setattr(georef, "align_model", self.align)
        monkeypatch.setattr(poses, "map_photos", self.map_photos)

    def map_photos(self, module, database, photo_dir, total, work_dir, **kwargs):
        self.remaps.append({"total": total, "folder": work_dir.name, **kwargs})
        kwargs["timings"][kwargs["key"]] = 4.0
        return pycolmap.Reconstruction(self.model_dir), False, False, []

    def align(self, model, positions, **kwargs):
        regs = sorted(model.images[i].name for i in model.reg_image_ids())
        self.aligned.append((len(positions), kwargs.get("crs_name")))
        if not positions:
            return None, {"units": "unknown", "source": None}
        good = len(regs) if (self.agrees_after and self.remaps) else 3
        rows = [{"name": n, "error": 2.0 if k < good else 50.0, "horizontal": 1.0, "inlier": k < good}
                for k, n in enumerate(regs)]
        return None, {"units": "unknown", "source": "gps", "gps": {"residuals": rows}}


def test_gps_that_still_disagrees_after_mapping_without_it_is_left_out_of_the_georeference(tmp_path, monkeypatch):
    """8 of the 12 registered photos far from their fixes (the 11 the vetting keeps are aligned,
    3 of them near): mapped again without priors (the same model: still 8 far), then aligned
    without GPS. The 11 photos the vetting keeps are
    written, not 3; the report says what happened."""
    photos, model_dir, _ = _scene(tmp_path, registered=12, photos=13, turned=(5,))
    stand = _Stand(monkeypatch, model_dir)
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False)
    assert [(r["total"], r["folder"], r["priors"], r["key"]) for r in stand.remaps] == [
        (13, "without_gps", False, "mapping_without_gps")]
    assert stand.aligned == [(13, None), (13, None), (0, None)]
    assert (summary["in_dataset"], summary["vetting"]["left_out"]) == (11, ["v05.png"])
    assert summary["gps_disagreed"] == {"far": 8, "registered": 12, "stopped_early": False, "remapped": True,
                                        "far_after": 8, "georeference": "without the GPS"}
    assert summary["georeference"]["gps_ignored"] == (
        "the GPS disagrees with the photos' reconstruction (8 of 12 registered photos more than 9 m from their "
        "fixes): a receiver that lags or drifts, or photos registered in the wrong place")
    assert summary["timings_s"]["mapping_without_gps"] == 4.0 and summary["gps_priors"] == 0
    report = (tmp_path / "data" / "poses_report.md").read_text()
    assert ("the GPS disagreed with the reconstruction (8 of 12 registered photos over 9 m from their fixes): mapped "
            "again without the GPS priors, then 8 over; scale and georeference without the GPS") in report
    assert "Units unknown: the GPS disagrees with the photos' reconstruction" in report


def test_gps_that_agrees_with_the_model_mapped_without_it_keeps_the_georeference(tmp_path, monkeypatch):
    photos, model_dir, _ = _scene(tmp_path, registered=12, photos=13, turned=(5,))
    stand = _Stand(monkeypatch, model_dir, agrees_after=True)
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False, crs="EPSG:2056")
    assert len(stand.remaps) == 1 and stand.aligned == [(13, "EPSG:2056"), (13, "EPSG:2056")]
    assert summary["gps_disagreed"] == {"far": 8, "registered": 12, "stopped_early": False, "remapped": True,
                                        "far_after": 0, "georeference": "GPS"}
    assert summary["in_dataset"] == 11 and "gps_ignored" not in summary["georeference"]


def test_gps_too_close_together_to_be_priors_is_not_mapped_again_but_left_out_of_the_georeference(
        tmp_path, monkeypatch):
    photos, model_dir, _ = _scene(tmp_path, registered=12, photos=13, turned=(5,))
    stand = _Stand(monkeypatch, model_dir, spread=False)
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False)
    assert stand.remaps == [] and stand.aligned == [(13, None), (0, None)]
    assert summary["gps_disagreed"] == {"far": 8, "registered": 12, "stopped_early": False, "remapped": False,
                                        "far_after": 8, "georeference": "without the GPS"}
    assert summary["in_dataset"] == 11


def test_a_refused_run_mapped_without_the_gps_is_reused_without_mapping_again(tmp_path, monkeypatch):
    """9 of 13 registered, v05 left out: 8 kept, refused after the second mapping; the run with
    accept_few_cameras takes that model and maps nothing again."""
    photos, model_dir, _ = _scene(tmp_path, registered=9, photos=13, turned=(5,))
    stand = _Stand(monkeypatch, model_dir)
    colmap = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", colmap)
    with pytest.raises(DataError, match="only 8 of 13 photos kept"):
        poses.poses_from_images(photos, tmp_path / "data", progress=False)
    assert len(stand.remaps) == 1
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False, accept_few_cameras=True)
    assert len(colmap.calls) == 1 and len(stand.remaps) == 1 and summary["reconstruction_reused"]
    assert summary["gps_disagreed"] == {"far": 5, "registered": 9, "stopped_early": False, "remapped": True,
                                        "far_after": 5, "georeference": "without the GPS"}
    assert summary["gps_priors"] == 0   # the model was mapped without them
    assert summary["in_dataset"] == 8


def test_gps_that_still_disagrees_with_a_crs_asked_is_a_one_line_error_naming_it(tmp_path, monkeypatch):
    photos, model_dir, _ = _scene(tmp_path, registered=12, photos=13, turned=(5,))
    _Stand(monkeypatch, model_dir)
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    with pytest.raises(DataError) as err:
        poses.poses_from_images(photos, tmp_path / "data", progress=False, crs="EPSG:2056")
    assert str(err.value) == (f"{photos}: poses.crs = EPSG:2056: the GPS disagrees with the photos' reconstruction "
                              "(8 of 12 registered photos more than 9 m from their fixes): a receiver that lags or "
                              "drifts, or photos registered in the wrong place; ground control points (poses.gcp) "
                              "place the model in the CRS without it")
    assert not (tmp_path / "data").exists()


class _StoppedColmap(_Colmap):
    """`run_colmap` whose mapping with the priors was stopped by its watch (6 of the first 10 placed
    photos far from their fixes) and which mapped without them: the watch says so."""

    def __call__(self, module, photo_dir, names, work_dir, **kwargs):
        kwargs["watch"].stopped = {"far": 6, "placed": 10}
        return super().__call__(module, photo_dir, names, work_dir, **kwargs)


@pytest.mark.parametrize("agrees_after", [False, True])
def test_a_mapping_stopped_as_it_grew_is_not_mapped_again_and_the_report_says_where_it_stopped(
        tmp_path, monkeypatch, agrees_after):
    """The watch stopped the mapping with the priors at 10 photos: the model mapped without them is
    judged once (no second mapping here); still disagreeing (8 far) it is georeferenced without the
    GPS, agreeing it keeps the GPS; the summary and the report say where the mapping stopped."""
    photos, model_dir, _ = _scene(tmp_path, registered=12, photos=13, turned=(5,))
    stand = _Stand(monkeypatch, model_dir)
    stand.agrees_after = agrees_after
    if agrees_after:
        stand.remaps.append("stopped")   # the stand-in's alignment agrees once a mapping without the GPS ran
    colmap = _StoppedColmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", colmap)
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False)
    assert colmap.calls[0]["watch"].fixes.keys() == set(NAMES)
    assert stand.remaps == (["stopped"] if agrees_after else [])
    assert summary["gps_disagreed"] == {"far": 6, "registered": 10, "stopped_early": True, "remapped": True,
                                        "far_after": 0 if agrees_after else 8,
                                        "georeference": "GPS" if agrees_after else "without the GPS"}
    assert summary["gps_priors"] == 0 and summary["in_dataset"] == 11
    report = (tmp_path / "data" / "poses_report.md").read_text()
    assert ("the GPS disagreed with the reconstruction as it grew (6 of 10 photos placed over 9 m from their fixes): "
            "the mapping with the GPS priors stopped there, mapped again without the GPS priors, then "
            f"{0 if agrees_after else 8} over; scale and georeference "
            f"{'from' if agrees_after else 'without'} the GPS") in report


def test_keep_all_maps_with_the_gps_priors_unwatched(tmp_path, monkeypatch):
    photos, model_dir, _ = _scene(tmp_path, registered=12, photos=13, turned=(5,))
    _Stand(monkeypatch, model_dir)
    colmap = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", colmap)
    poses.poses_from_images(photos, tmp_path / "data", progress=False, keep_all=True)
    assert colmap.calls[0]["watch"] is None and colmap.calls[0]["priors"]


def test_gps_of_larger_photos_stays_out_of_the_mapping_and_a_disagreement_maps_nothing_again(tmp_path, monkeypatch):
    """Photos over SMALL_SIDE (set to 50 px here; the photos are 80 x 60): the GPS fixes, 100 m
    apart, are handed on (the spatial matcher pairs by them) but neither watched nor in the
    mapping; when they disagree with the finished model nothing is mapped again, the model is
    georeferenced without them; the summary and the report say why the priors stayed out."""
    monkeypatch.setattr(poses, "SMALL_SIDE", 50)
    photos, model_dir, _ = _scene(tmp_path, registered=12, photos=13, turned=(5,))
    stand = _Stand(monkeypatch, model_dir)
    colmap = _Colmap(model_dir)
    monkeypatch.setattr(poses, "run_colmap", colmap)
    summary = poses.poses_from_images(photos, tmp_path / "data", progress=False)
    call = colmap.calls[0]
    assert call["watch"] is None and call["small_photos"] is False and len(call["priors"]) == 13
    assert stand.remaps == [] and stand.aligned == [(13, None), (0, None)]
    reason = ("photos over 50 px: their features tie the model, and the priors' bundle adjustments would double "
              "the mapping's time; the GPS aligns the finished model")
    assert summary["gps_priors"] == 0 and summary["gps_priors_skipped"] == reason
    assert summary["gps_disagreed"] == {"far": 8, "registered": 12, "stopped_early": False, "remapped": False,
                                        "far_after": 8, "georeference": "without the GPS"}
    report = (tmp_path / "data" / "poses_report.md").read_text()
    assert f"GPS as pose priors: not in the mapping ({reason})" in report.splitlines()


def test_the_cameras_far_from_their_fixes_are_judged_beside_the_fixes_in_local_metres(tmp_path, monkeypatch):
    """`poses` hands the GPS outlier test the photos' fixes in local metres (here 0.0009 degrees of
    latitude apart: about 100 m), so that a camera is judged beside its neighbours' residuals."""
    photos, model_dir, _ = _scene(tmp_path, registered=12, photos=13, turned=(5,))
    _Stand(monkeypatch, model_dir, agrees_after=True)
    monkeypatch.setattr(poses, "run_colmap", _Colmap(model_dir))
    handed = []
    judge = poses.gps_outliers
    monkeypatch.setattr(poses, "gps_outliers", lambda geo, fixes=None: handed.append(fixes) or judge(geo, fixes))
    poses.poses_from_images(photos, tmp_path / "data", progress=False)
    fixes = handed[0]
    assert sorted(fixes) == NAMES
    gaps = [float(np.linalg.norm(np.subtract(fixes[a], fixes[b]))) for a, b in zip(NAMES, NAMES[1:])]
    assert gaps == pytest.approx([100.1] * 12, abs=0.5)
