"""Measurements of the exported tower, and its orthographic picture (pure NumPy + SciPy).

All inputs are in the export's units (metres when the dataset's scale is known, docs/EXPORT.md)
with the ground plane n . x + d = 0 (|n| = 1, n_z > 0; `export.ground`).

* height: the highest mesh vertex above the plane.
* footprint (`footprint`): the vertices in the lowest `band` of the mesh (default 5 % of the
  height, at least one voxel), projected on the plane; the minimum-area rectangle around them
  (`min_area_rectangle`, exact: one side lies on an edge of the convex hull) gives the base
  width along its two sides.
* the arms' axes (`arm_axes`): the principal axes of the horizontal spread of the mesh's upper
  half, where the arms are the widest members (the footprint's rectangle is no guide to them: a
  base seen by its two lowest legs gives a diagonal rectangle).
* cross-arms (`cross_arms`, a heuristic): the mesh is cut into horizontal slices; a slice
  belongs to the cross-arm region when its width along the arms' axis or the one across it
  exceeds `ratio` times the body width (the other axis's width in that slice). Within that
  region, a cross-arm level is a slice holding a local maximum of vertices (arms are horizontal
  members, dense in height) with at least 1.5 times the median count of all slices; its span is the
  extent of the vertices within one slice of it along the wide axis, and its end points are that
  extent's two ends at the level's height, placed across the wide axis at the middle of those
  vertices' extent (the arm's centre line).
* the cross-arms that carry wires (`arm_levels`): of those levels, the ones along the axis most
  lie along, at or above a third of the height, the longest within an arm's depth of another
  (the footings, a bracing across the arms and an arm's top chord make wide slices too).
* `orthographic_views`: front (x-z), side (y-z) and top (x-y) views of coloured points, drawn
  with a z-buffer (nearest point wins), shaded by the normal when given.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from jaxnerf_grid.export import ground
from jaxnerf_grid.util import io


def plane_basis(normal) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (e1, e2) spanning the plane with normal n [3]: e1 = the world x axis
    projected on the plane (y when n is along x), e2 = n x e1."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def min_area_rectangle(points2d: np.ndarray) -> tuple[float, float, np.ndarray]:
    """The minimum-area rectangle around points [N, 2] (N >= 1).
    Returns (width_a >= width_b, the unit direction [2] of side a)."""
    p = np.asarray(points2d, np.float64).reshape(-1, 2)
    if len(p) < 3 or np.linalg.matrix_rank(p - p.mean(axis=0)) < 2:
        if len(p) < 2:
            return 0.0, 0.0, np.array([1.0, 0.0])
        centred = p - p.mean(axis=0)
        direction = np.linalg.svd(centred, full_matrices=False)[2][0]
        return float(np.ptp(centred @ direction)), 0.0, direction
    from scipy.spatial import ConvexHull

    hull = p[ConvexHull(p).vertices]
    edges = np.roll(hull, -1, axis=0) - hull
    dirs = edges / np.maximum(np.linalg.norm(edges, axis=1, keepdims=True), 1e-300)
    normals = np.stack([-dirs[:, 1], dirs[:, 0]], axis=1)
    along, across = hull @ dirs.T, hull @ normals.T            # [H, E]
    w1, w2 = np.ptp(along, axis=0), np.ptp(across, axis=0)
    k = int(np.argmin(w1 * w2))
    if w1[k] >= w2[k]:
        return float(w1[k]), float(w2[k]), dirs[k]
    return float(w2[k]), float(w1[k]), normals[k]


def footprint(points: np.ndarray, normal, d: float, band: float) -> dict:
    """The base of a tower: points [N, 3] within `band` of the lowest point's height above the
    plane, their minimum-area rectangle on the plane.
    Returns {"width_a", "width_b" (width_a >= width_b), "axis_a" [3], "axis_b" [3] (unit, in the
    plane), "band": [low, high] heights, "points": count}."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = np.asarray(normal, np.float64)
    h = p @ n + d
    low = float(h.min())
    base = p[h <= low + band]
    e1, e2 = plane_basis(n)
    wa, wb, direction = min_area_rectangle(np.stack([base @ e1, base @ e2], axis=1))
    axis_a = direction[0] * e1 + direction[1] * e2
    return {"width_a": wa, "width_b": wb, "axis_a": [float(v) for v in axis_a],
            "axis_b": [float(v) for v in np.cross(n, axis_a)], "band": [low, low + band], "points": int(len(base))}


