"""The survey outputs of `export` (docs/EXPORT.md "Survey outputs"): the export's units from the
georeference record, boxes mapped by their 8 corners, LAS 1.4 with a CRS, the tilt of the
tower's axis, the conductors' clearance and the alignment's uncertainty, each against an
independent answer (hand-computed boxes, generated geometry with known tilt, a Monte Carlo of the
similarity fit)."""


import numpy as np
import pytest

from jaxnerf_grid.capture import georef
from jaxnerf_grid.capture.georef import umeyama
from jaxnerf_grid.export import box_to_metric, box_to_scene, measure, survey
from jaxnerf_grid.export import run as export_run
from jaxnerf_grid.report import markdown as report
from jaxnerf_grid.util import io
from tests.train.test_loop import tiny_dataset

C30, S30 = np.sqrt(3.0) / 2.0, 0.5
TURNED = {"scale": 0.5, "translation": [1.0, 2.0, 3.0],
          "rotation": [[C30, -S30, 0.0], [S30, C30, 0.0], [0.0, 0.0, 1.0]]}   # 30 degrees about z


# --------------------------------------------------------------------------- units


def test_units_follow_the_georeference_record_else_the_synthetic_scale():
    ds = tiny_dataset()
    norm = {"scale": 0.05, "translation": [0.0, 0.0, 0.0]}
    ds.meta = {"scene_normalization": norm}                                     # synthetic: metres
    assert export_run.units_of(ds) == "metres"
    ds.meta = {"scene_normalization": norm, "georeference": {"units": "unknown"}, "poses": {}}   # poses, no GPS
    assert export_run.units_of(ds) == "unknown"
    ds.meta = {"scene_normalization": norm, "georeference": {"units": "metres", "source": "gps"}, "poses": {}}
    assert export_run.units_of(ds) == "metres"
    ds.meta = {"scene_normalization": norm, "poses": {}}              # poses before the record: no scale known
    assert export_run.units_of(ds) == "unknown"
    ds.meta = {}
    assert export_run.units_of(ds) == "unknown"


def test_the_loader_keeps_the_georeference_record(tmp_path):
    from jaxnerf_grid.data.formats import load_dataset, save_transforms_json

    ds = tiny_dataset()
    ds.frame_paths = [f"images/frame_{i:03d}.png" for i in range(ds.num_frames)]
    save_transforms_json(ds, tmp_path / "d")
    top = io.read_json(tmp_path / "d" / "transforms.json")
    geo = {"units": "unknown", "source": None}
    io.write_json(tmp_path / "d" / "transforms.json", {**top, "scene_normalization": {"scale": 0.1, "translation":
                                                                                      [0, 0, 0]},
                                                       "georeference": geo, "poses": {"registered": 5}})
    loaded = load_dataset(tmp_path / "d")
    assert loaded.meta["georeference"] == geo
    assert export_run.units_of(loaded) == "unknown"
    # a dataset written again from it (preprocess, save_transforms_json) keeps the records: its
    # scene_normalization alone would read as metres
    save_transforms_json(loaded, tmp_path / "again")
    again = load_dataset(tmp_path / "again")
    assert again.meta["georeference"] == geo and again.meta["poses"] == {"registered": 5}
    assert export_run.units_of(again) == "unknown"


# --------------------------------------------------------------------------- boxes


def test_a_metric_box_maps_to_the_scene_box_around_its_8_corners_by_hand():
    """x_norm = 0.5 R (x + t), R 30 degrees about z, box [0, 2] x [0, 1] x [0, 1]: x + t spans
    [1, 3] x [2, 3] x [3, 4]; x' = c x - s y is least at (1, 3), greatest at (3, 2); y' = s x + c y
    least at (1, 2), greatest at (3, 3)."""
    lo, hi = box_to_scene([0, 0, 0], [2, 1, 1], TURNED)
    np.testing.assert_allclose(lo, [0.5 * (C30 * 1 - S30 * 3), 0.5 * (S30 * 1 + C30 * 2), 1.5], atol=1e-12)
    np.testing.assert_allclose(hi, [0.5 * (C30 * 3 - S30 * 2), 0.5 * (S30 * 3 + C30 * 3), 2.0], atol=1e-12)
    assert np.all(hi > lo)


