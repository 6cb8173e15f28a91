"""`jaxnerf-grid export` (docs/EXPORT.md): marching cubes on analytic densities, the
metric round trip, the RANSAC ground, depth fusion, the measurements, the scores against brute
force, the PLY read back by plyfile, and the command's refusals on bad input."""


import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.data.normalize import apply_normalization_to_points
from jaxnerf_grid.eval import export_score as score_lib
from jaxnerf_grid.eval import geometry
from jaxnerf_grid.export import fuse, ground, measure, mesh, plane_to_metric, to_metric, to_metric64, to_scene
from jaxnerf_grid.render.clouds import lift_view
from jaxnerf_grid.util import io
from tests.train.test_loop import TINY_FIELD, tiny_dataset

NORM = {"scale": 0.05, "translation": [3.0, -2.0, -15.0]}


# --------------------------------------------------------------------------- marching cubes


def _grid(resolution=40, half=1.0):
    origin, h, shape = mesh.grid_spec([-half] * 3, [half] * 3, resolution)
    return origin, h, shape, mesh.grid_points(origin, h, shape).astype(np.float64)


def test_grid_spec_covers_the_box_with_resolution_voxels_on_the_longest_side():
    origin, h, shape = mesh.grid_spec([0, 0, 0], [2.0, 1.0, 0.35], 20)
    assert h == pytest.approx(0.1) and shape[0] == 21 and shape[1] == 11 and shape[2] == 5
    last = origin + h * (np.array(shape) - 1)
    assert np.all(origin <= 1e-9) and np.all(last >= np.array([2.0, 1.0, 0.35]) - 1e-9)
    np.testing.assert_allclose(0.5 * (origin + last), [1.0, 0.5, 0.175])      # centred on the box


def test_density_threshold_gives_the_opacity_of_one_voxel():
    for h, a in ((0.01, 0.5), (0.2, 0.05), (1.0, 0.9)):
        sigma = mesh.density_threshold(h, a)
        assert 1 - np.exp(-sigma * h) == pytest.approx(a)
    assert mesh.density_threshold(0.01, 0.5) == pytest.approx(np.log(2) / 0.01)
    assert mesh.density_threshold(0.01) == pytest.approx(-np.log(0.95) / 0.01)   # the default: 5 %


def test_marching_cubes_on_a_sphere_lies_on_the_surface_and_is_closed():
    origin, h, shape, p = _grid(40)
    r0 = 0.6
    level = mesh.density_threshold(h)
    density = level * np.exp(-8.0 * (np.linalg.norm(p, axis=-1) - r0))   # = level exactly on |x| = r0
    verts, faces, normals = mesh.extract_mesh(density, level, origin, h)
    radius = np.linalg.norm(verts, axis=1)
    assert len(faces) > 1000 and np.max(np.abs(radius - r0)) <= h
    assert mesh.is_closed(faces)
    assert np.all(np.sum(normals * verts, axis=1) > 0)          # normals point out of the dense side
    # the enclosed volume (divergence theorem) is the ball's
    tri = verts[faces]
    volume = np.sum(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))) / 6
    assert volume == pytest.approx(4 / 3 * np.pi * r0 ** 3, rel=0.03)


def test_marching_cubes_on_a_box_closes_at_the_grid_border():
    origin, h, shape, p = _grid(30)
    level = mesh.density_threshold(h)
    half = np.array([0.5, 0.3, 2.0])                          # taller than the grid: cut by its border
    density = np.where(np.all(np.abs(p) <= half, axis=-1), 50.0 * level, 0.0)
    verts, faces, _ = mesh.extract_mesh(density, level, origin, h)
    assert mesh.is_closed(faces)
    clipped = np.minimum(half, 1.0)
    # distance to the (clipped) box's surface: outside, or inside to the nearest face
    q = np.abs(verts) - clipped
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = -np.max(np.minimum(q, 0), axis=1)
    dist = np.where(np.any(q > 0, axis=1), outside, inside)
    assert np.max(dist) <= h + 1e-9


def test_no_surface_gives_an_empty_mesh():
    origin, h, shape, _ = _grid(8)
    verts, faces, _ = mesh.extract_mesh(np.zeros(shape), 1.0, origin, h)
    assert verts.shape == (0, 3) and faces.shape == (0, 3) and not mesh.is_closed(faces)


def test_small_components_are_removed():
    origin, h, shape, p = _grid(40)
    level = 1.0
    big = np.linalg.norm(p - [0.3, 0, 0], axis=-1) < 0.5
    small = np.linalg.norm(p - [-0.75, 0.6, 0.6], axis=-1) < 0.12
    verts, faces, normals = mesh.extract_mesh(np.where(big | small, 10.0, 0.0), level, origin, h)
    labels = mesh.face_components(faces, len(verts))
    assert labels.max() == 1
    sizes = np.bincount(labels)
    v2, f2, (n2,), stats = mesh.remove_small_components(verts, faces, 0.2, (normals,))
    assert stats["components"] == 2 and stats["kept_components"] == 1
    assert stats["kept_face_fraction"] == pytest.approx(sizes.max() / sizes.sum())
    assert len(f2) == sizes.max() and mesh.is_closed(f2) and len(n2) == len(v2)
    assert np.all(v2[:, 0] > -0.3)                            # the small one is gone
    np.testing.assert_array_equal(np.unique(f2), np.arange(len(v2)))   # every vertex used


# --------------------------------------------------------------------------- metric units


def test_metric_round_trip():
    rng = np.random.default_rng(0)
    metric = rng.uniform(-20, 40, (100, 3))
    scene = apply_normalization_to_points(metric, NORM)              # the loaders' map
    np.testing.assert_allclose(to_metric(scene, NORM), metric, atol=1e-4)
    np.testing.assert_allclose(to_scene(metric, NORM), scene, atol=1e-12)
    # a plane: points of a metric plane, normalised, fitted there and mapped back
    n = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    pts = rng.uniform(-10, 10, (50, 3))
    pts -= ((pts @ n) + 2.5)[:, None] * n                           # on n . x + 2.5 = 0
    n_s, d_s = ground.refine_plane(apply_normalization_to_points(pts, NORM))
    n_m, d_m = plane_to_metric(n_s, d_s, NORM)
    np.testing.assert_allclose(n_m, n, atol=1e-9)
    assert d_m == pytest.approx(2.5, abs=1e-6)


def test_metric_round_trip_with_rotation():
    """A record with a rotation (docs/DATASET.md: x_norm = s R (x + t)): to_scene, to_metric and
    plane_to_metric against that formula written out; without one, the old formula bit for bit."""
    rng = np.random.default_rng(2)
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    r = q * np.sign(np.linalg.det(q))                                # a random rotation
    norm = {"scale": 0.05, "translation": [3.0, -1.0, -15.0], "rotation": r.tolist()}
    metric = rng.uniform(-20, 40, (100, 3))
    scene = np.stack([0.05 * r @ (x + norm["translation"]) for x in metric])
    np.testing.assert_allclose(to_scene(metric, norm), scene, atol=1e-12)
    np.testing.assert_allclose(to_metric(scene, norm), metric, atol=1e-4)
    n = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    pts = rng.uniform(-10, 10, (50, 3))
    pts -= ((pts @ n) + 2.5)[:, None] * n                           # on n . x + 2.5 = 0
    n_s, d_s = ground.refine_plane(to_scene(pts, norm))
    n_m, d_m = plane_to_metric(n_s, d_s, norm)
    np.testing.assert_allclose(n_m * np.sign(n_m @ n), n, atol=1e-9)
    assert d_m * np.sign(n_m @ n) == pytest.approx(2.5, abs=1e-6)
    s, t = NORM["scale"], np.asarray(NORM["translation"], np.float64)
    np.testing.assert_array_equal(to_metric(scene, NORM), (scene / s - t).astype(np.float32))
    np.testing.assert_array_equal(to_scene(metric, NORM), s * (metric + t))


