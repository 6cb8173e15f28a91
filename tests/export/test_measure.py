"""The corners of export/measure.py's `cross_arms` and `axis_tilt`: an arm in the lowest slice, slices of
exactly two points, widths exactly `ratio` apart, slices under 1 m across, the median count over
slices with points only, the MAD rule's constants and its third pass, a fit left with exactly
three slices or two. Each answer is worked out by hand in the docstring (level ground z = 0,
axis a = x, axis b = y, so a height is z and a width a difference of coordinates) or taken from
scipy's linregress on the centres that should be used."""

import numpy as np
import pytest
from scipy.stats import linregress

from jaxnerf_grid.export import measure

UP, X, Y = [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]


# --------------------------------------------------------------------------- cross_arms
# slices 1 high from z = 0 (the lowest point): slice k holds z in [k, k + 1); every slice's points
# sit at z = k and k + 0.5


def _layer(k: int, ab) -> list:
    """Points [(a, b, z)] of slice k at the given (a, b), alternately at z = k and k + 0.5."""
    return [(a, b, k + 0.5 * (i % 2)) for i, (a, b) in enumerate(ab)]


SQUARE = [(a, b) for a in (-0.5, 0.5) for b in (-0.5, 0.5)]            # 1 x 1: not wide


def _arm(n: int, half: float) -> list:
    """n points along a in [-half, half], at b = -0.5 and 0.5 alternately (width 1 along b)."""
    return [(a, 0.5 if i % 2 else -0.5) for i, a in enumerate(np.linspace(-half, half, n))]


def _levels(arms: dict) -> list:
    return [(lv["height"], lv["span"], lv["axis"]) for lv in arms["levels"]]


def test_cross_arms_of_an_arm_in_the_lowest_slice_and_the_lowest_slices_neighbours():
    """Tower 1: slice 0 an arm of 8 points along a in [-3, 3] (6 x 1: wide), slices 1-4 squares
    of 4, slice 5 (the top) 10 points in a 1 x 1 square. Counts [8, 4, 4, 4, 4, 10], median 4:
    a level holds >= 6 points, slice 0 holds 8, has no slice below and 4 above: a level at 0.5,
    its span the arm's 6 (slices 0-1), its ends (-3, 0, 0.5) and (3, 0, 0.5); the region [0, 1].
    Tower 2: slice 0 the 10-point square, slice 1 the arm, slices 2-5 squares: the arm has 8
    points, fewer than the 10 below it: the region [1, 2] and no level."""
    ten = SQUARE + [(a, b) for a in (-0.5, 0.0, 0.5) for b in (-0.25, 0.25)]
    one = np.asarray(_layer(0, _arm(8, 3.0)) + sum((_layer(k, SQUARE) for k in range(1, 5)), [])
                     + _layer(5, ten), np.float64)
    arms = measure.cross_arms(one, UP, 0.0, X, Y, slice_height=1.0)
    assert arms["region"] == [0.0, 1.0]
    assert _levels(arms) == [(0.5, 6.0, "a")]
    np.testing.assert_allclose(arms["levels"][0]["ends"], [[-3.0, 0.0, 0.5], [3.0, 0.0, 0.5]], atol=1e-12)
    two = np.asarray(_layer(0, ten) + _layer(1, _arm(8, 3.0)) + sum((_layer(k, SQUARE) for k in range(2, 6)), []),
                     np.float64)
    arms = measure.cross_arms(two, UP, 0.0, X, Y, slice_height=1.0)
    assert arms["region"] == [1.0, 2.0] and arms["levels"] == []


