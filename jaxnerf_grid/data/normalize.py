"""Scene normalisation: a similarity (scale + translation, no rotation) that puts the region
of interest inside the unit sphere.

Convention (docs/DATASET.md): `x_norm = scale * (x + translation)`. Camera rotations are
unchanged; camera centres move like points. Metric ray distances scale by `scale`.

How the region of interest is found (`normalize_poses`):
- centre, method "cameras": the least-squares point closest to every camera's optical axis
  (the point an orbiting drone looks at). When the axes are nearly parallel (forward-facing
  captures) that point is ill-defined; the centre is then the mean camera centre moved
  `focus_depth` along the mean viewing direction (`focus_depth` defaults to the median
  distance from the cameras to the points, else to the spread of the camera centres).
- centre, method "points": the coordinate-wise median of the (sparse) points.
- radius: with points, the `percentile`-th percentile of the points' distances to the centre,
  capped at the largest camera distance to the centre (background points far behind the
  object must not blow the sphere up); without points, `camera_fraction` times the median
  camera distance. `scale = 1 / radius`.
"""

from __future__ import annotations

import numpy as np

from jaxnerf_grid.io import DataError


def optical_axis_focus(c2w: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares point closest to all optical axes.

    c2w: [N, 3|4, 4] OpenGL axes (the axis is -z). Returns (point [3], conditioning in [0, 1]:
    the smallest over the largest eigenvalue of sum(I - d d^T); near 0 = axes nearly parallel).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    origins = c2w[:, :3, 3]
    dirs = -c2w[:, :3, 2]
    dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # [N, 3, 3]
    a = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, origins)
    eig = np.linalg.eigvalsh(a)
    cond = float(eig[0] / max(eig[-1], 1e-12))
    point = np.linalg.lstsq(a, b, rcond=None)[0]
    return point, cond


def scene_center(c2w: np.ndarray, points: np.ndarray | None = None, method: str = "cameras",
                 focus_depth: float | None = None, min_conditioning: float = 1e-2) -> np.ndarray:
    """Centre of the region of interest. c2w: [N, 3|4, 4]; points: optional [P, 3]. Returns [3]."""
    c2w = np.asarray(c2w, dtype=np.float64)
    origins = c2w[:, :3, 3]
    if method == "points":
        if points is None or len(points) == 0:
            raise DataError("normalize_poses(method='points') needs 3-D points (none given)")
        return np.median(np.asarray(points, np.float64), axis=0)
    if method != "cameras":
        raise ValueError(f"method must be 'cameras' or 'points', got {method!r}")
    point, cond = optical_axis_focus(c2w)
    if len(c2w) >= 2 and cond >= min_conditioning:
        return point
    forward = -c2w[:, :3, 2].mean(0)
    forward = forward / max(np.linalg.norm(forward), 1e-12)
    if focus_depth is None:
        if points is not None and len(points):
            focus_depth = float(np.median(np.linalg.norm(np.asarray(points) - origins.mean(0), axis=-1)))
        else:
            spread = np.linalg.norm(origins - origins.mean(0), axis=-1).max() if len(origins) > 1 else 0.0
            focus_depth = float(spread) if spread > 0 else 1.0
    return origins.mean(0) + focus_depth * forward


def normalize_poses(c2w: np.ndarray, points: np.ndarray | None = None, method: str = "cameras", *,
                    percentile: float = 95.0, camera_fraction: float = 0.5,
                    focus_depth: float | None = None) -> tuple[np.ndarray, dict]:
    """Normalises poses so the region of interest lies in the unit sphere.

    c2w: [N, 3|4, 4] camera-to-world (any camera-axis convention; only -z matters for the
    focus); points: optional [P, 3] world points (e.g. COLMAP points3D).
    Returns (c2w_norm [N, 4, 4] float64, {"scale": float, "translation": [3] list}).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((3, 4), (4, 4)) or len(c2w) == 0:
        raise DataError(f"normalize_poses: c2w must be [N, 3|4, 4] with N > 0, got {c2w.shape}")
    pts = None if points is None or len(points) == 0 else np.asarray(points, np.float64).reshape(-1, 3)
    centre = scene_center(c2w, pts, method, focus_depth)
    cam_dist = np.linalg.norm(c2w[:, :3, 3] - centre, axis=-1)
    if pts is not None:
        radius = float(np.percentile(np.linalg.norm(pts - centre, axis=-1), percentile))
        if method == "cameras" and cam_dist.max() > 0:
            radius = min(radius, float(cam_dist.max()))
    else:
        radius = camera_fraction * float(np.median(cam_dist))
    if not np.isfinite(radius) or radius <= 1e-12:
        radius = 1.0
    norm = {"scale": 1.0 / radius, "translation": [float(v) for v in -centre]}
    return apply_normalization_to_poses(c2w, norm), norm


def apply_normalization_to_points(points: np.ndarray, norm: dict) -> np.ndarray:
    """x_norm = scale * (x + translation). points: [..., 3]. Returns [..., 3]."""
    return norm["scale"] * (np.asarray(points, np.float64) + np.asarray(norm["translation"], np.float64))


def apply_normalization_to_poses(c2w: np.ndarray, norm: dict) -> np.ndarray:
    """Moves camera centres like points, keeps rotations. c2w: [N, 3|4, 4]. Returns [N, 4, 4]."""
    c2w = np.asarray(c2w, dtype=np.float64)
    out = np.tile(np.eye(4), (len(c2w), 1, 1))
    out[:, :3, :3] = c2w[:, :3, :3]
    out[:, :3, 3] = apply_normalization_to_points(c2w[:, :3, 3], norm)
    return out


def invert_normalization(norm: dict) -> dict:
    """The inverse map in the same convention: x = s' * (x_norm + t') with s' = 1/s, t' = -s t."""
    scale = float(norm["scale"])
    return {"scale": 1.0 / scale, "translation": [float(-scale * v) for v in norm["translation"]]}


def compose_normalization(first: dict, second: dict) -> dict:
    """The map `second(first(x))` in the same convention: s = s2 s1, t = t1 + t2 / s1."""
    s1, s2 = float(first["scale"]), float(second["scale"])
    t1, t2 = np.asarray(first["translation"], float), np.asarray(second["translation"], float)
    return {"scale": s1 * s2, "translation": [float(v) for v in t1 + t2 / s1]}
