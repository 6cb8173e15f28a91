"""Ray-primitive intersections against brute-force marching with inside/outside tests.

The reference marches each ray in fine steps and reports the first step inside a primitive.
To make the comparison rigorous at grazing rays, it marches against a slightly shrunk and a
slightly grown copy of the primitive: shrunk ⊂ true ⊂ grown, so the exact first hit must lie
between the two marched distances (up to one step).
"""

import numpy as np
import pytest

from jaxnerf_grid.data.synthetic import intersect as ix

STEP = 2e-3
DELTA = 4e-3


def _rays(rng, n, target, spread, dist=4.0):
    """Rays from random points on a sphere of radius `dist` aimed near `target`."""
    origin_dir = rng.normal(size=(n, 3))
    origin_dir /= np.linalg.norm(origin_dir, axis=-1, keepdims=True)
    o = target + dist * origin_dir
    aim = target + rng.uniform(-spread, spread, size=(n, 3))
    d = aim - o
    return o, d / np.linalg.norm(d, axis=-1, keepdims=True)


def _march(o, d, inside, t_max=8.0):
    """First marched distance at which `inside(points [N, 3]) -> bool [N]` holds; inf if never."""
    ts = np.arange(STEP, t_max, STEP)
    first = np.full(len(o), np.inf)
    for t in ts:
        hit = inside(o + t * d) & ~np.isfinite(first)
        first[hit] = t
    return first


def _check(t, t_grown, t_shrunk):
    # Exact t must satisfy t_grown - STEP <= t <= t_shrunk (+inf = miss on either side).
    assert np.all((t >= t_grown - STEP - 1e-9) | ~np.isfinite(t_grown)), "hit earlier than the grown shape"
    assert np.all(np.isfinite(t) | ~np.isfinite(t_shrunk)), "missed a ray that hits the shrunk shape"
    assert np.all(~np.isfinite(t) | np.isfinite(t_grown)), "hit a ray that misses the grown shape"
    fin = np.isfinite(t) & np.isfinite(t_shrunk)
    assert np.all(t[fin] <= t_shrunk[fin] + 1e-9)
    assert np.isfinite(t).mean() > 0.15 and (~np.isfinite(t)).mean() > 0.05  # both cases exercised


def test_capsule_vs_marching():
    rng = np.random.default_rng(0)
    a, b, r = np.array([0.2, -0.3, 0.1]), np.array([-0.4, 0.5, 0.6]), 0.25
    o, d = _rays(rng, 1500, np.array([-0.1, 0.1, 0.35]), 0.8)
    t = ix.intersect_capsule(o, d, a[None], b[None], np.array([r]))[:, 0]
    grown = _march(o, d, lambda p: ix.inside_capsule(p, a, b, r + DELTA))
    shrunk = _march(o, d, lambda p: ix.inside_capsule(p, a, b, r - DELTA))
    _check(t, grown, shrunk)


def test_cylinder_vs_marching():
    rng = np.random.default_rng(1)
    a, b, r = np.array([0.0, 0.0, -0.5]), np.array([0.3, 0.2, 0.5]), 0.4
    o, d = _rays(rng, 1500, np.array([0.15, 0.1, 0.0]), 0.9)
    t = ix.intersect_cylinder(o, d, a[None], b[None], np.array([r]))[:, 0]
    grown = _march(o, d, lambda p: ix.inside_cylinder(p, a, b, r + DELTA, pad=DELTA))
    shrunk = _march(o, d, lambda p: ix.inside_cylinder(p, a, b, r - DELTA, pad=-DELTA))
    _check(t, grown, shrunk)


def test_ellipsoid_vs_marching():
    rng = np.random.default_rng(2)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    radii = np.array([0.7, 0.3, 0.15])
    A = np.diag(1 / radii) @ q.T      # world -> unit sphere
    c = np.array([0.1, -0.2, 0.3])
    o, d = _rays(rng, 1500, c, 0.7)
    t = ix.intersect_ellipsoid(o, d, c[None], A[None])[:, 0]
    # Growing/shrinking the level set by a factor changes the surface by <= factor * max radius.
    f = DELTA / radii.max()
    grown = _march(o, d, lambda p: ix.inside_ellipsoid(p, c, A, 1 + f))
    shrunk = _march(o, d, lambda p: ix.inside_ellipsoid(p, c, A, 1 - f))
    _check(t, grown, shrunk)


def test_box_vs_marching():
    rng = np.random.default_rng(3)
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    h = np.array([0.6, 0.2, 0.35])
    c = np.array([0.0, 0.3, -0.1])
    o, d = _rays(rng, 1500, c, 0.7)
    t = ix.intersect_box(o, d, c[None], R[None], h[None])[:, 0]
    grown = _march(o, d, lambda p: ix.inside_box(p, c, R, h + DELTA))
    shrunk = _march(o, d, lambda p: ix.inside_box(p, c, R, h - DELTA))
    _check(t, grown, shrunk)