def test_metric_map_of_a_missing_or_partial_record_is_the_identity_in_what_is_missing():
    """No record: the identity both ways; a record with only a scale: x_norm / s, in float64."""
    pts = np.random.default_rng(3).uniform(-5, 5, (20, 3))
    np.testing.assert_array_equal(to_metric64(pts, None), pts)
    np.testing.assert_array_equal(to_scene(pts, None), pts)
    np.testing.assert_allclose(to_metric64(pts, {"scale": 4.0}), pts / 4.0, rtol=1e-15)
    np.testing.assert_allclose(to_scene(pts, {"translation": [1.0, 2.0, 3.0]}), pts + [1.0, 2.0, 3.0], rtol=1e-15)
    assert to_metric64(pts, NORM).dtype == np.float64


def test_box_corners_are_the_eight_corners_each_once():
    """The 8 corners of [0, 1] x [-2, 2] x [3, 5] (integers in, float64 out), each once, against
    itertools.product of the bounds (a ninth row, a repeat of lo, changed no box
    extent)."""
    import itertools

    from jaxnerf_grid.export import box_corners

    corners = box_corners([0, -2, 3], [1, 2, 5])
    assert corners.shape == (8, 3) and corners.dtype == np.float64
    want = sorted(itertools.product((0.0, 1.0), (-2.0, 2.0), (3.0, 5.0)))
    assert sorted(map(tuple, corners.tolist())) == want


# --------------------------------------------------------------------------- ground and box


def test_lowest_points_match_brute_force():
    rng = np.random.default_rng(1)
    p = rng.uniform(-1, 1, (500, 3))
    low = ground.lowest_points(p, 0.25)
    keys = {tuple(k) for k in np.floor(p[:, :2] / 0.25).astype(int)}
    expected = []
    for k in keys:
        col = p[np.all(np.floor(p[:, :2] / 0.25).astype(int) == k, axis=1)]
        expected.append(col[np.argmin(col[:, 2])])
    assert len(low) == len(keys)
    np.testing.assert_allclose(sorted(map(tuple, low)), sorted(map(tuple, expected)))


def test_ransac_ground_against_the_true_plane():
    rng = np.random.default_rng(2)
    n_true = np.array([np.sin(np.radians(5)), 0.0, np.cos(np.radians(5))])
    d_true = 0.75
    xy = rng.uniform(-0.7, 0.7, (600, 2))
    z = -(n_true[0] * xy[:, 0] + n_true[1] * xy[:, 1] + d_true) / n_true[2]
    ground_pts = np.column_stack([xy, z + rng.normal(0, 0.005, len(xy))])
    tower = np.column_stack([rng.uniform(-0.1, 0.1, (250, 2)), rng.uniform(-0.7, 0.8, 250)])
    floaters = rng.uniform(-1, 1, (100, 3))
    pts = np.concatenate([ground_pts, tower, floaters])             # 35 % outliers
    n, d, inliers = ground.fit_plane_ransac(pts, 0.02)
    assert np.degrees(np.arccos(np.clip(n @ n_true, -1, 1))) < 0.5
    assert d == pytest.approx(d_true, abs=0.005)
    assert inliers[:600].mean() > 0.95
    np.testing.assert_allclose(ground.heights(ground_pts, n, d), 0, atol=0.03)


def noisy_ground_cloud(sigma=0.01, seed=3):
    """A 2 x 2 patch of the plane n . x + d = 0, n = (sin 4, 0, cos 4) degrees, d = 0.3, 40 000
    points with Gaussian noise sigma along n (a fused cloud's ground), and a column of 2 000
    points standing on it (a tower's leg). Returns (points [42000, 3], n, d)."""
    rng = np.random.default_rng(seed)
    n = np.array([np.sin(np.radians(4)), 0.0, np.cos(np.radians(4))])
    d = 0.3
    xy = rng.uniform(-1, 1, (40000, 2))
    on = np.column_stack([xy, -(n[0] * xy[:, 0] + d) / n[2]])
    noisy = on + rng.normal(0, sigma, (len(on), 1)) * n
    leg_xy = rng.uniform(0.1, 0.2, (2000, 2))
    leg = np.column_stack([leg_xy, -(n[0] * leg_xy[:, 0] + d) / n[2] + rng.uniform(0, 0.8, 2000)])
    return np.concatenate([noisy, leg]), n, d


def test_the_lowest_points_lie_below_a_noisy_ground_and_settling_finds_it():
    """The plane through the columns' lowest points (cells of 0.02, about 4 points each) lies
    well below the true plane (the minimum of 4 normal draws: about 1 sigma); settled on
    the cloud it is within 0.05 sigma of the true offset, its band the points within 0.025 of
    it, counted here; the normal is kept."""
    sigma = 0.01
    pts, n_true, d_true = noisy_ground_cloud(sigma)
    n, d, _ = ground.fit_plane_ransac(ground.lowest_points(pts, 0.02), 0.025, iterations=300)
    assert d - d_true > 0.8 * sigma                     # n . x + d = 0 with d too large: the plane is low
    settled, near = ground.settle_on_cloud(pts, n, d, 0.025)
    assert settled == pytest.approx(d_true, abs=0.05 * sigma)
    np.testing.assert_array_equal(near, np.abs(pts @ n + settled) <= 0.025)
    # the run's ground: the settled plane, and how far it moved (normalised units)
    from jaxnerf_grid.export import run as export_run

    plane = export_run._ground(pts)
    assert plane["offset"] == pytest.approx(d_true, abs=0.05 * sigma)
    assert plane["settled_shift"] == pytest.approx(d - plane["offset"], abs=0.05 * sigma)   # from the low plane
    assert plane["settled_on"] == int(np.sum(np.abs(pts @ plane["normal"] + plane["offset"]) <= 0.025))


def test_settling_leaves_a_plane_with_fewer_than_three_points_near_it():
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 5.0]])
    d, near = ground.settle_on_cloud(pts, np.array([0.0, 0.0, 1.0]), 0.0, 0.1)
    assert d == 0.0 and near.sum() == 2


def _column(heights) -> np.ndarray:
    """Points at the origin's (x, y) at the given heights above the ground z = 0."""
    z = np.asarray(heights, np.float64)
    return np.column_stack([np.zeros_like(z), np.zeros_like(z), z])


def test_settling_band_edges_three_points_and_the_stopping_step_by_hand():
    """Ground z = 0 (n = (0, 0, 1), d = 0), every height a binary fraction (exact). Band 0.5:
    three points 0, 0.25, 0.5 are enough (the band includes its edge): the plane moves to their
    median 0.25 (d = -0.25), then finds 0.25 within 0.5 again (-0.25, 0, 0.25: median 0) and
    stops; points at -0.5, -0.1, 0, 0.1, 0.5 leave it (median 0) with all five near, the edges
    included. Band 1, stop below band / 100 = 0.01: heights -0.5, 0.00995, 0.5 (1.005 outside
    the band) move it by 0.00995 < 0.01 and it stops there (1.005 then 0.99505 from it: near);
    with 0.01 (not less than 0.01) it goes on: 1.005 is then 0.995 from it, the median of the
    four is 0.255, where the next median is 0."""
    up = np.array([0.0, 0.0, 1.0])
    d, near = ground.settle_on_cloud(_column([0.0, 0.25, 0.5]), up, 0.0, 0.5)
    assert d == -0.25 and near.tolist() == [True, True, True]
    d, near = ground.settle_on_cloud(_column([-0.5, -0.1, 0.0, 0.1, 0.5]), up, 0.0, 0.5)
    assert d == 0.0 and near.tolist() == [True] * 5
    d, near = ground.settle_on_cloud(_column([-0.5, 0.00995, 0.5, 1.005]), up, 0.0, 1.0)
    assert d == pytest.approx(-0.00995, abs=1e-15) and near.tolist() == [True] * 4
    d, near = ground.settle_on_cloud(_column([-0.5, 0.01, 0.5, 1.005]), up, 0.0, 1.0)
    assert d == pytest.approx(-(0.01 + 0.5) / 2, abs=1e-12) and near.tolist() == [True] * 4


