"""Scene normalisation: a similarity that puts the region of interest inside the unit sphere.

Convention (docs/DATASET.md): `x_norm = scale * R (x + translation)`, a record
{"scale": s, "translation": [3], "rotation": [[3] x 3]} whose "rotation" R is optional: absent
means the identity, and every map below then computes exactly what it did before rotations
existed (`x_norm = scale * (x + translation)`, bit for bit). Camera centres move like points;
camera rotations turn by R (unchanged without one). Metric ray distances scale by `scale`.

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

from jaxnerf_grid.util.io import DataError


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


def normalization_rotation(norm: dict) -> np.ndarray | None:
    """The record's rotation R [3, 3] float64, or None when it has none (the identity)."""
    r = norm.get("rotation")
    return None if r is None else np.asarray(r, np.float64).reshape(3, 3)


def _record(scale: float, translation, rotation: np.ndarray | None) -> dict:
    out = {"scale": float(scale), "translation": [float(v) for v in np.asarray(translation).reshape(3)]}
    if rotation is not None:
        out["rotation"] = [[float(v) for v in row] for row in np.asarray(rotation, np.float64).reshape(3, 3)]
    return out


def normalization_record(norm: dict) -> dict:
    """A record as plain JSON numbers: {"scale", "translation" [3], and "rotation" [3][3] only when
    it has one} (what datasets hold and transforms.json files store)."""
    return _record(norm["scale"], norm["translation"], normalization_rotation(norm))


def apply_normalization_to_points(points: np.ndarray, norm: dict) -> np.ndarray:
    """x_norm = scale * R (x + translation) (R: the optional "rotation"). points: [..., 3]. Returns [..., 3]."""
    moved = norm["scale"] * (np.asarray(points, np.float64) + np.asarray(norm["translation"], np.float64))
    r = normalization_rotation(norm)
    return moved if r is None else moved @ r.T


def apply_normalization_to_poses(c2w: np.ndarray, norm: dict) -> np.ndarray:
    """Moves camera centres like points and turns the camera rotations by R (kept without one).
    c2w: [N, 3|4, 4]. Returns [N, 4, 4]."""
    c2w = np.asarray(c2w, dtype=np.float64)
    r = normalization_rotation(norm)
    out = np.tile(np.eye(4), (len(c2w), 1, 1))
    out[:, :3, :3] = c2w[:, :3, :3] if r is None else r @ c2w[:, :3, :3]
    out[:, :3, 3] = apply_normalization_to_points(c2w[:, :3, 3], norm)
    return out


def invert_normalization(norm: dict) -> dict:
    """The inverse map in the same convention: x = s' R' (x_norm + t') with s' = 1/s,
    R' = R^T, t' = -s R t (without a rotation: t' = -s t, and no rotation in the result)."""
    scale = float(norm["scale"])
    r = normalization_rotation(norm)
    if r is None:
        return {"scale": 1.0 / scale, "translation": [float(-scale * v) for v in norm["translation"]]}
    return _record(1.0 / scale, -scale * r @ np.asarray(norm["translation"], np.float64), r.T)


def compose_normalization(first: dict, second: dict) -> dict:
    """The map `second(first(x))` in the same convention: s = s2 s1, R = R2 R1,
    t = t1 + R1^T t2 / s1 (a rotation in the result only when either has one)."""
    s1, s2 = float(first["scale"]), float(second["scale"])
    t1, t2 = np.asarray(first["translation"], float), np.asarray(second["translation"], float)
    r1, r2 = normalization_rotation(first), normalization_rotation(second)
    if r1 is None and r2 is None:
        return {"scale": s1 * s2, "translation": [float(v) for v in t1 + t2 / s1]}
    r1 = np.eye(3) if r1 is None else r1
    r2 = np.eye(3) if r2 is None else r2
    return _record(s1 * s2, t1 + r1.T @ t2 / s1, r2 @ r1)