def test_cross_arms_counts_a_slice_of_two_points_and_spans_one_slice_either_side():
    """Slice 0 two points at a = -5 and 5 (10 wide, 0 across: wide; 2 points, no level), slice 1
    a square, slice 2 an arm of 12 points along a in [-2, 2] (wide), slices 3-4 squares. Counts
    [2, 4, 12, 4, 4], median 4: slice 2 is the one level, at 2.5, its span over slices 1-3 4 (not
    the 10 of slice 0, two below); the region [0, 3] (from the two-point slice)."""
    q = np.asarray(_layer(0, [(-5.0, 0.0), (5.0, 0.0)]) + _layer(1, SQUARE) + _layer(2, _arm(12, 2.0))
                   + _layer(3, SQUARE) + _layer(4, SQUARE), np.float64)
    arms = measure.cross_arms(q, UP, 0.0, X, Y, slice_height=1.0)
    assert arms["region"] == [0.0, 3.0]
    assert _levels(arms) == [(2.5, 4.0, "a")]
    np.testing.assert_allclose(arms["levels"][0]["ends"], [[-2.0, 0.0, 2.5], [2.0, 0.0, 2.5]], atol=1e-12)


@pytest.mark.parametrize("axes", [(X, Y), (Y, X)], ids=["wide along a", "wide along b"])
def test_cross_arms_widths_exactly_ratio_apart_are_not_wide(axes):
    """Slices 0-3 squares, slice 4 a rectangle 1.5 along x and 1 along y: exactly ratio 1.5 apart,
    so not wide (the rule is `>`): no region, along either axis. 0.99 along y instead: wide, the
    region [4, 5] (axes given either way round: the first rule or the second)."""
    body = sum((_layer(k, SQUARE) for k in range(4)), [])
    exact = np.asarray(body + _layer(4, [(a, b) for a in (-0.75, 0.75) for b in (-0.5, 0.5)]), np.float64)
    assert measure.cross_arms(exact, UP, 0.0, *axes, slice_height=1.0)["region"] is None
    wider = np.asarray(body + _layer(4, [(a, b) for a in (-0.75, 0.75) for b in (-0.495, 0.495)]), np.float64)
    assert measure.cross_arms(wider, UP, 0.0, *axes, slice_height=1.0)["region"] == [4.0, 5.0]


def test_cross_arms_median_counts_only_the_slices_with_points():
    """Tower 1: slice 0 a square, slices 1-4 empty, slice 5 an arm of 5 points, slice 6 a square.
    Counts [4, 0, 0, 0, 0, 5, 4]: the median of the slices with points is 4 (not the 0 of all
    seven), a level needs 6: the region [5, 6], no level. Tower 2: slices 0-2 one point each,
    slice 3 an arm of 6, slice 4 a square: counts [1, 1, 1, 6, 4], median 1 (one-point slices
    count), a level needs 1.5: slice 3 is a level at 3.5, span 4."""
    gaps = np.asarray(_layer(0, SQUARE) + _layer(5, _arm(5, 2.0)) + _layer(6, SQUARE), np.float64)
    arms = measure.cross_arms(gaps, UP, 0.0, X, Y, slice_height=1.0)
    assert arms["region"] == [5.0, 6.0] and arms["levels"] == []
    ones = np.asarray(_layer(0, [(0.0, 0.0)]) + _layer(1, [(0.0, 0.0)]) + _layer(2, [(0.0, 0.0)])
                      + _layer(3, _arm(6, 2.0)) + _layer(4, SQUARE), np.float64)
    arms = measure.cross_arms(ones, UP, 0.0, X, Y, slice_height=1.0)
    assert arms["region"] == [3.0, 4.0]
    assert _levels(arms) == [(3.5, 4.0, "a")]


def _level(height: float, span: float, axis: str = "a") -> dict:
    return {"height": height, "span": span, "axis": axis, "ends": []}


def test_arm_levels_leave_out_the_footings_a_level_across_the_arms_and_an_arms_top_chord():
    """A 30 m tower's levels as an export measured them: the pad at 0.4 m (10 long), a bracing at
    9.9 m along b, the arms at 17.3, 21.6 and 25.5 m along a, and 19.1 m (8.6 long, the 17.3 m
    arm's top chord). Along a: 5 levels against 1. A third of 30 is 10: the pad goes (9.9 goes as
    across); an arm's depth is 0.08 x 30 = 2.4: 19.1 lies 1.8 above 17.3 (13.8 long) and 2.5 below
    21.6, so it goes against 17.3's longer span; 17.3, 21.6 and 25.5 stay, 4 m apart."""
    arms = {"slice_height": 0.3, "levels": [_level(0.4, 10.0), _level(9.9, 5.7, "b"), _level(17.3, 13.8),
                                            _level(19.1, 8.6), _level(21.7, 17.7), _level(25.5, 15.5)]}
    out = measure.arm_levels(arms, 30.0)
    assert [lv["height"] for lv in out["levels"]] == [17.3, 21.7, 25.5]
    assert out["slice_height"] == 0.3
    why = {lv["height"]: lv["why"] for lv in out["left_out"]}
    assert sorted(why) == [0.4, 9.9, 19.1]
    assert "third" in why[0.4] and "across" in why[9.9] and "17.3" in why[19.1]


