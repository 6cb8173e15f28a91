"""Camera vetting (data/vetting.py) on hand-made reconstructions: a ring of cameras looking at
points on a cylinder, observations made here by a plain pinhole projection loop. No COLMAP;
the vetting of a real COLMAP model is in tests/capture/test_poses.py."""

from __future__ import annotations

import numpy as np
import pytest

from jaxnerf_grid.capture import vetting

RING, NUM_CAMS, FOCAL = 5.0, 12, 300.0


def _world_to_camera(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV world-to-camera [3, 4] looking from eye at target (+z forward, +y down)."""
    eye = np.asarray(eye, float)
    f = np.asarray(target, float) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    rot = np.stack([r, d, f])
    return np.concatenate([rot, -(rot @ eye)[:, None]], 1)


def _turn(pose: np.ndarray, deg: float) -> np.ndarray:
    """The pose turned by `deg` about the camera's own vertical axis (centre kept)."""
    a = np.radians(deg)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    centre = -pose[:, :3].T @ pose[:, 3]
    rot = ry @ pose[:, :3]
    return np.concatenate([rot, -(rot @ centre)[:, None]], 1)


def _ring(seed=0):
    """12 cameras on a ring of radius 5 at height 0.5, 360 points on a cylinder of radius 1 (z in
    -1..1); each camera sees the points on the cylinder's side facing it (normal within 60 degrees
    of the direction to the camera). Returns vetting.Records with exact observations (+0.1 px noise)."""
    rng = np.random.default_rng(seed)
    phi = rng.uniform(0, 2 * np.pi, 360)
    xyz = np.stack([np.cos(phi), np.sin(phi), rng.uniform(-1, 1, 360)], 1)
    angles = 2 * np.pi * np.arange(NUM_CAMS) / NUM_CAMS
    eyes = np.stack([RING * np.cos(angles), RING * np.sin(angles), np.full(NUM_CAMS, 0.5)], 1)
    poses, index, observed = [], [], []
    for eye in eyes:
        pose = _world_to_camera(eye)
        to_cam = eye - xyz
        normal = np.stack([xyz[:, 0], xyz[:, 1], np.zeros(len(xyz))], 1)
        cos = np.einsum("ij,ij->i", normal, to_cam) / np.linalg.norm(to_cam, axis=1)
        seen = np.flatnonzero(cos > np.cos(np.radians(60)))
        uv = []
        for k in seen:  # the pinhole projection, one point at a time
            x, y, z = pose[:, :3] @ xyz[k] + pose[:, 3]
            uv.append([x / z + rng.normal(0, 0.1 / FOCAL), y / z + rng.normal(0, 0.1 / FOCAL)])
        poses.append(pose)
        index.append(seen)
        observed.append(np.array(uv))
    track = np.zeros(len(xyz))
    for seen in index:
        track[seen] += 1
    names = [f"cam_{i:02d}" for i in range(NUM_CAMS)]
    return vetting.Records(names, np.stack(poses), np.full(NUM_CAMS, FOCAL), index, observed, xyz, track)


def test_reprojection_errors_against_a_loop():
    rec = _ring()
    pose = _turn(rec.cam_from_world[2], 3.0)
    idx, uv = rec.point_index[2], rec.observed[2]
    got = vetting.reprojection_errors(pose, FOCAL, rec.xyz[idx], uv)
    for k, (i, obs) in enumerate(zip(idx, uv)):
        x, y, z = pose[:, :3] @ rec.xyz[i] + pose[:, 3]
        assert got[k] == pytest.approx(FOCAL * np.hypot(x / z - obs[0], y / z - obs[1]), rel=1e-9)
    behind = vetting.reprojection_errors(_turn(rec.cam_from_world[2], 180.0), FOCAL, rec.xyz[idx], uv)
    assert np.all(behind == vetting.BEHIND_PX)


def test_a_good_reconstruction_is_kept_whole():
    rows = vetting.vet(_ring())
    assert [r["kept"] for r in rows] == [True] * NUM_CAMS, [r["reasons"] for r in rows]
    for r in rows:
        assert r["reprojection_px"] < 0.3 and 60 < r["observations"] < 200
        assert 0.8 < r["neighbour_ratio"] < 1.25


def test_a_camera_turned_20_degrees_is_left_out():
    rec = _ring()
    rec.cam_from_world[4] = _turn(rec.cam_from_world[4], 20.0)
    rows = vetting.vet(rec)
    assert [r["name"] for r in rows if not r["kept"]] == ["cam_04"]
    # 20 degrees at a focal of 300 px: the points move by about 300 tan(20 deg) = 109 px
    assert 60 < rows[4]["reprojection_px"] < 200
    assert any("reprojection" in why for why in rows[4]["reasons"])


def test_a_camera_put_far_from_the_photos_it_shares_points_with_is_left_out():
    """Camera 7 moved 1.7 ring radii outwards: the nearest of its covisible cameras (6, 8 and then
    5, the lower of the tied 5 / 9) is 9.5 away instead of the usual 2 R sin 15 deg = 2.59 (ratio
    3.7)."""
    rec = _ring()
    eye = -rec.cam_from_world[7][:, :3].T @ rec.cam_from_world[7][:, 3]
    moved = eye * (1 + 1.7 * RING / np.linalg.norm(eye[:2]))
    moved[2] = eye[2]
    rec.cam_from_world[7] = _world_to_camera(moved)
    scores = vetting.photo_scores(rec)
    a7 = 2 * np.pi * 7 / NUM_CAMS
    neighbours = [2 * np.pi * j / NUM_CAMS for j in (6, 8, 5)]
    dist = sorted(np.hypot(moved[0] - RING * np.cos(b), moved[1] - RING * np.sin(b)) for b in neighbours)
    assert np.linalg.norm(moved[:2]) == pytest.approx(RING * 2.7) and a7 > 0
    assert scores["neighbour_ratio"][7] == pytest.approx(dist[0] / (2 * RING * np.sin(np.pi / NUM_CAMS)), rel=1e-6)
    why = vetting.failures(scores)
    assert any("usual distance" in w for w in why[7])
    assert all(not any("usual distance" in w for w in why[i]) for i in range(NUM_CAMS) if i != 7)


def test_a_photo_at_the_edge_of_a_gap_is_judged_by_its_nearest_best_shared_photo():
    """Ten photos 1 apart on a line; photo 0 stands at the edge of a gap, its best-shared photos
    (by shared points) are photo 1 beside it and photos 4 and 5 further along: 1, 4 and 5 away
    (the median, 4, would be 4 times the usual 1). Every other photo shares the most with its
    two neighbours and the next one on: nearest 1. Photo 9, sharing the most with photos 0-2
    (8 and 9 away, nearest 7), is a photo put in the wrong place."""
    centres = np.stack([np.arange(10.0), np.zeros(10), np.zeros(10)], 1)
    shared = np.zeros((10, 10))
    for i in range(1, 9):
        for j, count in ((i - 1, 50), (i + 1, 50), (min(i + 2, 9) if i < 8 else i - 2, 30)):
            shared[i, j] = shared[j, i] = count
    shared[0, :] = shared[:, 0] = 0
    for j, count in ((1, 60), (4, 50), (5, 40)):
        shared[0, j] = shared[j, 0] = count
    shared[9, :] = shared[:, 9] = 0
    for j, count in ((0, 60), (1, 50), (2, 40)):
        shared[9, j] = shared[j, 9] = count
    dist = vetting.neighbour_distances(centres, shared)
    assert dist[0] == 1.0 and dist[9] == 7.0
    assert np.all(dist[1:9] == 1.0)
    scores = {"observations": np.full(10, 200), "reprojection_px": np.full(10, 0.5),
              "track_length": np.full(10, 4.0), "neighbour_ratio": dist / np.median(dist), "covisible": np.full(10, 3)}
    why = vetting.failures(scores)
    assert [bool(w) for w in why] == [False] * 9 + [True]
    assert "7.0x the usual distance" in why[9][0]


def test_few_observations_and_short_tracks_are_left_out():
    rec = _ring()
    rec.point_index[1], rec.observed[1] = rec.point_index[1][:10], rec.observed[1][:10]
    rec.track_length[:] = 6.0                   # every point seen by 6 photos ...
    rec.track_length[rec.point_index[9]] = 2.0  # ... but camera 9's by 2: mean 2 < 0.5 x the median 6
    why = vetting.failures(vetting.photo_scores(rec))
    assert any("10 observations < 15" in w for w in why[1])
    assert any("track length" in w for w in why[9])


def test_failures_thresholds_on_hand_made_scores():
    """Each rule just inside and just outside its threshold (module docstring)."""
    n = 8
    scores = {"observations": np.array([200, 200, 200, 200, 200, 200, 20, 14]),
              "reprojection_px": np.array([0.5, 1.99, 2.01, 0.5, 0.5, 0.5, 0.5, 0.5]),
              "track_length": np.array([4.0, 4.0, 4.0, 2.01, 1.99, 4.0, 4.0, 4.0]),
              "neighbour_ratio": np.array([1.0, 1.0, 1.0, 1.0, 1.0, 3.1, 2.9, 1.0]),
              "covisible": np.full(8, 7)}                     # every photo equally tied: the weak rule is silent
    why = vetting.failures(scores)
    assert [bool(w) for w in why] == [False, False, True, False, True, True, False, True]
    assert len(why) == n
    # fewer than MIN_PHOTOS_FOR_LAYOUT photos: the layout rule is not applied
    few = {k: v[:4] for k, v in scores.items()}
    few["neighbour_ratio"] = np.array([1.0, 9.0, 1.0, 1.0])
    assert [bool(w) for w in vetting.failures(few)] == [False, False, True, False]


def test_format_table_lists_reasons():
    rec = _ring()
    rec.cam_from_world[4] = _turn(rec.cam_from_world[4], 20.0)
    lines = vetting.format_table(vetting.vet(rec))
    assert len(lines) == 2 + NUM_CAMS
    assert "| cam_04 |" in lines[6] and "| no | reprojection" in lines[6]


def test_a_weakly_tied_photo_is_left_out_and_a_line_end_kept():
    """The weakly-tied rule on hand-made scores, at its thresholds: a photo sharing points with
    fewer than 2/3 of the median photo's covisible photos *and* with fewer than a quarter of its
    observations is left out; either alone (the end of a straight flight line: half the
    neighbours, the usual points) is kept."""
    base = {"reprojection_px": np.full(8, 0.5), "track_length": np.full(8, 4.0), "neighbour_ratio": np.ones(8)}
    scores = {**base, "observations": np.array([200, 200, 200, 200, 200, 40, 49, 200]),
              "covisible": np.array([21, 21, 21, 21, 21, 8, 13, 10])}
    why = vetting.failures(scores)
    # median covisible 21 (bar 14), median observations 200 (bar 50)
    assert [bool(w) for w in why] == [False, False, False, False, False, True, True, False]
    assert "weakly tied: shares points with 8 photos (median 21) through 40 observations (median 200)" in why[5]
    edge = {**scores, "observations": np.array([200, 200, 200, 200, 200, 50, 49, 200]),
            "covisible": np.array([21, 21, 21, 21, 21, 8, 14, 9])}
    assert [bool(w) for w in vetting.failures(edge)] == [False] * 8   # 50 is not < 50; 14 is not < 14


def test_covisible_counts_the_photos_sharing_a_point():
    """photo_scores' covisible against a loop over pairs of the ring's cameras."""
    rec = _ring()
    got = vetting.photo_scores(rec)["covisible"]
    sets = [set(np.asarray(i).tolist()) for i in rec.point_index]
    want = [sum(1 for j in range(NUM_CAMS) if j != i and sets[i] & sets[j]) for i in range(NUM_CAMS)]
    np.testing.assert_array_equal(got, want)
    rows = vetting.vet(rec)
    assert [r["covisible"] for r in rows] == want
    assert "covisible photos" in vetting.format_table(rows)[0]


def test_viewing_depths_are_each_photos_median_point_depth():
    """A camera at the origin looking along +z sees points at depths 2, 3 and 10 (median 3); the
    same camera moved 1 back along its axis sees them at 3, 4 and 11 (median 4); one that sees
    no point has NaN."""
    pose = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)
    back = np.concatenate([np.eye(3), np.array([[0.0], [0.0], [1.0]])], 1)   # centre (0, 0, -1)
    xyz = np.array([[0.1, 0.0, 2.0], [0.0, -0.2, 3.0], [1.0, 1.0, 10.0]])
    depths = vetting.viewing_depths(np.stack([pose, back, pose]), [np.arange(3), np.array([2, 0, 1]), []], xyz)
    np.testing.assert_allclose(depths[:2], [3.0, 4.0])
    assert np.isnan(depths[2])


