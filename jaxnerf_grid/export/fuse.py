"""Depth fusion with a multi-view consistency check (pure NumPy).

Each view's rendered depth is lifted to points (`clouds.lift_view`). A point from view i is
*confirmed* by another view j when it projects inside j's image, in front of j's camera, onto a
pixel with opacity >= `min_opacity` whose rendered z-depth d_j agrees with the point's z-depth
z_j in that camera:

    |d_j - z_j| <= tol_pixels * z_j / f_j

(the width of `tol_pixels` pixels of view j at that depth; f_j = its focal length in pixels). A
point is kept when at least `min_views` other views confirm it. Floaters seen by one view and
depth errors at silhouettes do not survive; a surface seen by several views does. A point that
view j cannot see (occluded, outside the picture) simply gets no vote from j.

Cameras follow jaxnerf_grid/nerf/rays.py: c2w [4, 4] (OpenGL axes, looking down -z), pixel centres
at (i + 0.5, j + 0.5), row 0 at the top.
"""

from __future__ import annotations

import numpy as np

DEFAULT_VIEWS = 16  # training views rendered and fused by `jaxnerf-grid export`
DEFAULT_MIN_VIEWS = 2
DEFAULT_TOL_PIXELS = 1.0


def project(points: np.ndarray, c2w: np.ndarray, intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pinhole projection. points [N, 3] (world); c2w [3|4, 4]; intrinsics (fx, fy, cx, cy).
    Returns (u [N], v [N] pixel coordinates, z [N] z-depth along the camera's -z axis)."""
    c2w = np.asarray(c2w, np.float64)
    rotation, centre = c2w[:3, :3], c2w[:3, 3]
    cam = (np.asarray(points, np.float64) - centre) @ rotation   # R^T (x - c), row vectors
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    z = -cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cx + fx * cam[:, 0] / z
        v = cy - fy * cam[:, 1] / z
    return u, v, z


def confirmations(points: np.ndarray, source: np.ndarray, cameras: list[dict], min_opacity: float = 0.5,
                  tol_pixels: float = DEFAULT_TOL_PIXELS) -> np.ndarray:
    """How many views other than its own confirm each point (module docstring).

    points [N, 3]; source [N] int: the index in `cameras` of the view each point came from;
    cameras: [{"c2w" [4, 4], "intrinsics" (fx, fy, cx, cy), "depth" [H, W], "opacity" [H, W]}].
    Returns counts [N] int.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    source = np.asarray(source).reshape(-1)
    counts = np.zeros(len(points), np.int64)
    for j, cam in enumerate(cameras):
        depth, opacity = np.asarray(cam["depth"]), np.asarray(cam["opacity"])
        height, width = depth.shape
        u, v, z = project(points, cam["c2w"], cam["intrinsics"])
        col, row = np.floor(u), np.floor(v)
        inside = (z > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height) & (source != j)
        idx = np.flatnonzero(inside)
        r, c = row[idx].astype(np.int64), col[idx].astype(np.int64)
        d, o = depth[r, c].astype(np.float64), opacity[r, c]
        tol = tol_pixels * z[idx] / float(cam["intrinsics"][0])
        ok = (o >= min_opacity) & np.isfinite(d) & (np.abs(d - z[idx]) <= tol)
        counts[idx[ok]] += 1
    return counts


def fuse(parts: list[tuple[np.ndarray, np.ndarray]], cameras: list[dict], min_views: int = DEFAULT_MIN_VIEWS,
         min_opacity: float = 0.5, tol_pixels: float = DEFAULT_TOL_PIXELS) -> tuple[np.ndarray, np.ndarray, dict]:
    """The confirmed points of every view.

    parts: per view (points [K_i, 3], colours [K_i, 3]) in the order of `cameras`.
    Returns (points [M, 3] float32, colours [M, 3] float32, stats {"lifted", "kept"}).
    """
    if not parts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), {"lifted": 0, "kept": 0}
    points = np.concatenate([np.asarray(p, np.float64).reshape(-1, 3) for p, _ in parts])
    colours = np.concatenate([np.asarray(c, np.float32).reshape(-1, 3) for _, c in parts])
    source = np.concatenate([np.full(len(p), i) for i, (p, _) in enumerate(parts)])
    keep = confirmations(points, source, cameras, min_opacity, tol_pixels) >= min_views
    return (points[keep].astype(np.float32), colours[keep], {"lifted": int(len(points)), "kept": int(keep.sum())})