def test_settling_stops_after_twenty_rounds_by_default():
    """A staircase of layers 0.5 apart (layer k at height 0.5 k, k = 0..21) with m_0 = 1, m_1 =
    3, m_k+1 = m_k-1 + m_k + 2 points, and band 0.5: a plane on layer k sees layers k - 1, k,
    k + 1 (the edges included), more than half of them on k + 1 (both middle values), so every
    round moves it up one layer, by 0.5 (never below band / 100). The documented default of 20
    rounds leaves it on layer 20 (d = -10); `rounds=3` on layer 3; the points near are layers
    19-21."""
    counts = [1, 3]
    while len(counts) < 22:
        counts.append(counts[-1] + counts[-2] + 2)
    layer = np.repeat(np.arange(22), counts)
    pts = _column(0.5 * layer)
    up = np.array([0.0, 0.0, 1.0])
    d, near = ground.settle_on_cloud(pts, up, 0.0, 0.5)
    assert d == -10.0
    np.testing.assert_array_equal(near, layer >= 19)
    assert ground.settle_on_cloud(pts, up, 0.0, 0.5, rounds=3)[0] == -1.5


def test_plane_through_and_refine_plane_against_a_known_tilted_plane():
    """Three points 2 cm apart (a normalised scene's scale) and a cloud on the plane
    n . x + d = 0, n = (sin 20, 0, cos 20), d = 0.3: the unit normal with n_z > 0 whatever the
    points' order, d exactly; collinear points give None."""
    n_true = np.array([np.sin(np.radians(20)), 0.0, np.cos(np.radians(20))])
    d_true = 0.3
    u, v = np.array([np.cos(np.radians(20)), 0.0, -np.sin(np.radians(20))]), np.array([0.0, 1.0, 0.0])
    a = -d_true * n_true
    for b, c in ((a + 0.02 * u, a + 0.02 * v), (a + 0.02 * v, a + 0.02 * u)):   # both orientations
        n, d = ground.plane_through(a, b, c)
        np.testing.assert_allclose(n, n_true, atol=1e-9)
        assert d == pytest.approx(d_true, abs=1e-9)
    assert ground.plane_through(a, a + 0.02 * u, a + 0.04 * u) is None
    rng = np.random.default_rng(9)
    cloud = a + rng.uniform(-1, 1, (50, 1)) * u + rng.uniform(-1, 1, (50, 1)) * v
    for points in (cloud, cloud[::-1] * [1, 1, 1]):
        n, d = ground.refine_plane(points)
        np.testing.assert_allclose(n, n_true, atol=1e-9)
        assert d == pytest.approx(d_true, abs=1e-9)


def test_ransac_needs_three_points_is_reproducible_and_returns_float64():
    """Exactly three points are enough, two are refused by a message that says so; the same seed
    gives the same plane on a slab where every sample gives another (three iterations); the
    lowest points of float32 input are float64, as documented."""
    three = np.array([[0.0, 0.0, 0.1], [1.0, 0.0, 0.1], [0.0, 1.0, 0.1]])
    n, d, inliers = ground.fit_plane_ransac(three, 0.01)
    np.testing.assert_allclose(n, [0, 0, 1], atol=1e-12)
    assert d == pytest.approx(-0.1) and inliers.all()
    with pytest.raises(ValueError, match="at least 3 points, got 2"):
        ground.fit_plane_ransac(three[:2], 0.01)
    cloud = np.random.default_rng(10).uniform(-1, 1, (200, 3)) * [1, 1, 0.1]     # a thick slab
    runs = [ground.fit_plane_ransac(cloud, 0.03, iterations=3, seed=4) for _ in range(2)]
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][2], runs[1][2])
    assert ground.lowest_points(cloud.astype(np.float32), 0.25).dtype == np.float64


def test_ransac_prefers_the_ground_to_a_larger_wall_and_refuses_a_wall_alone():
    """300 points on a vertical wall x = 0.5 (z above -0.3) and a 15 x 15 lattice on the ground z = -0.5 (its
    rows make some samples collinear): the plane within 45 degrees of horizontal is the ground,
    not the wall with more points; the wall alone is refused, by name."""
    rng = np.random.default_rng(11)
    wall = np.column_stack([np.full(300, 0.5), rng.uniform(-1, 1, 300), rng.uniform(-0.3, 1, 300)])
    xs, ys = np.meshgrid(np.linspace(-1, 0.3, 15), np.linspace(-1, 1, 15))
    floor = np.column_stack([xs.ravel(), ys.ravel(), np.full(225, -0.5)])
    n, d, inliers = ground.fit_plane_ransac(np.concatenate([wall, floor]), 0.01, iterations=200)
    np.testing.assert_allclose(n, [0, 0, 1], atol=1e-9)
    assert d == pytest.approx(0.5) and inliers.sum() == 225 and inliers[300:].all()
    with pytest.raises(ValueError, match="no plane within the tilt limit"):
        ground.fit_plane_ransac(wall, 0.01, iterations=50)


def test_ransac_keeps_its_sample_plane_when_the_refit_tilts_past_the_limit():
    """A noisy slab sloping 50 degrees and a threshold that takes all of it: only noisy samples
    within 45 degrees are accepted, and the least-squares refit of their inliers (50 degrees)
    would pass the limit, so the sample's plane is kept: within 45 degrees."""
    rng = np.random.default_rng(13)
    xy = rng.uniform(-0.5, 0.5, (300, 2))
    slab = np.column_stack([xy, np.tan(np.radians(50)) * xy[:, 0] + rng.uniform(-0.15, 0.15, 300)])
    assert np.degrees(np.arccos(ground.refine_plane(slab)[0][2])) > 47      # the refit alone
    n, d, inliers = ground.fit_plane_ransac(slab, 0.5, iterations=300)
    assert n[2] >= np.cos(np.radians(45)) and inliers.sum() > 250
    np.testing.assert_array_equal(inliers, np.abs(slab @ n + d) <= 0.5)


def test_plane_z_and_largest_cluster_of_none_and_one_point():
    """z of the plane 0.2 x - 0.3 y + z + 0.5 = 0 (normalised) at a few (x, y), by hand; the
    largest cluster of no points is an empty bool mask, of one point that point."""
    n = np.array([0.2, -0.3, 1.0]) / np.linalg.norm([0.2, -0.3, 1.0])
    d = 0.5 / np.linalg.norm([0.2, -0.3, 1.0])
    x, y = np.array([0.0, 1.0, 2.0, -1.5]), np.array([0.0, 2.0, -1.0, 0.5])
    np.testing.assert_allclose(ground.plane_z(n, d, x, y), -(0.2 * x - 0.3 * y + 0.5), atol=1e-12)
    none = ground.largest_cluster(np.zeros((0, 3)), 0.1)
    assert none.shape == (0,) and none.dtype == bool
    one = ground.largest_cluster(np.array([[0.3, 0.2, 0.1]]), 0.1)
    assert one.dtype == bool and one.tolist() == [True]


def _clusters_by_hand(cells: list, counts: list) -> set:
    """The largest group (by point count) of occupied cells [(i, j, k)], two cells joined when
    their Chebyshev distance is at most 3 (one-cell dilations that touch, corners included):
    union-find over every pair. Returns the set of its cells."""
    parent = list(range(len(cells)))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for a in range(len(cells)):
        for b in range(a):
            if max(abs(x - y) for x, y in zip(cells[a], cells[b])) <= 3:
                parent[root(a)] = root(b)
    totals = {}
    for i, c in enumerate(counts):
        totals[root(i)] = totals.get(root(i), 0) + c
    best = max(totals, key=totals.get)
    return {cells[i] for i in range(len(cells)) if root(i) == best}