def _panning_capture(wrong: int | None = None):
    """A video's frames: 8 frames panning in place (centres 1 mm apart, turning 10 degrees a frame)
    then 4 walking 0.3 m a frame, all looking outwards at points on a sphere of radius 5 about the
    origin; each sees the points within 35 degrees of its axis. Frame `wrong` is put 3 m to the
    side. Returns vetting.Records with exact observations."""
    rng = np.random.default_rng(1)
    v = rng.normal(size=(3000, 3))
    v[:, 2] *= 0.2
    xyz = 5.0 * v / np.linalg.norm(v, axis=1, keepdims=True)
    centres = [np.array([0.001 * i, 0.0, 0.0]) for i in range(8)] + \
        [np.array([0.3 * (i - 7), 0.0, 0.0]) for i in range(8, 12)]
    yaws = [np.radians(10.0 * i) for i in range(12)]
    poses, index, observed = [], [], []
    for i, (c, yaw) in enumerate(zip(centres, yaws)):
        look = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        seen = np.flatnonzero((xyz - c) @ look / np.linalg.norm(xyz - c, axis=1) > np.cos(np.radians(35)))
        if i == wrong:
            c = c + np.array([0.0, 3.0, 0.0])
        pose = _world_to_camera(c, c + look)
        cam = xyz[seen] @ pose[:, :3].T + pose[:, 3]
        poses.append(pose)
        index.append(seen)
        observed.append(cam[:, :2] / cam[:, 2:])
    track = np.zeros(len(xyz))
    for seen in index:
        track[seen] += 1
    return vetting.Records([f"frame_{i:02d}" for i in range(12)], np.stack(poses), np.full(12, FOCAL), index,
                           observed, xyz, track)


