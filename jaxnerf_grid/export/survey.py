"""The export's survey outputs (docs/EXPORT.md "Survey outputs and uncertainty").

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

from jaxnerf_grid.capture import georef
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError


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
    Each source k of the fit (the GPS inliers; the control points, `points_m` in the record)
    has n_k positions, a fit weight w_k (1 / georef.GPS_SIGMA^2, 1 / georef.GCP_SIGMA^2) and a
    per-coordinate error sigma_k estimated from its own residuals' 3-D RMS r_k:
    sigma_k = r_k sqrt(n_k / (3 n_k - p_k)) (p_k: the similarity's 7 parameters, 5 when it
    turned about z only, charged to the source that rules the fit, 0 to the other). The
    weighted least-squares scale is the weighted sum of the residuals' radial components over
    sum_k w_k S_k, with S_k = sum of |x - c|^2 over the source's positions (c: the weighted
    centroid of all of them), so its relative error is
        s_rel = sqrt(sum_k w_k^2 sigma_k^2 S_k) / sum_k w_k S_k,
    which for one source is sigma / (D sqrt(n)) (D: the RMS distance of its positions from
    their mean). The position (origin) error: sigma sqrt(3 / n) of the control points when
    there are any (their weight rules the fit), else of the GPS. A scale bar: the relative
    error its clicks give (`georef.scale_bar_relative_sigma`; None for a bar given as two 3-D
    points: no error estimate). The synthetic scenes' recorded scale: 0 (exact).
    Returns {"relative_scale", "position_m", "from", "n", "rms_m", "spread_m", "centroid" [3]
    (the centres' mean: the lever arm of a point's scale and turn errors runs from there)}."""
    if units != "metres":
        return {"relative_scale": None, "position_m": None, "from": "units unknown"}
    if geo is None:
        return {"relative_scale": 0.0, "position_m": 0.0, "from": "the dataset's recorded metric scale (exact)"}
    out = {"relative_scale": None, "position_m": None, "from": geo.get("source")}
    if geo.get("source") == "scale_bar":
        out["relative_scale"] = (geo.get("scale_bar") or {}).get("relative_sigma")
        return out
    gps = geo.get("gps") or {}
    control = (geo.get("gcp") or {}).get("control") or {}
    parameters = 5 if "about z" in str(geo.get("rotation", "")) else 7
    c = np.asarray(centres_m, np.float64).reshape(-1, 3)
    spread = float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=1)))) if len(c) else 0.0
    if len(c):
        out["centroid"] = [float(v) for v in c.mean(0)]
    sources = []  # (positions [n, 3] metres, n, residual RMS, fit weight)
    has_gps = gps.get("rms_m") is not None and bool(gps.get("inliers")) and len(c) > 0
    has_control = control.get("rms_m") is not None and bool(control.get("residuals")) and bool(control.get("points_m"))
    if has_gps:
        sources.append((c, int(gps["inliers"]), float(gps["rms_m"]), 1.0 / georef.GPS_SIGMA ** 2))
        out.update({"n": int(gps["inliers"]), "rms_m": float(gps["rms_m"]), "spread_m": spread})
    if has_control:
        points = np.asarray(control["points_m"], np.float64).reshape(-1, 3)
        sources.append((points, len(points), float(control["rms_m"]), 1.0 / georef.GCP_SIGMA ** 2))
        out["control_points"] = len(points)
    if sources:
        sigmas = source_sigmas(sources, parameters)
        if has_gps:
            out["sigma_per_coordinate_m"] = sigmas[0]
            if sigmas[0] is not None:
                out["position_m"] = sigmas[0] * math.sqrt(3.0 / int(gps["inliers"]))
        if has_control and sigmas[-1] is not None:  # the control points rule the position
            out["position_m"] = sigmas[-1] * math.sqrt(3.0 / sources[-1][1])
        out["relative_scale"] = weighted_scale_sigma(sources, sigmas)
    return out


def source_sigmas(sources: list[tuple], parameters: int) -> list[float | None]:
    """Per source (positions [n, 3], n, rms, weight) its per-coordinate sigma (`coordinate_sigma`),
    the fit's parameters charged to the source with the largest weight x n."""
    ruling = int(np.argmax([w * n for _, n, _, w in sources]))
    return [coordinate_sigma(r, n, parameters if k == ruling else 0) for k, (_, n, r, _) in enumerate(sources)]


def weighted_scale_sigma(sources: list[tuple], sigmas: list[float | None]) -> float | None:
    """s_rel = sqrt(sum_k w_k^2 sigma_k^2 S_k) / sum_k w_k S_k (`alignment_uncertainty`), S_k =
    n_k x the mean squared distance of source k's positions from the weighted centroid of all
    sources. None when a sigma is unknown or the positions have no spread."""
    known = [s for s in sigmas if s is not None]
    if len(known) < len(sigmas):
        return None
    total = sum(w * n for _, n, _, w in sources)
    centroid = sum(w * n * pos.mean(0) for pos, n, _, w in sources) / total
    spread_sums = [n * float(np.mean(np.sum((pos - centroid) ** 2, axis=1))) for pos, n, _, _ in sources]
    denominator = sum(w * sk for (_, _, _, w), sk in zip(sources, spread_sums))
    if not denominator > 0:
        return None
    numerator = sum(w ** 2 * sg ** 2 * sk for (_, _, _, w), sg, sk in zip(sources, known, spread_sums))
    return math.sqrt(numerator) / denominator


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


def write_las(path, points: np.ndarray, colours: np.ndarray, crs_name: str | None = None,
              vertical=None, classification: np.ndarray | None = None) -> Path:
    """Points [N, 3] (float64, the CRS's coordinates when crs_name is given) and colours [N, 3]
    in [0, 1] -> LAS 1.4, point format 7 (16-bit RGB), scale 1 mm, offset the points' minimum
    floored to the metre, the CRS's WKT in the header (`LasHeader.add_crs`) when named; with
    `vertical` (a pyproj vertical CRS) the compound CRS of the two; classification [N] (ASPRS
    classes, `export.classes`) when given, else 0 (never classified).
    Written to a temporary name, then renamed. Returns the path."""
    import laspy
    import pyproj

    p = np.asarray(points, np.float64).reshape(-1, 3)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(p.min(axis=0)) if len(p) else np.zeros(3)
    if crs_name is not None:
        crs = pyproj_crs(crs_name)
        if vertical is not None:
            crs = pyproj.crs.CompoundCRS(name=f"{crs.name} + {vertical.name}", components=[crs, vertical])
        header.add_crs(crs)
    las = laspy.LasData(header)
    las.x, las.y, las.z = p[:, 0], p[:, 1], p[:, 2]
    rgb = np.round(np.clip(np.asarray(colours, np.float64).reshape(-1, 3), 0, 1) * 65535).astype(np.uint16)
    las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    if classification is not None:
        las.classification = np.asarray(classification, np.uint8).reshape(-1)
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