def test_arm_levels_keep_the_longer_of_two_within_an_arms_depth_whichever_is_higher_and_break_an_axis_tie():
    """Two levels 1 m apart on a 30 m tower (depth 2.4): the upper one longer (16 against 9) is
    kept. Levels along a and b two each: the tie goes to the axis of the longest level (b, 18)."""
    out = measure.arm_levels({"levels": [_level(20.0, 9.0), _level(21.0, 16.0)]}, 30.0)
    assert [lv["height"] for lv in out["levels"]] == [21.0]
    tie = measure.arm_levels({"levels": [_level(15.0, 12.0), _level(20.0, 12.0), _level(24.0, 18.0, "b"),
                                         _level(28.0, 10.0, "b")]}, 30.0)
    assert [lv["height"] for lv in tie["levels"]] == [24.0, 28.0]
    assert measure.arm_levels({"levels": []}, 30.0)["levels"] == []


def _lattice_tower(theta_deg: float) -> tuple[np.ndarray, list[float]]:
    """A tower's surface points [N, 3] on level ground z = 0: four legs from (+-4, +-4) at z = 0 to
    (+-1, +-1) at z = 30 (the +x+y leg and the -x-y one reach down to z = 0, the other two stop
    at z = 2, so the lowest band holds two feet on a diagonal), and three arms at z = 15, 19, 23,
    each 16 long and 0.5 wide, centred on the axis, along the direction theta_deg from x.
    Returns (points, the arms' heights)."""
    pts = []
    for sx, sy in ((1, 1), (-1, -1), (1, -1), (-1, 1)):
        z0 = 0.0 if sx == sy else 2.0
        for z in np.arange(z0, 30.0, 0.1):
            r = 4.0 - 3.0 * z / 30.0
            pts.append((sx * r, sy * r, z))
    t = np.radians(theta_deg)
    along, across = np.array([np.cos(t), np.sin(t)]), np.array([-np.sin(t), np.cos(t)])
    heights = [15.0, 19.0, 23.0]
    for z in heights:
        for u in np.arange(-8.0, 8.01, 0.1):
            for v in (-0.25, 0.25):
                for dz in (0.0, 0.2):
                    pts.append((*(u * along + v * across), z + dz))
    return np.asarray(pts), heights


def test_arm_axes_lie_along_the_arms_whatever_the_legs():
    """The tower above with arms at 20 degrees from x: the arms' axis within 0.5 degrees of 20 (or
    200), the other axis a quarter turn from it, both in the ground plane."""
    pts, _ = _lattice_tower(20.0)
    axis, across = measure.arm_axes(pts, UP, 0.0)
    angle = np.degrees(np.arctan2(axis[1], axis[0])) % 180.0
    assert abs(angle - 20.0) < 0.5
    np.testing.assert_allclose([axis @ across, axis[2], across[2]], 0.0, atol=1e-12)
    np.testing.assert_allclose([np.linalg.norm(axis), np.linalg.norm(across)], 1.0, atol=1e-12)


