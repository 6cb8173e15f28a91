"""Metric scale and georeference of a reconstruction (docs/GEOREFERENCE.md): the robust
similarity from camera centres to their GPS positions, the projected coordinate system
(pyproj: a UTM zone from the GPS or a named EPSG code), ground control points and a scale bar.

Frames: the *model* frame is the SfM model's (COLMAP units, z up after `poses.orient_z_up`);
the *CRS* frame is a projected CRS in metres (easting, northing, height); the *local* frame is
the CRS less `origin` (a rounded point near the cameras), so float32 keeps centimetres.

The similarity is our own RANSAC over minimal samples of 3 centres, then a weighted Umeyama
fit on the inliers, rather than pycolmap's `estimate_sim3d_robust`: it is plain NumPy (its tests
need no COLMAP), the same weighted fit takes the ground control points (weights from each
source's accuracy), and it is seeded and deterministic.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from jaxnerf_grid.util.io import DataError, read_text

MIN_GPS_PHOTOS = 3           # fewer registered photos with GPS: no alignment (an error)
MIN_GPS_SPREAD = 1.0         # metres: GPS positions closer than this to their mean are "one spot"
GPS_SIGMA = 3.0              # metres: a consumer receiver's error (horizontal 1-3 m, vertical 2-5 m)
# GPS alone sets no scale for photos spread over less than this (RMS horizontal distance of their
# positions to the mean): the receivers' error is then the spread's size, and the fitted scale is
# noise, even negative (a mirrored scene).
MIN_GPS_SCALE_SPREAD = 3.0 * GPS_SIGMA
GCP_SIGMA = 0.05             # metres: a surveyed ground control point
RANSAC_ITERATIONS = 500
INLIER_METRES = 3.0 * GPS_SIGMA  # a centre farther than this from its GPS position is an outlier
# The GPS fit turns the model about z only: its z is the cameras' up (`poses.orient_z_up`), and
# consumer GPS heights (2-5 m errors) tilt a full similarity by degrees (1.6 degrees on the synthetic
# tower, 22 photos on a 58 m orbit, docs/GEOREFERENCE.md). 3 or more control points fit all of it.
YAW_ONLY_NOTE = "about z only (the cameras' up kept; fewer than 3 control points)"
SUSPECT_GPS_RMS = 2.0 * GPS_SIGMA  # metres: larger GPS residuals flag the reconstruction in the report
SUSPECT_CONTROL_RMS = 0.5          # metres: ... and so do larger control point residuals
CLICK_SIGMA_PX = 1.0         # pixels: the assumed 1-sigma error of a clicked scale-bar end, per axis
ORIGIN_ROUNDING = 1000.0     # metres: the local frame's origin is the cameras' mean rounded to this


# ----------------------------------------------------------------------------------------
# The similarity


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, yaw_only: bool = False):
    """Weighted least-squares similarity dst ~ s R src + t (Umeyama 1991, with weights w_i:
    minimises sum_i w_i |dst_i - s R src_i - t|^2). src, dst: [N, 3], N >= 3 not collinear;
    weights [N] >= 0 (None: all 1). yaw_only: R turns about z only (both frames z up), the
    closed form theta = atan2(sum w (x y' - y x'), sum w (x x' + y y')), s = sum w d.(R x) / sum w |x|^2
    on centred points. Returns (s, R [3, 3] proper rotation, t [3])."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mean_s, mean_d = w @ src, w @ dst
    xs, xd = src - mean_s, dst - mean_d
    if yaw_only:
        theta = np.arctan2(w @ (xs[:, 0] * xd[:, 1] - xs[:, 1] * xd[:, 0]),
                           w @ (xs[:, 0] * xd[:, 0] + xs[:, 1] * xd[:, 1]))
        c, n = np.cos(theta), np.sin(theta)
        rot = np.array([[c, -n, 0.0], [n, c, 0.0], [0.0, 0.0, 1.0]])
        var = float(w @ (xs ** 2).sum(1))
        scale = float(w @ (xd * (xs @ rot.T)).sum(1) / var) if var > 0 else 1.0
        return scale, rot, mean_d - scale * rot @ mean_s
    cov = (xd * w[:, None]).T @ xs
    rot = nearest_rotation(cov)
    var = float(w @ (xs ** 2).sum(1))
    scale = float(np.trace(rot.T @ cov) / var) if var > 0 else 1.0  # trace(R^T C) = sum of C's signed singular values
    return scale, rot, mean_d - scale * rot @ mean_s


