"""The too-few-cameras rule (`capture.camera_set`): arcs against closed forms, the rule at its
thresholds, and `poses` / `demo --data` refusing a thin camera set in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.capture.camera_set import (
    MIN_ARC_SHARE,
    MIN_KEPT_SHARE,
    arc_covered_deg,
    azimuths_deg,
    camera_set_record,
    camera_set_verdict,
    look_at_point,
)
from tests.support.cameras import look_at


def test_arc_covered_is_360_less_the_largest_gap():
    assert arc_covered_deg([0.0, 90.0, 180.0]) == pytest.approx(180.0)          # gap 180 from 180 round to 360
    assert arc_covered_deg([350.0, 10.0, 30.0]) == pytest.approx(40.0)          # across 0
    assert arc_covered_deg(np.arange(0.0, 360.0, 10.0)) == pytest.approx(350.0)
    assert arc_covered_deg([42.0]) == 0.0 and arc_covered_deg([]) == 0.0


def test_azimuths_and_the_looked_at_point_of_a_ring():
    """Cameras on a ring of radius 5 about (1, 2, 3), at 0, 90 and 225 degrees, 2 m above it, all
    looking at it: the point nearest their axes is (1, 2, 3), their azimuths the ring's."""
    target = np.array([1.0, 2.0, 3.0])
    angles = np.radians([0.0, 90.0, 225.0])
    eyes = target + np.stack([5 * np.cos(angles), 5 * np.sin(angles), np.full(3, 2.0)], -1)
    c2w = np.stack([look_at(e, target) for e in eyes])
    assert np.allclose(look_at_point(c2w), target, atol=1e-9)
    assert np.allclose(azimuths_deg(eyes, target), [0.0, 90.0, 225.0])


@pytest.mark.parametrize("kept, ok", [(27, True), (26, False)])
def test_kept_share_at_its_threshold(kept, ok):
    """36 photos: 27 kept is 75 % (enough), 26 is not; the reason names the counts."""
    assert MIN_KEPT_SHARE == 0.75
    verdict = camera_set_verdict(camera_set_record(36, kept, 300.0, 300.0, "gps"))
    assert (verdict is None) is ok
    if not ok:
        assert verdict.startswith("only 26 of 36 photos kept (72 %; training needs 27, 75%)")


@pytest.mark.parametrize("arc, ok", [(225.0, True), (224.9, False)])
def test_arc_share_at_its_threshold(arc, ok):
    """The flight covers 300 degrees: kept cameras over 225 (75 %) are enough, 224.9 are not."""
    assert MIN_ARC_SHARE == 0.75
    verdict = camera_set_verdict(camera_set_record(36, 36, arc, 300.0, "gps"))
    assert (verdict is None) is ok
    if not ok:
        assert "the 36 kept cameras cover 225 of the 300 degrees" in verdict and "GPS" in verdict


def _thin_dataset(folder, kept=16, photos=36, arc=160.0):
    """A transforms.json as `poses` writes it, its camera set thin (16 of 36 kept, 160 of 300
    degrees)."""
    folder.mkdir()
    record = dict(camera_set_record(photos, kept, arc, 300.0, "gps"), verdict="x", accepted=False)
    (folder / "transforms.json").write_text(json.dumps({"frames": [{"file_path": f"images/{k}.png"}
                                                                   for k in range(kept)],
                                                        "poses": {"camera_set": record}}))
    return folder