def test_a_scene_box_maps_to_the_metric_box_around_its_8_corners_by_hand():
    """x = R^T x_norm / 0.5 - t of the cube [-1, 1]^3: R^T turns its x and y extent into
    +-(c + s), z stays +-1."""
    lo, hi = box_to_metric([-1, -1, -1], [1, 1, 1], TURNED)
    e = (C30 + S30) / 0.5
    np.testing.assert_allclose(lo, [-e - 1, -e - 2, -2 - 3], atol=1e-12)
    np.testing.assert_allclose(hi, [e - 1, e - 2, 2 - 3], atol=1e-12)


def test_a_box_with_a_turn_of_more_than_90_degrees_is_not_inverted():
    """A record turned 150 degrees: mapping the two corners alone gives min x > max x."""
    c, s = np.cos(np.radians(150)), np.sin(np.radians(150))
    record = {"scale": 1.0, "translation": [0, 0, 0], "rotation": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}
    lo, hi = box_to_scene([0, 0, 0], [4, 1, 1], record)
    # x' = c x - s y (c < 0 < s): least at (4, 1), greatest at (0, 0); y' = s x + c y: least at
    # (0, 1), greatest at (4, 0)
    np.testing.assert_allclose(lo[:2], [4 * c - s, c], atol=1e-12)
    np.testing.assert_allclose(hi[:2], [0.0, 4 * s], atol=1e-12)


# --------------------------------------------------------------------------- tilt, conductors


def lattice_tower(tilt_deg: float, azimuth_deg: float, rng, ground_z: float = 3.0, arm_shift: float = 0.0):
    """Surface samples of a tapered square tower (base 8 m, top 2 m, 30 m high) with two
    cross-arms (16 m at 20 m, 12 m at 25 m), turned 20 degrees about its axis, tilted by
    `tilt_deg` about the base centre (2, -1, ground_z) towards azimuth `azimuth_deg`; arm_shift
    moves the arms sideways (a one-sided arm: its middle is off the axis); no ground.
    Returns (points [N, 3], the axis' top offset at the highest point's height)."""
    z = rng.uniform(0, 30, 40000)
    half = 4.0 - 3.0 * z / 30.0
    side = rng.integers(0, 4, len(z))
    u = rng.uniform(-1, 1, len(z)) * half
    x = np.where(side == 0, half, np.where(side == 1, -half, u))
    y = np.where(side == 2, half, np.where(side == 3, -half, u))
    body = np.column_stack([x, y, z])
    arms = []
    for height, span in ((20.0, 16.0), (25.0, 12.0)):
        a = rng.uniform(-span / 2, span / 2, 3000) + arm_shift
        arms.append(np.column_stack([a, rng.uniform(-0.4, 0.4, len(a)), height + rng.uniform(-0.5, 0.5, len(a))]))
    tower = np.vstack([body] + arms)
    turn = np.radians(20.0)
    tower = tower @ np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]]).T
    t, az = np.radians(tilt_deg), np.radians(azimuth_deg)
    k = np.array([-np.sin(az), np.cos(az), 0.0])           # tilt about this horizontal axis: the top goes to az
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rot = np.eye(3) + np.sin(t) * kx + (1 - np.cos(t)) * kx @ kx
    base = np.array([2.0, -1.0, ground_z])
    tower = tower @ rot.T + base
    return tower, np.tan(t) * float(tower[:, 2].max() - ground_z)


@pytest.mark.parametrize("tilt_deg, azimuth_deg, arm_shift", [(1.0, 35.0, 0.0), (0.0, 0.0, 0.0), (3.0, 200.0, 0.0),
                                                              (1.0, 35.0, 3.0)])
def test_tilt_of_a_generated_tower_within_0_3_degrees(tilt_deg, azimuth_deg, arm_shift):
    rng = np.random.default_rng(1)
    points, offset = lattice_tower(tilt_deg, azimuth_deg, rng, arm_shift=arm_shift)
    n, d = np.array([0.0, 0.0, 1.0]), -3.0
    fp = measure.footprint(points, n, d, 1.5)
    tilt = measure.axis_tilt(points, n, d, fp["axis_a"], fp["axis_b"], 0.3)
    assert tilt["tilt_degrees"] == pytest.approx(tilt_deg, abs=0.3)
    assert tilt["tilt_degrees"] == pytest.approx(tilt_deg, abs=0.05)           # what it does on this one
    assert tilt["top_offset"] == pytest.approx(offset, abs=0.05)
    if tilt_deg > 0:
        direction = np.degrees(np.arctan2(tilt["top_offset_xy"][1], tilt["top_offset_xy"][0])) % 360
        assert direction == pytest.approx(azimuth_deg, abs=3.0)
    np.testing.assert_allclose(tilt["base"], [2.0, -1.0, 3.0], atol=0.05)
    assert tilt["slices_left_out"] >= 0 and tilt["tilt_sigma_degrees"] < 0.1


