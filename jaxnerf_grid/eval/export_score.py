"""The export scored against a reference tower (what `jaxnerf-grid eval` adds as metrics["export"]).

Everything is in the export's units (metres for the synthetic scenes; docs/EXPORT.md):

* the reference (e.g. the synthetic dataset's `tower.ply`, normalised units of its file's
  `scene_normalization`) is brought into the loaded dataset's normalised frame
  (`geometry.reference_to_scene`), then to the export's units (`export.to_metric64`);
* the mesh's vertices and the fused points are each scored with `geometry.score_points`:
  precision / recall / F-score at 0.2, 0.4 and 1.0 (`THRESHOLDS`) and the Chamfer distance,
  both clouds cropped to the reference tower's box less the ground strip that `eval`'s
  geometry score uses (`geometry.DEFAULT_GROUND_STRIP` normalised units, 1 m in the synthetic
  scenes);
* the height error: the export's height (its highest mesh vertex above the fitted ground)
  against the reference's own extent along the up axis (highest minus lowest reference point),
  in the export's units and in percent of the reference's height.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid.eval import geometry
from jaxnerf_grid.export import to_metric64
from jaxnerf_grid.util import io

THRESHOLDS = (0.2, 0.4, 1.0)


def reference_in_export_units(points, file_normalization: dict | None, scene_normalization: dict) -> np.ndarray:
    """Reference points [M, 3] stored in `file_normalization`'s frame (None: already in the
    dataset's normalised frame) -> the export's units. Returns [M, 3] float64."""
    scene = geometry.reference_to_scene(points, file_normalization, scene_normalization if file_normalization else None)
    return to_metric64(scene, scene_normalization)


def height_error(export_height: float, reference: np.ndarray) -> dict:
    """{"export", "reference" (extent of reference [M, 3] along the up axis), "error" (export -
    reference), "error_percent" (|error| / reference * 100)}."""
    up = geometry.UP_AXIS
    ref_h = float(np.ptp(np.asarray(reference, np.float64)[:, up]))
    err = float(export_height) - ref_h
    return {"export": float(export_height), "reference": ref_h, "error": err,
            "error_percent": 100.0 * abs(err) / ref_h if ref_h > 0 else None}


def score_export(export_dir, reference: np.ndarray, scale: float, thresholds=THRESHOLDS) -> dict | None:
    """Scores an export folder (tower_mesh.ply, tower_points.ply, measurements.json) against
    reference points [M, 3] in the export's units. scale: the dataset's normalisation scale
    (normalised units per export unit), for the ground strip. None when the folder holds no
    export."""
    export_dir = Path(export_dir)
    meas_path = export_dir / "measurements.json"
    if not meas_path.is_file():
        return None
    meas = io.read_json(meas_path)
    strip = geometry.DEFAULT_GROUND_STRIP / float(scale)
    out = {"units": meas.get("units"), "ground_strip": strip, "reference_points": int(len(reference))}
    for key, name in (("mesh", "tower_mesh.ply"), ("points", "tower_points.ply")):
        path = export_dir / name
        if path.is_file():
            out[key] = geometry.score_points(io.read_ply_points(path), reference, thresholds, strip)
    if meas.get("height") is not None:
        out["height"] = height_error(meas["height"], reference)
    return out