def test_largest_cluster_joins_cells_three_apart_diagonally_and_not_four_apart():
    """Cells of side 1: two 3-point cells (3, 3, 3) apart (one group of 6, joined only through
    their corners) and three pairs of 5-point cells 4 apart along x, y and z (never joined):
    the group of 6 is the largest, as the union-find over cells says (a
    face-only dilation or labelling, or a 4-cell structure on any axis, passed the test above)."""
    cells = [(0, 0, 0), (3, 3, 3), (20, 0, 0), (24, 0, 0), (0, 20, 0), (0, 24, 0), (0, 0, 20), (0, 0, 24)]
    counts = [3, 3, 5, 5, 5, 5, 5, 5]
    points = np.concatenate([np.asarray(c, float) + 0.5 + 0.1 * np.arange(k)[:, None] for c, k in zip(cells, counts)])
    got = ground.largest_cluster(points, 1.0)
    want = _clusters_by_hand(cells, counts)
    assert want == {(0, 0, 0), (3, 3, 3)}
    np.testing.assert_array_equal(got, [tuple(np.floor(q).astype(int)) in want for q in points])


def test_tower_box_finds_the_largest_cluster_above_the_ground():
    rng = np.random.default_rng(3)
    floor = np.column_stack([rng.uniform(-0.8, 0.8, (2000, 2)), np.full(2000, -0.7)])
    legs = np.column_stack([rng.uniform(-0.2, 0.2, (3000, 2)), rng.uniform(-0.7, 0.6, 3000)])
    bush = np.column_stack([rng.uniform(0.6, 0.65, (40, 2)), rng.uniform(-0.7, -0.6, 40)])
    n, d = np.array([0, 0, 1.0]), 0.7
    lo, hi, stats = ground.tower_box(np.concatenate([floor, legs, bush]), n, d, clearance=0.03, cell=0.02)
    np.testing.assert_allclose(lo[:2], [-0.22, -0.22], atol=0.01)
    np.testing.assert_allclose(hi, [0.22, 0.22, 0.62], atol=0.01)
    assert lo[2] == pytest.approx(-0.67)                           # clearance above the ground
    assert stats["tower_points"] < stats["above_ground"]          # the bush is not the tower
    with pytest.raises(ValueError):
        ground.tower_box(floor, n, d, 0.03, 0.02)


def test_tower_box_reaches_down_to_the_ground_where_the_cloud_missed_the_legs():
    """A column whose cloud starts 0.3 above flat ground z = -0.2 (the fused views missed its
    lower legs): the box's bottom is still the clearance above the ground, not the column's
    lowest point less a cell; the rest is the column's extent plus a cell."""
    rng = np.random.default_rng(5)
    floor = np.column_stack([rng.uniform(-0.8, 0.8, (500, 2)), np.full(500, -0.2)])
    column = np.column_stack([rng.uniform(-0.1, 0.1, (2000, 2)), rng.uniform(0.1, 0.9, 2000)])
    lo, hi, _ = ground.tower_box(np.concatenate([floor, column]), np.array([0, 0, 1.0]), 0.2, clearance=0.03,
                                 cell=0.02)
    assert lo[2] == pytest.approx(-0.2 + 0.03, abs=1e-12)
    np.testing.assert_allclose(lo[:2], column[:, :2].min(0) - 0.02, atol=1e-12)
    np.testing.assert_allclose(hi, column.max(0) + 0.02, atol=1e-12)


def test_tower_box_on_sloping_ground_clears_its_highest_corner_and_refuses_by_name():
    """Ground sloping in x and in y, each of the four ways (so each bottom corner of the box is
    the highest once), a column of points standing on it: the box is the column's extent plus
    one cell, its bottom `clearance` above the plane at its highest bottom corner (each corner's
    z by hand); one point above the ground is a tower, none is refused with the documented
    message."""
    rng = np.random.default_rng(12)
    xy = rng.uniform([-0.1, 0.2], [0.1, 0.35], (3000, 2))
    rise = rng.uniform(0.0, 0.8, 3000)
    for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        a, b = 0.1 * sx, 0.15 * sy
        norm = np.linalg.norm([a, b, 1.0])
        n, d = np.array([a, b, 1.0]) / norm, 0.4 / norm
        z_of = lambda x, y: -(a * x + b * y + 0.4)  # noqa: E731,B023  the plane's z, by hand
        column = np.column_stack([xy, z_of(xy[:, 0], xy[:, 1]) + rise])
        lo, hi, stats = ground.tower_box(column, n, d, clearance=0.03, cell=0.02)
        tower = column[rise * (1.0 / norm) > 0.03]                   # heights above the plane
        np.testing.assert_allclose(lo[:2], tower[:, :2].min(0) - 0.02, atol=1e-12)
        np.testing.assert_allclose(hi, tower.max(0) + 0.02, atol=1e-12)
        corners = [z_of(x, y) for x in (lo[0], hi[0]) for y in (lo[1], hi[1])]
        assert lo[2] == pytest.approx(max(corners) + 0.03, abs=1e-12)
        assert stats == {"above_ground": len(tower), "tower_points": len(tower)}
    flat = np.array([0.0, 0.0, 1.0])
    one = np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.2, 0.1, 0.5]])
    lo1, hi1, _ = ground.tower_box(one, flat, 0.0, clearance=0.03, cell=0.02)
    np.testing.assert_allclose(hi1, [0.22, 0.12, 0.52], atol=1e-12)
    with pytest.raises(ValueError, match="nothing stands above the ground plane"):
        ground.tower_box(one[:2], flat, 0.0, clearance=0.03, cell=0.02)
    # one point 0.031 above ground z = -(0.9 x + 0.9 y): the box's uphill corner, a cell away,
    # is 0.18 higher, so clearance above it is above the box's top (0.031 / n_z + 0.1)
    steep = np.array([0.9, 0.9, 1.0]) / np.linalg.norm([0.9, 0.9, 1.0])
    with pytest.raises(ValueError, match="the tower's box is empty above the ground"):
        ground.tower_box(np.array([[0.0, 0.0, 0.031 / steep[2]]]), steep, 0.0, clearance=0.03, cell=0.1)


def test_tower_box_edges_exact_messages_and_a_float32_cloud():
    """Binary fractions, so every comparison is exact. Ground z = 0, clearance 0.25: a point at
    height exactly 0.25 does not stand above the ground (strictly higher), so a cloud of it alone
    is refused with the documented message, word for word; beside a point at 0.5, above_ground
    is 1. Ground z = 2 x (n = (-2, 0, 1) / sqrt 5), cell 0.25, clearance 0.125, one point at
    (0, 0, 0.375) (0.375 / sqrt 5 = 0.168 above the plane): the box's x runs -0.25..0.25, its
    uphill corner's ground is 0.5, so its bottom 0.625 equals its top 0.375 + 0.25: an empty box,
    refused word for word. A float32 cloud gives the float64 box of the same points: the
    extent plus one cell, worked out in float64 here."""
    flat = np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError) as err:
        ground.tower_box(_column([0.25, 0.0]), flat, 0.0, clearance=0.25, cell=0.25)
    assert str(err.value) == "nothing stands above the ground plane"
    _, _, stats = ground.tower_box(_column([0.25, 0.5]), flat, 0.0, clearance=0.25, cell=0.25)
    assert stats == {"above_ground": 1, "tower_points": 1}
    slope = np.array([-2.0, 0.0, 1.0]) / np.sqrt(5.0)
    with pytest.raises(ValueError) as err:
        ground.tower_box(_column([0.375]), slope, 0.0, clearance=0.125, cell=0.25)
    assert str(err.value) == "the tower's box is empty above the ground"
    rng = np.random.default_rng(14)
    cloud = np.column_stack([rng.uniform(-0.1, 0.1, (500, 2)), rng.uniform(0.1, 0.9, 500)]).astype(np.float32)
    lo, hi, _ = ground.tower_box(cloud, flat, 0.0, clearance=0.03, cell=0.02)
    exact = cloud.astype(np.float64)
    assert lo.dtype == np.float64 and hi.dtype == np.float64
    np.testing.assert_array_equal(hi, exact.max(0) + 0.02)
    np.testing.assert_array_equal(lo, [exact[:, 0].min() - 0.02, exact[:, 1].min() - 0.02, 0.03])