def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The proper rotation R maximising trace(R^T m) (the closest one to m in the Frobenius
    sense): U diag(1, 1, det(U V^T)) V^T of m = U S V^T. m: [3, 3] -> [3, 3]."""
    u, _, vt = np.linalg.svd(np.asarray(m, np.float64))
    d = np.diag([1.0, 1.0, 1.0 if np.linalg.det(u @ vt) >= 0 else -1.0])
    return u @ d @ vt


def apply_similarity(sim, points: np.ndarray) -> np.ndarray:
    """s R x + t for points [..., 3]; sim = (s, R, t)."""
    s, rot, t = sim
    return s * np.asarray(points, np.float64) @ np.asarray(rot).T + np.asarray(t)


def similarity_matrix(sim) -> np.ndarray:
    """(s, R, t) -> the [4, 4] matrix [[s R, t], [0, 1]]."""
    s, rot, t = sim
    m = np.eye(4)
    m[:3, :3] = s * np.asarray(rot)
    m[:3, 3] = t
    return m


def ransac_similarity(src: np.ndarray, dst: np.ndarray, threshold: float, *, iterations: int = RANSAC_ITERATIONS,
                      seed: int = 0, weights: np.ndarray | None = None, yaw_only: bool = False):
    """Robust similarity dst ~ s R src + t: RANSAC over minimal samples of 3 pairs (the model
    with the most pairs within `threshold` of their target, dst units), then `umeyama` on
    those inliers (weighted by `weights`), the inlier set recomputed once with that fit;
    `yaw_only` as in `umeyama`. src, dst: [N, 3], N >= 3. Returns ((s, R, t), inliers [N] bool)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    n = len(src)
    w = np.ones(n) if weights is None else np.asarray(weights, np.float64)
    rng = np.random.default_rng(seed)
    best = np.ones(n, bool)
    best_count = -1
    if n > 3:
        for _ in range(iterations):
            pick = rng.choice(n, 3, replace=False)
            if np.linalg.matrix_rank(src[pick] - src[pick].mean(0), tol=1e-9) < 2:
                continue
            sim = umeyama(src[pick], dst[pick], yaw_only=yaw_only)
            inliers = np.linalg.norm(apply_similarity(sim, src) - dst, axis=1) <= threshold
            if inliers.sum() > best_count:
                best, best_count = inliers, int(inliers.sum())
    if best.sum() < 3:
        best = np.ones(n, bool)
    sim = umeyama(src[best], dst[best], w[best], yaw_only)
    inliers = np.linalg.norm(apply_similarity(sim, src) - dst, axis=1) <= threshold
    if inliers.sum() >= 3 and not np.array_equal(inliers, best):
        sim = umeyama(src[inliers], dst[inliers], w[inliers], yaw_only)
    else:
        inliers = best
    return sim, inliers


# ----------------------------------------------------------------------------------------
# The coordinate system (pyproj)