def test_tilt_from_the_ground_normal_on_sloping_ground():
    """A vertical tower on ground sloping 5 degrees: 0 from vertical, 5 from the ground's normal."""
    rng = np.random.default_rng(2)
    points, _ = lattice_tower(0.0, 0.0, rng)
    slope = np.radians(5.0)
    n = np.array([-np.sin(slope), 0.0, np.cos(slope)])
    d = -float(n @ [2.0, -1.0, 3.0])
    fp = measure.footprint(points, n, d, 1.5)
    tilt = measure.axis_tilt(points, n, d, fp["axis_a"], fp["axis_b"], 0.3)
    assert tilt["tilt_degrees"] == pytest.approx(0.0, abs=0.1)
    assert tilt["tilt_from_ground_normal_degrees"] == pytest.approx(5.0, abs=0.1)


def test_conductor_clearance_is_the_lowest_point_of_the_wire_leaving_the_tower():
    """A wire from 0.1 m beyond the tower's box (x0, z = 23) sagging as z = 23 - 0.05 (x - x0)^2
    for 12 m (lowest: 23 - 0.05 * 144 = 15.8 m above the ground z = 0); a car-sized blob 1 m high
    beside the tower does not count; with no wire, not reconstructed."""
    rng = np.random.default_rng(3)
    tower, _ = lattice_tower(0.0, 0.0, rng, ground_z=0.0)
    lo, hi = tower.min(0) - 0.3, tower.max(0) + 0.3
    x0 = hi[0] + 0.1
    x = np.linspace(x0, x0 + 12.0, 400)
    wire = np.column_stack([x, np.zeros_like(x) + 0.01, 23.0 - 0.05 * (x - x0) ** 2])
    car = np.column_stack([rng.uniform(12, 16, 300), rng.uniform(5, 7, 300), rng.uniform(0, 1, 300)])
    n, d = np.array([0.0, 0.0, 1.0]), 0.0
    got = measure.conductor_clearance(np.vstack([tower, wire, car]), n, d, lo, hi, 10.0, 0.4)
    assert got["reconstructed"] is True and got["points"] == 400
    assert got["lowest_height"] == pytest.approx(23.0 - 0.05 * 144.0, abs=1e-9)
    assert got["extent"] == pytest.approx(12.1, abs=1e-9)
    none = measure.conductor_clearance(np.vstack([tower, car]), n, d, lo, hi, 10.0, 0.4)
    assert none["reconstructed"] is False and "outside the tower's box" in none["why"]


TURN = (np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]])
        @ np.array([[np.cos(0.5), -np.sin(0.5), 0], [np.sin(0.5), np.cos(0.5), 0], [0, 0, 1]]))
SHIFT = np.array([5.0, -7.0, 40.0])      # the tower frame (a, b, height) -> the world: x = TURN q + SHIFT


