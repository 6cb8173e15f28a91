"""Exact ray-primitive intersection (NumPy, float64) and a packet-traversed BVH.

Primitives (every field a NumPy array, M primitives of one kind):
  capsule   a [M, 3], b [M, 3], r [M]            segment a-b swept by a sphere of radius r
  cylinder  a [M, 3], b [M, 3], r [M]            capped cylinder with axis a-b
  ellipsoid c [M, 3], A [M, 3, 3]                {p : |A (p - c)| <= 1} (sphere: A = I / r)
  box       c [M, 3], R [M, 3, 3], h [M, 3]      oriented box, local axes = columns of R,
                                                 half extents h
The ground is the plane z = 0 (`intersect_ground`).

Every `intersect_*` function takes rays o [N, 3], d [N, 3] (d unit) and M primitives and
returns t [N, M], the distance to the first boundary crossing with t > T_EPS, +inf on a miss.
For rays starting outside a primitive this is the entry point. `normal_*` functions return
outward unit normals [N, 3] at points on the surface of one primitive per point.
`inside_*` functions are the plain point-membership tests the tests march rays with.

Two culling schemes: `binned_trace` (used by the renderer) groups rays by a 2-D cell (a screen
tile for one camera's rays, a cell of the plane perpendicular to the sun for shadow rays) and
tests each group only against the primitives whose projected bounds cover that cell; `trace`
walks a BVH with ray packets (general rays; kept as a second, independent culling path for
tests). Both are exact: culling only skips primitives a ray cannot hit.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

T_EPS = 1e-6
KINDS = ("capsule", "cylinder", "ellipsoid", "box")


def _dot(x, y):
    return np.einsum("...i,...i->...", x, y)


def _first_positive(*ts):
    """Elementwise min over candidates, ignoring t <= T_EPS and NaN. Each t: [N, M]."""
    out = np.full(np.broadcast(*ts).shape, np.inf)
    for t in ts:
        ok = t > T_EPS  # NaN compares False
        out = np.where(ok & (t < out), t, out)
    return out


def intersect_ground(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Plane z = 0 seen from above. o, d: [N, 3]. Returns t [N] (+inf on a miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[:, 2] / d[:, 2]
    return np.where((d[:, 2] < 0) & (o[:, 2] > 0) & (t > T_EPS), t, np.inf)


def _axis_terms(o, d, a, b, r):
    """Shared terms of the capsule / cylinder tests, all [N, M], from matrix products only
    (no [N, M, 3] temporaries). d must be unit length."""
    axis = b - a
    length = np.linalg.norm(axis, axis=-1)
    u = axis / np.maximum(length, 1e-12)[:, None]                      # [M, 3]
    du = d @ u.T                                                      # d.u
    oau = o @ u.T - np.sum(a * u, -1)[None]                           # (o - a).u
    d_oa = np.sum(d * o, -1)[:, None] - d @ a.T                       # d.(o - a)
    oa2 = np.sum(o * o, -1)[:, None] - 2.0 * (o @ a.T) + np.sum(a * a, -1)[None]   # |o - a|^2
    qa = 1.0 - du * du                                                # |d_perp|^2
    qb = d_oa - du * oau                                              # d_perp . oa_perp
    qc = oa2 - oau * oau - r[None] ** 2                               # |oa_perp|^2 - r^2
    return length, du, oau, d_oa, oa2, qa, qb, qc


def intersect_capsule(o, d, a, b, r):
    """o, d: [N, 3]; a, b: [M, 3]; r: [M]. Returns t [N, M]."""
    length, du, oau, d_oa, oa2, qa, qb, qc = _axis_terms(o, d, a, b, r)
    disc = qb * qb - qa * qc
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        t_body = (-qb - sq) / qa
        y = oau + t_body * du
        t_body = np.where((y >= 0) & (y <= length[None]) & (qa > 1e-12), t_body, np.nan)
        r2 = r[None] ** 2
        # Sphere at a: |o - a + t d|^2 = r^2.
        sd = d_oa * d_oa - (oa2 - r2)
        t_a = -d_oa - np.sqrt(np.where(sd >= 0, sd, np.nan))
        # Sphere at b: o - b = (o - a) - L u.
        d_ob = d_oa - length[None] * du
        ob2 = oa2 - 2.0 * length[None] * oau + length[None] ** 2
        sd = d_ob * d_ob - (ob2 - r2)
        t_b = -d_ob - np.sqrt(np.where(sd >= 0, sd, np.nan))
    return _first_positive(t_body, t_a, t_b)


def intersect_cylinder(o, d, a, b, r):
    """Capped cylinder. o, d: [N, 3]; a, b: [M, 3]; r: [M]. Returns t [N, M]."""
    length, du, oau, d_oa, oa2, qa, qb, qc = _axis_terms(o, d, a, b, r)
    disc = qb * qb - qa * qc
    cands = []
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        for sign in (-1.0, 1.0):
            t = (-qb + sign * sq) / qa
            y = oau + t * du
            cands.append(np.where((y >= 0) & (y <= length[None]) & (qa > 1e-12), t, np.nan))
        for level in (np.zeros_like(length), length):
            t = (level[None] - oau) / du
            # squared distance from the axis at t: |oa_perp + t d_perp|^2
            radial2 = (qc + r[None] ** 2) + 2.0 * t * qb + t * t * qa
            cands.append(np.where(radial2 <= r[None] ** 2, t, np.nan))
    return _first_positive(*cands)


def intersect_ellipsoid(o, d, c, A):
    """o, d: [N, 3]; c: [M, 3]; A: [M, 3, 3]. Returns t [N, M].

    Uses the quadratic form Q = A^T A: |A(o + t d - c)|^2 = 1, all terms as matrix products.
    """
    m = len(c)
    Q = np.einsum("mki,mkj->mij", A, A).reshape(m, 9)                  # [M, 9]
    Qc = np.einsum("mij,mj->mi", Q.reshape(m, 3, 3), c)               # [M, 3]
    dd = (d[:, :, None] * d[:, None, :]).reshape(-1, 9)
    od = (o[:, :, None] * d[:, None, :]).reshape(-1, 9)
    oo = (o[:, :, None] * o[:, None, :]).reshape(-1, 9)
    qa = dd @ Q.T
    qb = od @ Q.T - d @ Qc.T
    qc = oo @ Q.T - 2.0 * (o @ Qc.T) + np.sum(Qc * c, -1)[None] - 1.0
    disc = qb * qb - qa * qc
    with np.errstate(invalid="ignore"):
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
    return _first_positive((-qb - sq) / qa, (-qb + sq) / qa)


def intersect_box(o, d, c, R, h):
    """o, d: [N, 3]; c: [M, 3]; R: [M, 3, 3]; h: [M, 3]. Returns t [N, M]."""
    ol = np.einsum("mji,nmj->nmi", R, o[:, None, :] - c[None])       # R^T (o - c)
    dl = np.einsum("mji,nj->nmi", R, d)
    dl = np.where(np.abs(dl) < 1e-15, 1e-15, dl)
    t1 = (-h[None] - ol) / dl
    t2 = (h[None] - ol) / dl
    tn = np.max(np.minimum(t1, t2), axis=-1)
    tf = np.min(np.maximum(t1, t2), axis=-1)
    hit = tn <= tf
    return _first_positive(np.where(hit, tn, np.nan), np.where(hit, tf, np.nan))


# --- normals (one primitive per point) ---------------------------------------------------

def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def normal_capsule(p, a, b, r):
    """p, a, b: [N, 3]; r: [N]. Returns [N, 3]."""
    ab = b - a
    s = np.clip(_dot(p - a, ab) / np.maximum(_dot(ab, ab), 1e-12), 0.0, 1.0)
    return _unit(p - (a + s[:, None] * ab))


def normal_cylinder(p, a, b, r):
    """p, a, b: [N, 3]; r: [N]. Returns [N, 3] (cap normals on the end discs)."""
    ab = b - a
    length = np.linalg.norm(ab, axis=-1)
    u = ab / np.maximum(length, 1e-12)[:, None]
    y = _dot(p - a, u)
    radial = (p - a) - y[:, None] * u
    dist_side = np.abs(np.linalg.norm(radial, axis=-1) - r)
    dist_cap0, dist_cap1 = np.abs(y), np.abs(y - length)
    side = (dist_side < dist_cap0) & (dist_side < dist_cap1)
    cap = np.where((dist_cap0 < dist_cap1)[:, None], -u, u)
    return np.where(side[:, None], _unit(radial), cap)


def normal_ellipsoid(p, c, A):
    """p, c: [N, 3]; A: [N, 3, 3]. Returns [N, 3]."""
    local = np.einsum("nij,nj->ni", A, p - c)
    return _unit(np.einsum("nji,nj->ni", A, local))


def box_local(p, c, R, h):
    """Local coordinates and face axis. p, c: [N, 3]; R: [N, 3, 3]; h: [N, 3].

    Returns (local [N, 3], axis [N] in {0,1,2}, sign [N] in {-1,+1}).
    """
    local = np.einsum("nji,nj->ni", R, p - c)
    rel = np.abs(local) / np.maximum(h, 1e-12)
    axis = np.argmax(rel, axis=-1)
    sign = np.sign(np.take_along_axis(local, axis[:, None], 1)[:, 0])
    return local, axis, np.where(sign == 0, 1.0, sign)


def normal_box(p, c, R, h):
    """p, c: [N, 3]; R: [N, 3, 3]; h: [N, 3]. Returns [N, 3]."""
    _, axis, sign = box_local(p, c, R, h)
    return np.take_along_axis(R, axis[:, None, None].repeat(3, 1), 2)[..., 0] * sign[:, None]


# --- point membership (reference for tests) -----------------------------------------------

def inside_capsule(p, a, b, r):
    """p: [N, 3]; one capsule a, b: [3], r: scalar. Returns bool [N]."""
    ab = b - a
    s = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + s[:, None] * ab), axis=-1) <= r


def inside_cylinder(p, a, b, r, pad=0.0):
    ab = b - a
    length = np.linalg.norm(ab)
    u = ab / length
    y = (p - a) @ u
    radial = np.linalg.norm((p - a) - y[:, None] * u, axis=-1)
    return (radial <= r) & (y >= -pad) & (y <= length + pad)


def inside_ellipsoid(p, c, A, scale=1.0):
    return np.linalg.norm((p - c) @ A.T, axis=-1) <= scale


def inside_box(p, c, R, h):
    return np.all(np.abs((p - c) @ R) <= h, axis=-1)


# --- primitive tables and a BVH -----------------------------------------------------------

def prim_bounds(kind: str, geom: dict) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds of every primitive of one kind. Returns (lo [M, 3], hi [M, 3])."""
    if kind in ("capsule", "cylinder"):
        r = geom["r"][:, None]
        return np.minimum(geom["a"], geom["b"]) - r, np.maximum(geom["a"], geom["b"]) + r
    if kind == "ellipsoid":
        inv = np.linalg.inv(geom["A"])                  # columns: the semi-axes in world
        ext = np.linalg.norm(inv, axis=-1)              # row norms: half-extent per world axis
        return geom["c"] - ext, geom["c"] + ext
    if kind == "box":
        ext = np.einsum("mij,mj->mi", np.abs(geom["R"]), geom["h"])
        return geom["c"] - ext, geom["c"] + ext
    raise ValueError(f"unknown primitive kind {kind!r}")