def projected_crs(name: str | None, latitude: float | None = None, longitude: float | None = None):
    """The pyproj CRS: `name` ('EPSG:XXXX', or any string pyproj reads) when given, else the
    WGS 84 UTM zone holding (latitude, longitude) (pyproj's `query_utm_crs_info`).
    DataError naming poses.crs for an unknown code or a CRS that is not projected in metres."""
    from pyproj import CRS
    from pyproj.aoi import AreaOfInterest
    from pyproj.database import query_utm_crs_info
    from pyproj.exceptions import CRSError

    if name is None:
        if latitude is None or longitude is None:
            raise ValueError("projected_crs: give a CRS name or a latitude and longitude")
        found = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(
            west_lon_degree=longitude, south_lat_degree=latitude, east_lon_degree=longitude,
            north_lat_degree=latitude))
        if not found:
            raise DataError(f"poses.crs: no UTM zone found for latitude {latitude}, longitude {longitude}; "
                            "name a projected CRS (EPSG:XXXX)")
        return CRS.from_epsg(found[0].code)
    try:
        crs = CRS.from_user_input(name)
    except CRSError:
        raise DataError(f"poses.crs: unknown coordinate system {name!r} (expected e.g. EPSG:32633)") from None
    units = {axis.unit_name for axis in crs.axis_info[:2]}
    if not crs.is_projected or not units <= {"metre", "meter"}:
        raise DataError(f"poses.crs: {name} ({crs.name}) is not a projected coordinate system in metres")
    return crs


def crs_label(crs) -> str:
    """'EPSG:XXXX' when pyproj knows the code, else the CRS's name."""
    code = crs.to_epsg()
    return f"EPSG:{code}" if code else crs.name


def geodetic_to_projected(crs, latitude, longitude, height) -> np.ndarray:
    """WGS 84 latitude / longitude (degrees) and height (m) -> [N, 3] (easting, northing,
    height) in `crs` (pyproj Transformer, always_xy; the height passes through)."""
    from pyproj import Transformer

    transformer = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    x, y = transformer.transform(np.asarray(longitude, np.float64), np.asarray(latitude, np.float64))
    return np.stack([np.atleast_1d(x), np.atleast_1d(y), np.atleast_1d(np.asarray(height, np.float64))], -1)


def projected_to_geodetic(crs, easting, northing) -> tuple[np.ndarray, np.ndarray]:
    """`geodetic_to_projected`'s inverse for the horizontal part: (latitude, longitude) degrees."""
    from pyproj import Transformer

    transformer = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon, lat = transformer.transform(np.asarray(easting, np.float64), np.asarray(northing, np.float64))
    return np.atleast_1d(lat), np.atleast_1d(lon)


def gps_heights(records: list[dict]) -> tuple[np.ndarray, str]:
    """Each photo's height (m) from its GPS record, and which tag gave it: DJI's relative
    altitude (barometric, steadier) lifted by the median of (GPSAltitude - relative altitude)
    when every photo has both, else GPSAltitude (0 where missing)."""
    rel = [r.get("relative_altitude") for r in records]
    alt = [r.get("altitude") for r in records]
    if all(v is not None for v in rel) and all(v is not None for v in alt):
        offset = float(np.median(np.asarray(alt) - np.asarray(rel)))
        return np.asarray(rel, np.float64) + offset, "XMP RelativeAltitude + median(GPSAltitude - RelativeAltitude)"
    return np.asarray([0.0 if v is None else v for v in alt], np.float64), "EXIF GPSAltitude"


# ----------------------------------------------------------------------------------------
# Alignment of camera centres to GPS


def precheck_gps(positions: dict, crs_name, readable: int, source) -> None:
    """`check_gps` on every readable photo's GPS before the reconstruction (a quick refusal)."""
    records = list(positions.values())
    lat = np.asarray([r["latitude"] for r in records])
    lon = np.asarray([r["longitude"] for r in records])
    crs = projected_crs(crs_name, float(np.median(lat)), float(np.median(lon)))
    heights, _ = gps_heights(records)
    check_gps(list(positions), geodetic_to_projected(crs, lat, lon, heights), readable, source, "readable")