def test_axis_tilt_of_slices_on_a_known_line_against_linregress():
    """Slices 0.5 m thick of a tower on tilted ground (normal TURN z, offset -n . SHIFT), each a
    2 x 2 square of 4 points centred on the line a = 0.4 + 0.2 h, b = -0.3 - 0.1 h (+ 2 cm of
    noise) at mean height (k + 0.5) / 2; slice 6 moved 0.6 m off the line (past the floor of the
    MAD rule, half a slice: left out), slice 9 an arm (4 x 2: ratio 2, not a centre), slice 10
    of 3 points. The axis, base, top, tilts and sigmas from scipy's linregress over the 10 kept
    centres."""
    from scipy.stats import linregress

    rng = np.random.default_rng(4)
    q, centres = [[0.0, 0.0, 0.0]], []                       # a lone point at height 0 starts the slices
    for k in range(1, 13):
        h = 0.5 * (k + 0.5)
        a, b = 0.4 + 0.2 * h + rng.normal(0, 0.02), -0.3 - 0.1 * h + rng.normal(0, 0.02)
        if k == 6:
            a += 0.6
        lo, hi = 0.5 * (k + 0.3), 0.5 * (k + 0.7)
        square = [(a - 1, b - 1, lo), (a + 1, b + 1, lo), (a - 1, b + 1, hi), (a + 1, b - 1, hi)]
        if k == 9:
            square += [(a + 3, b, h)]
        if k == 10:
            square = square[:2] + square[3:]
        q += square
        if k not in (6, 9):
            centres.append((np.mean([s[2] for s in square]), a, b))
    n = TURN[:, 2]
    tilt = measure.axis_tilt(np.asarray(q) @ TURN.T + SHIFT, n, -float(n @ SHIFT), TURN[:, 0], TURN[:, 1], 0.5)
    c = np.asarray(centres)
    fa, fb = linregress(c[:, 0], c[:, 1]), linregress(c[:, 0], c[:, 2])
    assert (tilt["slices"], tilt["slices_left_out"]) == (10, 1)
    direction = TURN @ [fa.slope, fb.slope, 1.0]
    direction /= np.linalg.norm(direction)
    np.testing.assert_allclose(tilt["direction"], direction, atol=1e-9)
    assert tilt["tilt_degrees"] == pytest.approx(np.degrees(np.arccos(direction[2])))
    assert tilt["tilt_from_ground_normal_degrees"] == pytest.approx(np.degrees(np.arctan(np.hypot(fa.slope, fb.slope))))
    top_h = 0.5 * 12.7
    base = TURN @ [fa.intercept, fb.intercept, 0.0] + SHIFT
    top = TURN @ [fa.intercept + fa.slope * top_h, fb.intercept + fb.slope * top_h, top_h] + SHIFT
    np.testing.assert_allclose(tilt["base"], base, atol=1e-9)
    np.testing.assert_allclose(tilt["top"], top, atol=1e-9)
    np.testing.assert_allclose(tilt["top_offset_xy"], (top - base)[:2], atol=1e-9)
    assert tilt["top_offset"] == pytest.approx(np.hypot(*(top - base)[:2]))
    sigma = np.degrees(np.arctan(np.sqrt(0.5 * (fa.stderr ** 2 + fb.stderr ** 2))))
    assert tilt["tilt_sigma_degrees"] == pytest.approx(sigma)
    assert tilt["top_offset_sigma"] == pytest.approx(np.radians(sigma) * top_h)


def test_axis_tilt_of_three_slices_of_three_points_and_the_line_fit_of_two():
    """Nine points, three slices of three (the fewest it takes): centres a = 0.5 k at mean
    heights k + 1/12, on level ground: slope 0.5, no residual; eight points: None. A highest
    point exactly on
    the top slice's upper edge, 3 m out, belongs to that slice (which is then an arm: None)."""
    q = [(0.5 * k + da, db, k + dh) for k in range(3) for da, db, dh in ((-1, -1, 0.0), (1, 1, 0.0), (1, -1, 0.25))]
    axes = ([1.0, 0, 0], [0, 1.0, 0])
    tilt = measure.axis_tilt(np.asarray(q, np.float64), [0, 0, 1.0], 0.0, *axes, 1.0)
    assert tilt is not None and tilt["slices"] == 3
    assert tilt["tilt_degrees"] == pytest.approx(np.degrees(np.arctan(0.5)))
    np.testing.assert_allclose(tilt["base"], [-1.0 / 24, 0.0, 0.0], atol=1e-12)     # a(0) = 0.5 (0 - 1/12)
    assert tilt["tilt_sigma_degrees"] == pytest.approx(0.0, abs=1e-6)
    assert tilt["thickness_spread_degrees"] == 0.0      # 2 m and 4 m slices: fewer than 3, no other axis
    assert measure.axis_tilt(np.asarray(q[:8], np.float64), [0, 0, 1.0], 0.0, *axes, 1.0) is None
    top = q + [(1.0 + 3.0, 0.0, 3.0)]
    assert measure.axis_tilt(np.asarray(top, np.float64), [0, 0, 1.0], 0.0, *axes, 1.0) is None
    assert measure._line_fit(np.array([0.0, 1.0]), np.array([1.0, 3.0])) == (1.0, 2.0, 0.0)   # K = 2: no spread
    from scipy.stats import linregress

    three = linregress([0.0, 1.0, 2.0], [0.0, 1.0, 3.0])                            # K = 3: one degree of freedom
    np.testing.assert_allclose(measure._line_fit(np.array([0.0, 1.0, 2.0]), np.array([0.0, 1.0, 3.0])),
                               [three.intercept, three.slope, three.stderr], atol=1e-12)