def test_cross_arms_along_the_arm_axes_finds_every_arm_where_the_footprint_axes_find_none():
    """The tower above (arms along x): its footprint is the two feet on the diagonal, a rectangle
    along (1, 1) / sqrt 2, across which an arm along x is as wide as along it, so no slice is
    wide and no level is found; along `arm_axes` every arm is found, within one 0.3-high slice
    of its middle height (z + 0.1), each span 16 within one point spacing and two slices' spread."""
    pts, heights = _lattice_tower(0.0)
    fp = measure.footprint(pts, UP, 0.0, band=1.5)
    assert abs(abs(fp["axis_a"][0]) - np.sqrt(0.5)) < 1e-6
    assert measure.cross_arms(pts, UP, 0.0, fp["axis_a"], fp["axis_b"], slice_height=0.3)["levels"] == []
    arms = measure.cross_arms(pts, UP, 0.0, *measure.arm_axes(pts, UP, 0.0), slice_height=0.3)
    found = sorted(lv["height"] for lv in arms["levels"])
    assert len(found) == 3
    np.testing.assert_allclose(found, np.array(heights) + 0.1, atol=0.3)   # the arm's middle height
    np.testing.assert_allclose([lv["span"] for lv in arms["levels"]], 16.0, atol=0.2)


# --------------------------------------------------------------------------- axis_tilt
# slice k of a tower: a square (or rectangle) of 4 points centred on (a, b), two at z = k + 0.25,
# two at k + 0.75 (mean height k + 0.5; the lowest point 0.25 starts the slices, so slice k is
# z in [k + 0.25, k + 1.25)); on level ground each centre's offset from a fitted line is exact


def _slab(k: int, a: float, b: float, half_a: float = 0.25, half_b: float | None = None) -> list:
    hb = half_a if half_b is None else half_b
    return [(a - half_a, b - hb, k + 0.25), (a + half_a, b + hb, k + 0.25),
            (a - half_a, b + hb, k + 0.75), (a + half_a, b - hb, k + 0.75)]


def _tower(centres) -> np.ndarray:
    """centres: [(a, b)] of slices 0, 1, ... -> points [4 K, 3]."""
    return np.asarray(sum((_slab(k, a, b) for k, (a, b) in enumerate(centres)), []), np.float64)


def _tilt(q, **kw):
    return measure.axis_tilt(np.asarray(q, np.float64), UP, 0.0, X, Y, 1.0, **kw)


def test_axis_tilt_uses_widths_exactly_ratio_apart_and_drops_a_narrow_arm():
    """Tower 1: slices 0-2 squares 1 x 1 on the axis, slice 3 a rectangle 1.5 x 1 (exactly ratio
    1.5 apart: not wide, so a centre) whose centre is 0.25 out along a: four centres, the slope
    of a(h) linregress' over them. Tower 2: slices 0-3 squares 0.2 x 0.2 on the axis, slice 4 an
    arm 0.6 x 0.2 (a in [-0.1, 0.5]): 0.6 > 1.5 x 0.2, wide although under 1 m across, left
    out: four slices, no tilt."""
    q = sum((_slab(k, 0.0, 0.0, 0.5) for k in range(3)), []) + _slab(3, 0.25, 0.0, 0.75, 0.5)
    tilt = _tilt(q)
    fit = linregress([0.5, 1.5, 2.5, 3.5], [0.0, 0.0, 0.0, 0.25])
    assert (tilt["slices"], tilt["slices_left_out"]) == (4, 0)
    assert tilt["tilt_degrees"] == pytest.approx(np.degrees(np.arctan(fit.slope)), rel=1e-9)
    narrow = sum((_slab(k, 0.0, 0.0, 0.1) for k in range(4)), []) + _slab(4, 0.2, 0.0, 0.3, 0.1)
    tilt = _tilt(narrow)
    assert (tilt["slices"], tilt["slices_left_out"]) == (4, 0)
    assert tilt["tilt_degrees"] == pytest.approx(0.0, abs=1e-9)


def _balanced(n: int, tiers: dict, normals: dict) -> list:
    """Centres [(a, b)] of n slices: tiers {offset X: (k1, k2, k3, k4)}: a = +X at k1, k4 and -X
    at k2, k3 (symmetric about the middle height, so they add nothing to the fitted lines: both
    stay a = b = 0); normals {k: b}."""
    centres = [(0.0, 0.0)] * n
    for x, (k1, k2, k3, k4) in tiers.items():
        for k, sign in ((k1, 1), (k2, -1), (k3, -1), (k4, 1)):
            centres[k] = (sign * x, 0.0)
    for k, b in normals.items():
        centres[k] = (0.0, b)
    return centres