# --------------------------------------------------------------------------- fusion


def _plane_views(count=4, width=24, height=18):
    """Cameras around the origin looking at the plane z = -0.5; exact z-depth maps of it."""
    import jax.numpy as jnp

    from jaxnerf_grid.nerf import rays as rays_lib

    fx = 20.0
    cams, parts = [], []
    for k in range(count):
        a = 2 * np.pi * k / count
        c2w = np.asarray(rays_lib.look_at([1.5 * np.cos(a), 1.5 * np.sin(a), 1.0], [0, 0, -0.5]))
        r = rays_lib.generate_rays(jnp.asarray(c2w), fx, fx, width / 2, height / 2, width, height)
        o, dirs = np.asarray(r.origins, np.float64), np.asarray(r.directions, np.float64)
        t = (-0.5 - o[..., 2]) / dirs[..., 2]
        depth = (t * np.asarray(r.cos_to_axis)).astype(np.float32)
        opacity = np.ones((height, width), np.float32)
        parts.append(lift_view(r, np.full((height, width, 3), 0.5), depth, opacity, radius=10.0))
        cams.append({"c2w": c2w, "intrinsics": (fx, fx, width / 2, height / 2), "depth": depth, "opacity": opacity})
    return parts, cams


def test_project_inverts_lift_view():
    parts, cams = _plane_views(1)
    u, v, z = fuse.project(parts[0][0], cams[0]["c2w"], cams[0]["intrinsics"])
    cols, rows = np.meshgrid(np.arange(24) + 0.5, np.arange(18) + 0.5)
    np.testing.assert_allclose(u, cols.ravel(), atol=1e-3)
    np.testing.assert_allclose(v, rows.ravel(), atol=1e-3)
    np.testing.assert_allclose(z, cams[0]["depth"].ravel(), rtol=1e-5)


def test_fusion_keeps_the_surface_and_drops_floaters():
    parts, cams = _plane_views(4)
    floaters = np.random.default_rng(4).uniform(-0.4, 0.4, (50, 3)) + [0, 0, 0.3]
    parts[0] = (np.concatenate([parts[0][0], floaters]), np.concatenate([parts[0][1], np.zeros((50, 3))]))
    pts, cols, stats = fuse.fuse(parts, cams, min_views=2)
    assert stats["lifted"] == sum(len(p) for p, _ in parts)
    assert np.all(np.abs(pts[:, 2] + 0.5) < 1e-4)                # no floater survives
    source = np.concatenate([np.full(len(p), i) for i, (p, _) in enumerate(parts)])
    counts = fuse.confirmations(np.concatenate([p for p, _ in parts]), source, cams)
    assert np.all(counts[len(parts[0][0]) - 50:len(parts[0][0])] == 0)
    assert stats["kept"] > 0.5 * (stats["lifted"] - 50)          # most of the plane is seen by 2 others


# --------------------------------------------------------------------------- measurements


def test_min_area_rectangle_against_brute_force():
    rng = np.random.default_rng(5)
    theta = np.radians(27)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    pts = rng.uniform([-4, -1.5], [4, 1.5], (300, 2)) @ rot.T
    corners = np.array([[-4, -1.5], [4, -1.5], [4, 1.5], [-4, 1.5]]) @ rot.T
    wa, wb, direction = measure.min_area_rectangle(np.concatenate([pts, corners]))
    assert wa == pytest.approx(8.0) and wb == pytest.approx(3.0)
    assert abs(direction @ rot[:, 0]) == pytest.approx(1.0)
    angles = np.radians(np.arange(0, 180, 0.05))                   # brute force over directions
    areas = [np.ptp(pts @ [np.cos(a), np.sin(a)]) * np.ptp(pts @ [-np.sin(a), np.cos(a)]) for a in angles]
    wa2, wb2, _ = measure.min_area_rectangle(pts)
    assert wa2 * wb2 <= min(areas) + 1e-9 and wa2 * wb2 == pytest.approx(min(areas), rel=1e-3)


def _synthetic_tower(rng):
    """A tapering square body 30 high (base 8 x 8), arms of span 16 at heights 17, 21, 25 (x axis)."""
    z = rng.uniform(0, 30, 20000)
    half = 4.0 - 3.0 * z / 30
    side = rng.integers(0, 4, len(z))
    s = rng.uniform(-1, 1, len(z)) * half
    x = np.where(side == 0, half, np.where(side == 1, -half, s))
    y = np.where(side == 2, half, np.where(side == 3, -half, s))
    body = np.column_stack([x, y, z])
    arms = [np.column_stack([rng.uniform(-8, 8, 1500), rng.uniform(-0.3, 0.3, 1500),
                             rng.uniform(h - 0.3, h + 0.3, 1500)])
            for h in (17.0, 21.0, 25.0)]
    return np.concatenate([body] + arms)


def test_footprint_and_cross_arms_of_a_synthetic_tower():
    rng = np.random.default_rng(6)
    pts = _synthetic_tower(rng)
    n, d = np.array([0, 0, 1.0]), 0.0
    fp = measure.footprint(pts, n, d, band=0.5)
    assert fp["width_a"] == pytest.approx(8.0, abs=0.15) and fp["width_b"] == pytest.approx(8.0, abs=0.15)
    arms = measure.cross_arms(pts, n, d, [1.0, 0, 0], [0, 1.0, 0], slice_height=0.3)
    heights = [a["height"] for a in arms["levels"]]
    assert len(heights) == 3 and np.allclose(heights, [17, 21, 25], atol=0.5)
    assert all(a["span"] == pytest.approx(16.0, abs=0.2) and a["axis"] == "a" for a in arms["levels"])
    assert arms["region"][0] == pytest.approx(16.7, abs=0.4)


def test_cross_arm_ends_of_a_one_sided_arm_on_a_tilted_ground():
    """An arm from y = -3 to y = 9 (off the body's axis x = y = 0, along the second axis) at
    height 21 of a tower turned by R (the ground's normal R z): its recorded ends are R (0, -3, 21)
    and R (0, 9, 21), not a span centred on the axis."""
    rng = np.random.default_rng(8)
    body = _synthetic_tower(rng)[:20000]
    arm = np.column_stack([rng.uniform(-0.3, 0.3, 1500), rng.uniform(-3, 9, 1500), rng.uniform(20.7, 21.3, 1500)])
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    pts = np.concatenate([body, arm]) @ rot.T
    arms = measure.cross_arms(pts, rot[:, 2], 0.0, rot[:, 0], rot[:, 1], slice_height=0.3)
    (level,) = arms["levels"]
    assert level["axis"] == "b" and level["span"] == pytest.approx(12.0, abs=0.1)
    ends = np.asarray(level["ends"]) @ rot                          # back in the tower's frame
    np.testing.assert_allclose(ends[:, :2], [[0, -3], [0, 9]], atol=0.1)
    np.testing.assert_allclose(ends[:, 2], 21.0, atol=0.5)
    assert np.linalg.norm(ends[1] - ends[0]) == pytest.approx(level["span"])


def test_orthographic_views_draw_the_nearest_point():
    pts = np.array([[0.0, 0.0, 0.0], [0.0, -1.0, 0.0], [1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [0, 0, 0.5]])
    cols = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, 1.0], [1.0, 1.0, 0]])
    img = measure.orthographic_views(pts, cols, size=41, labels=False)
    assert img.shape == (41, 3 * 41 + 8, 3)
    np.testing.assert_allclose(img[20, 20], [0, 1, 0])      # front, seen from -y: y = -1 is nearer
    np.testing.assert_allclose(img[20, 45 + 20], [1, 0, 0])  # side, from +x: the red point alone there
    np.testing.assert_allclose(img[20, 90 + 20], [1, 1, 0])  # top, from +z: z = 0.5 is nearer than 0
    np.testing.assert_allclose(img[0, 0], [1, 1, 1])         # background



# --------------------------------------------------------------------------- scores