INTERSECT = {
    "capsule": lambda o, d, g: intersect_capsule(o, d, g["a"], g["b"], g["r"]),
    "cylinder": lambda o, d, g: intersect_cylinder(o, d, g["a"], g["b"], g["r"]),
    "ellipsoid": lambda o, d, g: intersect_ellipsoid(o, d, g["c"], g["A"]),
    "box": lambda o, d, g: intersect_box(o, d, g["c"], g["R"], g["h"]),
}


def take(geom: dict, idx) -> dict:
    """Rows `idx` of every field of a primitive table."""
    return {k: v[idx] for k, v in geom.items()}


class BVH(NamedTuple):
    """Binary bounding-volume hierarchy over a mixed primitive soup.

    lo, hi: [K, 3] node bounds; left, right: [K] child ids (-1 at leaves);
    leaves: {node id: {kind: local index array}}; tables: {kind: geometry dict}.
    """

    lo: np.ndarray
    hi: np.ndarray
    left: np.ndarray
    right: np.ndarray
    leaves: dict
    tables: dict


def build_bvh(tables: dict, leaf_size: int = 8) -> BVH:
    """Median-split BVH. tables: {kind: geometry dict}; empty kinds are allowed."""
    kinds, locals_, los, his = [], [], [], []
    for kind, geom in tables.items():
        n = len(next(iter(geom.values()))) if geom else 0
        if n == 0:
            continue
        lo, hi = prim_bounds(kind, geom)
        kinds += [kind] * n
        locals_.append(np.arange(n))
        los.append(lo)
        his.append(hi)
    if not los:
        empty = np.zeros((0, 3))
        return BVH(empty, empty, np.zeros(0, int), np.zeros(0, int), {}, tables)
    kinds = np.array(kinds)
    local = np.concatenate(locals_)
    lo, hi = np.concatenate(los), np.concatenate(his)
    centre = 0.5 * (lo + hi)
    node_lo, node_hi, left, right, leaves = [], [], [], [], {}

    def build(ids):
        node = len(node_lo)
        node_lo.append(lo[ids].min(0))
        node_hi.append(hi[ids].max(0))
        left.append(-1)
        right.append(-1)
        if len(ids) <= leaf_size:
            leaves[node] = {k: local[ids[kinds[ids] == k]] for k in np.unique(kinds[ids])}
            return node
        spread = centre[ids].max(0) - centre[ids].min(0)
        axis = int(np.argmax(spread))
        order = ids[np.argsort(centre[ids, axis], kind="stable")]
        half = len(order) // 2
        left[node] = build(order[:half])
        right[node] = build(order[half:])
        return node

    build(np.arange(len(kinds)))
    return BVH(np.array(node_lo), np.array(node_hi), np.array(left), np.array(right), leaves, tables)


