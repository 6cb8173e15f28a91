"""The GPS judged while the mapping with its priors grows (`capture.gps_watch`): the placed cameras
against their fixes, when the model is judged, and the stop; and through COLMAP itself, a mapping
whose fixes climb away from the photos stops once 10 photos are placed while one with the true
fixes maps to the end."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jaxnerf_grid.capture import gps_watch


def _ring(count: int, radius: float = 40.0, height: float = 20.0) -> tuple[list[str], np.ndarray]:
    """Level cameras (no roll) on a ring about the origin, each looking at it: names, c2w [N, 4, 4]
    (OpenGL axes: +y up in the image, looking along -z) in a z-up world of metres."""
    names, poses = [], []
    for k in range(count):
        angle = 2.0 * math.pi * k / count
        eye = np.array([radius * math.cos(angle), radius * math.sin(angle), height])
        back = eye / np.linalg.norm(eye)                  # the camera looks along -back, at the origin
        right = np.cross(np.array([0.0, 0.0, 1.0]), back)
        right /= np.linalg.norm(right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, eye
        names.append(f"p{k:02d}.jpg")
        poses.append(c2w)
    return names, np.stack(poses)


def _model_frame(poses: np.ndarray) -> np.ndarray:
    """The same cameras as a reconstruction holds them: scaled by 0.03, turned 70 degrees about an
    oblique axis and shifted (a similarity the fit must undo)."""
    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    angle = math.radians(70.0)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    turn = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    out = poses.copy()
    out[:, :3, :3] = turn @ poses[:, :3, :3]
    out[:, :3, 3] = 0.03 * poses[:, :3, 3] @ turn.T + np.array([5.0, -2.0, 7.0])
    return out


@pytest.mark.parametrize("moved", [0, 3, 6])
def test_far_from_fixes_counts_the_cameras_moved_off_their_fixes_whatever_the_models_frame(moved):
    """12 ring cameras in a turned, scaled, shifted frame; fixes are the true centres with `moved`
    of them 30 m off (horizontally, the fit turns about z only): exactly those are far."""
    names, poses = _ring(12)
    fixes = {n: poses[k, :3, 3].copy() for k, n in enumerate(names)}
    for k in range(moved):
        fixes[names[2 * k]] = fixes[names[2 * k]] + np.array([30.0, 0.0, 0.0])
    c2w = dict(zip(names, _model_frame(poses)))
    assert gps_watch.far_from_fixes(c2w, fixes) == (moved, 12)


def test_far_from_fixes_sees_a_climb_the_photos_do_not_show():
    """A receiver whose heights climb 4 m a photo round the ring: the cameras are level, the fit
    about z cannot tilt to follow, and half of them or more end up over 9 m off (no centre lands
    on the 9 m limit itself, where rounding would decide)."""
    names, poses = _ring(12)
    fixes = {n: poses[k, :3, 3] + np.array([0.0, 0.0, 4.0 * k]) for k, n in enumerate(names)}
    far, placed = gps_watch.far_from_fixes(dict(zip(names, _model_frame(poses))), fixes)
    assert placed == 12 and far >= 6
    assert gps_watch.gps_disagrees(far, placed) is not None


def test_far_from_fixes_counts_only_cameras_with_a_fix_and_fits_none_under_three():
    names, poses = _ring(12)
    c2w = dict(zip(names, _model_frame(poses)))
    fixes = {n: poses[k, :3, 3] for k, n in enumerate(names) if k < 5}
    assert gps_watch.far_from_fixes(c2w, fixes) == (0, 5)
    assert gps_watch.far_from_fixes(c2w, {n: np.zeros(3) + k for k, n in enumerate(names[:2])}) == (0, 2)


def test_gps_disagrees_from_half_the_photos():
    assert gps_watch.gps_disagrees(5, 11) is None
    assert gps_watch.gps_disagrees(6, 12) == ("the GPS disagrees with the photos' reconstruction (6 of 12 registered "
                                              "photos more than 9 m from their fixes): a receiver that lags or drifts, "
                                              "or photos registered in the wrong place")
    assert gps_watch.gps_disagrees(0, 0) is None


def test_the_watch_judges_from_ten_photos_and_stops_only_on_disagreement():
    names, poses = _ring(30)
    truth = {n: poses[k, :3, 3] for k, n in enumerate(names)}
    assert [gps_watch.MappingWatch.due(n) for n in (2, 9, 10, 11, 30)] == [False, False, True, True, True]
    c2w = dict(zip(names[:12], _model_frame(poses[:12])))
    watch = gps_watch.MappingWatch(truth)
    watch.check(c2w)                                        # the true fixes: no stop
    assert (watch.stopped, watch.checks) == (None, 1)
    off = {n: p + np.array([0.0, 40.0, 0.0]) if k % 2 else p for k, (n, p) in enumerate(truth.items())}
    watch = gps_watch.MappingWatch(off)
    with pytest.raises(gps_watch.GpsStopped, match=r"first 12 photos' reconstruction \(6 of them more than 9 m"):
        watch.check(c2w)
    assert watch.stopped == {"far": 6, "placed": 12}
    five = {n: p + np.array([0.0, 40.0, 0.0]) if k % 2 and k < 10 else p for k, (n, p) in enumerate(truth.items())}
    gps_watch.MappingWatch(five).check(c2w)                 # 5 of 12 far: under half, no stop


@pytest.mark.slow
def test_a_mapping_whose_fixes_climb_stops_at_ten_photos_and_the_true_fixes_map_to_the_end(tmp_path):
    """COLMAP on the generated orbit of the pose tests (16 photos); the mapping with a watch on the
    true centres (in metres: 20 m a unit) registers 15 or 16 and is never stopped; with fixes that
    climb 4 m a photo it stops at 10 placed photos and `run_colmap` maps them without the priors."""
    pycolmap = pytest.importorskip("pycolmap")
    from jaxnerf_grid.capture import poses
    from tests.capture.test_poses import _orbit, _write_photos

    photos = tmp_path / "photos"
    photos.mkdir()
    views = _orbit()
    names = _write_photos(photos, views)
    truth = {n: 20.0 * views[k, :3, 3] for k, n in enumerate(names)}
    climb = {n: p + np.array([0.0, 0.0, 4.0 * k]) for k, (n, p) in enumerate(truth.items())}
    assert poses.priors_hold(truth, small_photos=True)
    runs = {}
    for label, fixes in (("true", truth), ("climb", climb)):
        work = tmp_path / label
        work.mkdir()
        watch, timings = gps_watch.MappingWatch(fixes), {}
        model, _, _, _ = poses.run_colmap(pycolmap, photos, names, work, matcher="exhaustive",
                                       camera_model="SIMPLE_RADIAL", single_camera=True, show=False,
                                       timings=timings, priors=truth, watch=watch, small_photos=True)
        runs[label] = (model.num_reg_images(), watch.stopped, sorted(timings), (work / "without_gps").is_dir(),
                       watch.checks)
    registered, stopped, keys, remapped, checks = runs["true"]
    assert registered >= 15 and (stopped, keys, remapped) == (None, ["features", "mapping", "matching"], False)
    assert checks >= registered - 9                              # judged after each photo from the 10th
    registered, stopped, keys, remapped, _ = runs["climb"]
    assert registered >= 15 and stopped["placed"] == 10 and stopped["far"] >= 5
    assert "mapping_without_gps" in keys and remapped
