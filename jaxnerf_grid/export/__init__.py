"""3D export of the tower: the metric model of `jaxnerf-grid export` (docs/EXPORT.md).

This file holds the dataset's normalisation, used by the submodules and by `evaluate.py` through
`eval.export_score` (no JAX at import time); the depth clouds it shares with evaluation are `clouds.py`:

* `to_metric` / `to_scene`: the dataset's normalisation x_norm = scale * R (x + translation)
  (R: the optional rotation; docs/DATASET.md) undone / applied; `plane_to_metric` does it for a plane;
  `box_to_scene` / `box_to_metric` for an axis-aligned box: the box around all 8 mapped corners
  (with a rotation, mapping the two opposite corners alone gives a wrong, even inverted, box).

The export itself lives in submodules, each imported by its user:
`export.field` (the trained density and colour, sampled in chunks; JAX), `export.mesh`
(marching cubes, thresholds, components), `export.ground` (RANSAC ground plane, the tower's box),
`export.fuse` (multi-view consistent depth fusion), `export.measure` (height, footprint,
cross-arms, the orthographic picture), `eval.export_score` (the export against a reference tower) and
`export.run` (`export_run`, the `jaxnerf-grid export` pipeline).
"""

from __future__ import annotations

import numpy as np

from jaxnerf_grid.data.normalize import apply_normalization_to_points, invert_normalization, normalization_rotation


def _scale_translation(normalization: dict | None) -> tuple[float, np.ndarray, np.ndarray | None]:
    """(scale, translation [3], rotation [3, 3] or None) of a record; a missing one is the identity."""
    normalization = normalization or {}
    scale = float(normalization.get("scale", 1.0))
    translation = np.asarray(normalization.get("translation", [0.0, 0.0, 0.0]), np.float64)
    return scale, translation, normalization_rotation(normalization)


def _record_or_identity(normalization: dict | None) -> dict:
    """The record as `data.normalize` takes it, with a missing one (or missing fields) the identity."""
    scale, translation, rotation = _scale_translation(normalization)
    record = {"scale": scale, "translation": translation}
    if rotation is not None:
        record["rotation"] = rotation
    return record


def to_metric(points: np.ndarray, normalization: dict) -> np.ndarray:
    """Normalised scene points [M, 3] -> metric world points (inverse of x_norm = s R (x + t)).
    Returns [M, 3] float32."""
    return to_metric64(points, normalization).astype(np.float32)


def to_metric64(points: np.ndarray, normalization: dict | None) -> np.ndarray:
    """`to_metric` in float64 (for measurements): x = R^T x_norm / s - t (without a rotation,
    x_norm / s - t), the dataset's inverse map (`data.normalize.invert_normalization`).
    points [..., 3] -> [..., 3]."""
    return apply_normalization_to_points(points, invert_normalization(_record_or_identity(normalization)))


def to_scene(points: np.ndarray, normalization: dict | None) -> np.ndarray:
    """Metric world points [..., 3] -> normalised scene points, x_norm = s R (x + t). float64.
    The dataset's own map (`data.normalize.apply_normalization_to_points`), with a missing
    normalisation taken as the identity."""
    return apply_normalization_to_points(points, _record_or_identity(normalization))


def plane_to_metric(normal, offset: float, normalization: dict | None) -> tuple[np.ndarray, float]:
    """A plane n . x + d = 0 of the normalised scene (n [3] unit) -> the same plane in metric
    units: n' . x_m + (n' . t + d / s) = 0 with n' = R^T n (n itself without a rotation).
    Returns (normal [3], offset)."""
    scale, translation, rotation = _scale_translation(normalization)
    n = np.asarray(normal, np.float64)
    if rotation is not None:
        n = rotation.T @ n
    return n, float(n @ translation + float(offset) / scale)


def box_corners(lo, hi) -> np.ndarray:
    """The 8 corners [8, 3] of the axis-aligned box lo [3] - hi [3]."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    pick = np.array([[(k >> axis) & 1 for axis in range(3)] for k in range(8)], bool)
    return np.where(pick, hi, lo)


def box_to_scene(lo, hi, normalization: dict | None) -> tuple[np.ndarray, np.ndarray]:
    """A metric axis-aligned box lo [3] - hi [3] -> the axis-aligned box of the normalised scene
    holding it: the extent of its 8 corners mapped by `to_scene`. Returns (lo [3], hi [3])."""
    corners = to_scene(box_corners(lo, hi), normalization)
    return corners.min(axis=0), corners.max(axis=0)


def box_to_metric(lo, hi, normalization: dict | None) -> tuple[np.ndarray, np.ndarray]:
    """A box of the normalised scene lo [3] - hi [3] -> the metric axis-aligned box holding it:
    the extent of its 8 corners mapped by `to_metric64`. Returns (lo [3], hi [3])."""
    corners = to_metric64(box_corners(lo, hi), normalization)
    return corners.min(axis=0), corners.max(axis=0)