def test_axis_tilt_mad_rule_drops_past_4_45_mads_and_keeps_its_threshold():
    """Nine slices (middle height 4.5); the fitted lines are a = b = 0 whatever is kept. Five
    normal centres at b = s, -s, 0, -s, s (slices 0, 1, 4, 7, 8) and four outliers at a = +U, -U,
    -U, +U (slices 2, 3, 5, 6). Offsets: s x 4, 0, U x 4; their median s, the median absolute
    deviation s. With s = 0.2 and U = 1.04 = 5.2 s, past 3 x 1.4826 s = 0.89 (and the floor
    0.5): the four are left out (then the MAD of the five is 0, the floor keeps them); 4 x
    1.4826 s = 1.19, 3 x 2.4826 s = 1.49 or the deviations from -median (median 2 s) would keep
    them. With s = 27/64 and U exactly 3 x (1.4826 s) (every sum and product here exact in
    float64) the outliers sit on the threshold and are kept (`<=`)."""
    tiers, normals = (2, 3, 5, 6), {0: 1.0, 1: -1.0, 4: 0.0, 7: -1.0, 8: 1.0}
    s = 0.2
    tilt = _tilt(_tower(_balanced(9, {5.2 * s: tiers}, {k: v * s for k, v in normals.items()})))
    assert (tilt["slices"], tilt["slices_left_out"]) == (5, 4)
    assert tilt["tilt_degrees"] == pytest.approx(0.0, abs=1e-9)
    s = 27 / 64
    threshold = 3.0 * (1.4826 * s)
    tilt = _tilt(_tower(_balanced(9, {threshold: tiers}, {k: v * s for k, v in normals.items()})))
    assert (tilt["slices"], tilt["slices_left_out"]) == (9, 0)


def test_axis_tilt_mad_rule_runs_two_passes_not_three():
    """17 slices (middle height 8.5): normals b = 0.1, -0.1, 0, -0.1, 0.1 at slices 6-10 and three
    balanced tiers off along a: 1 (slices 5, 4, 12, 11), 4.2 (3, 2, 14, 13), 10 (1, 0, 16, 15).
    Pass 1 (all 17): median offset 1, MAD 1, threshold 4.45: the 10s go. Pass 2 (13): median 1,
    MAD 0.9, threshold 4.00: the 4.2s go. That is the last pass: 9 slices kept, 8 left out (a
    third, MAD 0.1, threshold max(0.445, 0.5), would drop the 1s too)."""
    centres = _balanced(17, {1.0: (5, 4, 12, 11), 4.2: (3, 2, 14, 13), 10.0: (1, 0, 16, 15)},
                        {6: 0.1, 7: -0.1, 8: 0.0, 9: -0.1, 10: 0.1})
    tilt = _tilt(_tower(centres))
    assert (tilt["slices"], tilt["slices_left_out"]) == (9, 8)
    assert tilt["tilt_degrees"] == pytest.approx(0.0, abs=1e-9)


def test_axis_tilt_goes_on_with_three_slices_and_stops_at_two():
    """Seven slices: three on the axis (2, 3, 4), four balanced 2 off (a = +2 at 1, 5, -2 at 0,
    6). Offsets 0 x 3, 2 x 4: median 2, MAD 0, the floor 0.5 keeps the three: exactly three are
    enough, the fit goes on without the four. Six slices: two on the axis (2, 3), four 2 off
    (+2 at 0, 5, -2 at 1, 4): the rule would keep two, too few: it stops and keeps all six."""
    tilt = _tilt(_tower(_balanced(7, {2.0: (1, 0, 6, 5)}, {})))
    assert (tilt["slices"], tilt["slices_left_out"]) == (3, 4)
    tilt = _tilt(_tower(_balanced(6, {2.0: (0, 1, 4, 5)}, {})))
    assert (tilt["slices"], tilt["slices_left_out"]) == (6, 0)
    assert tilt["tilt_degrees"] == pytest.approx(0.0, abs=1e-9)


