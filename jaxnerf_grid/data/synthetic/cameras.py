"""Drone camera paths around the tower, intrinsics, and per-view supersampled rays."""

from __future__ import annotations

import math

import numpy as np

from jaxnerf_grid.nerf import rays as rays_lib


def intrinsics(width: int, height: int, fov_deg: float) -> dict:
    """Pinhole intrinsics from a horizontal field of view: {fl_x, fl_y, cx, cy, w, h}."""
    f = rays_lib.focal_from_fov(math.radians(fov_deg), width)
    return {"fl_x": float(f), "fl_y": float(f), "cx": width / 2.0, "cy": height / 2.0, "w": int(width), "h": int(height)}


LINE_GAP_DEG = 30.0   # orbits skip this half-width around the line direction (+-y): no cables at the lens


def orbit_azimuth(f: float) -> float:
    """Maps f in [0, 1) to an azimuth (radians) outside the sectors around +-y (the line)."""
    arc = 180.0 - 2.0 * LINE_GAP_DEG
    a = (f % 1.0) * 2.0 * arc
    deg = -90.0 + LINE_GAP_DEG + a if a < arc else 90.0 + LINE_GAP_DEG + (a - arc)
    return math.radians(deg)


def camera_path(num_train: int, num_test: int, orbits, low_pass, rng: np.random.Generator):
    """Metric camera-to-world poses on orbits plus a low pass, with interleaved test views.

    orbits: ((radius, height, share), ...), skipping +-LINE_GAP_DEG around the line;
    low_pass: (radius, height, share), an arc over 140 degrees. Views are ordered along the path; test views are spread evenly among them
    (every k-th view), so they interpolate the training orbits.
    Returns (c2w [N, 4, 4] metric, split: list of "train"/"test").
    """
    total = num_train + num_test
    shares = np.array([o[2] for o in orbits] + [low_pass[2]], float)
    counts = np.floor(shares / shares.sum() * total).astype(int)
    counts[np.argsort(-shares)[: total - counts.sum()]] += 1
    eyes, targets = [], []
    for (radius, height, _), n in zip(orbits, counts[:-1]):
        phase = rng.uniform(0, 1)
        for k in range(n):
            az = orbit_azimuth(phase + k / max(n, 1)) + rng.uniform(-0.04, 0.04)
            r = radius * rng.uniform(0.95, 1.05)
            eyes.append([r * np.cos(az), r * np.sin(az), height + rng.uniform(-1.5, 1.5)])
            targets.append([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(12.0, 18.0)])
    radius, height, _ = low_pass
    start = rng.uniform(0, 2 * np.pi)
    n = counts[-1]
    for k in range(n):
        az = start + np.radians(140.0) * k / max(n - 1, 1)   # low enough to pass under the cables
        eyes.append([radius * np.cos(az), radius * np.sin(az), height + rng.uniform(-0.5, 0.5)])
        targets.append([0.0, 0.0, rng.uniform(11.0, 15.0)])
    c2w = np.stack([np.asarray(rays_lib.look_at(e, t), np.float64) for e, t in zip(eyes, targets)])
    split = ["train"] * total
    if num_test:
        stride = total / num_test
        for i in range(num_test):
            split[int(stride * i + stride / 2)] = "test"
    return c2w, split


def view_rays(c2w: np.ndarray, intr: dict, supersample: int):
    """Rays of one view: `supersample`^2 regular subpixel samples plus the pixel centre.

    c2w: [4, 4] metric. Returns (origins [H, W, K, 3], directions [H, W, K, 3] unit,
    cos_to_axis [H, W, K]) with K = supersample^2 + 1; the last sample is the pixel centre.
    """
    w, h, s = intr["w"], intr["h"], int(supersample)
    off = (np.arange(s) + 0.5) / s - 0.5
    ou, ov = np.meshgrid(off, off, indexing="xy")
    ou = np.append(ou.ravel(), 0.0)
    ov = np.append(ov.ravel(), 0.0)
    u = (np.arange(w) + 0.5)[None, :, None] + ou[None, None, :] + np.zeros((h, 1, 1))
    v = (np.arange(h) + 0.5)[:, None, None] + ov[None, None, :] + np.zeros((1, w, 1))
    r = rays_lib.rays_for_pixels(c2w.astype(np.float32), intr["fl_x"], intr["fl_y"], intr["cx"], intr["cy"],
                                 u.astype(np.float32), v.astype(np.float32))
    d = np.asarray(r.directions, np.float64)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.broadcast_to(c2w[:3, 3], d.shape).copy()
    return o, d, np.asarray(r.cos_to_axis, np.float64)


def normalise_pose(c2w: np.ndarray, scale: float, translation) -> np.ndarray:
    """Metric c2w [4, 4] -> normalised scene (rotation kept, position scale * (x + translation))."""
    out = np.array(c2w, np.float64)
    out[:3, 3] = scale * (out[:3, 3] + np.asarray(translation, float))
    return out