def test_axis_tilt_thicker_fit_keeps_a_centre_within_half_its_own_slice_height():
    """The thicker fits reject their centres with their own floor, half the thicker slice's
    height. A straight vertical body of 4-point levels at heights 0.5, 1.5, ..., 11.5, corners
    (+-1, +-1), except level 8.5 (a from -1 to 1, b from -1.4 to 1.4: 2 x 2.8, within the ratio
    1.5) and level 9.5 (a from -1 to 2.2, b from -1 to 1: 3.2 x 2, a wide member). 1 m slices:
    9.5 is left out, every other centre is on a = b = 0, so the axis is the normal (tilt 0). 2 m
    slices: centres at heights 1, 3, ..., 11, a = 0 but 0.6 at height 9 (levels 8.5 and 9.5
    together: 3.2 x 2.8, within the ratio); least squares by hand: slope 1.8 / 70, residual of
    that centre 0.6 - (0.1 - 6 s) - 9 s = 0.4229, 3 x 1.4826 MAD of the six = 0.330: it is kept
    by the floor 0.5 x 2 m = 1.0 (it would be dropped by a floor below 0.42), so the thicker axis
    leans by atan(1.8 / 70)."""
    q = []
    for k in range(12):
        h = k + 0.5
        if k == 8:
            corners = [(-1.0, -1.4), (1.0, 1.4), (1.0, -1.4), (-1.0, 1.4)]
        elif k == 9:
            corners = [(-1.0, -1.0), (2.2, 1.0), (2.2, -1.0), (-1.0, 1.0)]
        else:
            corners = [(-1.0, -1.0), (1.0, 1.0), (1.0, -1.0), (-1.0, 1.0)]
        q += [(a, b, h) for a, b in corners]
    axes = ([1.0, 0, 0], [0, 1.0, 0])
    tilt = measure.axis_tilt(np.asarray(q, np.float64), [0, 0, 1.0], 0.0, *axes, 1.0, thicker=(2.0,))
    # 1 m slices from 0.5: the last edge is 11.5, so the top two levels share the last slice; 9.5 left out
    assert tilt["slices"] == 10 and tilt["slices_left_out"] == 0
    assert tilt["tilt_degrees"] == pytest.approx(0.0, abs=1e-9)
    heights, centres = np.array([1.0, 3, 5, 7, 9, 11]), np.array([0.0, 0, 0, 0, 0.6, 0])
    slope = np.polyfit(heights, centres, 1)[0]
    assert slope == pytest.approx(1.8 / 70, rel=1e-12)
    assert tilt["thickness_spread_degrees"] == pytest.approx(np.degrees(np.arctan(1.8 / 70)), rel=1e-9)


def _wire(x0: float, ks) -> np.ndarray:
    """Wire points x = x0 + 0.25 k (k in ks), y = 0, z = 12 - 0.25 k."""
    k = np.asarray(list(ks), np.float64)
    return np.column_stack([x0 + 0.25 * k, np.zeros_like(k), 12.0 - 0.25 * k])


def test_conductor_clearance_counts_the_box_edge_the_height_limit_and_the_gap_by_hand():
    """Level ground z = 2 (n = z, d = -2), the tower's box x, y in [-1, 1], cells 0.5, points
    higher than 4.5 above the ground: a wire from the box's edge (x = 1, on the box: not outside)
    falling 0.25 m per 0.25 m out to k = 20 (exactly the 20 points needed; lowest 5.0 above the
    ground at (6, 0, 7)), then one point beside it exactly 4.5 above (not higher: left out)."""
    n, d, lo, hi = [0, 0, 1.0], -2.0, [-1.0, -1.0, 2.0], [1.0, 1.0, 12.0]
    wire = np.vstack([_wire(1.0, range(21)), [[6.25, 0.0, 6.5]]])
    got = measure.conductor_clearance(wire, n, d, lo, hi, 4.5, 0.5)
    assert got["reconstructed"] is True and got["points"] == 20 and got["min_height"] == 4.5
    assert got["lowest_height"] == 5.0 and got["lowest_point"] == [6.0, 0.0, 7.0] and got["extent"] == 5.0
    mirrored = measure.conductor_clearance(wire * [-1, 1, 1], n, d, lo, hi, 4.5, 0.5)      # the box's lower edge
    assert mirrored["points"] == 20 and mirrored["lowest_point"] == [-6.0, 0.0, 7.0]
    # starting 2 cells from the box still leaves it; 2.5 cells does not
    assert measure.conductor_clearance(_wire(1.75, range(1, 21)), n, d, lo, hi, 4.5, 0.5)["reconstructed"] is True
    far = measure.conductor_clearance(_wire(2.0, range(1, 21)), n, d, lo, hi, 4.5, 0.5)
    assert far["reconstructed"] is False and "does not leave the tower" in far["why"] and far["min_height"] == 4.5
    # 24 points in two groups of 12 on either side: enough points, no group large enough
    two = np.vstack([_wire(1.0, range(1, 13)), _wire(1.0, range(1, 13)) * [-1, 1, 1]])
    assert measure.conductor_clearance(two, n, d, lo, hi, 4.5, 0.5)["reconstructed"] is False
    assert measure.conductor_clearance(wire[:20], n, d, lo, hi, 4.5, 0.5)["reconstructed"] is False   # 19 outside


