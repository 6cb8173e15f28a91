"""The clearance of a fitted span over the ground and over what stands beneath it (pure NumPy).

All in the export's frame and units, the ground the plane n . x + d = 0 (`export.ground`; |n| = 1,
n . x + d the height above it), the span a dense polyline of points along it
(`export.catenary.sample_span`), up the frame's vertical (`export.conductors`).

* ground: the span's lowest point's height above the plane; `lowest_above_ground` also takes the
  least height of any of the span's points (the same on level ground; on a slope the least
  clearance need not be at the lowest point).
* objects: the cloud's points standing more than `ground_band` above the plane, outside the
  tower's box, within `corridor` horizontally of the span's vertical plane and between its two
  ends along it: what could come near the wire (trees, buildings). For each, the wire's height
  above it at its station along the span (the vertical clearance) and its horizontal distance
  from the wire's plane; the span's object clearance is the least vertical clearance, reported
  with that point, its horizontal distance and its height above the ground; `nearest` is the
  least 3-D distance of any of them to the wire. The fused cloud reaches only as far as the
  photos' region of interest: `covered` gives the stretch of the span (stations) where the
  cloud has any point within the corridor, so a reader knows what was checked.
* `ground_seen`: whether the ground beneath the span's lowest point is seen, and where the
  plane says it is. The clearance over the ground is the lowest point's height above a plane fitted
  to the ground the cloud holds, which may be only the ground around the tower: beneath a sag
  point far out the figure is the plane's extrapolation. The evidence: the cloud's ground points
  (at most `ground_band` above the plane, as `export.classes` calls ground) within a horizontal
  radius of the lowest point, their count and their median height above the plane; doubtful when
  fewer than `min_count` (the ground there not seen) or that median is more than `tolerance` off
  the plane (the plane does not fit the ground there).
  `lowest_point_ground_seen` asks the same of `export.measure.conductor_clearance`'s lowest
  reconstructed conductor point (the cloud-only heuristic), its radius from the wire group's reach.
* `flag`: a span is flagged when its ground or object clearance is below the clearance the user
  gives (`export --min-clearance`; no default: regulations differ by voltage and country).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from jaxnerf_grid.export import ground as ground_lib


def span_frame(curve: np.ndarray, up) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(start [3], e_line [3], e_across [3]) of a span's polyline curve [K >= 2, 3]: the
    horizontal unit vector from its first to its last point, and the horizontal across it."""
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    chord = curve[-1] - curve[0]
    line = chord - (chord @ u) * u
    line /= np.linalg.norm(line)
    return curve[0], line, np.cross(u, line)


def lowest_above_ground(curve: np.ndarray, normal, d: float) -> tuple[float, np.ndarray]:
    """(the least height above the plane of a polyline's points [K, 3], that point [3])."""
    h = np.asarray(curve, np.float64) @ np.asarray(normal, np.float64) + float(d)
    k = int(np.argmin(h))
    return float(h[k]), curve[k]


def objects_beneath(curve: np.ndarray, points: np.ndarray, normal, d: float, ground_band: float, corridor: float,
                    up=(0.0, 0.0, 1.0), box: tuple | None = None) -> dict:
    """The points of a cloud [N, 3] that could come near a span (module docstring) and the
    span's clearance over them. curve [K, 3]: the span's points from one end to the other;
    box: the tower's (lo [3], hi [3]) whose points are left out.
    Returns {"count", "covered": [s_lo, s_hi] | None (stations with any cloud point in the
    corridor), "clearance": the least vertical clearance | None, "point" [3], "horizontal_distance",
    "height_above_ground", "nearest": the least 3-D distance to the wire | None}."""
    curve = np.asarray(curve, np.float64)
    p = np.asarray(points, np.float64).reshape(-1, 3)
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    start, line, across = span_frame(curve, u)
    station_curve = (curve - start) @ line
    rel = p - start
    station, offset = rel @ line, rel @ across
    wire_offset = float(np.median((curve - start) @ across))
    in_corridor = (np.abs(offset - wire_offset) <= corridor) & (station >= station_curve.min()) & \
        (station <= station_curve.max())
    out: dict[str, Any] = {"count": 0, "covered": None, "clearance": None, "point": None, "horizontal_distance": None,
           "height_above_ground": None, "nearest": None}
    if in_corridor.any():
        out["covered"] = [float(station[in_corridor].min()), float(station[in_corridor].max())]
    height = p @ np.asarray(normal, np.float64) + float(d)
    keep = in_corridor & (height > ground_band)
    if box is not None:
        lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
        keep &= ~np.all((p >= lo) & (p <= hi), axis=1)
    if not keep.any():
        return out
    q = p[keep]
    wire_z = np.interp(station[keep], station_curve, curve @ u)
    vertical = wire_z - q @ u
    k = int(np.argmin(vertical))
    from scipy.spatial import cKDTree

    nearest, _ = cKDTree(curve).query(q)
    out.update({"count": int(keep.sum()), "clearance": float(vertical[k]), "point": [float(v) for v in q[k]],
                "horizontal_distance": float(abs(offset[keep][k] - wire_offset)),
                "height_above_ground": float(height[keep][k]), "nearest": float(nearest.min())})
    return out