def check_gps(names: list[str], positions: np.ndarray, total: int, source, what: str = "registered") -> None:
    """DataError (one line, naming `source`) unless at least MIN_GPS_PHOTOS of the `total`
    (registered) photos have GPS and those positions are not all at one spot (within
    MIN_GPS_SPREAD m)."""
    if len(names) < MIN_GPS_PHOTOS:
        raise DataError(f"{source}: only {len(names)} of the {total} {what} photos have GPS; the "
                        f"alignment needs at least {MIN_GPS_PHOTOS}; ignore_gps=True leaves the GPS unread")
    spread = float(np.linalg.norm(positions - positions.mean(0), axis=1).max())
    if spread < MIN_GPS_SPREAD:
        raise DataError(f"{source}: the GPS positions of all {len(names)} photos lie within {spread:.2f} m of one "
                        f"spot; the alignment needs photos taken from different places (ignore_gps=True leaves "
                        f"the GPS unread)")


def gps_too_close(positions: np.ndarray, scale: float) -> str | None:
    """Why GPS alone cannot scale a model whose photos have the local `positions` [N, 3] and whose
    fit gave `scale`, or None when it can: positions spread (RMS horizontal distance to their mean)
    under MIN_GPS_SCALE_SPREAD, or a scale that is not positive."""
    xy = np.asarray(positions, np.float64)[:, :2]
    spread = float(np.sqrt(np.mean(np.sum((xy - xy.mean(0)) ** 2, axis=1))))
    if spread < MIN_GPS_SCALE_SPREAD:
        return (f"the photos' GPS positions spread over {spread:.1f} m (RMS about their mean), under "
                f"{MIN_GPS_SCALE_SPREAD:g} m, three times a receiver's error: GPS sets no scale for so small a "
                "capture (give control points or a scale bar)")
    if not scale > 0:
        return f"the GPS fit gives a scale of {scale:.3g}, not positive: the GPS positions do not follow the cameras"
    return None


def residual_rows(names: list[str], predicted: np.ndarray, target: np.ndarray, inliers=None) -> list[dict]:
    """Per point: name, dx, dy, dz (predicted - target, m), horizontal and 3-D error (m), inlier."""
    d = np.asarray(predicted, np.float64) - np.asarray(target, np.float64)
    inliers = np.ones(len(names), bool) if inliers is None else inliers
    return [{"name": n, "dx": round(float(v[0]), 4), "dy": round(float(v[1]), 4), "dz": round(float(v[2]), 4),
             "horizontal": round(float(np.hypot(v[0], v[1])), 4), "error": round(float(np.linalg.norm(v)), 4),
             "inlier": bool(i)} for n, v, i in zip(names, d, inliers)]


def rms(rows: list[dict], key: str = "error", inliers_only: bool = True) -> float | None:
    """Root mean square of `key` over the rows (the inliers only by default); None when empty."""
    values = [r[key] for r in rows if r["inlier"] or not inliers_only]
    return round(float(np.sqrt(np.mean(np.square(values)))), 4) if values else None


def suspect(record: dict) -> bool:
    """Whether an alignment's residuals exceed what its sources explain: GPS RMS above
    SUSPECT_GPS_RMS or control points' RMS above SUSPECT_CONTROL_RMS (a model bent by a photo
    registered in the wrong place; docs/GEOREFERENCE.md)."""
    gps_rms = (record.get("gps") or {}).get("rms_m")
    control_rms = ((record.get("gcp") or {}).get("control") or {}).get("rms_m")
    return bool((gps_rms is not None and gps_rms > SUSPECT_GPS_RMS)
                or (control_rms is not None and control_rms > SUSPECT_CONTROL_RMS))


def local_origin(points: np.ndarray) -> np.ndarray:
    """The local frame's origin: the points' mean, rounded to ORIGIN_ROUNDING m (height to 0)."""
    mean = np.asarray(points, np.float64).mean(0)
    return np.array([np.round(mean[0] / ORIGIN_ROUNDING) * ORIGIN_ROUNDING,
                     np.round(mean[1] / ORIGIN_ROUNDING) * ORIGIN_ROUNDING, 0.0])