# --------------------------------------------------------------------------- uncertainty


@pytest.mark.parametrize("yaw_only", [False, True])
def test_scale_uncertainty_formula_against_a_monte_carlo_of_the_fit(yaw_only):
    """25 cameras on an orbit (radius 50 m, heights 10-40 m) with isotropic errors of 3 m RMS
    (3-D): the spread of umeyama's scale over 400 draws matches the formula fed with the fits'
    own residual RMS (median over the draws) within 15 %."""
    rng = np.random.default_rng(4)
    a = np.linspace(0, 2 * np.pi, 25, endpoint=False)
    centres = np.column_stack([50 * np.cos(a), 50 * np.sin(a), np.linspace(10, 40, 25)])
    scales, residuals = [], []
    for _ in range(400):
        noisy = centres + rng.normal(0, np.sqrt(3.0), centres.shape)
        s, rot, t = umeyama(centres, noisy, yaw_only=yaw_only)
        scales.append(s)
        residuals.append(np.sqrt(np.mean(np.sum((s * centres @ rot.T + t - noisy) ** 2, axis=1))))
    r = float(np.median(residuals))
    rotation = "about z only" if yaw_only else "full"
    geo = {"units": "metres", "source": "gps", "rotation": rotation, "gps": {"inliers": 25, "rms_m": r}}
    got = survey.alignment_uncertainty(geo, "metres", centres)
    assert got["relative_scale"] == pytest.approx(np.std(scales), rel=0.15)
    spread = np.sqrt(np.mean(np.sum((centres - centres.mean(0)) ** 2, axis=1)))
    sigma = r * np.sqrt(25 / (75 - (5 if yaw_only else 7)))
    assert got["relative_scale"] == pytest.approx(sigma / (spread * 5))
    assert got["position_m"] == pytest.approx(sigma * np.sqrt(3 / 25))


def _fit_scales(truth_gps, truth_gcp, gps_sd, gcp_sd, draws, seed):
    """Monte Carlo of georef's weighted fit: per draw the truth plus isotropic normal errors
    (per-coordinate sd), umeyama weighted as `georef.align_model` weights its sources (full
    similarity: 3 or more control points). Returns (scales [draws], GPS residual RMS, control
    residual RMS), each RMS over the draws (a median of a 2-degree-of-freedom residual would
    understate sigma by a fifth)."""
    rng = np.random.default_rng(seed)
    src = np.concatenate([truth_gps, truth_gcp])
    weights = np.concatenate([np.full(len(truth_gps), 1 / georef.GPS_SIGMA ** 2),
                              np.full(len(truth_gcp), 1 / georef.GCP_SIGMA ** 2)])
    scales, r_gps, r_gcp = [], [], []
    for _ in range(draws):
        dst = np.concatenate([truth_gps + rng.normal(0, gps_sd, truth_gps.shape),
                              truth_gcp + rng.normal(0, gcp_sd, truth_gcp.shape)])
        s, rot, t = umeyama(src, dst, weights)
        res = np.linalg.norm(s * src @ rot.T + t - dst, axis=1)
        scales.append(s)
        r_gps.append(np.sqrt(np.mean(res[:len(truth_gps)] ** 2)) if len(truth_gps) else 0.0)
        r_gcp.append(np.sqrt(np.mean(res[len(truth_gps):] ** 2)))
    return np.asarray(scales), float(np.sqrt(np.mean(np.square(r_gps)))), float(np.sqrt(np.mean(np.square(r_gcp))))