def test_export_score_matches_brute_force(tmp_path):
    rng = np.random.default_rng(7)
    ref = np.column_stack([rng.uniform(-3, 3, (400, 2)), rng.uniform(0, 30, 400)])
    verts = ref[:300] + rng.normal(0, 0.3, (300, 3))
    io.write_ply(tmp_path / "tower_mesh.ply", verts, faces=np.zeros((0, 3), int))
    io.write_ply(tmp_path / "tower_points.ply", ref[100:] + rng.normal(0, 0.1, (300, 3)))
    io.write_json(tmp_path / "measurements.json", {"units": "metres", "height": 31.2})
    scale = 0.05
    out = score_lib.score_export(tmp_path, ref, scale)
    strip = geometry.DEFAULT_GROUND_STRIP / scale
    lo, hi = ref.min(0), ref.max(0)
    lo[2] += strip
    pred = io.read_ply_points(tmp_path / "tower_mesh.ply").astype(np.float64)
    p = pred[np.all((pred >= lo) & (pred <= hi), axis=1)]
    r = ref[np.all((ref >= lo) & (ref <= hi), axis=1)]
    dist = np.linalg.norm(p[:, None] - r[None], axis=-1)           # brute force
    for tau in (0.2, 0.4, 1.0):
        prec, rec = np.mean(dist.min(1) <= tau), np.mean(dist.min(0) <= tau)
        f = 2 * prec * rec / (prec + rec)
        assert out["mesh"]["thresholds"][f"{tau:g}"]["fscore"] == pytest.approx(f)
    assert out["mesh"]["chamfer"] == pytest.approx(0.5 * (dist.min(1).mean() + dist.min(0).mean()))
    assert out["height"]["reference"] == pytest.approx(np.ptp(ref[:, 2]))
    assert out["height"]["error"] == pytest.approx(31.2 - np.ptp(ref[:, 2]))
    assert out["height"]["error_percent"] == pytest.approx(100 * abs(31.2 - np.ptp(ref[:, 2])) / np.ptp(ref[:, 2]))
    assert "points" in out and score_lib.score_export(tmp_path / "none", ref, scale) is None


def test_reference_in_export_units():
    rng = np.random.default_rng(8)
    metric = rng.uniform(-10, 30, (20, 3))
    file_norm = {"scale": 0.05, "translation": [0, 0, -15.0]}
    stored = apply_normalization_to_points(metric, file_norm)
    np.testing.assert_allclose(score_lib.reference_in_export_units(stored, file_norm, NORM), metric, atol=1e-9)
    normalized = apply_normalization_to_points(metric, NORM)
    np.testing.assert_allclose(score_lib.reference_in_export_units(normalized, None, NORM), metric, atol=1e-9)


# --------------------------------------------------------------------------- PLY


def test_mesh_ply_read_back_by_plyfile(tmp_path):
    plyfile = pytest.importorskip("plyfile")
    origin, h, shape, p = _grid(12)
    verts, faces, _ = mesh.extract_mesh(np.where(np.linalg.norm(p, axis=-1) < 0.6, 5.0, 0.0), 1.0, origin, h)
    colours = np.random.default_rng(9).uniform(0, 1, (len(verts), 3))
    io.write_ply(tmp_path / "m.ply", verts, colours, faces, comments=("units: metres", "second line"))
    data = plyfile.PlyData.read(str(tmp_path / "m.ply"))
    assert data.comments == ["units: metres", "second line"]
    v = data["vertex"]
    np.testing.assert_allclose(np.column_stack([v["x"], v["y"], v["z"]]), verts, atol=1e-6)
    np.testing.assert_array_equal(np.column_stack([v["red"], v["green"], v["blue"]]),
                                  np.round(colours * 255).astype(np.uint8))
    np.testing.assert_array_equal(np.stack(data["face"]["vertex_indices"]), faces)
    np.testing.assert_allclose(io.read_ply_points(tmp_path / "m.ply"), verts, atol=1e-6)   # ours agrees


