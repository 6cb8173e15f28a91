"""A span's clearance (export.clearance) over a known ground and a known tree, worked out by hand,
and the classified cloud's ASPRS classes (export.classes) read back with laspy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jaxnerf_grid.export import catenary, classes, clearance, measure, survey
from jaxnerf_grid.export import conductors as cond

A, XV = 1600.0, 160.0                 # catenary parameter, lowest point's station (m)
ATTACH_Z = 14.9
GROUND_Z = 0.5                        # the ground: the plane z = 0.5 (n = +z, d = -0.5)


def span_curve() -> np.ndarray:
    """The span x = 7.6, y = s in [0, 320], z = ATTACH_Z + a (cosh((s - x_v) / a) - cosh(x_v / a)). [K, 3]"""
    theta = (-7.6, ATTACH_Z, math.pi / 2, -math.sinh(XV / A), 1.0 / A)
    return catenary.sample_span(theta, np.zeros(3), 0.25)


def tree(centre, radius: float, top: float, count: int = 4000, seed: int = 0) -> np.ndarray:
    """Points [count, 3] filling a vertical cylinder of the radius from the ground to `top`."""
    rng = np.random.default_rng(seed)
    r, phi = radius * np.sqrt(rng.uniform(size=count)), rng.uniform(0, 2 * np.pi, count)
    z = rng.uniform(GROUND_Z + 1.0, top, count)
    return np.stack([centre[0] + r * np.cos(phi), centre[1] + r * np.sin(phi), z], 1)


def test_lowest_point_clearance_over_a_known_ground():
    curve = span_curve()
    sag = A * (math.cosh(XV / A) - 1.0)
    height, point = clearance.lowest_above_ground(curve, [0.0, 0.0, 1.0], -GROUND_Z)
    assert height == pytest.approx(ATTACH_Z - sag - GROUND_Z, abs=1e-4)
    assert point[1] == pytest.approx(XV, abs=0.25)


def test_clearance_over_a_known_tree_beneath_the_span():
    curve = span_curve()
    # a tree 2 m across the wire (x = 9.6) at y = 100, its top at 5 m: the wire's height there by hand
    wire_z = ATTACH_Z + A * (math.cosh((100.0 - XV) / A) - math.cosh(XV / A))
    crown = tree((9.6, 100.0), 0.3, 5.0)
    ground = np.stack(np.meshgrid(np.linspace(-20, 20, 41), np.linspace(0, 320, 161)), -1).reshape(-1, 2)
    ground = np.concatenate([ground, np.full((len(ground), 1), GROUND_Z)], 1)
    far_tree = tree((40.0, 150.0), 0.5, 25.0, seed=1)          # outside the 10 m corridor: not counted
    cloud = np.concatenate([ground, crown, far_tree])
    out = clearance.objects_beneath(curve, cloud, [0.0, 0.0, 1.0], -GROUND_Z, 0.2, 10.0)
    # by hand: the wire's height over each crown point from the closed form, the least gap
    gaps = ATTACH_Z + A * (np.cosh((crown[:, 1] - XV) / A) - math.cosh(XV / A)) - crown[:, 2]
    worst = crown[np.argmin(gaps)]
    assert out["count"] == len(crown)
    assert out["clearance"] == pytest.approx(gaps.min(), abs=1e-3)
    assert out["clearance"] == pytest.approx(wire_z - 5.0, abs=0.05)          # about the crown's top
    assert out["horizontal_distance"] == pytest.approx(abs(worst[0] - 7.6), abs=1e-6)
    assert out["height_above_ground"] == pytest.approx(worst[2] - GROUND_Z, abs=1e-9)
    assert out["covered"][0] == pytest.approx(0.0, abs=1e-9) and out["covered"][1] == pytest.approx(320.0, abs=1.0)
    assert clearance.flag(6.0, out["clearance"], 20.0) is True
    assert clearance.flag(6.0, out["clearance"], 3.0) is False
    assert clearance.flag(6.0, out["clearance"], None) is None


def test_classified_las_reads_back_with_the_asprs_classes(tmp_path):
    laspy = pytest.importorskip("laspy")
    points = np.array([[0.0, 0.0, 0.5], [5.0, 5.0, 0.6], [5.0, 5.0, 0.9], [5.0, 5.0, 2.0], [5.0, 5.0, 9.0],
                       [0.0, 0.0, 20.0], [30.0, 30.0, 4.0]])
    box = (np.array([-4.0, -4.0, 1.0]), np.array([4.0, 4.0, 31.0]))
    building = np.array([False, False, False, False, False, False, True])
    got = classes.classify(points, [0.0, 0.0, 1.0], -0.5, 0.2, box, building)
    # heights 0, 0.1 (ground band) | 0.4 low | 1.5 medium | 8.5 high | inside the box: tower | building
    expected = [2, 2, 3, 4, 5, 15, 6]
    np.testing.assert_array_equal(got, expected)
    wire = np.array([[7.6, 10.0, 14.0], [7.6, 10.5, 13.9]])
    path = survey.write_las(tmp_path / "c.las", np.concatenate([points, wire]), np.full((9, 3), 0.5),
                            classification=np.concatenate([got, [classes.CONDUCTOR] * 2]))
    las = laspy.read(str(path))
    np.testing.assert_array_equal(np.asarray(las.classification), expected + [14, 14])
    np.testing.assert_allclose(np.stack([las.x, las.y, las.z], 1)[-2:], wire, atol=1e-3)


def test_the_report_table_shows_each_span_its_sigmas_and_its_flag():
    from jaxnerf_grid.report import markdown as report

    theta = np.array([-7.6, ATTACH_Z, math.pi / 2, -math.sinh(XV / A), 1.0 / A])
    fit = {"theta": theta, "cov": np.diag([1e-4, 1e-4, 1e-8, 1e-8, 1e-14]), "side": 1, "sigma_px": 0.5,
           "inlier_share": 0.9, "residuals": 100, "seen": 110, "stations": np.array([4.5, 320.0])}
    rec = cond.span_record(fit, np.zeros(3))
    rec["clearance"] = {"ground": 6.9, "ground_sigma": 0.01, "objects": None, "flag": True}
    lines = report.conductor_lines({"conductor_spans": {"found": 1, "photos": 40, "min_clearance": 8.0, "flagged": 1,
                                                        "spans": [rec]}}, "m", "conductors_views.png")
    text = "\n".join(lines)
    sag = A * (math.cosh(XV / A) - 1.0)
    assert f"{sag:.2f} +- " in text and "14.90 +- 0.01" in text and "6.90 +- 0.01" in text
    assert "**below**" in text and "clearance below 8.00 m: **1**" in text
    assert "![the fitted conductors on the photos](conductors_views.png)" in text
    assert "curvature from the photos alone" in text
    given = report.conductor_lines({"conductor_spans": {"found": 1, "photos": 40, "min_clearance": None,
                                                        "span_length": 320.0, "spans": [rec]}}, "m")
    assert "each a level span of 320.00 m (`export.span_length`)" in "\n".join(given)
    measured = {**rec, "span_length_shared": [320.9, 0.6],
                "next_tower": {"length": 320.9, "sigma": 0.6, "score": 0.2, "photos": 5, "pairs": 7}}
    other = {**rec, "side": -1, "span_length_shared": [319.6, 0.5], "next_tower": None}
    both = "\n".join(report.conductor_lines({"conductor_spans": {"found": 2, "photos": 40, "spans": [measured, other]}},
                                            "m"))
    assert ("side +: 320.90 +- 0.60 m, measured at the next tower, seen along the line in 5 photos; "
            "side -: 319.60 +- 0.50 m, from the wires' slopes and curvature") in both
    none = report.conductor_lines({"conductor_spans": {"found": 0, "photos": 40, "spans": [], "why": "no wire"}}, "m")
    assert "No conductor found in the 40 photos: no wire" in "\n".join(none)


# --------------------------------------------------------------------------- the ground beneath the lowest point

LOW = np.array([7.6, XV, 6.9])          # the span's lowest point (x = 7.6, y = x_v); the plane z = 0.5
RADIUS = clearance.GROUND_RADIUS_SHARE * 2 * XV   # 5 % of the 320 m span: 16 m
BAND = 0.3                              # the ground's clearance band: the tolerance 2 x 0.3 / 3 = 0.2


def ground_grid(y_lo: float, y_hi: float, z: float) -> np.ndarray:
    """The ground z over x in [-20, 20] every 1 m, y in [y_lo, y_hi] every 2 m. [N, 3]"""
    xy = np.stack(np.meshgrid(np.arange(-20.0, 20.5, 1.0), np.arange(y_lo, y_hi + 1.0, 2.0)), -1).reshape(-1, 2)
    return np.concatenate([xy, np.full((len(xy), 1), z)], 1)


def test_ground_seen_all_along_the_span_is_not_doubtful():
    """A flat ground on the plane sampled all along the span, and a tree 3-5 m tall beneath the
    lowest point (not ground: above the band): the ground points within 16 m of the point beneath,
    counted here by hand, their median height 0."""
    ground = ground_grid(0.0, 320.0, GROUND_Z)
    crown = tree((7.6, XV), 2.0, 5.5)
    seen = clearance.ground_seen(LOW, np.concatenate([ground, crown]), [0.0, 0.0, 1.0], -GROUND_Z, BAND, RADIUS)
    by_hand = sum(1 for x, y, _ in ground if math.hypot(x - 7.6, y - XV) <= 16.0)
    assert RADIUS == pytest.approx(16.0, abs=1e-12) and by_hand > 300
    assert seen == {"radius": RADIUS, "count": by_hand, "min_count": clearance.GROUND_MIN_POINTS,
                    "median_height": 0.0, "tolerance": pytest.approx(0.2, abs=1e-12), "doubtful": False,
                    "reason": None}


def test_ground_seen_only_near_the_tower_is_doubtful_too_few():
    """The cloud's ground reaches 20 m from the tower (the unit sphere's reach on the generated
    scenes), the lowest point 160 m out: no ground point within 16 m of the point beneath."""
    seen = clearance.ground_seen(LOW, ground_grid(-20.0, 20.0, GROUND_Z), [0.0, 0.0, 1.0], -GROUND_Z, BAND, RADIUS)
    assert seen["count"] == 0 and seen["median_height"] is None
    assert seen["doubtful"] is True and seen["reason"] == clearance.NOT_SEEN == "too few ground points"


def test_ground_two_metres_off_the_plane_beneath_is_doubtful():
    """The plane on the ground around the tower (z = 0.5, y < 100); beneath the span the ground
    2 m lower (z = -1.5): counted as ground (below the band's top), its median height -2 off the
    plane. 2 m higher instead (z = 2.5) it is above the band, no ground there: too few."""
    near_tower = ground_grid(0.0, 98.0, GROUND_Z)
    low = clearance.ground_seen(LOW, np.concatenate([near_tower, ground_grid(100.0, 320.0, GROUND_Z - 2.0)]),
                                [0.0, 0.0, 1.0], -GROUND_Z, BAND, RADIUS)
    assert low["count"] > 300 and low["median_height"] == pytest.approx(-2.0, abs=1e-12)
    assert low["doubtful"] is True and low["reason"] == clearance.OFF_PLANE == "ground off the plane"
    high = clearance.ground_seen(LOW, np.concatenate([near_tower, ground_grid(100.0, 320.0, GROUND_Z + 2.0)]),
                                 [0.0, 0.0, 1.0], -GROUND_Z, BAND, RADIUS)
    assert high["count"] == 0 and high["reason"] == clearance.NOT_SEEN


def test_ground_seen_thresholds_at_their_limits():
    """The plane z = 0, the lowest point (8, 160, 10), radius 16, band 0.75 (tolerance 2 x 0.75 / 3
    = 0.5 exactly). Exactly 10 points (GROUND_MIN_POINTS) within the radius, one at exactly 16 m:
    seen; 9, or that one 1e-9 m further out: too few. The median height exactly +-0.5: on the
    plane; 1e-9 past it: off."""
    assert clearance.GROUND_MIN_POINTS == 10
    point, up = np.array([8.0, 160.0, 10.0]), [0.0, 0.0, 1.0]

    def cloud(count: int, z: float, edge: float = 24.0) -> np.ndarray:
        pts = np.array([[8.0 + 0.5 * k, 160.0, z] for k in range(count - 1)] + [[edge, 160.0, z]])
        return np.concatenate([pts, [[8.0, 177.0, 0.0], [8.0, 160.0, 0.76]]])   # out of the radius; above the band

    def check(pts: np.ndarray) -> dict:
        return clearance.ground_seen(point, pts, up, 0.0, 0.75, 16.0)

    at = check(cloud(10, 0.0))
    assert (at["count"], at["tolerance"], at["doubtful"]) == (10, 0.5, False)
    assert check(cloud(9, 0.0))["reason"] == clearance.NOT_SEEN
    assert check(cloud(10, 0.0, edge=24.0 + 1e-9))["reason"] == clearance.NOT_SEEN
    for z in (0.5, -0.5):
        assert check(cloud(10, z))["doubtful"] is False
    for z in (0.5 + 1e-9, -0.5 - 1e-9):
        assert check(cloud(10, z))["reason"] == clearance.OFF_PLANE
    # a tolerance given overrides the band's
    assert clearance.ground_seen(point, cloud(10, 0.3), up, 0.0, 0.75, 16.0, tolerance=0.25)["reason"] == \
        clearance.OFF_PLANE


def _wire_and_ground(x_hi: float) -> tuple[np.ndarray, np.ndarray]:
    """A wire leaving the tower's box (x, y in [-1, 1]) at x = 1.25 and falling 0.25 m per 0.25 m
    to its lowest point (6, 0, 7), 5 m above the ground z = 2 (test_survey's wire), and that ground
    every 0.5 m over x in [-3, x_hi], y in [-3, 3]. Returns (wire [20, 3], ground [M, 3])."""
    k = np.arange(1.0, 21.0)
    wire = np.column_stack([1.0 + 0.25 * k, np.zeros_like(k), 12.0 - 0.25 * k])
    xy = np.stack(np.meshgrid(np.arange(-3.0, x_hi + 0.25, 0.5), np.arange(-3.0, 3.25, 0.5)), -1).reshape(-1, 2)
    return wire, np.concatenate([xy, np.full((len(xy), 1), 2.0)], 1)


def test_ground_beneath_the_heuristic_lowest_conductor_point_seen_or_not():
    """measure.conductor_clearance on a hand-built cloud (cells 0.5: its lowest point (6, 0, 7),
    its extent 5 m) then lowest_point_ground_seen with the ground's band 0.3: the radius is the
    floor, 5 cells = 2.5 m (5 % of 5 m is 0.25). The ground reaching x = 10: the ground points
    within 2.5 m of (6, 0), counted by hand, on the plane: sound. The ground only around the tower
    (x <= 3, 3 m from the point): none, doubtful (too few). Not reconstructed: None."""
    n, d, lo, hi = [0.0, 0.0, 1.0], -2.0, [-1.0, -1.0, 2.0], [1.0, 1.0, 12.0]
    for x_hi, doubtful in ((10.0, False), (3.0, True)):
        wire, ground = _wire_and_ground(x_hi)
        cloud = np.concatenate([wire, ground])
        cond_rec = measure.conductor_clearance(cloud, n, d, lo, hi, 4.5, 0.5)
        assert cond_rec["lowest_point"] == [6.0, 0.0, 7.0] and cond_rec["extent"] == 5.0
        seen = clearance.lowest_point_ground_seen(cond_rec, cloud, n, d, 0.3, 0.5)
        by_hand = sum(1 for x, y, _ in ground if math.hypot(x - 6.0, y) <= 2.5)
        assert seen["radius"] == 2.5 and seen["count"] == by_hand
        assert seen["doubtful"] is doubtful
        if doubtful:
            assert by_hand == 0 and seen["reason"] == clearance.NOT_SEEN
        else:
            assert by_hand > 60 and seen["median_height"] == 0.0 and seen["reason"] is None
    assert clearance.lowest_point_ground_seen({"reconstructed": False, "why": "-"}, cloud, n, d, 0.3, 0.5) is None
    assert clearance.lowest_point_ground_seen(None, cloud, n, d, 0.3, 0.5) is None


def test_heuristic_radius_is_five_percent_of_the_wire_groups_extent_above_the_floor():
    """A wire group reaching 100 m from the tower: the radius 5 m (5 % of 100, above the 2.5 m
    floor of 5 cells of 0.5). Ten ground points at exactly 5 m from the lowest point (10, 0, 8)
    along x and y, then 1e-9 m further: seen, then not."""
    cond_rec = {"reconstructed": True, "lowest_point": [10.0, 0.0, 8.0], "extent": 100.0}
    for r, doubtful in ((5.0, False), (5.0 + 1e-9, True)):
        ring = np.array([[10.0 + r, 0.0, 0.0], [10.0 - r, 0.0, 0.0], [10.0, r, 0.0], [10.0, -r, 0.0]] * 3)[:10]
        seen = clearance.lowest_point_ground_seen(cond_rec, ring, [0.0, 0.0, 1.0], 0.0, 0.3, 0.5)
        assert seen["radius"] == 5.0 and seen["doubtful"] is doubtful