KIND_CODE = {k: i for i, k in enumerate(KINDS)}


def trace(bvh: BVH, o: np.ndarray, d: np.ndarray, t_max: np.ndarray | None = None,
          any_hit: bool = False):
    """Closest hit (or any hit) of rays against a BVH.

    o, d: [N, 3] (d unit); t_max: optional [N] (only hits with t < t_max count).
    Returns (t [N] (+inf: no hit), kind [N] (code into KINDS, -1: none), index [N] local
    index into that kind's table). With any_hit, t is finite for occluded rays but not
    necessarily the closest.
    """
    n = len(o)
    best = np.full(n, np.inf) if t_max is None else np.asarray(t_max, np.float64).copy()
    kind_out = np.full(n, -1, np.int64)
    idx_out = np.full(n, -1, np.int64)
    t_out = np.full(n, np.inf)
    if len(bvh.lo) == 0 or n == 0:
        return t_out, kind_out, idx_out
    with np.errstate(divide="ignore"):
        inv = 1.0 / np.where(d == 0, 1e-300, d)
    stack = [(0, np.arange(n))]
    while stack:
        node, ids = stack.pop()
        oi, ii = o[ids], inv[ids]
        with np.errstate(invalid="ignore"):
            t1 = (bvh.lo[node] - oi) * ii
            t2 = (bvh.hi[node] - oi) * ii
        tn = np.max(np.minimum(t1, t2), axis=1)
        tf = np.min(np.maximum(t1, t2), axis=1)
        keep = (tn <= tf) & (tf > T_EPS) & (tn < best[ids])
        ids = ids[keep]
        if ids.size == 0:
            continue
        leaf = bvh.leaves.get(node)
        if leaf is None:
            l, r = bvh.left[node], bvh.right[node]
            # Visit the child nearer to the packet's first origin first (pushed last).
            cl = 0.5 * (bvh.lo[l] + bvh.hi[l]) - o[ids[0]]
            cr = 0.5 * (bvh.lo[r] + bvh.hi[r]) - o[ids[0]]
            first, second = (l, r) if cl @ cl <= cr @ cr else (r, l)
            stack.append((second, ids))
            stack.append((first, ids))
            continue
        for kind, local in leaf.items():
            t = INTERSECT[kind](o[ids], d[ids], take(bvh.tables[kind], local))   # [n, m]
            j = np.argmin(t, axis=1)
            tm = t[np.arange(len(ids)), j]
            better = tm < best[ids]
            sel = ids[better]
            t_out[sel] = tm[better]
            kind_out[sel] = KIND_CODE[kind]
            idx_out[sel] = local[j[better]]
            best[sel] = -np.inf if any_hit else tm[better]
    return t_out, kind_out, idx_out


