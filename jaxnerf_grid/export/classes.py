"""ASPRS point classes of the export's classified cloud (LAS 1.4 R15, table 17; pure NumPy).

The fused cloud's points are classed by where they stand: within `ground_band` of the ground
plane (or below it) 2 ground; inside the tower's box 15 transmission tower; where a building
mask is given 6 building (the export has none: no detector tells a roof from a crown, so its
other points are all called vegetation); else vegetation by height above the ground: 3 low
(below LOW_VEGETATION), 4 medium (below MEDIUM_VEGETATION), 5 high. The conductors are points
sampled along their fitted catenaries, class 14 (wire - conductor).
"""

from __future__ import annotations

import numpy as np

from jaxnerf_grid.export import ground as ground_lib

GROUND, LOW_VEGETATION_CLASS, MEDIUM_VEGETATION_CLASS, HIGH_VEGETATION_CLASS = 2, 3, 4, 5
BUILDING, CONDUCTOR, TOWER = 6, 14, 15
LOW_VEGETATION = 0.5      # m (export units) above the ground: below, low vegetation
MEDIUM_VEGETATION = 2.0   # m: below, medium vegetation; above, high


def classify(points: np.ndarray, normal, d: float, ground_band: float, box: tuple | None = None,
             building: np.ndarray | None = None, low: float = LOW_VEGETATION,
             medium: float = MEDIUM_VEGETATION) -> np.ndarray:
    """ASPRS classes [N] uint8 of points [N, 3] (module docstring). box: the tower's (lo [3], hi [3]);
    building: [N] bool or None."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    h = ground_lib.heights(p, normal, d)
    out = np.where(h < low, LOW_VEGETATION_CLASS, np.where(h < medium, MEDIUM_VEGETATION_CLASS,
                                                           HIGH_VEGETATION_CLASS)).astype(np.uint8)
    if building is not None:
        out[np.asarray(building, bool)] = BUILDING
    if box is not None:
        inside = np.all((p >= np.asarray(box[0], np.float64)) & (p <= np.asarray(box[1], np.float64)), axis=1)
        out[inside] = TOWER
    out[h <= ground_band] = GROUND
    return out