def test_demo_refuses_a_thin_poses_dataset_in_one_line(tmp_path, capsys):
    data = _thin_dataset(tmp_path / "data")
    code = cli.main(["demo", "--data", str(data), "--out", str(tmp_path / "run"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1, err
    assert "only 16 of 36 photos kept" in err and "--accept-few-cameras" in err
    assert not (tmp_path / "run" / "run").exists()


def test_demo_camera_line_says_how_many_photos_trained(tmp_path):
    from jaxnerf_grid.demo import check_camera_set

    data = _thin_dataset(tmp_path / "data")
    line = check_camera_set(data, accept_few_cameras=True)
    # 16 frames: every 8th (0, 8) tests, 14 train
    assert line.startswith("Cameras: 14 photos trained (2 held out for testing) of the 36 photos given to `poses` "
                           "(16 kept")
    assert "trained anyway" in line
    ok = _thin_dataset(tmp_path / "ok", kept=36, arc=290.0)
    assert "trained anyway" not in check_camera_set(ok)
    assert check_camera_set(tmp_path) is None                     # not a poses dataset: no rule



def test_a_camera_far_from_its_gps_fix_is_left_out():
    """The GPS residuals' outliers (more than 9 m after the alignment, `georef.INLIER_METRES`, on a
    receiver whose median residual is 3 m) are left out with the distance as the reason; inliers
    stay; no GPS, nothing."""
    from jaxnerf_grid.capture.poses import gps_off_count, gps_outliers, mark_left_out

    near = [{"name": f"n{k}.jpg", "error": e, "inlier": True} for k, e in enumerate((2.0, 2.5, 3.0, 3.5, 4.0))]
    geo = {"gps": {"residuals": [*near, {"name": "b.jpg", "error": 31.04, "inlier": False}]}}
    far = gps_outliers(geo)
    assert far == [("b.jpg", "31.0 m from its GPS position (more than 9 m)")]
    assert gps_off_count(geo) == 1
    rows = [{"name": "a.jpg", "kept": True, "reasons": []}, {"name": "b.jpg", "kept": True, "reasons": []}]
    mark_left_out(rows, far)
    assert rows == [{"name": "a.jpg", "kept": True, "reasons": []},
                    {"name": "b.jpg", "kept": False, "reasons": ["31.0 m from its GPS position (more than 9 m)"]}]
    assert gps_outliers({"units": "unknown"}) == [] and gps_off_count({"units": "unknown"}) == 0


def test_a_noisy_receivers_spread_leaves_no_camera_out_but_a_misplaced_one():
    """A receiver with a 5.5 m median residual (1 to 11 m, the alignment's 9 m leaving 4 outside):
    the limit is 2.5 medians, 13.75 m by hand, so those 4 stay and a camera 40 m off is left out;
    the alignment's outliers over 9 m still count 5 (for `gps_disagrees`)."""
    from jaxnerf_grid.capture.poses import gps_off_count, gps_outlier_metres, gps_outliers

    errors = [1.0, 2.0, 3.0, 4.0, 5.0, 5.0, 5.0, 6.0, 7.0, 9.5, 10.0, 10.5, 11.0, 40.0]
    assert gps_outlier_metres(errors) == 13.75
    geo = {"gps": {"residuals": [{"name": f"p{k:02d}.jpg", "error": e, "inlier": e <= 9.0}
                                 for k, e in enumerate(errors)]}}
    assert gps_outliers(geo) == [("p13.jpg", "40.0 m from its GPS position (more than 14 m)")]
    assert gps_off_count(geo) == 5
    assert gps_outlier_metres([2.0, 3.0, 3.0]) == 9.0 and gps_outlier_metres([]) == 9.0


def test_a_camera_as_far_from_its_fix_as_its_neighbours_stays_and_one_far_alone_is_left_out():
    """15 fixes 10 m apart on a line; photos 0-9 1 m off in height, photos 10-14 a receiver's
    drift (5, 8, 10, 12, 13 m in height), photo 4 placed 40 m off along x. The median residual is
    1 m, so the limit is 9 m: by distance alone photos 12-14 and 4 are over it. Against the median
    of the residuals of the 4 photos taken next (named in sequence; here also the nearest), by hand:
    photo 12 0 m (5, 8, 12, 13: 10), 13 3 m (9), 14 4 m (9), photo 4 40 m: only photo 4 is left out.
    """
    from jaxnerf_grid.capture.poses import gps_outlier_metres, gps_outliers, local_residuals

    heights = [1.0] * 10 + [5.0, 8.0, 10.0, 12.0, 13.0]
    rows = [{"name": f"p{k:02d}.jpg", "dx": 0.0, "dy": 0.0, "dz": h, "error": h, "inlier": h <= 9.0}
            for k, h in enumerate(heights)]
    rows[4].update(dx=40.0, dz=0.0, error=40.0, inlier=False)
    fixes = {row["name"]: [10.0 * k, 0.0, 0.0] for k, row in enumerate(rows)}
    geo = {"gps": {"residuals": rows}}
    limit = gps_outlier_metres([row["error"] for row in rows])
    assert limit == 9.0 and [r["name"] for r in rows if r["error"] > limit] == ["p04.jpg", "p12.jpg", "p13.jpg",
                                                                                 "p14.jpg"]
    assert gps_outliers(geo) == [("p04.jpg", "40.0 m from its GPS position (more than 9 m)")]   # named in sequence
    assert gps_outliers(geo, fixes) == [("p04.jpg", "40.0 m from its GPS position (more than 9 m)")]
    local = local_residuals(rows, fixes)
    assert local["p12.jpg"] == pytest.approx(0.0) and local["p13.jpg"] == pytest.approx(3.0)
    assert local["p14.jpg"] == pytest.approx(4.0) and local["p04.jpg"] == pytest.approx(np.hypot(40.0, 1.0))
    assert local_residuals(rows[:4], fixes) == {}           # too few photos to say where the receiver stood


def test_a_residual_is_set_beside_the_photos_taken_next_or_without_a_sequence_beside_the_nearest_fixes():
    """Six fixes: three on a line 100 m apart, then three back over them 1 m aside; the receiver
    10 m high on the second line. Photo 4 beside its 2 neighbours: named in sequence, photos 3 and
    5 (10 m high: 0 m apart); named out of sequence, the nearest fixes, photos 1 and 2 (0 m: 10 m)."""
    from jaxnerf_grid.capture.poses import local_residuals

    where = [(0.0, 0.0), (100.0, 0.0), (200.0, 0.0), (1.0, 1.0), (101.0, 1.0), (201.0, 1.0)]
    for names, expected in ((["p0", "p1", "p2", "p3", "p4", "p5"], 0.0), (["pa", "pb", "pc", "pd", "pe", "pf"], 10.0)):
        rows = [{"name": f"{n}.jpg", "dx": 0.0, "dy": 0.0, "dz": 10.0 if k >= 3 else 0.0} for k, n in enumerate(names)]
        fixes = {row["name"]: [x, y, 0.0] for row, (x, y) in zip(rows, where)}
        assert local_residuals(rows, fixes, neighbours=2)[rows[4]["name"]] == pytest.approx(expected), names
    assert local_residuals(rows, {}, neighbours=2) == {}     # out of sequence and no fixes: no neighbours


def test_the_gps_is_distrusted_when_half_the_registered_photos_or_more_are_far_from_their_fixes():
    """49 of 57 registered photos over 9 m from their GPS fixes (a camera's GPS that lagged and
    drifted 90 m in height): the reason names the count; exactly half still is distrust (5 of
    10); 4 of 10, or no photo registered, is not."""
    from jaxnerf_grid.capture.poses import gps_disagrees

    assert gps_disagrees(49, 57) == ("the GPS disagrees with the photos' reconstruction (49 of 57 registered photos "
                                     "more than 9 m from their fixes): a receiver that lags or drifts, "
                                     "or photos registered in the wrong place")
    assert gps_disagrees(5, 10) is not None
    assert gps_disagrees(4, 10) is None and gps_disagrees(0, 0) is None


def test_gps_places_cameras_only_when_its_error_is_small_against_the_capture():
    """A 4 m GPS RMS places cameras 60 m from the scene (4 < 60 / 4), not cameras 5 m from a tree
    (4 > 5 / 4); no GPS alignment, no placing."""
    from jaxnerf_grid.capture.poses import gps_places_cameras

    ring = np.stack([np.cos(np.linspace(0, 6, 8)), np.sin(np.linspace(0, 6, 8)), np.zeros(8)], -1)
    geo = {"units": "metres", "gps": {"rms_m": 4.0}}
    assert gps_places_cameras(geo, 60.0 * ring, np.zeros(3))
    assert not gps_places_cameras(geo, 5.0 * ring, np.zeros(3))
    assert not gps_places_cameras({"units": "unknown"}, 60.0 * ring, np.zeros(3))


def test_gps_priors_hold_only_over_a_wide_capture_of_small_photos():
    """GPS enters the mapping only when the positions spread over 30 m (their median distance
    from their mean) and the photos are small (at most 800 px): a 60 m orbit of small photos yes,
    of larger ones no, a 5 m walk round a tree no, none no; each no with its reason."""
    from jaxnerf_grid.capture.poses import priors_hold, priors_skipped

    ring = {f"p{k}": np.array([np.cos(a), np.sin(a), 0.0]) for k, a in enumerate(np.linspace(0, 6, 12))}
    wide, walk = ({k: r * v for k, v in ring.items()} for r in (60.0, 5.0))
    assert priors_hold(wide, True) and priors_skipped(wide, True) is None
    assert not priors_hold(wide, False)
    assert priors_skipped(wide, False).startswith("photos over 800 px: ")
    assert not priors_hold(walk, True)
    assert priors_skipped(walk, True).startswith("the GPS positions spread 5 m, under 30 m: ")
    assert not priors_hold({}, True) and priors_skipped({}, True) is None