def brute_force_closest(tables: dict, o: np.ndarray, d: np.ndarray):
    """Closest hit by testing every primitive (no culling). Same returns as `trace`."""
    n = len(o)
    t_out = np.full(n, np.inf)
    kind_out = np.full(n, -1, np.int64)
    idx_out = np.full(n, -1, np.int64)
    for kind, geom in tables.items():
        if not geom or len(next(iter(geom.values()))) == 0:
            continue
        t = INTERSECT[kind](o, d, geom)
        j = np.argmin(t, axis=1)
        tm = t[np.arange(n), j]
        better = tm < t_out
        t_out[better], kind_out[better], idx_out[better] = tm[better], KIND_CODE[kind], j[better]
    return t_out, kind_out, idx_out


# --- 2-D binning: rays grouped by a cell of a projection, primitives by their projected rect --

def rect_pairs(rects: np.ndarray, grid_w: int) -> tuple[np.ndarray, np.ndarray]:
    """Enumerates the cells of inclusive integer rectangles.

    rects: [M, 4] (x0, y0, x1, y1), empty when x1 < x0 or y1 < y0; grid_w: cells per row.
    Returns (cell [P] = y * grid_w + x, prim [P]).
    """
    rects = np.asarray(rects, np.int64)
    wx = np.maximum(rects[:, 2] - rects[:, 0] + 1, 0)
    wy = np.maximum(rects[:, 3] - rects[:, 1] + 1, 0)
    count = wx * wy
    prim = np.repeat(np.arange(len(rects)), count)
    k = np.arange(len(prim)) - np.repeat(np.cumsum(count) - count, count)
    cx = rects[prim, 0] + k % np.maximum(wx[prim], 1)
    cy = rects[prim, 1] + k // np.maximum(wx[prim], 1)
    return cy * grid_w + cx, prim


