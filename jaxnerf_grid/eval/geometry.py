"""Tower geometry metrics: a predicted point cloud against a reference one (pure NumPy + SciPy).

Protocol (`score_points`), in the spirit of the Tanks and Temples benchmark:
  * both clouds are cropped to the axis-aligned box of the reference tower points with its
    bottom raised by `ground_strip` along the up axis: the ground the tower stands on is
    reconstructed too (it is not part of the reference), so the lowest strip is left out of
    both clouds; points outside the box (background, floaters away from the tower) are not
    scored;
  * precision at tau = share of the cropped predicted points within tau of the cropped
    reference; recall at tau = share of the cropped reference points within tau of the cropped
    prediction; F-score = harmonic mean (0 when both are 0);
  * Chamfer distance = (mean nearest distance pred -> ref + mean nearest distance ref -> pred) / 2
    (distances, not squared; None when either cropped cloud is empty).

Units: everything is in **normalised scene units** (x_norm = scale * (x + translation), the
frame the model is trained in; docs/DATASET.md). The synthetic scenes have scale 0.05, so
0.02 units = 0.4 m. The exported tower_points.ply and the synthetic datasets' tower.ply are
both in these units; a user's own survey cloud must be brought into the dataset's normalised
frame first (`jaxnerf_grid.data.normalize.apply_normalization_to_points` with the dataset's
`normalization` maps metric points there).

Up axis: +z (`UP_AXIS = 2`). The synthetic world is z-up (tower base on the plane z = 0) and the
scene normalisation is a similarity without rotation, so the normalised scene is z-up too.
The reference tower.ply holds the main tower's members only (legs, bracing, cross-arms,
insulators); conductors leaving the tower are not in it, so reconstructed conductor points
inside the box count against precision.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid.data.normalize import apply_normalization_to_points, compose_normalization, invert_normalization
from jaxnerf_grid.util import io

UP_AXIS = 2
DEFAULT_THRESHOLDS = (0.01, 0.02, 0.05)
# 0.05 normalised units = 1 m in the synthetic scenes: the ground plane and its reconstruction
# noise near the tower's feet.
DEFAULT_GROUND_STRIP = 0.05


def _as_points(points) -> np.ndarray:
    """[N, 3] float64 (an empty input gives [0, 3])."""
    p = np.asarray(points, np.float64)
    if p.size == 0:
        return np.zeros((0, 3))
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be [N, 3], got {p.shape}")
    return p


def nearest_distances(a, b) -> np.ndarray:
    """Distance from every point of a [N, 3] to its nearest point of b [M, 3]. Returns [N]
    (+inf everywhere when b is empty)."""
    from scipy.spatial import cKDTree

    a, b = _as_points(a), _as_points(b)
    if len(b) == 0:
        return np.full(len(a), np.inf)
    if len(a) == 0:
        return np.zeros(0)
    dist, _ = cKDTree(b).query(a, k=1)
    return np.asarray(dist, np.float64)


def _fscore(precision: float, recall: float) -> float:
    total = precision + recall
    return 0.0 if total == 0 else 2.0 * precision * recall / total


def prf_from_distances(d_pred: np.ndarray, d_ref: np.ndarray, thresholds) -> dict:
    """Precision / recall / F-score per threshold from nearest distances.

    d_pred: [N] predicted -> reference distances; d_ref: [M] reference -> predicted distances.
    Returns {tau: {"precision", "recall", "fscore"}} (a share of an empty set is 0).
    """
    out = {}
    for tau in thresholds:
        p = float(np.mean(d_pred <= tau)) if len(d_pred) else 0.0
        r = float(np.mean(d_ref <= tau)) if len(d_ref) else 0.0
        out[float(tau)] = {"precision": p, "recall": r, "fscore": _fscore(p, r)}
    return out


def precision_recall_fscore(pred, ref, thresholds=DEFAULT_THRESHOLDS) -> dict:
    """pred [N, 3], ref [M, 3]. Returns {tau (float): {"precision", "recall", "fscore"}}:
    precision = share of pred within tau of ref, recall = share of ref within tau of pred,
    F = 2 P R / (P + R) (0 when P = R = 0; an empty cloud scores 0)."""
    return prf_from_distances(nearest_distances(pred, ref), nearest_distances(ref, pred), thresholds)


def chamfer(pred, ref) -> float | None:
    """Symmetric Chamfer distance of pred [N, 3] and ref [M, 3]: the mean of the two mean
    nearest-neighbour distances, (mean_i d(p_i, ref) + mean_j d(r_j, pred)) / 2, in the units of
    the points (distances, not squared). None when either cloud is empty."""
    pred, ref = _as_points(pred), _as_points(ref)
    if len(pred) == 0 or len(ref) == 0:
        return None
    return 0.5 * float(nearest_distances(pred, ref).mean() + nearest_distances(ref, pred).mean())


def crop_to_box(points, box_min, box_max) -> np.ndarray:
    """The points of points [N, 3] inside the closed box [box_min, box_max] ([3] each). Returns [K, 3]."""
    p = _as_points(points)
    inside = np.all((p >= np.asarray(box_min, np.float64)) & (p <= np.asarray(box_max, np.float64)), axis=-1)
    return p[inside]


def tower_box(ref_points, ground_strip: float = DEFAULT_GROUND_STRIP, up_axis: int = UP_AXIS):
    """Axis-aligned box of the reference tower points ref_points [M, 3] with its bottom raised by
    `ground_strip` along `up_axis` (+z). Returns (box_min [3], box_max [3])."""
    ref = _as_points(ref_points)
    if len(ref) == 0:
        raise ValueError("tower_box: the reference cloud is empty")
    lo, hi = ref.min(axis=0), ref.max(axis=0)
    lo[up_axis] += float(ground_strip)
    if lo[up_axis] > hi[up_axis]:
        raise ValueError(f"tower_box: ground_strip {ground_strip} is taller than the reference "
                         f"({hi[up_axis] - ref.min(axis=0)[up_axis]:.4g} units)")
    return lo, hi


def score_points(pred, ref, thresholds=DEFAULT_THRESHOLDS, ground_strip: float = DEFAULT_GROUND_STRIP,
                 up_axis: int = UP_AXIS) -> dict:
    """Scores a predicted cloud pred [N, 3] against a reference ref [M, 3] (module docstring).

    Both are cropped to `tower_box(ref, ground_strip)`. Returns a JSON-ready dict
    {"thresholds": {"0.02": {"precision", "recall", "fscore"}, ...}, "chamfer": float | None,
    "num_pred": cropped predicted points, "num_ref": cropped reference points,
    "box": {"min": [3], "max": [3]}, "ground_strip": float, "up_axis": int}.
    """
    lo, hi = tower_box(ref, ground_strip, up_axis)
    p, r = crop_to_box(pred, lo, hi), crop_to_box(ref, lo, hi)
    d_pred, d_ref = nearest_distances(p, r), nearest_distances(r, p)
    prf = prf_from_distances(d_pred, d_ref, thresholds)
    cham = 0.5 * float(d_pred.mean() + d_ref.mean()) if len(p) and len(r) else None
    return {"thresholds": {f"{tau:g}": v for tau, v in prf.items()}, "chamfer": cham,
            "num_pred": int(len(p)), "num_ref": int(len(r)),
            "box": {"min": [float(v) for v in lo], "max": [float(v) for v in hi]},
            "ground_strip": float(ground_strip), "up_axis": int(up_axis)}


def reference_to_scene(points, file_normalization: dict | None, scene_normalization: dict | None) -> np.ndarray:
    """Reference points [M, 3] stored in the normalised frame `file_normalization` (metric ->
    file units, e.g. a transforms.json's `scene_normalization`) -> the frame
    `scene_normalization` the model was trained in (the loaded dataset's `normalization`).
    Identity when either is None. Records may carry a "rotation" (docs/DATASET.md). Returns [M, 3] float64."""
    p = _as_points(points)
    if file_normalization is None or scene_normalization is None:
        return p
    if "rotation" in file_normalization or "rotation" in scene_normalization:
        return apply_normalization_to_points(
            p, compose_normalization(invert_normalization(file_normalization), scene_normalization))
    s1, t1 = float(file_normalization["scale"]), np.asarray(file_normalization["translation"], np.float64)
    s2, t2 = float(scene_normalization["scale"]), np.asarray(scene_normalization["translation"], np.float64)
    if s1 == s2 and np.array_equal(t1, t2):
        return p
    return s2 * (p / s1 - t1 + t2)


def read_reference_points(ply_path) -> np.ndarray:
    """The vertices [N, 3] of a reference cloud (`io.read_ply_points`); DataError naming the
    file when it holds no point or a coordinate that is not finite. `evaluate_run` calls it
    before rendering, so a bad reference costs nothing."""
    points = io.read_ply_points(ply_path)
    if len(points) == 0:
        raise io.DataError(f"{ply_path}: the reference point cloud is empty")
    if not np.all(np.isfinite(points)):
        raise io.DataError(f"{ply_path}: the reference point cloud has coordinates that are not finite numbers")
    return points


def score_against_ply(cloud_parts, ply_path, *, file_normalization: dict | None = None,
                      scene_normalization: dict | None = None, thresholds=DEFAULT_THRESHOLDS,
                      ground_strip: float = DEFAULT_GROUND_STRIP) -> dict:
    """Scores the exported cloud against a reference PLY (what `jaxnerf-grid eval` stores as
    metrics.json["geometry"]).

    cloud_parts: [(points [K, 3], colours [K, 3])] as built for tower_points.ply, in normalised
    scene units; ply_path: the reference (vertex x, y, z); file/scene_normalization: see
    `reference_to_scene` (None: the reference is already in the scene's units).
    Returns `score_points`'s dict plus "reference" (the path) and "units".
    """
    parts = [np.asarray(p, np.float64).reshape(-1, 3) for p, _ in cloud_parts]
    pred = np.concatenate(parts) if parts else np.zeros((0, 3))
    ref = reference_to_scene(read_reference_points(ply_path), file_normalization, scene_normalization)
    result = score_points(pred, ref, thresholds, ground_strip)
    return {**result, "reference": str(Path(ply_path)), "units": "normalised scene units"}
