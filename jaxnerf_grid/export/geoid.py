"""Heights above a geoid for the export's CRS outputs (`export --geoid GRID`, docs/GEOREFERENCE.md).

GPS gives ellipsoidal heights h; a surveyor wants orthometric heights H = h - N(lat, lon), N the
geoid's undulation read from a local grid file that PROJ reads (GTX or GeoTIFF, e.g.
`us_nga_egm96_15.tif`). PROJ interpolates the grid (`+proj=vgridshift +multiplier=-1`, a
pyproj `Transformer` pipeline); the CRS's eastings and northings go to WGS 84 latitude and
longitude (`georef.projected_to_geodetic`) only to look N up: they are not changed.

* `open_grid`: the pipeline of a grid file; DataError naming the file when it does not exist or
  PROJ cannot read it as a grid.
* `orthometric`: points [N, 3] in a projected CRS, ellipsoidal heights -> (the same points with
  H, N [N]); DataError naming the grid when it does not cover a point.
* `vertical_crs`: the named vertical datum (`export.vertical_crs`, e.g. EPSG:5773) the LAS header
  carries with the horizontal CRS as a compound CRS; only with a grid.
* `vertical_record` / `ELLIPSOIDAL`: what measurements.json's `survey.vertical` says.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid.capture import georef
from jaxnerf_grid.util.io import DataError

# the vertical reference of the CRS outputs without a geoid grid, by the record's `source`
ELLIPSOIDAL = "ellipsoidal (GPS heights as written)"
AS_CONTROL_POINTS = "as the control points' Z (the GCP file's heights as written)"


def as_written(geo: dict | None) -> str:
    """The vertical reference of a record's heights without a geoid grid: the GPS's for `gps`,
    the control points' Z for `gcp` and `gps+gcp` (their weight rules the fit)."""
    return AS_CONTROL_POINTS if "gcp" in str((geo or {}).get("source", "")) else ELLIPSOIDAL


def pipeline_text(path: Path) -> str:
    """The PROJ pipeline of a grid file: longitude, latitude (degrees), h -> the same, h - N."""
    return ("+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
            f'+step +proj=vgridshift +grids="{path}" +multiplier=-1 '
            "+step +proj=unitconvert +xy_in=rad +xy_out=deg")


def open_grid(path):
    """pyproj Transformer (lon, lat, h) -> (lon, lat, h - N) of a local grid file. DataError
    naming the file when it does not exist, is not a file, or PROJ cannot read it as a grid.
    The path is made absolute, so PROJ never looks it up elsewhere (nor on its network)."""
    import pyproj

    path = Path(path).expanduser()
    if not path.is_file():
        what = "is not a file" if path.exists() else "does not exist"
        raise DataError(f"{path}: export.geoid {what} (a geoid grid PROJ reads: GTX or GeoTIFF, docs/GEOREFERENCE.md)")
    path = path.resolve()
    if '"' in str(path):
        raise DataError(f"{path}: export.geoid: a path with a double quote cannot be passed to PROJ; rename it")
    try:
        return pyproj.Transformer.from_pipeline(pipeline_text(path))
    except pyproj.exceptions.ProjError:
        raise DataError(f"{path}: export.geoid: PROJ cannot read this file as a geoid grid (GTX or GeoTIFF)") from None


def undulation(grid, path, latitude: np.ndarray, longitude: np.ndarray) -> np.ndarray:
    """N [N] (metres) of the grid at WGS 84 latitude / longitude [N] (degrees): h - H of h = 0.
    DataError naming the grid file `path` when it does not cover a point (PROJ gives inf)."""
    lat = np.atleast_1d(np.asarray(latitude, np.float64))
    lon = np.atleast_1d(np.asarray(longitude, np.float64))
    _, _, minus_n = grid.transform(lon, lat, np.zeros_like(lat), errcheck=False)
    n = -np.atleast_1d(np.asarray(minus_n, np.float64))
    outside = ~np.isfinite(n)
    if outside.any():
        k = int(np.argmax(outside))
        raise DataError(f"{path}: export.geoid does not cover {int(outside.sum())} of the {len(n)} points (e.g. "
                        f"latitude {lat[k]:.6f}, longitude {lon[k]:.6f}); use a grid that covers the site")
    return n


def orthometric(points_crs: np.ndarray, crs_name: str, grid, path) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] (easting, northing, ellipsoidal height h) in the projected CRS `crs_name` ->
    (the points with H = h - N in place of h [N, 3] float64, N [N]). DataError naming the grid
    file `path` when a point lies outside it."""
    p = np.array(points_crs, np.float64).reshape(-1, 3)
    if len(p) == 0:
        return p, np.zeros(0)
    lat, lon = georef.projected_to_geodetic(crs_name, p[:, 0], p[:, 1])
    n = undulation(grid, path, lat, lon)
    p[:, 2] -= n
    return p, n


def vertical_crs(name: str | None, grid_path) -> object | None:
    """pyproj.CRS of `export.vertical_crs` (e.g. 'EPSG:5773', EGM96 height: the named datum the
    geoid grid realises, written into the LAS header with the horizontal CRS), or None. DataError
    naming the key when it is given without a grid, unknown to pyproj, or not a vertical CRS."""
    if name is None:
        return None
    import pyproj

    if grid_path is None:
        raise DataError(f"export.vertical_crs = {name!r} names the datum of heights above a geoid: give "
                        f"export.geoid (the grid) too")
    try:
        crs = pyproj.CRS.from_user_input(name)
    except pyproj.exceptions.CRSError:
        raise DataError(f"export.vertical_crs = {name!r}: pyproj does not know it "
                        f"(e.g. EPSG:5773, EGM96 height)") from None
    if not crs.is_vertical:
        raise DataError(f"export.vertical_crs = {name!r} is not a vertical CRS ({crs.name}); "
                        f"e.g. EPSG:5773, EGM96 height")
    return crs


def vertical_record(path=None, n_at_base: float | None = None, n_range=None, geo: dict | None = None,
                    datum=None) -> dict:
    """measurements.json's `survey.vertical`: {"reference" (the sentence the report shows), "geoid_grid"
    (the file, or None), "n_at_base_m", "n_range_m" ([min, max] over the CRS outputs' points),
    "vertical_crs" (`datum`'s 'EPSG:code name', or None)}."""
    if path is None:
        return {"reference": as_written(geo), "geoid_grid": None, "n_at_base_m": None, "n_range_m": None,
                "vertical_crs": None}
    where = f", N = {n_at_base:.3f} m at the base" if n_at_base is not None else ""
    named = None if datum is None else crs_label(datum)
    return {"reference": f"above the geoid of {Path(path).name}{where}" + (f" ({named})" if named else ""),
            "geoid_grid": str(path), "n_at_base_m": None if n_at_base is None else float(n_at_base),
            "n_range_m": None if n_range is None else [float(v) for v in n_range], "vertical_crs": named}


def crs_label(crs) -> str:
    """'EPSG:5773 EGM96 height' of a pyproj CRS (its name alone when it has no EPSG code)."""
    code = crs.to_epsg()
    return f"EPSG:{code} {crs.name}" if code is not None else crs.name