# ----------------------------------------------------------------------------------------
# Ground control points


def read_gcp_csv(path, image_sizes: dict) -> list[dict]:
    """A ground control point file: CSV rows `image, x, y, X, Y, Z[, check]` (a header row
    whose second field is not a number is skipped; pixel x, y in the photo as given, origin
    at the top-left corner; X, Y, Z in the projected CRS, metres; check: 1 / true / yes /
    check marks a check point, left out of the fit). Rows with the same X, Y, Z are one point.
    image_sizes: {photo name: (W, H)} of the input photos.
    Returns [{"name", "world" [3], "check", "observations": [(image, x, y)]}].
    DataError (one line, naming the file and row) for a malformed row, an unknown image or a
    pixel outside its photo."""
    path = Path(path)
    text = read_text(path, "ground control point file", encoding="utf-8-sig")
    points: dict = {}
    for row_number, row in enumerate(csv.reader(text.splitlines()), start=1):
        row = [field.strip() for field in row]
        if not row or not any(row) or row[0].startswith("#"):
            continue
        try:
            x, y, wx, wy, wz = (float(v) for v in row[1:6])
        except (ValueError, IndexError):
            if row_number == 1:
                continue  # a header
            raise DataError(f"{path}: row {row_number}: expected image, x, y, X, Y, Z[, check]; got "
                            f"{','.join(row)!r}") from None
        image = row[0]
        if image not in image_sizes:
            raise DataError(f"{path}: row {row_number}: image {image!r} is not one of the photos")
        width, height = image_sizes[image]
        if not (0 <= x <= width and 0 <= y <= height):
            raise DataError(f"{path}: row {row_number}: pixel ({x:g}, {y:g}) lies outside {image} "
                            f"({width} x {height})")
        check = len(row) > 6 and row[6].lower() in ("1", "true", "yes", "check", "c")
        key = (round(wx, 3), round(wy, 3), round(wz, 3))
        point = points.setdefault(key, {"name": f"gcp{len(points) + 1}", "world": [wx, wy, wz], "check": check,
                                        "observations": []})
        point["check"] = point["check"] or check
        point["observations"].append((image, x, y))
    if not points:
        raise DataError(f"{path}: no ground control points in the file")
    return list(points.values())


