"""The ground plane and the tower's box, found without ground truth (pure NumPy + SciPy).

Up is +z (`geometry.UP_AXIS`; the normalised scene keeps the world's axes, docs/DATASET.md).

* `lowest_points`: the lowest point of each vertical column (cell x cell in x, y) of a dense
  cloud: where the cameras see the ground, that is the ground; columns under the tower or a
  floater give outliers.
* `fit_plane_ransac`: RANSAC (3-point planes, at most `max_tilt_deg` from horizontal, the one
  with the most points within `threshold`), refined by least squares (SVD) on its inliers.
  The plane is n . x + d = 0 with |n| = 1, n_z > 0, so n . x + d is the height above it.
* `settle_on_cloud`: the plane moved along its normal to the median height of all the cloud's
  points within a band around it. The lowest point of a column is the lowest of that column's
  noisy ground points, so the plane through the lowest points lies below the surface by about
  the depths' spread (0.30 m on the GPS chain's model posed by `poses`, 0.14 m on the demo's,
  docs/EXPORT.md); the median of every point near the plane has no such bias.
* `tower_box`: the points higher than `clearance` above the plane, binned into cubic cells;
  cells joined when they touch (26-neighbours, after a one-cell dilation that bridges the
  gaps of a lattice); the largest group by point count is the tower. Its box is the group's
  extent plus one cell on every side in x, y and at the top; its bottom is `clearance` above
  the plane at the box's highest bottom corner (so the ground is not meshed), also where the
  group itself starts higher: a tower stands on the ground, and a cloud fused from a few
  views can miss the lower legs that the field still holds (the GPS chain's model of
  docs/EXPORT.md: the cloud's tower began 11 m above the ground).
"""

from __future__ import annotations

import numpy as np

UP = 2


def lowest_points(points: np.ndarray, cell: float) -> np.ndarray:
    """The lowest point (in z) of each occupied column of side `cell`. points [N, 3].
    Returns [M, 3] float64."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) == 0:
        return p
    keys = np.floor(p[:, :2] / float(cell)).astype(np.int64)
    order = np.lexsort((p[:, UP], keys[:, 1], keys[:, 0]))   # by column, then by height
    k = keys[order]
    first = np.ones(len(k), bool)
    first[1:] = np.any(k[1:] != k[:-1], axis=1)
    return p[order[first]]


def plane_through(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The plane through three points [3] as (unit normal with n_z >= 0, d); None when they are
    (nearly) collinear."""
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n)
    if norm < 1e-12:
        return None
    n = n / norm
    if n[UP] < 0:
        n = -n
    return n, float(-n @ a)


def refine_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane of points [N >= 3, 3] (orthogonal distances, SVD). Returns (n, d),
    n_z >= 0."""
    p = np.asarray(points, np.float64)
    centre = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - centre, full_matrices=False)
    n = vt[-1]
    if n[UP] < 0:
        n = -n
    return n, float(-n @ centre)


def fit_plane_ransac(points: np.ndarray, threshold: float, iterations: int = 500, seed: int = 0,
                     max_tilt_deg: float = 45.0) -> tuple[np.ndarray, float, np.ndarray]:
    """Robust plane of points [N, 3] (module docstring). threshold: inlier distance.
    Returns (normal [3], d, inliers [N] bool). Raises ValueError with fewer than 3 points or
    no acceptable plane."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) < 3:
        raise ValueError(f"fit_plane_ransac: need at least 3 points, got {len(p)}")
    rng = np.random.default_rng(seed)
    min_nz = np.cos(np.radians(max_tilt_deg))
    best, best_count = None, -1
    for _ in range(int(iterations)):
        plane = plane_through(*p[rng.choice(len(p), 3, replace=False)])
        if plane is None or plane[0][UP] < min_nz:
            continue
        count = int(np.sum(np.abs(p @ plane[0] + plane[1]) <= threshold))
        if count > best_count:
            best, best_count = plane, count
    if best is None:
        raise ValueError("fit_plane_ransac: no plane within the tilt limit")
    inliers = np.abs(p @ best[0] + best[1]) <= threshold
    n, d = refine_plane(p[inliers]) if inliers.sum() >= 3 else best
    if n[UP] < min_nz:   # the refinement may not tilt it past the limit
        n, d = best
    inliers = np.abs(p @ n + d) <= threshold
    return n, d, inliers


def settle_on_cloud(points: np.ndarray, normal, d: float, band: float,
                    rounds: int = 20) -> tuple[float, np.ndarray]:
    """The offset d of the plane n . x + d = 0 (normal kept) moved to the median height of the
    points [N, 3] within `band` of it, again until it moves less than band / 100 or `rounds`
    times (each round's band is centred on the plane of the round before). Returns (d, near [N]
    bool: the points within `band` of the returned plane); the plane unchanged where fewer than 3
    points lie in the band."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    d = float(d)
    for _ in range(int(rounds)):
        h = heights(p, normal, d)
        near = np.abs(h) <= band
        if near.sum() < 3:
            break
        shift = float(np.median(h[near]))
        d -= shift
        if abs(shift) < band / 100.0:
            break
    return d, np.abs(heights(p, normal, d)) <= band


def heights(points: np.ndarray, normal, d: float) -> np.ndarray:
    """Signed heights above the plane n . x + d = 0 of points [N, 3]. Returns [N]."""
    return np.asarray(points, np.float64).reshape(-1, 3) @ np.asarray(normal, np.float64) + float(d)


def plane_z(normal, d: float, x, y) -> np.ndarray:
    """z of the plane n . x + d = 0 above (x, y) (arrays broadcast)."""
    n = np.asarray(normal, np.float64)
    return -(n[0] * np.asarray(x) + n[1] * np.asarray(y) + d) / n[UP]


def largest_cluster(points: np.ndarray, cell: float) -> np.ndarray:
    """The largest group of touching cells (module docstring) of points [N, 3].
    Returns a mask [N] bool (all False for no points)."""
    from scipy import ndimage

    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0, bool)
    idx = np.floor((p - p.min(axis=0)) / float(cell)).astype(np.int64) + 1
    occ = np.zeros(tuple(idx.max(axis=0) + 2), bool)
    occ[tuple(idx.T)] = True
    grown = ndimage.binary_dilation(occ, structure=np.ones((3, 3, 3), bool))
    labels, _ = ndimage.label(grown, structure=np.ones((3, 3, 3), bool))
    point_labels = labels[tuple(idx.T)]
    counts = np.bincount(point_labels)
    counts[0] = 0
    return point_labels == int(np.argmax(counts))


def tower_box(points: np.ndarray, normal, d: float, clearance: float,
              cell: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """The tower's box from a dense cloud points [N, 3] and the ground plane (module docstring).
    Returns (box_min [3], box_max [3], stats {"above_ground", "tower_points"}). Raises
    ValueError when nothing stands above the ground."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    above = p[heights(p, normal, d) > clearance]
    if len(above) == 0:
        raise ValueError("nothing stands above the ground plane")
    tower = above[largest_cluster(above, cell)]
    lo, hi = tower.min(axis=0) - cell, tower.max(axis=0) + cell
    corners_z = plane_z(normal, d, np.array([lo[0], lo[0], hi[0], hi[0]]), np.array([lo[1], hi[1], lo[1], hi[1]]))
    lo[UP] = float(corners_z.max()) + clearance   # a tower stands on the ground, seen or not
    if lo[UP] >= hi[UP]:
        raise ValueError("the tower's box is empty above the ground")
    return lo, hi, {"above_ground": int(len(above)), "tower_points": int(len(tower))}