def test_ground_plane():
    o = np.array([[0.0, 0.0, 2.0], [1.0, 2.0, 3.0], [0.0, 0.0, 1.0]])
    d = np.array([[0.0, 0.6, -0.8], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    t = ix.intersect_ground(o, d)
    np.testing.assert_allclose(t[0], 2.5)
    assert np.isinf(t[1]) and np.isinf(t[2])


@pytest.mark.parametrize("kind", ["capsule", "cylinder", "ellipsoid", "box"])
def test_normals_point_outward_and_are_perpendicular(kind):
    rng = np.random.default_rng(4)
    tables = _random_tables(rng, 1)
    geom = tables[kind]
    lo, hi = ix.prim_bounds(kind, geom)
    c = 0.5 * (lo[0] + hi[0])
    o, d = _rays(rng, 400, c, 0.05, dist=6.0)
    t = ix.INTERSECT[kind](o, d, geom)[:, 0]
    ok = np.isfinite(t)
    p, dd = o[ok] + t[ok, None] * d[ok], d[ok]
    one = {k: np.repeat(v[:1], len(p), 0) for k, v in geom.items()}
    n = {"capsule": lambda: ix.normal_capsule(p, one["a"], one["b"], one["r"]),
         "cylinder": lambda: ix.normal_cylinder(p, one["a"], one["b"], one["r"]),
         "ellipsoid": lambda: ix.normal_ellipsoid(p, one["c"], one["A"]),
         "box": lambda: ix.normal_box(p, one["c"], one["R"], one["h"])}[kind]()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-9)
    assert np.all(np.sum(n * dd, -1) < 1e-9)            # facing the incoming ray
    # A step outwards along the normal leaves the primitive; a step inwards enters it.
    step_out = ix.INTERSECT[kind](p + 1e-3 * n, -n, geom)[:, 0]
    assert np.all(np.isfinite(step_out)) and np.all(step_out < 2e-3)


def _random_tables(rng, m):
    a = rng.uniform(-3, 3, size=(m, 3))
    b = a + rng.uniform(-1.5, 1.5, size=(m, 3))
    q = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(m)])
    radii = rng.uniform(0.1, 0.8, size=(m, 3))
    return {
        "capsule": {"a": a, "b": b, "r": rng.uniform(0.05, 0.3, m)},
        "cylinder": {"a": b, "b": b + rng.uniform(-1, 1, size=(m, 3)), "r": rng.uniform(0.05, 0.4, m)},
        "ellipsoid": {"c": rng.uniform(-3, 3, size=(m, 3)),
                      "A": np.einsum("mi,mji->mij", 1 / radii, q)},
        "box": {"c": rng.uniform(-3, 3, size=(m, 3)), "R": q, "h": rng.uniform(0.1, 0.7, size=(m, 3))},
    }


def test_bvh_trace_matches_brute_force():
    rng = np.random.default_rng(5)
    tables = _random_tables(rng, 60)
    bvh = ix.build_bvh(tables, leaf_size=4)
    o, d = _rays(rng, 3000, np.zeros(3), 3.0, dist=9.0)
    t, kind, idx = ix.trace(bvh, o, d)
    tb, kb, ib = ix.brute_force_closest(tables, o, d)
    np.testing.assert_allclose(t, tb, rtol=1e-10)
    assert np.isfinite(t).mean() > 0.3
    hit = np.isfinite(t)
    np.testing.assert_array_equal(kind[hit], kb[hit])
    np.testing.assert_array_equal(idx[hit], ib[hit])
    # any-hit agrees on occlusion; t_max limits the hits.
    ta, _, _ = ix.trace(bvh, o, d, any_hit=True)
    np.testing.assert_array_equal(np.isfinite(ta), hit)
    tl, _, _ = ix.trace(bvh, o, d, t_max=np.full(len(o), 7.0))
    np.testing.assert_array_equal(np.isfinite(tl), tb < 7.0)


def test_binned_trace_screen_and_sun_culling_match_brute_force():
    """The renderer's culling (screen tiles for camera rays, sun-plane cells for shadow rays)."""
    from jaxnerf_grid.data.synthetic import cameras
    from jaxnerf_grid.data.synthetic.generate import TILE, SunGrid, scene_bounds, screen_rects
    from jaxnerf_grid.data.synthetic.scene import Scene
    from jaxnerf_grid.nerf.rays import look_at

    rng = np.random.default_rng(6)
    tables = _random_tables(rng, 40)
    # crosses the camera plane
    tables["capsule"]["a"][0], tables["capsule"]["b"][0] = [0.0, -30.0, 2.0], [0.0, 30.0, 2.0]
    scene = Scene(tables, {k: {"cls": np.zeros(40)} for k in tables})
    bounds = scene_bounds(scene)
    intr = cameras.intrinsics(48, 36, 60.0)
    c2w = np.asarray(look_at([0.0, 9.0, 3.0], [0.0, 0.0, 0.0]), np.float64)
    o, d, _ = cameras.view_rays(c2w, intr, 2)
    h, w, k = o.shape[:3]
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    rects, gw = screen_rects(bounds, c2w, intr)
    flat = np.arange(len(o))
    tile = (flat // (w * k) // TILE) * gw + (flat // k % w) // TILE
    t, kind, idx = ix.binned_trace(tables, rects, gw, tile, o, d)
    tb, kb, ib = ix.brute_force_closest(tables, o, d)
    np.testing.assert_allclose(t, tb, rtol=1e-10)
    assert np.isfinite(t).mean() > 0.1
    hit = np.isfinite(t)
    np.testing.assert_array_equal(kind[hit], kb[hit])
    # Shadow rays from points spread through the scene towards a sun direction.
    sun = np.array([0.3, -0.4, 0.8]) / np.linalg.norm([0.3, -0.4, 0.8])
    grid = SunGrid(sun, bounds, cell=0.7)
    pts = rng.uniform(-4, 4, size=(4000, 3))
    occ = grid.occluded(tables, grid.rects(bounds), pts, sun)
    ts, _, _ = ix.brute_force_closest(tables, pts, np.broadcast_to(sun, pts.shape))
    np.testing.assert_array_equal(occ, np.isfinite(ts))
    assert 0.1 < occ.mean() < 0.9