def triangulate(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The point nearest (least squares) to rays o_i + t d_i: solves
    sum_i (I - d_i d_i^T) x = sum_i (I - d_i d_i^T) o_i. origins, directions: [K, 3], K >= 2
    rays not all parallel. Returns [3]."""
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    return np.linalg.solve(proj.sum(0), np.einsum("kij,kj->i", proj, np.asarray(origins, np.float64)))


# ----------------------------------------------------------------------------------------
# The scale bar


def parse_scale_bar(text: str) -> dict:
    """`poses.scale_bar`: 'X1,Y1,Z1,X2,Y2,Z2,METRES' (two points of the model frame, written
    in sparse/0 before scaling) or 'IMAGE1:x,y;IMAGE2:x,y;IMAGE3:x,y;IMAGE4:x,y;METRES' (each
    end seen in two photos: the first two pixels are one end, the last two the other).
    Returns {"points": [[3], [3]]} or {"pixels": [(image, x, y)] * 4} with "metres".
    DataError naming poses.scale_bar for anything else."""
    text = str(text).strip()
    try:
        if ":" in text:
            *parts, metres = text.split(";")
            pixels = []
            for part in parts:
                image, xy = part.rsplit(":", 1)
                x, y = (float(v) for v in xy.split(","))
                pixels.append((image.strip(), x, y))
            if len(pixels) != 4:
                raise ValueError
            out: dict[str, Any] = {"pixels": pixels, "metres": float(metres)}
        else:
            values = [float(v) for v in text.split(",")]
            if len(values) != 7:
                raise ValueError
            out = {"points": [values[0:3], values[3:6]], "metres": values[6]}
    except ValueError:
        raise DataError(f"poses.scale_bar: expected 'X1,Y1,Z1,X2,Y2,Z2,METRES' or "
                        f"'IMG1:x,y;IMG2:x,y;IMG3:x,y;IMG4:x,y;METRES', got {text!r}") from None
    if not (out["metres"] > 0 and np.isfinite(out["metres"])):
        raise DataError(f"poses.scale_bar: the distance must be a positive number of metres, got {out['metres']}")
    numbers = [v for p in out.get("points", []) for v in p] + [v for p in out.get("pixels", []) for v in p[1:]]
    if not np.all(np.isfinite(numbers)):
        raise DataError(f"poses.scale_bar: every coordinate must be a finite number, got {text!r}")
    if "points" in out and out["points"][0] == out["points"][1]:
        raise DataError(f"poses.scale_bar: the bar's two ends are the same point, got {text!r}")
    if "pixels" in out and out["pixels"][:2] == out["pixels"][2:]:
        raise DataError(f"poses.scale_bar: the bar's two ends are seen at the same pixels, got {text!r}")
    return out


# ----------------------------------------------------------------------------------------
# A pycolmap model aligned to metres (the model is read, never changed, here)


def model_centres(model) -> dict:
    """{photo name: camera centre [3]} of a pycolmap.Reconstruction's registered photos."""
    return {model.images[i].name: np.asarray(model.images[i].projection_center(), np.float64)
            for i in model.reg_image_ids()}


def pixel_ray(model, name: str, x: float, y: float, ratio: tuple[float, float]):
    """The model-frame ray (origin [3], direction [3]) through pixel (x, y) of photo `name`
    (input-photo pixels, origin at the top-left corner; `ratio`: working size / input size,
    the scaling COLMAP's copy had), through its camera's distortion (`Camera.cam_from_img`).
    DataError when the photo is not registered."""
    images = {model.images[i].name: model.images[i] for i in model.reg_image_ids()}
    if name not in images:
        raise DataError(f"{name}: this photo is not in the reconstruction (not registered or left out by the "
                        f"vetting); a point seen in it cannot be placed")
    im = images[name]
    uv = np.asarray(model.cameras[im.camera_id].cam_from_img(np.array([x * ratio[0], y * ratio[1]])),
                    np.float64).reshape(2)
    rot = np.asarray(im.cam_from_world().rotation.matrix(), np.float64)
    return np.asarray(im.projection_center(), np.float64), rot.T @ np.array([uv[0], uv[1], 1.0])


def place_points(model, points: list[dict], ratios: dict, source) -> np.ndarray:
    """Each point's model-frame position triangulated from its observations
    ([(image, x, y)]) in registered photos (the others are passed over; at least two needed).
    Returns [P, 3]. DataError naming `source` and the point when fewer than two remain."""
    registered = {model.images[i].name for i in model.reg_image_ids()}
    out = []
    for point in points:
        rays = [pixel_ray(model, image, x, y, ratios[image]) for image, x, y in point["observations"]
                if image in registered]
        if len(rays) < 2:
            raise DataError(f"{source}: {point['name']} is seen in {len(rays)} registered photo(s) of the "
                            f"{len(point['observations'])} it names; a point needs two")
        out.append(triangulate(np.stack([r[0] for r in rays]), np.stack([r[1] for r in rays])))
    return np.stack(out)


def align_model(model, gps: dict, *, crs_name=None, gcp_path=None, scale_bar=None, sizes=None, ratios=None,
                source=None):
    """The similarity from a model's frame to metres and the record transforms.json keeps
    (docs/GEOREFERENCE.md). gps: {photo name: `gps.read_gps` record}; sizes / ratios: {photo
    name: input size (W, H)} / {name: working size / input size}, for pixels; source: the
    photo folder (for messages).

    Returns (sim (s, R, t) model -> local metres, or None when units stay unknown; record):
    record["units"] "metres" or "unknown", "source" (gps, gps+gcp, gcp, scale_bar),
    "crs", "origin" (CRS = local + origin), "model_to_local" [4, 4], "metres_per_model_unit",
    "gps" (residual rows, rms), "gcp" (control / check rows, rms). DataError (one line) for
    too few GPS photos, GPS at one spot, a bad GCP file, an unknown CRS; nothing is written."""
    centres = model_centres(model)
    with_gps = sorted(n for n in gps if n in centres)
    gcps = read_gcp_csv(gcp_path, sizes or {}) if gcp_path is not None else []
    control = [p for p in gcps if not p["check"]]
    check = [p for p in gcps if p["check"]]
    record: dict[str, Any] = {"units": "unknown", "source": None}
    if not with_gps and len(control) < 3:
        if gcps:
            raise DataError(f"{gcp_path}: {len(control)} control point(s) and no photo with GPS; the alignment "
                            f"needs GPS or at least 3 control points (not marked check)")
        if crs_name is not None:
            raise DataError(f"{source}: no registered photo has GPS; poses.crs needs GPS or poses.gcp")
        if scale_bar is None:
            return None, record
        return _scale_bar_alignment(model, parse_scale_bar(scale_bar), ratios or {}, record)
    src_parts, dst_parts, weights = [], [], []
    if with_gps:
        records = [gps[n] for n in with_gps]
        lat = np.asarray([r["latitude"] for r in records])
        lon = np.asarray([r["longitude"] for r in records])
        heights, height_source = gps_heights(records)
        crs = projected_crs(crs_name, float(np.median(lat)), float(np.median(lon)))
        gps_crs = geodetic_to_projected(crs, lat, lon, heights)
        check_gps(with_gps, gps_crs, len(centres), source)
        origin = local_origin(gps_crs)
        src_gps = np.stack([centres[n] for n in with_gps])
        dst_gps = gps_crs - origin
        sim, inliers = ransac_similarity(src_gps, dst_gps, INLIER_METRES, yaw_only=True)
        src_parts.append(src_gps[inliers])
        dst_parts.append(dst_gps[inliers])
        weights.append(np.full(int(inliers.sum()), 1.0 / GPS_SIGMA ** 2))
        record.update({"source": "gps", "height_from": height_source})
    else:
        crs = projected_crs(crs_name) if crs_name is not None else None
        origin = local_origin(np.asarray([p["world"] for p in control]))
    if control:
        control_model = place_points(model, control, ratios or {}, gcp_path)
        src_parts.append(control_model)
        dst_parts.append(np.asarray([p["world"] for p in control]) - origin)
        weights.append(np.full(len(control), 1.0 / GCP_SIGMA ** 2))
        record["source"] = "gps+gcp" if with_gps else "gcp"
    yaw_only = len(control) < 3
    sim = umeyama(np.concatenate(src_parts), np.concatenate(dst_parts), np.concatenate(weights), yaw_only)
    if with_gps and not control:
        ignored = gps_too_close(dst_gps, sim[0])
        if ignored is not None:
            if crs_name is not None:
                raise DataError(f"{source}: poses.crs = {crs_name}: {ignored}")
            return None, {"units": "unknown", "source": None, "gps_ignored": ignored}
    rotation = YAW_ONLY_NOTE if yaw_only else "full (3 or more control points)"
    record.update({"units": "metres", "rotation": rotation, "crs": None if crs is None else crs_label(crs),
                   "crs_name": None if crs is None else crs.name, "origin": origin.tolist(),
                   "model_to_local": similarity_matrix(sim).tolist(), "metres_per_model_unit": sim[0]})
    if with_gps:
        inl = np.linalg.norm(apply_similarity(sim, src_gps) - dst_gps, axis=1) <= INLIER_METRES
        rows = residual_rows(with_gps, apply_similarity(sim, src_gps), dst_gps, inl)
        record["gps"] = {"photos": len(with_gps), "registered": len(centres), "inliers": int(inl.sum()),
                         "rms_m": rms(rows), "rms_horizontal_m": rms(rows, "horizontal"), "residuals": rows}
    if gcps:
        record["gcp"] = {"file": str(gcp_path)}
        for label, group in (("control", control), ("check", check)):
            if group:
                placed = apply_similarity(sim, place_points(model, group, ratios or {}, gcp_path))
                rows = residual_rows([p["name"] for p in group], placed,
                                     np.asarray([p["world"] for p in group]) - origin)
                record["gcp"][label] = {"rms_m": rms(rows), "residuals": rows}
        if control:  # where they are (local metres): the lever arms of the scale's uncertainty
            record["gcp"]["control"]["points_m"] = (np.asarray([p["world"] for p in control]) - origin).tolist()
    return sim, record


def _scale_bar_alignment(model, bar: dict, ratios: dict, record: dict):
    """A scale alone: s = metres / the bar's length in the model (no rotation, no CRS)."""
    ends = np.asarray(bar["points"], np.float64) if "points" in bar else bar_ends(model, bar["pixels"], ratios)
    length = float(np.linalg.norm(ends[1] - ends[0]))
    if not length > 0:
        raise DataError("poses.scale_bar: the two ends are the same point in the model")
    sim = (bar["metres"] / length, np.eye(3), np.zeros(3))
    record.update({"units": "metres", "source": "scale_bar", "crs": None, "origin": [0.0, 0.0, 0.0],
                   "model_to_local": similarity_matrix(sim).tolist(), "metres_per_model_unit": sim[0],
                   "scale_bar": {"metres": bar["metres"], "model_length": length}})
    if "pixels" in bar:
        record["scale_bar"].update({"click_sigma_px": CLICK_SIGMA_PX,
                                    "relative_sigma": scale_bar_relative_sigma(model, bar["pixels"], ratios)})
    return sim, record


def bar_ends(model, pixels: list, ratios: dict) -> np.ndarray:
    """[2, 3] the scale bar's two ends in the model frame, each triangulated (`place_points`)
    from its two clicks (pixels: [(image, x, y)] * 4, the first two one end)."""
    ends = [{"name": f"scale bar end {k + 1}", "observations": pixels[2 * k:2 * k + 2]} for k in range(2)]
    return place_points(model, ends, ratios, "poses.scale_bar")


def scale_bar_length(model, pixels: list, ratios: dict) -> float:
    """The model-frame distance between the bar's two ends (`bar_ends`)."""
    ends = bar_ends(model, pixels, ratios)
    return float(np.linalg.norm(ends[1] - ends[0]))


def scale_bar_relative_sigma(model, pixels: list, ratios: dict, click_sigma_px: float | None = None) -> float:
    """The 1-sigma relative error of a scale bar's length (so of the scale it gives) when each of
    its 4 clicks is off by `click_sigma_px` (default CLICK_SIGMA_PX) in x and in y, independently:
    sigma_L / L = click_sigma sqrt(sum_j (dL / dp_j)^2) / L over the 8 pixel coordinates p_j
    (the length linearised by central differences of 0.01 px; the pixel step is in input-photo
    pixels, as the clicks are). The bar's own tolerance in metres is not included."""
    click = CLICK_SIGMA_PX if click_sigma_px is None else float(click_sigma_px)
    length = scale_bar_length(model, pixels, ratios)
    step, grad = 0.01, []
    for j in range(4):
        for axis in (1, 2):
            moved = []
            for sign in (1.0, -1.0):
                changed = [list(p) for p in pixels]
                changed[j][axis] += sign * step
                moved.append(scale_bar_length(model, [tuple(p) for p in changed], ratios))
            grad.append((moved[0] - moved[1]) / (2 * step))
    return click * float(np.sqrt(np.sum(np.square(grad)))) / length
