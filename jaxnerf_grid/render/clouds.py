"""Point clouds lifted from rendered depth: what evaluation and export share.

`evaluate.evaluate_run` writes tower_points.ply from these pieces and `export.run.export_run`
fuses the same lifted views into its dense cloud; both sit above this module, which imports
only NumPy and `io`, so neither needs the other.

* `cloud_view_ids`: which training frames a cloud is lifted from (evenly spaced).
* `lift_view`: each rendered pixel with opacity >= `min_opacity` is lifted to the world point
  x = o + d * (z_depth / cos_to_axis) (the depth maps are z-depth along the camera's -z axis)
  and kept when |x| <= `radius` (the scene is normalised so the tower sits inside the unit
  sphere). Points are in normalised scene units.
* `write_point_cloud`: (points, colours) parts -> a binary PLY.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid.util import io


def views_within(views: int, pixels: int, width: int, height: int, least: int = 2) -> int:
    """How many of `views` training views of width x height fit a budget of `pixels` pixels,
    never fewer than `least` (nor more than `views`)."""
    return min(int(views), max(int(least), int(pixels) // max(1, int(width) * int(height))))


def cloud_view_ids(ds, cloud_views: int) -> list[int]:
    """`cloud_views` training frame ids of the dataset `ds`, evenly spaced (all of them when
    there are fewer). Returns a list of ints (empty for cloud_views <= 0)."""
    train_ids = np.asarray(ds.split["train"])
    if cloud_views <= 0 or not len(train_ids):
        return []
    picks = np.linspace(0, len(train_ids) - 1, min(cloud_views, len(train_ids))).round().astype(int)
    return [int(i) for i in train_ids[picks]]


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


def write_point_cloud(path, parts: list[tuple[np.ndarray, np.ndarray]], comments: tuple[str, ...] = ()) -> Path:
    """Concatenates (points [M_i, 3], colours [M_i, 3]) parts and writes a binary PLY (with
    header comments). Returns the path."""
    points = np.concatenate([p for p, _ in parts]) if parts else np.zeros((0, 3), np.float32)
    colours = np.concatenate([c for _, c in parts]) if parts else np.zeros((0, 3), np.float32)
    io.write_ply(path, points, np.clip(colours, 0, 1), comments=comments)
    return Path(path)
