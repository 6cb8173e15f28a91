"""3D export: a coloured point cloud of the tower from rendered depth maps.

Each rendered pixel with opacity >= `min_opacity` is lifted to the world point
x = o + d * (z_depth / cos_to_axis) (the depth maps are z-depth along the camera's -z axis)
and kept when |x| <= `radius` (the scene is normalised so the tower sits inside the unit
sphere). Points are in normalised scene units; `to_metric` maps them back with the dataset's
normalisation (x_metric = x / scale - translation).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid import io


def lift_view(rays, rgb: np.ndarray, depth: np.ndarray, opacity: np.ndarray, min_opacity: float = 0.5,
              radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Points of one view. rays: Rays [H, W]; rgb [H, W, 3]; depth, opacity [H, W].
    Returns (points [M, 3], colours [M, 3])."""
    o = np.asarray(rays.origins, np.float64)
    d = np.asarray(rays.directions, np.float64)
    t = np.asarray(depth, np.float64) / np.asarray(rays.cos_to_axis, np.float64)
    x = o + d * t[..., None]
    keep = (np.asarray(opacity) >= min_opacity) & (np.linalg.norm(x, axis=-1) <= radius) & np.isfinite(t)
    return x[keep].astype(np.float32), np.asarray(rgb)[keep].astype(np.float32)


def to_metric(points: np.ndarray, normalization: dict) -> np.ndarray:
    """Normalised scene points [M, 3] -> metric world points (inverse of x_norm = s (x + t))."""
    scale = float(normalization.get("scale", 1.0))
    translation = np.asarray(normalization.get("translation", [0.0, 0.0, 0.0]), np.float64)
    return (np.asarray(points, np.float64) / scale - translation).astype(np.float32)


def write_point_cloud(path, parts: list[tuple[np.ndarray, np.ndarray]]) -> Path:
    """Concatenates (points, colours) parts and writes a binary PLY. Returns the path."""
    points = np.concatenate([p for p, _ in parts]) if parts else np.zeros((0, 3), np.float32)
    colours = np.concatenate([c for _, c in parts]) if parts else np.zeros((0, 3), np.float32)
    io.write_ply(path, points, np.clip(colours, 0, 1))
    return Path(path)
