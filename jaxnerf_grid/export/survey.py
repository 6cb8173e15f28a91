"""The export's survey outputs (issue 41 items 3-4, docs/EXPORT.md "Survey outputs").

* `georeference_of` / `units_of`: what the dataset's transforms.json says of its units
  (`georeference`, written by `poses`, docs/GEOREFERENCE.md; or the synthetic scenes'
  `scene_normalization`, metres by construction).
* `to_crs`: the export's metric frame (the dataset's local metres) -> the projected CRS:
  x_crs = x_local + origin.
* `alignment_uncertainty`: the 1-sigma relative scale error and position error of the
  alignment to metres, from its residuals (the formula is in the docstring and in docs/EXPORT.md).
* `with_sigma`: a figure with its uncertainty, sqrt((L s_rel)^2 + fit^2).
* `write_las`: a LAS 1.4 point cloud (laspy, point format 7: xyz, RGB) with the CRS's WKT.
* `write_ply_double`: a binary PLY with float64 coordinates (the mesh in CRS coordinates:
  eastings and northings of 10^5-10^6 m keep their millimetres only in doubles).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from jaxnerf_grid import io
from jaxnerf_grid.io import DataError


def georeference_of(ds) -> dict | None:
    """transforms.json's `georeference` record of a dataset (`ds.meta`), or None."""
    geo = (getattr(ds, "meta", None) or {}).get("georeference")
    return geo if isinstance(geo, dict) else None


def units_of(ds) -> str:
    """'metres' or 'unknown': the `georeference` record's `units` where it exists (every
    dataset `poses` writes has one); else 'unknown' for a `poses` dataset written before the
    record; else 'metres' when transforms.json has `scene_normalization` (the synthetic scenes
    state their metric normalisation, docs/DATASET.md); else 'unknown'."""
    meta = getattr(ds, "meta", None) or {}
    geo = georeference_of(ds)
    if geo is not None:
        return "metres" if geo.get("units") == "metres" else "unknown"
    if "poses" in meta:
        return "unknown"
    return "metres" if meta.get("scene_normalization") else "unknown"


def crs_of(geo: dict | None) -> tuple[str | None, np.ndarray]:
    """(the CRS's name, e.g. 'EPSG:32632', or None; origin [3], CRS = local + origin) of a record."""
    if not geo or geo.get("units") != "metres" or not geo.get("crs"):
        return None, np.zeros(3)
    return str(geo["crs"]), np.asarray(geo.get("origin", [0.0, 0.0, 0.0]), np.float64)


def to_crs(points_local: np.ndarray, geo: dict | None) -> np.ndarray:
    """Local metres [..., 3] -> the projected CRS: + origin (float64). Unchanged without a CRS."""
    return np.asarray(points_local, np.float64) + crs_of(geo)[1]


def alignment_uncertainty(geo: dict | None, units: str, centres_m: np.ndarray) -> dict:
    """The 1-sigma errors the alignment to metres adds to every figure (docs/EXPORT.md).

    centres_m [K, 3]: the cameras' centres in metres (what the GPS fit was made on).
    With a similarity of p parameters (7; 5 when it turned about z only) fitted to N positions
    whose 3-D residuals have RMS r, spread D (the RMS distance of the centres from their mean):
    per coordinate sigma = r sqrt(N / (3N - p)) (the residuals' unbiased spread); the scale's
    relative error s_rel = sigma / (D sqrt(N)) (the fit of the scale is a least-squares fit of
    the radial components, whose lever arm is D); the position (origin) error sigma sqrt(3 / N).
    Positions: from the GPS inliers' residuals; with ground control points, the position error
    comes from the control points' residuals (their weight rules the fit), the scale error still
    from the GPS when present. No GPS (control points alone, a scale bar): s_rel None (not
    estimated: a scale bar has no redundancy). The synthetic scenes' recorded scale: 0 (exact).
    Returns {"relative_scale", "position_m", "from", "n", "rms_m", "spread_m", "centroid" [3]
    (the centres' mean: the lever arm of a point's scale and turn errors runs from there)}."""
    if units != "metres":
        return {"relative_scale": None, "position_m": None, "from": "units unknown"}
    if geo is None:
        return {"relative_scale": 0.0, "position_m": 0.0, "from": "the dataset's recorded metric scale (exact)"}
    out = {"relative_scale": None, "position_m": None, "from": geo.get("source")}
    gps = geo.get("gps") or {}
    control = (geo.get("gcp") or {}).get("control") or {}
    c = np.asarray(centres_m, np.float64).reshape(-1, 3)
    spread = float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=1)))) if len(c) else 0.0
    if len(c):
        out["centroid"] = [float(v) for v in c.mean(0)]
    if gps.get("rms_m") is not None and gps.get("inliers"):
        n, r = int(gps["inliers"]), float(gps["rms_m"])
        sigma = coordinate_sigma(r, n, 5 if "about z" in str(geo.get("rotation", "")) else 7)
        if spread > 0 and sigma is not None:
            out["relative_scale"] = sigma / (spread * math.sqrt(n))
        out.update({"position_m": None if sigma is None else sigma * math.sqrt(3.0 / n), "n": n, "rms_m": r,
                    "spread_m": spread, "sigma_per_coordinate_m": sigma})
    if control.get("rms_m") is not None and control.get("residuals"):
        n = len(control["residuals"])
        sigma = coordinate_sigma(float(control["rms_m"]), n, 7 if n >= 3 else 5)
        if sigma is not None:
            out["position_m"] = sigma * math.sqrt(3.0 / n)
        out["control_points"] = n
    return out