def binned_trace(tables: dict, rects: dict, grid_w: int, ray_cell: np.ndarray, o: np.ndarray, d: np.ndarray,
                 t_max: np.ndarray | None = None):
    """Closest hits when rays can only hit primitives binned to their cell.

    Valid whenever every primitive a ray can hit covers the ray's cell (e.g. cells of the
    image for rays of one camera and the primitives' projected bounds; or cells of the plane
    perpendicular to parallel shadow rays).
    tables: {kind: geometry}; rects: {kind: [M, 4] inclusive cell rectangles};
    ray_cell: [N] cell id of each ray (-1: no cell, never hits); o, d: [N, 3].
    Returns (t [N], kind [N], index [N]) as `trace`.
    """
    n = len(o)
    best = np.full(n, np.inf) if t_max is None else np.asarray(t_max, np.float64).copy()
    t_out = np.full(n, np.inf)
    kind_out = np.full(n, -1, np.int64)
    idx_out = np.full(n, -1, np.int64)
    cells, kinds, prims = [], [], []
    for kind, r in rects.items():
        if len(r) == 0:
            continue
        c, p = rect_pairs(r, grid_w)
        cells.append(c)
        kinds.append(np.full(len(c), KIND_CODE[kind]))
        prims.append(p)
    if not cells or n == 0:
        return t_out, kind_out, idx_out
    pc, pk, pi = np.concatenate(cells), np.concatenate(kinds), np.concatenate(prims)
    order = np.lexsort((pi, pk, pc))
    pc, pk, pi = pc[order], pk[order], pi[order]
    rorder = np.argsort(ray_cell, kind="stable")
    rc = ray_cell[rorder]
    rcells, rstart, rcount = np.unique(rc, return_index=True, return_counts=True)
    pcells, pstart, pcount = np.unique(pc, return_index=True, return_counts=True)
    common, ri, pj = np.intersect1d(rcells, pcells, assume_unique=True, return_indices=True)
    for cell, a, b in zip(common, ri, pj):
        if cell < 0:
            continue
        ids = rorder[rstart[a]: rstart[a] + rcount[a]]
        lo, hi = pstart[b], pstart[b] + pcount[b]
        ks = pk[lo:hi]
        bounds = np.flatnonzero(np.diff(ks)) + 1
        for seg_lo, seg_hi in zip(np.r_[0, bounds], np.r_[bounds, hi - lo]):
            kind = KINDS[ks[seg_lo]]
            local = pi[lo + seg_lo: lo + seg_hi]
            t = INTERSECT[kind](o[ids], d[ids], take(tables[kind], local))
            j = np.argmin(t, axis=1)
            tm = t[np.arange(len(ids)), j]
            better = tm < best[ids]
            sel = ids[better]
            best[sel] = t_out[sel] = tm[better]
            kind_out[sel] = KIND_CODE[kind]
            idx_out[sel] = local[j[better]]
    return t_out, kind_out, idx_out


def box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Corners [M, 8, 3] of axis-aligned boxes lo, hi: [M, 3]."""
    sel = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], bool)
    return np.where(sel[None], hi[:, None, :], lo[:, None, :])