def _orbit_and_ground_points(gcps: int):
    a = np.linspace(0, 2 * np.pi, 25, endpoint=False)
    centres = np.column_stack([50 * np.cos(a), 50 * np.sin(a), np.linspace(10, 40, 25)])
    b = np.linspace(0, 2 * np.pi, gcps, endpoint=False) + 0.3
    ground = np.column_stack([15 * np.cos(b), 15 * np.sin(b), 0.5 * np.arange(gcps)])
    return centres, ground


def test_scale_uncertainty_of_gps_with_control_points_against_a_monte_carlo():
    """25 GPS centres (3-D RMS 3 m) and 3 control points (sd 0.03 m per coordinate) 15 m from
    the tower, fitted with the alignment's own weights: the spread of the weighted fit's scale
    over 400 draws matches the formula fed with each source's residual RMS within 20 %.
    The control points rule the scale: the GPS-only formula would say 6x more."""
    centres, ground = _orbit_and_ground_points(3)
    scales, r_gps, r_gcp = _fit_scales(centres, ground, np.sqrt(3.0), 0.03, 400, 5)
    geo = {"units": "metres", "source": "gps+gcp", "rotation": "full (3 or more control points)",
           "gps": {"inliers": 25, "rms_m": r_gps},
           "gcp": {"control": {"rms_m": r_gcp, "residuals": [{}] * 3, "points_m": ground.tolist()}}}
    got = survey.alignment_uncertainty(geo, "metres", centres)
    assert got["relative_scale"] == pytest.approx(np.std(scales), rel=0.2)
    gps_only = survey.alignment_uncertainty({**geo, "gcp": None}, "metres", centres)["relative_scale"]
    assert gps_only > 4 * got["relative_scale"]


def test_scale_uncertainty_of_control_points_alone_against_a_monte_carlo():
    """5 control points alone (sd 0.05 m per coordinate, no GPS): the formula against the
    spread of the fit's scale over 600 draws, within 20 %."""
    _, ground = _orbit_and_ground_points(5)
    scales, _, r_gcp = _fit_scales(np.zeros((0, 3)), ground, 1.0, 0.05, 600, 6)
    geo = {"units": "metres", "source": "gcp", "rotation": "full (3 or more control points)",
           "gcp": {"control": {"rms_m": r_gcp, "residuals": [{}] * 5, "points_m": ground.tolist()}}}
    got = survey.alignment_uncertainty(geo, "metres", np.zeros((0, 3)))
    assert got["relative_scale"] == pytest.approx(np.std(scales), rel=0.2)
    assert got["position_m"] is not None


def test_uncertainty_without_gps_synthetic_and_unknown_units():
    assert survey.alignment_uncertainty(None, "metres", np.zeros((3, 3)))["relative_scale"] == 0.0
    assert survey.alignment_uncertainty({"units": "unknown"}, "unknown", np.zeros((3, 3)))["relative_scale"] is None
    bar = survey.alignment_uncertainty({"units": "metres", "source": "scale_bar"}, "metres", np.ones((3, 3)))
    assert bar["relative_scale"] is None
    assert survey.with_sigma(30.0, 0.1, bar)["sigma"] is None
    fig = survey.with_sigma(30.0, 0.4, {"relative_scale": 0.01, "position_m": 0.6}, position=True)
    assert fig["sigma"] == pytest.approx(np.sqrt(0.3 ** 2 + 0.4 ** 2 + 0.6 ** 2))


# --------------------------------------------------------------------------- LAS


def test_las_without_crs_reads_back_with_laspy(tmp_path):
    import laspy

    rng = np.random.default_rng(5)
    points = rng.uniform(-20, 40, (500, 3))
    colours = rng.uniform(0, 1, (500, 3))
    survey.write_las(tmp_path / "p.las", points, colours)
    las = laspy.read(tmp_path / "p.las")
    assert las.header.parse_crs() is None and str(las.header.version) == "1.4"
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), points, atol=5e-4 + 1e-9)
    np.testing.assert_allclose(np.column_stack([las.red, las.green, las.blue]) / 65535, colours, atol=1e-5)


def test_las_with_an_unknown_crs_is_a_data_error_naming_it(tmp_path):
    with pytest.raises(io.DataError, match="EPSG:999999"):
        survey.write_las(tmp_path / "p.las", np.zeros((2, 3)), np.zeros((2, 3)), "EPSG:999999")
    assert not any(tmp_path.iterdir())