# --------------------------------------------------------------------------- the command


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny trained run (a ball of radius 0.7, 2 x 32 MLP, 30 steps) on a dataset that states
    its metric normalisation and names a reference tower.ply."""
    from jaxnerf_grid.data.formats import save_transforms_json
    from jaxnerf_grid.train import runs

    root = tmp_path_factory.mktemp("export")
    ds = tiny_dataset()
    ds.frame_paths = [f"images/frame_{i:03d}.png" for i in range(ds.num_frames)]
    data = root / "data"
    save_transforms_json(ds, data)
    rng = np.random.default_rng(0)
    ball = rng.normal(size=(400, 3))
    io.write_ply(data / "tower.ply", 0.7 * ball / np.linalg.norm(ball, axis=1, keepdims=True))
    meta = io.read_json(data / "transforms.json")
    io.write_json(data / "transforms.json", {**meta, "tower_ply": "tower.ply", "scene_normalization": NORM})
    overrides = {"model": {"field": TINY_FIELD, "num_coarse": 8, "num_fine": 8},
                 "train": {"batch_rays": 64, "max_steps": 30, "checkpoint_every": 30, "log_every": 10, "warmup": 5,
                           "lr_init": 5e-3, "lr_final": 1e-3, "chunk": 256,
                           "num_devices": 1}}  # one device compiles faster
    run, _, _ = runs.train_run(str(data), "ours", root / "run", overrides, progress=False)
    return run


def _metric_box(lo, hi):
    return ",".join(f"{v:.6f}" for v in np.concatenate([to_metric(np.array([lo]), NORM)[0],
                                                        to_metric(np.array([hi]), NORM)[0]]))


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_export_writes_metric_files_inside_the_given_box(tiny_run, tmp_path, capsys):
    out = tmp_path / "export"
    box = _metric_box([-0.9] * 3, [0.9] * 3)
    assert cli.main(["export", "--run", str(tiny_run), "--out", str(out), f"--box={box}", "--resolution", "24",
                     "--threshold", "0.02", "--views", "4", "--quiet"]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(["box.json", "export_views.png", "measurements.json",
                                                            "report.md", "report.html", "tower_mesh.ply",
                                                            "tower_points.ply", "tower_points.las",
                                                            "classified_points.las", "conductors_views.png",
                                                            ".jaxnerf-grid-export"])  # the marker (folders)
    saved = io.read_json(out / "box.json")
    np.testing.assert_allclose(saved["min"] + saved["max"], [float(v) for v in box.split(",")], atol=1e-4)
    np.testing.assert_allclose(saved["normalised"]["min"], [-0.9] * 3, atol=1e-6)   # the round trip
    m = io.read_json(out / "measurements.json")
    assert m["units"] == "metres" and m["box"]["source"] == "given"
    cond = m["conductors"]
    if cond is not None:     # a ground was fitted: the heuristic's lowest point carries its ground's evidence
        assert "ground_seen" in cond and (cond["ground_seen"] is None) == (not cond["reconstructed"])
    verts = io.read_ply_points(out / "tower_mesh.ply")
    voxel = m["voxel_size"]
    assert len(verts) == m["mesh"]["vertices"] > 0
    assert np.all(verts >= np.array(saved["min"]) - 1.5 * voxel)
    assert np.all(verts <= np.array(saved["max"]) + 1.5 * voxel)
    header = (out / "tower_mesh.ply").read_bytes()[:400].decode("ascii", "replace")
    assert "comment units: metres" in header
    assert "## Tower model (export)" in (out / "report.md").read_text()


def test_eval_scores_the_export(tiny_run, capsys):
    from jaxnerf_grid.eval import evaluate
    from jaxnerf_grid.train import runs

    assert cli.main(["export", "--run", str(tiny_run), f"--box={_metric_box([-0.9] * 3, [0.9] * 3)}", "--resolution",
                     "16", "--threshold", "0.02", "--views", "3", "--quiet"]) == 0
    assert "## Tower model (export)" in (tiny_run / "report.md").read_text()
    cfg, data = runs.load_run(tiny_run)
    info = evaluate.export_section(runs.load_dataset(data, progress=False), tiny_run)
    assert info["measurements"]["mesh"]["faces"] > 0
    sc = info["score"]
    assert set(sc["mesh"]["thresholds"]) == {"0.2", "0.4", "1"} and sc["reference_points"] == 400
    if "height" in sc:                 # only when a ground plane was fitted under the ball
        assert sc["height"]["reference"] == pytest.approx(2 * 0.7 / NORM["scale"], rel=0.05)
    # eval rewrites report.md with the section and the score, and stores them in metrics.json
    assert cli.main(["eval", "--run", str(tiny_run), "--quiet", "--distractor-views", "0"]) == 0
    m = io.read_json(tiny_run / "metrics.json")
    assert m["export"]["score"]["mesh"]["num_ref"] == sc["mesh"]["num_ref"]
    report = (tiny_run / "report.md").read_text()
    assert report.count("## Tower model (export)") == 1 and "Against the reference tower" in report


def test_export_refuses_a_run_without_a_checkpoint(tiny_run, tmp_path, capsys):
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "config.json").write_bytes((tiny_run / "config.json").read_bytes())
    assert cli.main(["export", "--run", str(bare), "--quiet"]) == 1
    assert "no checkpoint" in _error_line(capsys)
    assert sorted(p.name for p in bare.iterdir()) == ["config.json"]


@pytest.mark.parametrize("box, words", [("0,0,0,0,1,1", "empty"), ("1,2,3", "six finite numbers"),
                                        ("5000,5000,5000,5100,5100,5100", "outside the scene")])
def test_export_refuses_a_bad_box(tiny_run, tmp_path, capsys, box, words):
    out = tmp_path / "out"
    assert cli.main(["export", "--run", str(tiny_run), "--out", str(out), f"--box={box}", "--quiet"]) == 1
    assert words in _error_line(capsys)
    assert not out.exists()


def test_export_refuses_a_folder_with_files(tiny_run, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert cli.main(["export", "--run", str(tiny_run), "--out", str(out), "--quiet"]) == 1
    assert "--overwrite" in _error_line(capsys)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_export_auto_box_without_ground_is_a_one_line_error(tiny_run, tmp_path, capsys):
    out = tmp_path / "out"
    code = cli.main(["export", "--run", str(tiny_run), "--out", str(out), "--views", "3", "--quiet"])
    if code == 0:                      # the ball's lower half may pass for a ground: then files exist
        assert (out / "box.json").is_file() and io.read_json(out / "box.json")["source"] == "auto"
    else:
        assert code == 1 and "--box" in _error_line(capsys) and not out.exists()


def test_units_are_metres_only_when_the_dataset_states_its_normalisation():
    from jaxnerf_grid.export import run as export_run
    from jaxnerf_grid.report import markdown as report

    ds = tiny_dataset()
    assert export_run.units_of(ds) == "unknown" and "unknown" in export_run.units_comment("unknown")
    ds.meta = {"scene_normalization": NORM}
    assert export_run.units_of(ds) == "metres" and "metres" in export_run.units_comment("metres")
    lines = "\n".join(report.export_lines({"measurements": {"units": "unknown", "height": 2.0}}))
    assert "units unknown" in lines and "2.00 units" in lines


def test_parse_box():
    from jaxnerf_grid.config.schema import ConfigError
    from jaxnerf_grid.export.run import parse_box

    assert parse_box("auto") is None and parse_box(" AUTO ") is None
    np.testing.assert_array_equal(parse_box("-1,-2,-3,4,5,6.5"), [-1, -2, -3, 4, 5, 6.5])
    for bad in ("1,2,3,4,5", "a,b,c,d,e,f", "0,0,0,1,1,nan", "0,0,1,1,1,1"):
        with pytest.raises(ConfigError):
            parse_box(bad)


# --------------------------------------------------------------------------- measurements by hand
# Each figure of export/measure.py on a cloud built so that its answer is known exactly: a
# tower frame q = (a, b, height) turned by TURN and moved by SHIFT into the world, so that the
# ground's normal is not z and its offset d = -n . SHIFT is not 0.

TURN = (np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]])
        @ np.array([[np.cos(0.5), -np.sin(0.5), 0], [np.sin(0.5), np.cos(0.5), 0], [0, 0, 1]]))
SHIFT = np.array([5.0, -7.0, 40.0])
GROUND_D = -float(TURN[:, 2] @ SHIFT)


def _world(q) -> np.ndarray:
    """Tower-frame points [N, 3] (a, b, height above the ground) -> the world."""
    return np.asarray(q, np.float64) @ TURN.T + SHIFT


def _tower_frame(x) -> np.ndarray:
    """World points [N, 3] -> the tower frame (the inverse of _world)."""
    return (np.asarray(x, np.float64) - SHIFT) @ TURN


def test_plane_basis_is_the_x_axis_projected_on_the_plane_and_orthonormal():
    for normal, ref in (([0.2, -0.3, 2.0], [1.0, 0, 0]), ([3.0, 0.0, 0.1], [0, 1.0, 0])):   # not unit length
        n = np.asarray(normal) / np.linalg.norm(normal)
        e1_true = np.asarray(ref) - (np.asarray(ref) @ n) * n
        e1_true /= np.linalg.norm(e1_true)
        e1, e2 = measure.plane_basis(normal)
        np.testing.assert_allclose(e1, e1_true, atol=1e-12)
        np.testing.assert_allclose(e2, np.cross(n, e1_true), atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm([e1, e2], axis=1), 1.0, atol=1e-12)


def test_min_area_rectangle_of_one_two_three_and_collinear_points():
    assert measure.min_area_rectangle(np.array([[2.0, 3.0]]))[:2] == (0.0, 0.0)
    np.testing.assert_array_equal(measure.min_area_rectangle(np.array([[2.0, 3.0]]))[2], [1.0, 0.0])
    line = np.array([0.6, 0.8])
    for pts in (np.array([[1.0, 1.0], [4.0, 5.0]]),                                  # two points 5 apart
                np.array([10.0, -4.0]) + np.linspace(-2.0, 3.0, 6)[:, None] * line):  # six on a line, off the origin
        wa, wb, direction = measure.min_area_rectangle(pts)
        assert (wa, wb) == (pytest.approx(5.0), 0.0)
        assert abs(direction @ line) == pytest.approx(1.0)
    triangle = np.array([[0.0, 0.0], [4.0, 0.0], [1.0, 3.0]])                        # area 6: the rectangle is 12
    wa, wb, _ = measure.min_area_rectangle(triangle)
    assert wb > 0 and wa >= wb and wa * wb == pytest.approx(12.0)


def test_footprint_of_a_turned_rectangle_on_tilted_offset_ground():
    """A base 6 x 2 turned 25 degrees in the tower frame, a narrower body above: the widths, the
    axes (along the base's long side, in the world), the band above the ground, the base's count."""
    rng = np.random.default_rng(11)
    turn = np.radians(25.0)
    long_side = np.array([np.cos(turn), np.sin(turn)])
    across = np.array([-np.sin(turn), np.cos(turn)])
    u, v = rng.uniform(-3, 3, 400), rng.uniform(-1, 1, 400)
    base = np.column_stack([np.outer(u, long_side) + np.outer(v, across), rng.uniform(0, 0.4, 400)])
    corners = np.array([[s * 3, t * 1] for s in (-1, 1) for t in (-1, 1)], np.float64)
    base = np.vstack([base, np.column_stack([corners @ np.vstack([long_side, across]), np.zeros(4)])])
    body = np.column_stack([rng.uniform(-0.5, 0.5, (300, 2)), rng.uniform(1.0, 10.0, 300)])
    fp = measure.footprint(_world(np.vstack([base, body])), TURN[:, 2], GROUND_D, band=0.5)
    assert fp["width_a"] == pytest.approx(6.0) and fp["width_b"] == pytest.approx(2.0)
    axis_a = TURN @ [long_side[0], long_side[1], 0.0]
    assert abs(np.asarray(fp["axis_a"]) @ axis_a) == pytest.approx(1.0)
    np.testing.assert_allclose(fp["axis_b"], np.cross(TURN[:, 2], fp["axis_a"]), atol=1e-12)
    np.testing.assert_allclose(fp["band"], [0.0, 0.5], atol=1e-9)
    assert fp["points"] == len(base)


def test_footprint_band_includes_its_upper_edge():
    """Level ground z = 3 (n = z, d = -3), exact heights: a point exactly `band` above the lowest
    is in the base; one above it is not."""
    pts = np.array([[0, 0, 3.0], [4, 0, 3.0], [4, 2, 3.0], [0, 2, 3.5], [8, 0, 3.75], [0, 9, 5.0]])
    fp = measure.footprint(pts, [0, 0, 1.0], -3.0, band=0.5)
    assert fp["points"] == 4 and fp["band"] == [0.0, 0.5]
    assert (fp["width_a"], fp["width_b"]) == (pytest.approx(4.0), pytest.approx(2.0))


def _counted_tower() -> np.ndarray:
    """Tower-frame points, slices 1 high: a body of 4 points (a, b = +-1) in each of 20 slices
    (height 0 in slice 0, k + 0.5 in slice k), and
    slice 4: the body twice (8 points, not wide);
    slice 5: 4 more at a = +-2 (8, widths 4 x 2: ratio 2, wide along a; a level, as many as
    the slice below; span 4);
    slice 12: 2 more at b = +-2.5 (6: exactly 1.5 x the median count 4; a level, span 6.5
    with slice 13's point);
    slice 13: 1 more at b = -4 (5, wide along b; not a level: under 6);
    slice 14: the main arm, 40 more along b in [-3, 9] at a = 2, 3 (44; a level, span 14 with
    its neighbours' b = -4 and 10, its centre line at a = 1, the middle of -1 .. 3);
    slice 15: 4 more at b = -3, 10, a = 2.5 (8, wide along b; not a level: 44 below);
    slices 18 and 19, the top: 20 more each along a in [-5, 5] (24 each, wide along a; 19 is a
    level, 18 is not: a level has more points than the slice above)."""
    body = [[a, b, 0.0 if k == 0 else k + 0.5] for k in range(20) for a in (-1.0, 1.0) for b in (-1.0, 1.0)]
    extra = [[a, b, 4.5] for a in (-1.0, 1.0) for b in (-1.0, 1.0)]
    extra += [[a, b, 5.5] for a in (-2.0, 2.0) for b in (-1.0, 1.0)]
    extra += [[0.0, -2.5, 12.5], [0.0, 2.5, 12.5], [0.0, -4.0, 13.5]]
    extra += [[2.0 + (i % 2), b, 14.5] for i, b in enumerate(np.linspace(-3.0, 9.0, 40))]
    extra += [[2.5, b, 15.5] for b in (-3.0, 10.0, -3.0, 10.0)]
    extra += [[a, 0.0, h] for h in (18.5, 19.5) for a in np.linspace(-5.0, 5.0, 20)]
    return np.array(body + extra)


def test_cross_arms_of_a_counted_tower_on_tilted_offset_ground():
    pts = _world(_counted_tower())
    n, e_a, e_b = TURN[:, 2], TURN[:, 0], TURN[:, 1]
    arms = measure.cross_arms(pts, n, GROUND_D, e_a, e_b, slice_height=1.0, separation=0.5)
    assert arms["slice_height"] == 1.0 and arms["ratio"] == 1.5
    np.testing.assert_allclose(arms["region"], [5.0, 20.0], atol=1e-9)
    levels = arms["levels"]
    np.testing.assert_allclose([lv["height"] for lv in levels], [5.5, 12.5, 14.5, 19.5], atol=1e-9)
    np.testing.assert_allclose([lv["span"] for lv in levels], [4.0, 6.5, 14.0, 10.0], atol=1e-9)
    assert [lv["axis"] for lv in levels] == ["a", "b", "b", "a"]
    ends = [_tower_frame(lv["ends"]) for lv in levels]
    np.testing.assert_allclose(ends[0], [[-2, 0, 5.5], [2, 0, 5.5]], atol=1e-9)
    np.testing.assert_allclose(ends[1], [[0, -4, 12.5], [0, 2.5, 12.5]], atol=1e-9)
    np.testing.assert_allclose(ends[2], [[1, -4, 14.5], [1, 10, 14.5]], atol=1e-9)
    np.testing.assert_allclose(ends[3], [[-5, 0, 19.5], [5, 0, 19.5]], atol=1e-9)
    # the default separation (6 % of 19.5 = 1.17) keeps the four; 2.5 keeps the stronger of 12.5 / 14.5
    default = measure.cross_arms(pts, n, GROUND_D, e_a, e_b, slice_height=1.0)
    assert [lv["height"] for lv in default["levels"]] == [lv["height"] for lv in levels]
    wider = measure.cross_arms(pts, n, GROUND_D, e_a, e_b, slice_height=1.0, separation=2.5)
    np.testing.assert_allclose([lv["height"] for lv in wider["levels"]], [5.5, 14.5, 19.5], atol=1e-9)
    # on level ground (exact heights) levels exactly `separation` apart are both kept
    level = measure.cross_arms(_counted_tower(), [0, 0, 1.0], 0.0, [1.0, 0, 0], [0, 1.0, 0], 1.0, separation=2.0)
    assert [lv["height"] for lv in level["levels"]] == [5.5, 12.5, 14.5, 19.5]
    # one point 60 above the ground: the default separation is 6 % of 60 = 3.6, and 12.5 goes
    tall = np.vstack([_counted_tower(), [[0.0, 0.0, 60.0]]])
    tall_arms = measure.cross_arms(tall, [0, 0, 1.0], 0.0, [1.0, 0, 0], [0, 1.0, 0], 1.0)
    assert [lv["height"] for lv in tall_arms["levels"]] == [5.5, 14.5, 19.5]


def test_cross_arms_counts_the_highest_point_in_the_top_slice_and_looks_past_a_sparse_slice():
    """Slices 1 high from 0: slice 0 of 6 points 0.5 x 0.5 wide, slice 1 of one point, slice 2 of
    4 points 0.5 x 0.5 and the highest point, exactly on the top edge (height 3), 0.7 out along
    one axis: with it, slice 2 is 0.95 x 0.5 (wide: 0.95 > 1.5 x 0.5); without it, not."""
    square = [(a, b) for a in (-0.25, 0.25) for b in (-0.25, 0.25)]
    q = ([(a, b, 0.0) for a, b in square] + [(0.0, 0.0, 0.5), (0.1, 0.1, 0.5), (0.0, 0.0, 1.5)]
         + [(a, b, 2.5) for a, b in square] + [(0.7, 0.0, 3.0)])
    q = np.asarray(q)
    for axes, name in (([[1.0, 0, 0], [0, 1.0, 0]], "a"), ([[0, 1.0, 0], [1.0, 0, 0]], "b")):
        got = measure.cross_arms(q, [0, 0, 1.0], 0.0, *axes, slice_height=1.0)
        assert got["region"] == [2.0, 3.0], name
        assert measure.cross_arms(q[:-1], [0, 0, 1.0], 0.0, *axes, slice_height=1.0)["region"] is None


def test_cross_arms_needs_ten_points():
    """Ten points in one slice, 4 wide along a and 1 along b: a region (no level: the slice is
    the median); nine: nothing."""
    ten = np.array([[a, b, h] for a in (-2.0, -1.0, 0.0, 1.0, 2.0) for b, h in ((0.0, 0.0), (1.0, 0.5))])
    got = measure.cross_arms(ten, [0, 0, 1.0], 0.0, [1.0, 0, 0], [0, 1.0, 0], slice_height=1.0)
    assert got["region"] == [0.0, 1.0] and got["levels"] == []
    got = measure.cross_arms(ten[:9], [0, 0, 1.0], 0.0, [1.0, 0, 0], [0, 1.0, 0], slice_height=1.0)
    assert got["region"] is None and got["levels"] == []