# --------------------------------------------------------------------------- the picture

SHIFT = np.array([10.0, -5.0, 3.0])


def _ortho_cloud():
    """A (0, 0, 0), B (92, 40, 20), C (46, 20, 10) (the middle), D (46, 30, 10) (behind C seen
    from -y), E (60, 20, 10) (in front of C seen from +x), all moved by SHIFT (the picture is
    centred on the cloud's middle: no pixel moves), each its own colour, B's outside [0, 1]
    (drawn clipped: (1, 0, 0.5)). The largest extent is 92, so at size 100 one unit is one pixel
    ((100 - 8) / 92) and the middle lands on the panel's centre (50, 50). Returns (points,
    colours given, colours drawn)."""
    pts = np.array([[0.0, 0.0, 0.0], [92.0, 40.0, 20.0], [46.0, 20.0, 10.0], [46.0, 30.0, 10.0],
                    [60.0, 20.0, 10.0]]) + SHIFT
    cols = np.array([[1.0, 0.0, 0.0], [1.5, -0.5, 0.5], [0.0, 0.0, 1.0], [0.5, 0.5, 0.0], [0.0, 0.5, 0.5]])
    return pts, cols, np.clip(cols, 0, 1)


# {(row, column): point} in each panel, worked out by hand: front (x-z seen from -y): column
# 50 + (x - 46), row 50 - (z - 10); side (y-z seen from +x): column 50 + (y - 20), row as the
# front's; top (x-y seen from +z): column as the front's, row 50 - (y - 20) (before SHIFT). D
# hides behind C in the front panel (the viewer at -y sees the smaller y), C behind E in the side
# panel (the viewer at +x sees the larger x).
ORTHO_PIXELS = [{(60, 4): 0, (40, 96): 1, (50, 50): 2, (50, 64): 4},
                {(60, 30): 0, (40, 70): 1, (50, 50): 4, (50, 60): 3},
                {(70, 4): 0, (30, 96): 1, (50, 50): 2, (40, 50): 3, (50, 64): 4}]
# the shade of a normal (0.48, 0.6, 0.64) seen from -y, +x, +z: 0.35 + 0.65 |n . view|
ORTHO_SHADE = [0.35 + 0.65 * 0.6, 0.35 + 0.65 * 0.48, 0.35 + 0.65 * 0.64]


def _drawn(panel, background):
    return {tuple(int(v) for v in rc) for rc in np.argwhere(np.any(panel != background, axis=-1))}


def test_orthographic_views_draw_a_known_cloud_at_the_pixels_worked_out_by_hand():
    """Each panel (100 x 100, 4 pixels apart: columns 0, 104, 208) holds exactly the points'
    pixels worked out by hand (ORTHO_PIXELS), in their colours clipped to [0, 1], the rest the
    background; shaded by the normal (0.48, 0.6, 0.64) by ORTHO_SHADE; a splat of 1 paints
    exactly the 3 x 3 pixels around each point; the same cloud 200 times smaller is drawn at
    the same pixels (one scale: the largest extent fills 92 pixels); a grey background; the
    empty cloud; the default size 400."""
    pts, cols, drawn = _ortho_cloud()
    img = measure.orthographic_views(pts, cols, size=100, labels=False)
    assert img.shape == (100, 308, 3) and img.dtype == np.float32
    normals = np.tile([0.48, 0.6, 0.64], (len(pts), 1))
    shaded = measure.orthographic_views(pts, cols, normals, size=100, labels=False)
    splat = measure.orthographic_views(pts, cols, size=100, labels=False, splat=1, background=0.5)
    small = measure.orthographic_views(pts * 0.005, cols, size=100, labels=False)
    np.testing.assert_array_equal(small, img)
    for k, pixels in enumerate(ORTHO_PIXELS):
        x0 = 104 * k
        assert _drawn(img[:, x0:x0 + 100], 1.0) == set(pixels), k
        for (row, col), i in pixels.items():
            np.testing.assert_allclose(img[row, x0 + col], drawn[i], atol=1e-7)
            np.testing.assert_allclose(shaded[row, x0 + col], drawn[i] * ORTHO_SHADE[k], atol=1e-6)
            assert np.all(np.abs(splat[row - 1:row + 2, x0 + col - 1:x0 + col + 2] - drawn[i]) < 1e-7), (k, i)
            assert np.all(np.abs(splat[:, x0:x0 + 100] - drawn[i]) < 1e-7, axis=-1).sum() == 9, (k, i)
        assert len(_drawn(splat[:, x0:x0 + 100], 0.5)) == 9 * len(pixels)
    assert np.all(img[:, 100:104] == 1.0) and np.all(img[:, 204:208] == 1.0)      # the gaps
    assert np.all(splat[:, 100:104] == 0.5)
    empty = measure.orthographic_views(np.zeros((0, 3)), np.zeros((0, 3)), size=20, labels=False, background=0.25)
    assert empty.shape == (20, 68, 3) and np.all(empty == 0.25)
    assert measure.orthographic_views(pts, cols, labels=False).shape == (400, 1208, 3)