def check_rotation(rotation, source: str, tol: float = 1e-5) -> np.ndarray:
    """A record's "rotation" checked: a 3x3 of finite numbers, orthonormal with determinant +1
    (within `tol`). Returns it [3, 3] float64; a DataError naming `source` otherwise."""
    try:
        r = np.asarray(rotation, np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{source}: scene_normalization 'rotation' must be a 3x3 list of numbers") from None
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise DataError(f"{source}: scene_normalization 'rotation' must be a 3x3 list of finite numbers, "
                        f"got shape {r.shape}")
    if np.abs(r @ r.T - np.eye(3)).max() > tol or abs(np.linalg.det(r) - 1.0) > tol:
        raise DataError(f"{source}: scene_normalization 'rotation' is not a rotation (R R^T != I or det != 1)")
    return r


def z_up_turn(c2w: np.ndarray) -> np.ndarray:
    """The rotation [3, 3] that turns the cameras' up axis (`up_from_cameras`, c2w [N, 3|4, 4]
    OpenGL) onto +z."""
    return rotation_between(up_from_cameras(c2w), np.array([0.0, 0.0, 1.0]))


def z_up_normalization(c2w: np.ndarray, points: np.ndarray | None = None, method: str = "cameras",
                       **kwargs) -> tuple[np.ndarray, dict]:
    """`normalize_poses` after turning the scene so the up axis found from the cameras
    (`up_from_cameras`) is +z; the record carries that turn as its "rotation" (none when the
    up axis is +z already). c2w: [N, 3|4, 4] OpenGL; points: optional [P, 3]; kwargs go to
    `normalize_poses`. Returns (c2w_norm [N, 4, 4], record)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((3, 4), (4, 4)) or len(c2w) == 0:
        raise DataError(f"z_up_normalization: c2w must be [N, 3|4, 4] with N > 0, got {c2w.shape}")
    rot = z_up_turn(c2w)
    if np.array_equal(rot, np.eye(3)):
        return normalize_poses(c2w, points, method, **kwargs)
    turned, pts = rotate_scene(c2w, rot, points)
    c2w_norm, extra = normalize_poses(turned, pts, method, **kwargs)
    return c2w_norm, compose_normalization(_record(1.0, np.zeros(3), rot), extra)


# ----------------------------------------------------------------------------------------
# The up axis of a capture, for scenes whose world frame is arbitrary (structure from motion)


NADIR_MARGIN = 0.3   # the viewing directions agree this much more than the image-up vectors: a nadir survey


def up_from_cameras(c2w: np.ndarray, *, spread: float = 0.05, flatness: float = 0.25,
                    max_tilt_deg: float = 45.0) -> np.ndarray:
    """World up direction of a capture, from its cameras. Returns a unit vector [3].

    c2w: [N, 3|4, 4] OpenGL axes (camera +x right, +y up in the image). Three estimates, the
    first that applies (each must lie within `max_tilt_deg` of the mean up vector, whose
    side it takes):
    1. level cameras (a drone's gimbal holds the roll at zero): every camera's right vector
       `c2w[:, :3, 0]` is horizontal, so up is the direction most perpendicular to all of
       them, the eigenvector of the smallest eigenvalue of sum(x x^T) over the right vectors.
       It needs the headings to vary (the middle eigenvalue at least `spread` times the
       largest); any pitch, any part of an orbit, any heights;
    2. the normal of a plane fitted to the camera centres, when they lie near one (N >= 3;
       the smallest eigenvalue of their covariance at most `flatness` times the middle one,
       which is at least `flatness` times the largest: a plane, not a line): one heading
       over a flat survey pattern;
    3. the mean of the cameras' up vectors `c2w[:, :3, 1]` (exact for level, unpitched cameras).
    A nadir survey (cameras looking down, headings turning back and forth) has its image-up
    vectors horizontal and cancelling, its viewing directions all alike: where the mean of the
    cameras' backward axes `c2w[:, :3, 2]` (towards the sky for a camera looking down) is longer
    than the mean up vector's by NADIR_MARGIN, it takes the mean up vector's place as the
    direction estimates 1 and 2 must lie near (the last resort stays 3).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    mean_up = c2w[:, :3, 1].mean(0)
    norm = np.linalg.norm(mean_up)
    mean_up = mean_up / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])
    mean_back = c2w[:, :3, 2].mean(0)
    nadir = np.linalg.norm(mean_back) > norm + NADIR_MARGIN
    reference = mean_back / np.linalg.norm(mean_back) if nadir else mean_up
    min_cos = np.cos(np.radians(max_tilt_deg))

    def oriented(v):
        v = v / np.linalg.norm(v)
        v = v if v @ reference >= 0 else -v
        return v if v @ reference >= min_cos else None

    right = c2w[:, :3, 0] / np.linalg.norm(c2w[:, :3, 0], axis=-1, keepdims=True)
    eig, vec = np.linalg.eigh(right.T @ right / len(right))
    if eig[1] >= spread * eig[2] and (up := oriented(vec[:, 0])) is not None:
        return up
    centres = c2w[:, :3, 3]
    if len(centres) >= 3:
        eig, vec = np.linalg.eigh(np.cov((centres - centres.mean(0)).T, bias=True))
        if eig[2] > 1e-12 and eig[0] <= flatness * eig[1] and eig[1] >= flatness * eig[2]:
            if (up := oriented(vec[:, 0])) is not None:
                return up
    return mean_up


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3, 3] taking direction a [3] to direction b [3] (Rodrigues).

    Opposite directions: a half turn about an axis perpendicular to a.
    """
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        perp /= np.linalg.norm(perp)
        return 2.0 * np.outer(perp, perp) - np.eye(3)
    k = axis / s
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * kx + (1.0 - c) * kx @ kx


def rotate_scene(c2w: np.ndarray, rotation: np.ndarray, points: np.ndarray | None = None):
    """Rotates a whole scene about the origin: x' = R x.

    c2w: [N, 3|4, 4]; rotation: [3, 3]; points: optional [P, 3].
    Returns (c2w' [N, 4, 4], points' [P, 3] or None).
    """
    c2w = np.asarray(c2w, np.float64)
    r = np.asarray(rotation, np.float64)
    out = np.tile(np.eye(4), (len(c2w), 1, 1))
    out[:, :3, :3] = r @ c2w[:, :3, :3]
    out[:, :3, 3] = c2w[:, :3, 3] @ r.T
    pts = None if points is None else np.asarray(points, np.float64).reshape(-1, 3) @ r.T
    return out, pts


def normalize_orbit(c2w: np.ndarray, points: np.ndarray | None = None, *, percentile: float = 95.0,
                    camera_fraction: float = 1.0 / 3.0) -> tuple[np.ndarray, dict]:
    """Normalisation for an orbit around a tower (`jaxnerf-grid poses`, docs/POSES.md).

    c2w: [N, 3|4, 4] OpenGL, already z-up (`up_from_cameras`, `rotate_scene`); points:
    optional [P, 3]. The centre is the point the cameras look at (`scene_center`, cameras
    method); the radius is the `percentile`-th percentile of the points' distances to it,
    capped at `camera_fraction` times the median camera distance (the synthetic scenes put
    the cameras about 3 radii away: docs/DATASET.md, `data.synthetic.NORMALIZATION`); without
    points, that cap. Returns (c2w_norm [N, 4, 4], {"scale", "translation"}) as `normalize_poses`.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((3, 4), (4, 4)) or len(c2w) == 0:
        raise DataError(f"normalize_orbit: c2w must be [N, 3|4, 4] with N > 0, got {c2w.shape}")
    centre, radius = orbit_roi(c2w, points, percentile=percentile, camera_fraction=camera_fraction)
    norm = {"scale": 1.0 / radius, "translation": [float(v) for v in -centre]}
    return apply_normalization_to_poses(c2w, norm), norm


def orbit_roi(c2w: np.ndarray, points: np.ndarray | None = None, *, percentile: float = 95.0,
              camera_fraction: float = 1.0 / 3.0) -> tuple[np.ndarray, float]:
    """The region of interest of an orbit, (centre [3], radius): the point the cameras look at
    (`scene_center`, cameras method) and the `percentile`-th percentile of the points' distances
    to it, capped at `camera_fraction` times the median camera distance; without points, that
    cap (1 when it is not positive). c2w: [N, 3|4, 4] OpenGL; points: optional [P, 3].
    `normalize_orbit` scales it to the unit sphere; `data.bounds` records it (docs/BOUNDS.md)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    pts = None if points is None or len(points) == 0 else np.asarray(points, np.float64).reshape(-1, 3)
    centre = scene_center(c2w, pts, "cameras")
    cap = camera_fraction * float(np.median(np.linalg.norm(c2w[:, :3, 3] - centre, axis=-1)))
    radius = cap
    if pts is not None:
        radius = float(np.percentile(np.linalg.norm(pts - centre, axis=-1), percentile))
        radius = min(radius, cap) if cap > 0 else radius
    if not np.isfinite(radius) or radius <= 1e-12:
        radius = 1.0
    return centre, radius
