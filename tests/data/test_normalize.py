"""The normalisation's rules where the block tests left them open (the survivors of
mutmut's run on data/normalize.py, docs/TESTING.md): the orbit's region of interest when its cap
decides, far from the origin, below one unit, for one point or none; forward-facing captures;
the shape checks; z_up_normalization's two paths; check_rotation's tolerance. Each expected value
is computed here from the scene as built (the orbit's target, the points' distances to it), not
from the code under test.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxnerf_grid.data import normalize
from jaxnerf_grid.util.io import DataError
from tests.support.cameras import look_at

CENTRE = np.array([100.0, -50.0, 20.0])


def _orbit(radius, centre=CENTRE, n=8, height=0.3) -> np.ndarray:
    """[n, 4, 4] cameras on a ring of `radius` around `centre`, `height` above it, looking at it."""
    angles = 2 * np.pi * (np.arange(n) + 0.25) / n
    eyes = centre + np.column_stack([radius * np.cos(angles), radius * np.sin(angles), np.full(n, height)])
    return np.stack([look_at(e, centre) for e in eyes])


def _shell(distances, centre=CENTRE, seed=0) -> np.ndarray:
    """Points at the given distances from centre, in random directions. [P, 3]."""
    d = np.random.default_rng(seed).normal(size=(len(distances), 3))
    return centre + d / np.linalg.norm(d, axis=1, keepdims=True) * np.asarray(distances)[:, None]


def test_orbit_roi_far_from_the_origin_with_its_cap_deciding_below_one_unit():
    """A ring 0.9 units around a centre 100 m from the origin: cap = 0.9 / 3 (the median camera
    distance is sqrt(0.9^2 + 0.3^2)); points 0.5 away (the cap decides, radius < 1), then points
    0.05-0.2 away (their 95th percentile decides, measured from the centre, not the origin)."""
    c2w = _orbit(0.9)
    cap = np.hypot(0.9, 0.3) / 3
    centre, radius = normalize.orbit_roi(c2w, _shell(np.full(50, 0.5)))
    np.testing.assert_allclose(centre, CENTRE, atol=1e-9)
    assert radius == pytest.approx(cap, rel=1e-9)
    distances = np.linspace(0.05, 0.2, 41)
    _, radius = normalize.orbit_roi(c2w, _shell(distances))
    assert radius == pytest.approx(np.percentile(distances, 95.0), rel=1e-9)
    _, radius = normalize.orbit_roi(c2w, _shell(distances), percentile=50.0, camera_fraction=0.01)
    assert radius == pytest.approx(0.01 * np.hypot(0.9, 0.3), rel=1e-9)
    # one point is a cloud of one; no point: the cap
    assert normalize.orbit_roi(c2w, _shell([0.1]))[1] == pytest.approx(0.1, rel=1e-9)
    assert normalize.orbit_roi(c2w, None)[1] == pytest.approx(cap, rel=1e-9)
    # normalize_orbit scales that region to the unit sphere, the centre to the origin
    c2w_norm, record = normalize.normalize_orbit(c2w, _shell(distances))
    assert record["scale"] == pytest.approx(1.0 / np.percentile(distances, 95.0), rel=1e-9)
    np.testing.assert_allclose(record["translation"], -CENTRE, atol=1e-9)
    np.testing.assert_allclose(c2w_norm[:, :3, 3], (c2w[:, :3, 3] - CENTRE) * record["scale"], atol=1e-9)


def test_orbit_roi_of_points_at_the_centre_and_of_cameras_at_one_point():
    """Degenerate regions: every point at the centre (radius 0: 1 instead); cameras at one point
    looking outwards, a panorama (cap 0: the points' percentile alone)."""
    c2w = _orbit(3.0)
    assert normalize.orbit_roi(c2w, np.tile(CENTRE, (5, 1)))[1] == 1.0
    headings = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    panorama = np.stack([look_at(CENTRE, CENTRE + [np.cos(a), np.sin(a), 0.0]) for a in headings])
    distances = np.linspace(2.0, 4.0, 21)
    centre, radius = normalize.orbit_roi(panorama, _shell(distances))
    np.testing.assert_allclose(centre, CENTRE, atol=1e-9)
    assert radius == pytest.approx(np.percentile(distances, 95.0), rel=1e-9)
    _, record = normalize.normalize_poses(panorama, _shell(distances))       # no camera distance to cap it
    assert record["scale"] == pytest.approx(1.0 / np.percentile(distances, 95.0), rel=1e-9)


def test_forward_facing_cameras_centre_at_the_points_median_depth():
    """Cameras on a line, all looking along +y (parallel axes: no focus point). The centre is the
    mean camera centre moved along the view by the points' median distance from it (module
    docstring), for orbit_roi and normalize_poses alike; without points, by the cameras' spread
    (the largest distance from their mean, 1.5), or by 1 for a single camera."""
    eyes = np.column_stack([np.linspace(-1.5, 1.5, 5), np.zeros(5), np.full(5, 2.0)])
    c2w = np.stack([look_at(e, e + [0.0, 1.0, 0.0]) for e in eyes])
    points = np.array([[0.0, 5.0, 2.0], [1.0, 6.0, 2.0], [-2.0, 4.0, 3.0]])
    depth = np.median(np.linalg.norm(points - eyes.mean(0), axis=1))
    expected = eyes.mean(0) + [0.0, depth, 0.0]
    np.testing.assert_allclose(normalize.orbit_roi(c2w, points)[0], expected, atol=1e-9)
    _, record = normalize.normalize_poses(c2w, points)
    np.testing.assert_allclose(record["translation"], -expected, atol=1e-9)
    _, record = normalize.normalize_poses(c2w, None)
    np.testing.assert_allclose(record["translation"], -(eyes.mean(0) + [0.0, 1.5, 0.0]), atol=1e-9)
    _, record = normalize.normalize_poses(c2w[:1], None)
    np.testing.assert_allclose(record["translation"], -(eyes[0] + [0.0, 1.0, 0.0]), atol=1e-9)
    _, record = normalize.normalize_poses(c2w, points, focus_depth=3.0)
    np.testing.assert_allclose(record["translation"], -(eyes.mean(0) + [0.0, 3.0, 0.0]), atol=1e-9)
    _, record = normalize.normalize_poses(c2w[1:3], None)           # two cameras 0.75 apart: spread 0.375
    np.testing.assert_allclose(record["translation"], -(eyes[1:3].mean(0) + [0.0, 0.375, 0.0]), atol=1e-9)
    _, record = normalize.normalize_poses(c2w, points[:1], "points")  # one point is a median
    np.testing.assert_allclose(record["translation"], -points[0], atol=1e-12)


@pytest.mark.parametrize("name", ["normalize_orbit", "z_up_normalization", "normalize_poses"])
def test_camera_shapes_accepted_and_refused_by_name(name):
    """[N, 3, 4] is [N, 4, 4] without its last row; one camera is a capture; [N, 3, 3], [4, 4]
    and no camera are refused with a DataError naming the function."""
    fn = getattr(normalize, name)
    c2w = _orbit(3.0)
    points = _shell(np.linspace(0.5, 1.0, 20))
    full, record = fn(c2w, points)
    short, record_short = fn(c2w[:, :3, :], points)
    np.testing.assert_allclose(short, full, atol=1e-12)
    assert record_short == record
    assert fn(c2w[:1], points)[0].shape == (1, 4, 4)
    for bad in (c2w[:, :3, :3], c2w[0], c2w[:0]):
        with pytest.raises(DataError, match=f"{name}: c2w must be"):
            fn(bad, points)


def test_z_up_normalization_of_a_z_up_scene_has_no_rotation_and_passes_its_settings_on():
    """Cameras level about +z: no "rotation" in the record, and method / percentile reach the
    normalisation (centre the points' median, radius their median distance)."""
    c2w = _orbit(3.0)
    distances = np.linspace(0.2, 1.0, 33)
    points = _shell(distances)
    _, record = normalize.z_up_normalization(c2w, points, "points", percentile=50.0)
    assert "rotation" not in record
    median = np.median(points, axis=0)
    np.testing.assert_allclose(record["translation"], -median, atol=1e-9)
    assert record["scale"] == pytest.approx(1.0 / np.median(np.linalg.norm(points - median, axis=1)), rel=1e-9)


def test_z_up_normalization_of_a_tilted_scene_keeps_the_points_radius():
    """The same orbit turned 40 degrees about x: the record turns it back (its rotation takes the
    cameras' up to +z) and the radius is still the points' 95th percentile distance to the orbit's
    target (distances do not change under a turn); percentile 50 reaches it too."""
    turn = Rotation.from_euler("x", 40, degrees=True).as_matrix()
    c2w = _orbit(3.0)
    distances = np.linspace(0.2, 1.0, 33)
    points = _shell(distances)
    tilted = c2w.copy()
    tilted[:, :3, :3] = turn @ c2w[:, :3, :3]
    tilted[:, :3, 3] = c2w[:, :3, 3] @ turn.T
    for percentile in (95.0, 50.0):
        c2w_norm, record = normalize.z_up_normalization(tilted, points @ turn.T, percentile=percentile)
        np.testing.assert_allclose(np.asarray(record["rotation"]) @ turn, np.eye(3), atol=1e-9)
        assert record["scale"] == pytest.approx(1.0 / np.percentile(distances, percentile), rel=1e-9)
        np.testing.assert_allclose(c2w_norm[:, :3, 3], (c2w[:, :3, 3] - CENTRE) * record["scale"], atol=1e-8)
    # method "points" reaches the turned scene: the centre is the points' median, turned back
    _, record = normalize.z_up_normalization(tilted, points @ turn.T, "points")
    median = np.median(points, axis=0)
    assert record["scale"] == pytest.approx(1.0 / np.percentile(np.linalg.norm(points - median, axis=1), 95.0),
                                            rel=1e-9)


def test_check_rotation_tolerance_message_and_dtype():
    """A turn within 1e-5 is accepted (as float64, also from integers); 1e-3 off, a reflection,
    or text are refused with the file's name."""
    r = Rotation.from_euler("zyx", [30, 10, -20], degrees=True).as_matrix()
    np.testing.assert_allclose(normalize.check_rotation(r * (1 + 1e-7), "a.json"), r * (1 + 1e-7))
    identity = normalize.check_rotation([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "a.json")
    assert identity.dtype == np.float64
    for bad in (r * (1 + 1e-3), r @ np.diag([1.0, 1.0, -1.0])):
        with pytest.raises(DataError, match="a.json: scene_normalization 'rotation' is not a rotation"):
            normalize.check_rotation(bad, "a.json")
    with pytest.raises(DataError, match="a.json: scene_normalization 'rotation' must be a 3x3 list of numbers"):
        normalize.check_rotation([["a", "b", "c"]] * 3, "a.json")


def test_normalize_poses_radius_capped_by_the_cameras_below_one_unit_and_uncapped_for_points():
    """A ring 0.6 units around a centre far from the origin (camera distance sqrt(0.6^2 + 0.3^2)
    < 1): points beyond the cameras are capped at that distance (method "cameras"), not with
    method "points" (centre: the points' median); points inside: their 95th percentile (the
    default); one point: its distance; all at the centre: radius 1."""
    c2w = _orbit(0.6)
    cam = np.hypot(0.6, 0.3)
    far = _shell(np.linspace(0.7, 0.9, 21))
    _, record = normalize.normalize_poses(c2w, far)
    np.testing.assert_allclose(record["translation"], -CENTRE, atol=1e-9)
    assert record["scale"] == pytest.approx(1.0 / cam, rel=1e-9)
    _, record = normalize.normalize_poses(c2w, far, "points")
    median = np.median(far, axis=0)
    assert record["scale"] == pytest.approx(1.0 / np.percentile(np.linalg.norm(far - median, axis=1), 95.0), rel=1e-9)
    distances = np.linspace(0.1, 0.5, 41)
    _, record = normalize.normalize_poses(c2w, _shell(distances))
    assert record["scale"] == pytest.approx(1.0 / np.percentile(distances, 95.0), rel=1e-9)
    assert normalize.normalize_poses(c2w, _shell([0.2]))[1]["scale"] == pytest.approx(5.0, rel=1e-9)
    assert normalize.normalize_poses(c2w, np.tile(CENTRE, (4, 1)))[1]["scale"] == 1.0


@pytest.mark.parametrize("a", [[0.0, 1.0, 0.0], [0.5, 0.5, np.sqrt(0.5)], [1.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
def test_rotation_between_opposite_and_unnormalised_directions(a):
    """A half turn for opposite directions (a proper rotation: R R^T = I, det 1, R a = -a) and the
    smallest turn onto a direction given at any length."""
    a = np.asarray(a)
    unit = a / np.linalg.norm(a)
    for r in (normalize.rotation_between(a, -2.5 * a), normalize.rotation_between(a, -unit)):
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
        np.testing.assert_allclose(r @ unit, -unit, atol=1e-12)
    b = np.array([0.3, -0.4, 1.2])
    np.testing.assert_allclose(normalize.rotation_between(a, 4.0 * b) @ unit, b / np.linalg.norm(b), atol=1e-12)


def _heading_y(eye, pitch_deg):
    """OpenGL c2w at eye, heading +y, pitched down by pitch_deg, level (no roll)."""
    p = np.radians(pitch_deg)
    return look_at(np.asarray(eye, float), np.asarray(eye, float) + [0.0, np.cos(p), -np.sin(p)])


def test_up_from_cameras_one_heading_small_plane_blob_and_wall():
    """One heading (+y), pitched 30 degrees down, so the cameras' mean up is 30 degrees off +z:
    three centres on a horizontal plane 0.6 units across give +z (the plane's normal); centres
    filling a small box (no plane) give the mean up; centres on a vertical wall (its normal 90
    degrees off) give the mean up too."""
    mean_up = np.array([0.0, np.sin(np.radians(30)), np.cos(np.radians(30))])
    plane = [[0.0, 0.0, 1.0], [0.6, 0.1, 1.0], [0.2, 0.5, 1.0]]
    np.testing.assert_allclose(normalize.up_from_cameras(np.stack([_heading_y(e, 30) for e in plane])),
                               [0.0, 0.0, 1.0], atol=1e-9)
    # the box's variances 0.09, 0.044, 0.018: not flat (0.018 > 0.25 x 0.044), though 0.018 < 0.25 x 0.09
    box = np.array([[x, y, z] for x in (0.0, 0.6) for y in (0.0, 0.42) for z in (0.0, 0.27)])
    np.testing.assert_allclose(normalize.up_from_cameras(np.stack([_heading_y(e, 30) for e in box])), mean_up,
                               atol=1e-9)
    wall = [[x, 0.0, z] for x in (0.0, 5.0, 10.0) for z in (0.0, 4.0, 8.0)]
    np.testing.assert_allclose(normalize.up_from_cameras(np.stack([_heading_y(e, 30) for e in wall])), mean_up,
                               atol=1e-9)
    # centres nearly on a line (10 units along x, 0.3 across in y: not a plane), the mean up
    line = [[x, 0.3 * (i % 2), 1.0] for i, x in enumerate(np.linspace(0.0, 10.0, 6))]
    np.testing.assert_allclose(normalize.up_from_cameras(np.stack([_heading_y(e, 30) for e in line])), mean_up,
                               atol=1e-9)


def test_up_from_cameras_whose_up_vectors_cancel_is_plus_z():
    """Two cameras, one upside down (rolled half a turn): their up vectors sum to zero, the right
    vectors are one line and there are too few centres for a plane: +z."""
    upright = _heading_y([0.0, 0.0, 0.0], 0)
    rolled = upright.copy()
    rolled[:3, 0], rolled[:3, 1] = -upright[:3, 0], -upright[:3, 1]
    rolled[:3, 3] = [1.0, 0.0, 0.0]
    np.testing.assert_array_equal(normalize.up_from_cameras(np.stack([upright, rolled])), [0.0, 0.0, 1.0])


@pytest.mark.parametrize("turn", [0.0, 90.0, 180.0, 270.0])
def test_up_from_cameras_of_pitched_orbits_is_plus_z_whatever_the_eigenvectors_sign(turn):
    """Level cameras pitched down on part of an orbit (mean up off +z by the pitch): +z exactly,
    for several starting headings (the eigenvector's sign is the solver's choice)."""
    angles = np.radians(turn + np.linspace(0, 120, 5))
    eyes = np.column_stack([10 * np.cos(angles), 10 * np.sin(angles), np.full(5, 6.0)])
    c2w = np.stack([look_at(e, [0.0, 0.0, 0.0]) for e in eyes])
    np.testing.assert_allclose(normalize.up_from_cameras(c2w), [0.0, 0.0, 1.0], atol=1e-9)


def test_scene_center_of_two_cameras_nearly_parallel_axes_and_bad_requests():
    """Two cameras whose axes cross at a point: that point. Five cameras on a line converging on
    a point 10 units away (conditioning 0.005, under the 1e-2 limit: nearly parallel): the
    fallback, the mean centre moved along the mean view by the points' median distance. The
    points method without points, and an unknown method, are refused by name."""
    target = np.array([3.0, 4.0, 1.0])
    two = np.stack([look_at(target + [5.0, 0.0, 0.5], target), look_at(target + [0.0, -5.0, 0.5], target)])
    np.testing.assert_allclose(normalize.scene_center(two), target, atol=1e-9)
    eyes = np.column_stack([np.linspace(-1.0, 1.0, 5), np.zeros(5), np.full(5, 2.0)])
    c2w = np.stack([look_at(e, [0.0, 10.0, 2.0]) for e in eyes])
    points = np.array([[0.0, 6.0, 2.0], [0.5, 6.0, 2.0], [-0.5, 6.0, 2.0]])
    depth = np.median(np.linalg.norm(points - eyes.mean(0), axis=1))
    forward = -c2w[:, :3, 2].mean(0)
    np.testing.assert_allclose(normalize.scene_center(c2w, points),
                               eyes.mean(0) + depth * forward / np.linalg.norm(forward), atol=1e-9)
    np.testing.assert_allclose(normalize.scene_center(c2w, points, min_conditioning=1e-3), [0.0, 10.0, 2.0],
                               atol=1e-9)
    for none in (None, np.zeros((0, 3))):
        with pytest.raises(DataError, match=r"normalize_poses\(method='points'\) needs 3-D points"):
            normalize.normalize_poses(c2w, none, "points")
    with pytest.raises(ValueError, match="method must be 'cameras' or 'points', got 'median'"):
        normalize.scene_center(c2w, points, "median")


def _nadir(eye, heading_deg):
    """OpenGL c2w at eye looking straight down, the image's top towards heading_deg from +x."""
    h = np.radians(heading_deg)
    forward = np.array([np.cos(h), np.sin(h), 0.0])
    m = np.eye(4)
    m[:3, 1], m[:3, 2] = forward, [0.0, 0.0, 1.0]          # image up along the flight, backward to the sky
    m[:3, 0] = np.cross(m[:3, 1], m[:3, 2])
    m[:3, 3] = eye
    return m


def test_up_from_cameras_of_a_nadir_survey_is_the_sky_not_the_flight_direction():
    """A lawnmower survey 40 m up, legs flown north and south (headings 90 and 270 degrees) and one
    east (0): the image-up vectors are horizontal, their mean (1/5, 0, 0) a fifth long; the
    backward axes all +z, their mean 1 long: a nadir survey (longer by more than NADIR_MARGIN). The
    right vectors are horizontal with headings that vary, so up is the normal to them, +z, taken on
    the sky's side; before, it fell back to the mean image-up vector (+x, the flight's east leg)."""
    legs = [(0.0, 0.0, 90.0), (10.0, 0.0, 270.0), (20.0, 0.0, 90.0), (30.0, 0.0, 270.0), (30.0, 10.0, 0.0)]
    c2w = np.stack([_nadir([x, y, 40.0], h) for x, y, h in legs])
    np.testing.assert_allclose(c2w[:, :3, 1].mean(0), [0.2, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(normalize.up_from_cameras(c2w), [0.0, 0.0, 1.0], atol=1e-9)
    # an orbit pitched 30 degrees down keeps its up from the image-up vectors (its backward axes cancel)
    orbit = np.stack([look_at(np.array([20 * np.cos(a), 20 * np.sin(a), 11.5]), np.zeros(3))
                      for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)])
    np.testing.assert_allclose(normalize.up_from_cameras(orbit), [0.0, 0.0, 1.0], atol=1e-9)