def test_orthographic_views_scale_on_an_odd_size_and_splats_cut_at_the_panel_edges():
    """Size 101, (0, 0, 0) and (93, 0, 0): 93 pixels for 93 units, centre 50.5: columns 4 and
    97, row 50 (50.5 rounds to even). Size 100, (0, 0, 0) and (92, 0, 92) with a splat of 4:
    the front panel's 9 x 9 blocks about (row 96, column 4) and (row 4, column 96) are cut at the
    panel's edges (rows 92-99 x columns 0-8 and rows 0-8 x columns 92-99), nothing wraps."""
    img = measure.orthographic_views(np.array([[0.0, 0, 0], [93.0, 0, 0]]), np.array([[1.0, 0, 0], [0, 1.0, 0]]),
                                     size=101, labels=False)
    assert _drawn(img[:, :101], 1.0) == {(50, 4), (50, 97)}
    np.testing.assert_array_equal(img[50, 97], [0.0, 1.0, 0.0])
    img = measure.orthographic_views(np.array([[0.0, 0, 0], [92.0, 0, 92]]), np.array([[1.0, 0, 0], [0, 1.0, 0]]),
                                     size=100, labels=False, splat=4)
    want = {(r, c) for r in range(92, 100) for c in range(0, 9)} | {(r, c) for r in range(0, 9) for c in range(92, 100)}
    assert _drawn(img[:, :100], 1.0) == want


def test_orthographic_views_labels_each_panel_in_its_corner():
    """labels=True: each panel's name, "front (x-z)", "side (y-z)", "top (x-y)", in OpenCV's
    Hershey simplex at 0.45, dark grey (40, 40, 40), 1 px, anti-aliased, its baseline at (6, 16)
    of the panel, on the 8-bit picture (the expected image drawn here with those literals); without
    OpenCV the picture is returned unlabelled."""
    from jaxnerf_grid.util import io

    cv2 = io.opencv()
    pts, cols, _ = _ortho_cloud()
    plain = measure.orthographic_views(pts, cols, size=100, labels=False)
    labelled = measure.orthographic_views(pts, cols, size=100)
    want = np.ascontiguousarray((plain * 255).astype(np.uint8))
    for x0, name in ((6, "front (x-z)"), (110, "side (y-z)"), (214, "top (x-y)")):
        cv2.putText(want, name, (x0, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (40, 40, 40), 1, cv2.LINE_AA)
    assert labelled.dtype == np.float32
    np.testing.assert_array_equal(np.round(labelled * 255).astype(np.uint8), want)
    np.testing.assert_array_equal(labelled[60, 4], [1.0, 0.0, 0.0])            # A, below the labels
    for x0 in (0, 104, 208):                                     # each panel's corner is written on
        corner = want[4:20, x0 + 6:x0 + 60]
        assert (corner < 128).any(axis=-1).sum() > 30
    assert not np.array_equal(want[4:20, 6:60], want[4:20, 110:164])     # different names

    def no_opencv():
        raise ImportError("no cv2")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(io, "opencv", no_opencv)
        np.testing.assert_array_equal(measure.orthographic_views(pts, cols, size=100), plain)