def test_report_gives_each_figure_with_its_uncertainty():
    meas = {"units": "metres", "height": 30.0, "conductors": {"reconstructed": False, "why": "none found"},
            "survey": {"height": {"value": 30.0, "sigma": 0.25}, "cross_arm_heights": [{"value": 17.0, "sigma": 0.2}],
                       "tilt_degrees": {"value": 1.0, "sigma": 0.05}, "top_offset": {"value": 0.52, "sigma": 0.03},
                       "base_centre": {"local": [0, 0, 0], "crs": [465000.0, 5247000.0, 410.0],
                                       "crs_name": "EPSG:32632", "sigma": 0.6}}}
    text = "\n".join(report.export_lines({"measurements": meas}))
    assert "30.00 m +- 0.25 m" in text and "17.00 m +- 0.20 m" in text and "1.00 deg +- 0.05 deg" in text
    assert "(465000.000, 5247000.000, 410.000) in EPSG:32632 +- 0.60 m" in text
    assert "not reconstructed: none found" in text


def test_axis_tilt_thickness_spread_and_lowest_height_against_a_brute_force_refit():
    """Twelve 1 m slices on level ground z = -0.5 (heights z + 0.5), each a 2 x 2 square of 4
    points around a = 0.1 k, b = -0.05 k at heights k + 0.2, k + 0.8 (slice 0's at 0.1 and 0.9:
    the slices start at 0.1, clear of every point); each odd slice with a lump 0.002 k^2 beyond its
    +a side, so the middles of thin and thick slices lie on different lines. The spread is the RMS
    angle between the 1 m axis and the 2 m and 4 m ones, each refitted here by brute force (bins
    by floor, middles of the extents, np.polyfit; every deviation is under half a slice, so no
    slice is left out). Without the lumps every thickness finds the same axis."""
    def tower(lumps):
        q = []
        for k in range(12):                  # 4 m slices: exactly 3, the fewest a fit takes
            a, b, lo = 0.1 * k, -0.05 * k, (0.1 if k == 0 else 0.2)
            q += [(a - 1, b - 1, k + lo - 0.5), (a + 1, b + 1, k + lo - 0.5), (a - 1, b + 1, k + 1 - lo - 0.5),
                  (a + 1, b - 1, k + 1 - lo - 0.5)]
            if lumps and k % 2:
                q.append((a + 1 + 0.002 * k * k, b, k + 0.5 - 0.5))
        return np.asarray(q, np.float64)

    def axis(p, t):
        h = p[:, 2] + 0.5
        bins = np.floor((h - h.min()) / t).astype(int)
        rows = [(h[bins == s].mean(), 0.5 * (p[bins == s, 0].min() + p[bins == s, 0].max()),
                 0.5 * (p[bins == s, 1].min() + p[bins == s, 1].max()))
                for s in np.unique(bins) if (bins == s).sum() >= 3]
        c = np.asarray(rows)
        u = np.array([np.polyfit(c[:, 0], c[:, 1], 1)[0], np.polyfit(c[:, 0], c[:, 2], 1)[0], 1.0])
        return u / np.linalg.norm(u)

    axes = ([1.0, 0, 0], [0, 1.0, 0])
    p = tower(lumps=True)
    tilt = measure.axis_tilt(p, [0, 0, 1.0], 0.5, *axes, 1.0)
    u1 = axis(p, 1.0)
    angles = [np.degrees(np.arccos(min(1.0, float(u1 @ axis(p, t))))) for t in (2.0, 4.0)]
    assert min(angles) > 0.1 and abs(angles[0] - angles[1]) > 0.05   # the thicknesses disagree, unequally
    np.testing.assert_allclose(tilt["direction"], u1, atol=1e-12)
    assert tilt["thickness_spread_degrees"] == pytest.approx(np.sqrt(np.mean(np.square(angles))), rel=1e-9)
    assert tilt["lowest_height"] == pytest.approx(0.1)
    assert tilt["slices_left_out"] == 0
    straight = measure.axis_tilt(tower(lumps=False), [0, 0, 1.0], 0.5, *axes, 1.0)
    assert straight["thickness_spread_degrees"] == pytest.approx(0.0, abs=1e-6)
    assert straight["tilt_degrees"] == pytest.approx(np.degrees(np.arctan(np.hypot(0.1, 0.05))))