def test_frames_a_few_millimetres_apart_do_not_make_walking_frames_look_misplaced(monkeypatch):
    """The usual neighbour distance of a panning video is a millimetre; the walking frames'
    0.3-0.6 m is compared with the floor, a tenth of the ~5 m viewing depth, and every frame is
    kept (with no floor they are hundreds of times the usual distance); a frame put 3 m to the
    side is still left out (its neighbours ~3 m away: ratio ~6)."""
    scores = vetting.photo_scores(_panning_capture())
    depth = float(np.nanmedian(vetting.viewing_depths(*_arrays(_panning_capture()))))
    assert 4.5 < depth < 5.5
    assert np.nanmax(scores["neighbour_ratio"]) < 0.65 / (0.1 * depth)
    assert all(not why for why in vetting.failures(scores))
    wrong = vetting.failures(vetting.photo_scores(_panning_capture(wrong=5)))
    assert any("usual distance" in w for w in wrong[5])
    assert [i for i, why in enumerate(wrong) if any("usual distance" in w for w in why)] == [5]
    monkeypatch.setattr(vetting, "NEIGHBOUR_DEPTH_FLOOR", 0.0)
    assert np.nanmax(vetting.photo_scores(_panning_capture())["neighbour_ratio"]) > 100


def _arrays(rec):
    return rec.cam_from_world, rec.point_index, rec.xyz