# of the span's horizontal length, the radius around the lowest point where the ground counts: a
# catenary's bottom is flat, the wire 5 % of the span either side of its lowest point is within
# (2 x 0.05)^2 = 1 % of the sag of its height there, so that ground is what its clearance stands over
GROUND_RADIUS_SHARE = 0.05
# ground points the radius must hold: the demo's cloud has about 3 a 0.4 m ground column (6431 on
# 2108 columns, benchmarks/results/demo_export_settled.json) and a 16 m radius (a 320 m span)
# thousands where the ground is seen; fewer than 10 are a few stray points, not a surface
GROUND_MIN_POINTS = 10
# the ground's robust spread (the survey's ground sigma: its band / 3) the median height may be off
# the plane: past twice it, the clearance is off by more than its ground term says
GROUND_OFF_SPREADS = 2.0
NOT_SEEN, OFF_PLANE = "too few ground points", "ground off the plane"


def ground_seen(point, points: np.ndarray, normal, d: float, ground_band: float, radius: float,
                up=(0.0, 0.0, 1.0), min_count: int = GROUND_MIN_POINTS,
                tolerance: float | None = None) -> dict:
    """The evidence for the ground beneath a span's lowest point [3] (module docstring) in a cloud
    points [N, 3]: its ground points (height above the plane n . x + d = 0 at most ground_band)
    within `radius` horizontally (across up) of the point. tolerance: how far their median height
    may be off the plane (default GROUND_OFF_SPREADS x ground_band / 3).
    Returns {"radius", "count", "min_count", "median_height": None without points, "tolerance",
    "doubtful": bool, "reason": NOT_SEEN | OFF_PLANE | None}."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    rel = p - np.asarray(point, np.float64)
    across_up = rel - np.outer(rel @ u, u)
    height = ground_lib.heights(p, normal, d)
    near = (height <= ground_band) & (np.linalg.norm(across_up, axis=1) <= radius)
    count = int(near.sum())
    median = float(np.median(height[near])) if count else None
    tol = GROUND_OFF_SPREADS * float(ground_band) / 3.0 if tolerance is None else float(tolerance)
    reason = NOT_SEEN if count < min_count else OFF_PLANE if median is not None and abs(median) > tol else None
    return {"radius": float(radius), "count": count, "min_count": int(min_count), "median_height": median,
            "tolerance": tol, "doubtful": reason is not None, "reason": reason}


# the least radius around the heuristic's lowest conductor point, in ground columns (the ground
# fit's cell): with ~3 points a column (the demo's cloud), a seen ground gives pi x 5^2 ~ 78
# columns' ~240 points there, far above GROUND_MIN_POINTS
LOWEST_MIN_CELLS = 5


def lowest_point_ground_seen(cond: dict, points: np.ndarray, normal, d: float, ground_band: float, cell: float,
                             up=(0.0, 0.0, 1.0)) -> dict | None:
    """`ground_seen` beneath the conductors' lowest reconstructed point of a cloud points [N, 3]:
    cond is `export.measure.conductor_clearance`'s record ("lowest_point" [3], "extent"). The
    radius: GROUND_RADIUS_SHARE of the wire group's extent, at least LOWEST_MIN_CELLS x cell (the
    ground's column size). None when cond is not reconstructed."""
    if not (cond or {}).get("reconstructed"):
        return None
    # no span length here: the group's reach from the tower stands in for the span the point hangs on
    radius = max(GROUND_RADIUS_SHARE * float(cond["extent"]), LOWEST_MIN_CELLS * float(cell))
    return ground_seen(cond["lowest_point"], points, normal, d, ground_band, radius, up)


def flag(ground: float | None, objects: float | None, min_clearance: float | None) -> bool | None:
    """Whether a span's least clearance (over the ground, over the objects) is below min_clearance;
    None when no clearance was given."""
    if min_clearance is None:
        return None
    values = [v for v in (ground, objects) if v is not None]
    return bool(values) and min(values) < float(min_clearance)