def arm_axes(points: np.ndarray, normal, d: float, top_share: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The cross-arms' axis and the one across it, both in the plane: the principal axes of the
    plane coordinates of the points [N, 3] in the upper `top_share` of their height range.
    Returns (axis [3], across [3] = n x axis), unit vectors; the world x projected on the plane
    and n x it when the points are fewer than two or spread alike both ways."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    e1, e2 = plane_basis(n)
    if len(p) < 2:
        return e1, e2
    h = p @ n + d
    top = p[h >= h.min() + (1.0 - top_share) * np.ptp(h)]
    q = np.stack([top @ e1, top @ e2], axis=1)
    q -= q.mean(axis=0)
    values, vectors = np.linalg.eigh(q.T @ q)      # ascending
    if values[1] <= values[0] * (1.0 + 1e-9):
        return e1, e2
    major = vectors[:, 1]
    axis = major[0] * e1 + major[1] * e2
    return axis, np.cross(n, axis)


def cross_arms(points: np.ndarray, normal, d: float, axis_a, axis_b, slice_height: float, ratio: float = 1.5,
               separation: float | None = None) -> dict:
    """The cross-arm region and levels of a tower (module docstring). points [N, 3]; axis_a,
    axis_b: the axes the widths are taken along [3] (`arm_axes`); separation: levels closer than this keep only the one
    with more vertices (default 6 % of the points' height range).
    Returns {"region": [low, high] | None, "levels": [{"height", "span", "axis", "ends"}],
    "slice_height", "ratio", "axis_a", "axis_b"} (heights above the plane; a level's "axis": "a" or
    "b", the one its arms lie along; "ends": the span's two end points [2, 3] in the points' frame,
    |ends[1] - ends[0]| = span)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    out: dict[str, Any] = {"region": None, "levels": [], "slice_height": float(slice_height), "ratio": float(ratio),
                           "axis_a": [float(v) for v in axis_a], "axis_b": [float(v) for v in axis_b]}
    if len(p) < 10:
        return out
    h = p @ np.asarray(normal, np.float64) + d
    a, b = p @ np.asarray(axis_a, np.float64), p @ np.asarray(axis_b, np.float64)
    edges = np.arange(h.min(), h.max() + slice_height, slice_height)
    idx = np.clip(np.digitize(h, edges) - 1, 0, len(edges) - 2)
    nslices = len(edges) - 1
    wide_axis = np.full(nslices, -1)
    counts = np.bincount(idx, minlength=nslices)
    for s in range(nslices):
        sel = idx == s
        if sel.sum() < 2:
            continue
        wa, wb = np.ptp(a[sel]), np.ptp(b[sel])
        if wa > ratio * max(wb, 1e-9):
            wide_axis[s] = 0
        elif wb > ratio * max(wa, 1e-9):
            wide_axis[s] = 1
    wide = np.flatnonzero(wide_axis >= 0)
    if len(wide) == 0:
        return out
    out["region"] = [float(edges[wide.min()]), float(edges[wide.max() + 1])]
    median = float(np.median(counts[counts > 0]))
    separation = 0.06 * float(np.ptp(h)) if separation is None else float(separation)
    peaks = []
    for s in wide.tolist():
        lo_count = int(counts[s - 1]) if s > 0 else -1
        hi_count = int(counts[s + 1]) if s + 1 < nslices else -1
        if counts[s] >= 1.5 * median and counts[s] >= lo_count and counts[s] > hi_count:
            peaks.append(int(s))
    kept: list[int] = []
    for s in sorted(peaks, key=lambda s: -counts[s]):        # the strongest first
        if all(abs(edges[s] - edges[k]) >= separation for k in kept):
            kept.append(s)
    n = np.asarray(normal, np.float64)
    pairs = [(a, np.asarray(axis_a, np.float64)), (b, np.asarray(axis_b, np.float64))]
    for s in sorted(kept):
        sel = (idx >= s - 1) & (idx <= s + 1)
        (along, e_along), (across, e_across) = pairs if wide_axis[s] == 0 else pairs[::-1]
        height = float(0.5 * (edges[s] + edges[s + 1]))
        values, middle = along[sel], 0.5 * (across[sel].min() + across[sel].max())
        ends = [v * e_along + middle * e_across + (height - d) * n for v in (values.min(), values.max())]
        out["levels"].append({"height": height, "span": float(np.ptp(values)),
                              "axis": "a" if wide_axis[s] == 0 else "b", "ends": [[float(v) for v in e] for e in ends]})
    return out


ARM_MIN_SHARE = 1.0 / 3.0   # of the tower's height: a cross-arm lower than this would hang its wires on the ground
ARM_DEPTH_SHARE = 0.08      # of the tower's height: an arm's truss is shallower; a level within it is its top chord


def arm_levels(arms: dict, height: float) -> dict:
    """The levels of `cross_arms` that are cross-arms carrying conductors, and those left out with
    why: of the levels along the axis most of them lie along (the tie broken by the longest span:
    a tower's arms lie one way), at or above ARM_MIN_SHARE of height (lower down the legs' spread
    and the footings are wide too), the longest of those within ARM_DEPTH_SHARE of height of one
    another (an arm's bottom chord and its top chord, running from the tip up to the body, make
    two wide slices one truss deep; the bottom one reaches the tip).
    Returns arms with "levels" those kept (by height) and "left_out" [{"height", "span", "axis",
    "why"}]."""
    levels = list(arms.get("levels") or [])
    out = {**arms, "levels": [], "left_out": []}
    if not levels:
        return out
    names = [lv["axis"] for lv in levels]
    longest = max(levels, key=lambda lv: lv["span"])["axis"]
    axis = max(("a", "b"), key=lambda name: (names.count(name), name == longest))
    candidates = []
    for lv in levels:
        why = None
        if lv["axis"] != axis:
            why = "across the other levels' arms"
        elif lv["height"] < ARM_MIN_SHARE * height:
            why = f"below a third of the tower's height ({ARM_MIN_SHARE * height:.3g}): the legs or the footings"
        if why:
            out["left_out"].append({"height": lv["height"], "span": lv["span"], "axis": lv["axis"], "why": why})
        else:
            candidates.append(lv)
    depth = ARM_DEPTH_SHARE * height
    kept: list[dict] = []
    for lv in sorted(candidates, key=lambda lv: -lv["span"]):
        near = [k for k in kept if abs(k["height"] - lv["height"]) < depth]
        if near:
            out["left_out"].append({"height": lv["height"], "span": lv["span"], "axis": lv["axis"],
                                    "why": f"within an arm's depth ({depth:.3g}) of the longer level at "
                                           f"{near[0]['height']:.3g}: its top chord"})
        else:
            kept.append(lv)
    out["levels"] = sorted(kept, key=lambda lv: lv["height"])
    return out


def orthographic_views(points: np.ndarray, colours: np.ndarray, normals: np.ndarray | None = None,
                       size: int = 400, background: float = 1.0, labels: bool = True, splat: int = 0) -> np.ndarray:
    """Front (x-z, seen from -y), side (y-z, seen from +x) and top (x-y, seen from +z) views of
    points [N, 3] with colours [N, 3] in [0, 1], side by side, one scale for all three (the
    largest extent fills `size` pixels). normals [N, 3] (optional) shade by |n . view|; splat:
    each point covers the (2 splat + 1)^2 pixels around it (still nearest first).
    Returns an image [size, 3 * size + gaps, 3] float32 in [0, 1]."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    c = np.clip(np.asarray(colours, np.float64).reshape(-1, 3), 0, 1)
    gap = 4
    canvas = np.full((size, 3 * size + 2 * gap, 3), background, np.float32)
    if len(p) == 0:
        return canvas
    lo, hi = p.min(axis=0), p.max(axis=0)
    scale = (size - 8) / max(float((hi - lo).max()), 1e-12)
    # (horizontal axis, sign), (vertical axis, sign), (depth axis, +1 = nearer the viewer)
    layouts = [((0, 1), (2, 1), (1, -1)), ((1, 1), (2, 1), (0, 1)), ((0, 1), (1, 1), (2, 1))]
    view_dirs = [np.array([0, -1.0, 0]), np.array([1.0, 0, 0]), np.array([0, 0, 1.0])]
    for k, ((ax_u, su), (ax_v, sv), (ax_d, sd)) in enumerate(layouts):
        mid = 0.5 * (lo + hi)
        u = np.round(size / 2 + su * (p[:, ax_u] - mid[ax_u]) * scale).astype(np.int64)
        v = np.round(size / 2 - sv * (p[:, ax_v] - mid[ax_v]) * scale).astype(np.int64)
        depth = sd * p[:, ax_d]
        shade = c
        if normals is not None:
            n = np.asarray(normals, np.float64).reshape(-1, 3)
            shade = c * (0.35 + 0.65 * np.abs(n @ view_dirs[k]))[:, None]
        offsets = [(du, dv) for dv in range(-splat, splat + 1) for du in range(-splat, splat + 1)]
        u = np.concatenate([u + du for du, _ in offsets])
        v = np.concatenate([v + dv for _, dv in offsets])
        depth, shade = np.tile(depth, len(offsets)), np.tile(shade, (len(offsets), 1))
        ok = (u >= 0) & (u < size) & (v >= 0) & (v < size)
        order = np.flatnonzero(ok)[np.argsort(-depth[ok], kind="stable")]   # nearest first
        pix = v[order] * size + u[order]
        _, first = np.unique(pix, return_index=True)                       # nearest point per pixel
        panel = np.full((size * size, 3), background, np.float32)
        panel[pix[first]] = shade[order[first]]
        x0 = k * (size + gap)
        canvas[:, x0:x0 + size] = panel.reshape(size, size, 3)
    if labels:
        canvas = _label(canvas, ["front (x-z)", "side (y-z)", "top (x-y)"], size, gap)
    return canvas


def _label(canvas: np.ndarray, names: list[str], size: int, gap: int) -> np.ndarray:
    """Writes a name in the corner of each panel (OpenCV when available; unchanged otherwise)."""
    try:
        cv2 = io.opencv()
    except Exception:  # noqa: BLE001 - the picture is still useful without its labels
        return canvas
    img = np.ascontiguousarray((canvas * 255).astype(np.uint8))
    for k, name in enumerate(names):
        cv2.putText(img, name, (k * (size + gap) + 6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (40, 40, 40), 1,
                    cv2.LINE_AA)
    return img.astype(np.float32) / 255.0


def _line_fit(h: np.ndarray, v: np.ndarray) -> tuple[float, float, float]:
    """Least-squares line v = a + b h over samples h, v [K >= 2]. Returns (a, b, standard error
    of b: the residuals' spread sqrt(sum r^2 / (K - 2)) / sqrt(sum (h - mean h)^2); 0 for K = 2)."""
    hc = h - h.mean()
    sxx = float(hc @ hc)
    b = float(hc @ (v - v.mean())) / sxx
    a = float(v.mean() - b * h.mean())
    r = v - (a + b * h)
    dof = len(h) - 2
    return a, b, (float(np.sqrt(r @ r / dof / sxx)) if dof > 0 else 0.0)


def _slice_centres(h: np.ndarray, a: np.ndarray, b: np.ndarray, slice_height: float, ratio: float,
                   min_points: int) -> np.ndarray:
    """The centres of the slices without a wide member (axis_tilt's docstring): h, a, b [N] the
    points' heights and coordinates along the footprint's axes. Returns [K, 3] (mean height,
    middle along a, middle along b), K >= 0."""
    edges = np.arange(h.min(), h.max() + slice_height, slice_height)
    idx = np.clip(np.digitize(h, edges) - 1, 0, max(len(edges) - 2, 0))
    rows = []
    for s in np.unique(idx):
        sel = idx == s
        if sel.sum() < min_points:
            continue
        wa, wb = np.ptp(a[sel]), np.ptp(b[sel])
        if max(wa, wb) > ratio * max(min(wa, wb), 1e-9):
            continue
        rows.append((h[sel].mean(), 0.5 * (a[sel].min() + a[sel].max()), 0.5 * (b[sel].min() + b[sel].max())))
    return np.asarray(rows, np.float64).reshape(-1, 3)


def _axis_lines(c: np.ndarray, slice_height: float) -> tuple[tuple, tuple, np.ndarray]:
    """Lines a(h), b(h) through slice centres c [K >= 3, 3] (axis_tilt's docstring: least squares,
    again without the centres more than 3 x 1.4826 MAD off). Returns (fit_a, fit_b, keep [K] bool),
    each fit (intercept, slope, slope's standard error)."""
    keep = np.ones(len(c), bool)
    for _ in range(2):
        fa, fb = _line_fit(c[keep, 0], c[keep, 1]), _line_fit(c[keep, 0], c[keep, 2])
        off = np.hypot(c[:, 1] - (fa[0] + fa[1] * c[:, 0]), c[:, 2] - (fb[0] + fb[1] * c[:, 0]))
        mad = 1.4826 * float(np.median(np.abs(off[keep] - np.median(off[keep]))))
        new = off <= max(3.0 * mad, 1e-9 + 0.5 * slice_height)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    return _line_fit(c[keep, 0], c[keep, 1]), _line_fit(c[keep, 0], c[keep, 2]), keep


def _slopes_angle(s1, s2) -> float:
    """Angle in degrees between the axes n + s_a e_a + s_b e_b of two slope pairs (s_a, s_b)."""
    u1, u2 = np.array([s1[0], s1[1], 1.0]), np.array([s2[0], s2[1], 1.0])
    cos = float(u1 @ u2) / float(np.linalg.norm(u1) * np.linalg.norm(u2))
    return float(np.degrees(np.arccos(min(1.0, cos))))


def axis_tilt(points: np.ndarray, normal, d: float, axis_a, axis_b, slice_height: float,
              ratio: float = 1.5, min_points: int = 3, thicker: tuple = (2.0, 4.0)) -> dict | None:
    """The tower's axis and its tilt. points [N, 3] (mesh vertices), the ground plane n . x + d = 0,
    the footprint's axes (unit, in the plane), slices `slice_height` thick in height above the plane.

    Each slice with >= min_points points and no wide member (its widths along a and b within
    `ratio` of each other: the cross-arms are left out) gives a centre: the middle of its extent
    along a and along b (a lattice's faces are symmetric about the axis, so is that middle) at
    its mean height h. Lines a(h), b(h) are fitted by least squares, once more without the slices
    more than 3 x 1.4826 MAD off; the axis is u = normalise(n + b_a e_a + b_b e_b) (b_a, b_b the
    slopes). The same fit with slices `thicker` times as thick gives other axes: on a clean mesh
    they agree, on a blobby one (a model's lumps bias the slices' middles, the more the thinner
    the slices) they do not, and their spread is a systematic error the fit's own scatter misses.
    Returns None with fewer than 3 slices, else
    {"tilt_degrees": angle of u from the frame's +z, "tilt_from_ground_normal_degrees": from n,
    "tilt_sigma_degrees": atan of the slopes' standard errors (RMS of the two),
    "thickness_spread_degrees": the RMS angle between u and the thicker slices' axes (those with
    3 or more slices; 0 when none has),
    "direction" [3] (u, u_z > 0), "base" [3] (the axis at the ground), "top" [3] (the axis at the
    highest point's height), "top_offset" (|top - base| horizontally, in x, y), "top_offset_xy" [2],
    "top_offset_sigma" (tilt_sigma in radians x the height), "lowest_height" (the lowest point's
    height above the plane: how far down the base is extrapolated), "slices": used,
    "slices_left_out"}."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = np.asarray(normal, np.float64)
    e_a, e_b = np.asarray(axis_a, np.float64), np.asarray(axis_b, np.float64)
    if len(p) < 3 * min_points:
        return None
    h, a, b = p @ n + d, p @ e_a, p @ e_b
    c = _slice_centres(h, a, b, slice_height, ratio, min_points)
    if len(c) < 3:
        return None
    fa, fb, keep = _axis_lines(c, slice_height)
    angles = []
    for k in thicker:
        ck = _slice_centres(h, a, b, slice_height * float(k), ratio, min_points)
        if len(ck) >= 3:
            ka, kb, _ = _axis_lines(ck, slice_height * float(k))
            angles.append(_slopes_angle((fa[1], fb[1]), (ka[1], kb[1])))

    def at(height):   # the axis at a height: x . e_a = a(h), x . e_b = b(h), x . n + d = h
        return (fa[0] + fa[1] * height) * e_a + (fb[0] + fb[1] * height) * e_b + (height - d) * n

    u = n + fa[1] * e_a + fb[1] * e_b
    u /= np.linalg.norm(u)
    if u[2] < 0:
        u = -u
    base, top = at(0.0), at(float(h.max()))
    sigma = float(np.degrees(np.arctan(np.sqrt(0.5 * (fa[2] ** 2 + fb[2] ** 2)))))
    offset = top[:2] - base[:2]
    return {"tilt_degrees": float(np.degrees(np.arccos(np.clip(u[2], -1.0, 1.0)))),
            "tilt_from_ground_normal_degrees": float(np.degrees(np.arctan(np.hypot(fa[1], fb[1])))),
            "tilt_sigma_degrees": sigma,
            "thickness_spread_degrees": float(np.sqrt(np.mean(np.square(angles)))) if angles else 0.0,
            "direction": [float(v) for v in u], "base": [float(v) for v in base],
            "top": [float(v) for v in top], "top_offset": float(np.hypot(*offset)),
            "top_offset_xy": [float(v) for v in offset],
            "top_offset_sigma": float(np.radians(sigma) * float(h.max())),
            "lowest_height": float(h.min()),
            "slices": int(keep.sum()), "slices_left_out": int(len(c) - keep.sum())}


def conductor_clearance(points: np.ndarray, normal, d: float, box_lo, box_hi, min_height: float,
                        cell: float, min_points: int = 20) -> dict:
    """The conductors' lowest reconstructed point above the ground (a heuristic). points [N, 3]
    (the dense cloud, every point, not only the box's); the tower's box [3], [3]; min_height:
    conductors hang from the cross-arms, so only points higher than this above the plane count
    (the caller passes half the lowest cross-arm's height: people, cars and shrubs stay below).

    Conductor points: those outside the tower's box in x or y, higher than min_height; their
    largest group of touching `cell` cells (26-neighbours) must hold >= min_points points and
    leave the box's side (start within 2 cells of it). Returns {"reconstructed": False, "why"}
    or {"reconstructed": True, "lowest_height" (above the plane), "lowest_point" [3], "points",
    "min_height", "extent": the group's largest horizontal distance from the box}."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    lo, hi = np.asarray(box_lo, np.float64), np.asarray(box_hi, np.float64)
    h = p @ np.asarray(normal, np.float64) + d
    outside = np.any((p[:, :2] < lo[:2]) | (p[:, :2] > hi[:2]), axis=1)
    cand = p[outside & (h > min_height)]
    out = {"reconstructed": False, "min_height": float(min_height)}
    if len(cand) < min_points:
        return {**out, "why": f"{len(cand)} points outside the tower's box higher than {min_height:.3g} above the "
                              f"ground (at least {min_points} needed)"}
    group = cand[ground.largest_cluster(cand, cell)]
    gap = np.max(np.maximum(np.maximum(lo[:2] - group[:, :2], group[:, :2] - hi[:2]), 0.0), axis=1)
    if len(group) < min_points or gap.min() > 2 * cell:
        return {**out, "why": f"the largest group above {min_height:.3g} outside the box ({len(group)} points) "
                              "does not leave the tower"}
    gh = group @ np.asarray(normal, np.float64) + d
    k = int(np.argmin(gh))
    return {"reconstructed": True, "lowest_height": float(gh[k]), "lowest_point": [float(v) for v in group[k]],
            "points": int(len(group)), "min_height": float(min_height), "extent": float(gap.max())}