def coordinate_sigma(rms_3d: float, n: int, parameters: int) -> float | None:
    """Per-coordinate 1-sigma error from the 3-D residual RMS of a fit of `parameters` to n
    points: rms sqrt(n / (3n - p)); None when 3n <= p (no redundancy)."""
    dof = 3 * int(n) - int(parameters)
    return float(rms_3d) * math.sqrt(n / dof) if dof > 0 else None


def with_sigma(value: float | None, fit_sigma: float, alignment: dict, lever: float | None = None,
               position: bool = False) -> dict | None:
    """{"value", "sigma", "fit_sigma"}: sigma = sqrt((lever s_rel)^2 + fit_sigma^2 (+ position_m^2
    when `position`)), lever = |value| by default (a length scales with the model); sigma None
    when s_rel is unknown. None for a None value."""
    if value is None:
        return None
    rel = alignment.get("relative_scale")
    lever = abs(float(value)) if lever is None else float(lever)
    if rel is None:
        return {"value": float(value), "sigma": None, "fit_sigma": float(fit_sigma)}
    var = (lever * rel) ** 2 + float(fit_sigma) ** 2
    if position:
        var += float(alignment.get("position_m") or 0.0) ** 2
    return {"value": float(value), "sigma": math.sqrt(var), "fit_sigma": float(fit_sigma)}


def pyproj_crs(name: str):
    """pyproj.CRS of a name ('EPSG:32632'); DataError naming it when pyproj does not know it."""
    import pyproj

    try:
        return pyproj.CRS.from_user_input(name)
    except pyproj.exceptions.CRSError as err:
        raise DataError(f"georeference.crs = {name!r}: pyproj does not know it ({err})") from None


def write_las(path, points: np.ndarray, colours: np.ndarray, crs_name: str | None = None) -> Path:
    """Points [N, 3] (float64, the CRS's coordinates when crs_name is given) and colours [N, 3]
    in [0, 1] -> LAS 1.4, point format 7 (16-bit RGB), scale 1 mm, offset the points' minimum
    floored to the metre, the CRS's WKT in the header (`LasHeader.add_crs`) when named.
    Written to a temporary name, then renamed. Returns the path."""
    import laspy

    p = np.asarray(points, np.float64).reshape(-1, 3)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(p.min(axis=0)) if len(p) else np.zeros(3)
    if crs_name is not None:
        header.add_crs(pyproj_crs(crs_name))
    las = laspy.LasData(header)
    las.x, las.y, las.z = p[:, 0], p[:, 1], p[:, 2]
    rgb = np.round(np.clip(np.asarray(colours, np.float64).reshape(-1, 3), 0, 1) * 65535).astype(np.uint16)
    las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    las.write(str(tmp))
    tmp.replace(path)
    return path


def write_ply_double(path, points: np.ndarray, colours: np.ndarray, faces: np.ndarray,
                     comments: tuple[str, ...] = ()) -> Path:
    """A binary little-endian PLY with `property double x, y, z`, uchar colours (colours [N, 3]
    in [0, 1]) and triangles faces [F, 3] (atomic). Returns the path."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int32).reshape(-1, 3)
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {io.ascii_text(' '.join(str(c).split()))}" for c in comments]
    header += [f"element vertex {len(p)}", "property double x", "property double y", "property double z",
               "property uchar red", "property uchar green", "property uchar blue",
               f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    vertex = np.empty(len(p), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = p.T
    rgb = np.round(np.clip(np.asarray(colours, np.float64).reshape(-1, 3), 0, 1) * 255).astype(np.uint8)
    vertex["r"], vertex["g"], vertex["b"] = rgb.T
    face_rec = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face_rec["n"], face_rec["v"] = 3, faces
    io.atomic_write_bytes(path, ("\n".join(header) + "\n").encode("ascii") + vertex.tobytes() + face_rec.tobytes())
    return Path(path)
