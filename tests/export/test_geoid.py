"""`export --geoid GRID`, heights above a geoid (docs/GEOREFERENCE.md). The grids are
GTX files written here by hand (a big-endian header, then float32 rows from south to north)
holding a field whose bilinear interpolation is exact (N = a + b lat + c lon, or a constant), so
that the heights are checked against a closed form in NumPy; the export is the analytic tower's
(tests/joins/test_join_export.py: no training), with and without a grid."""

import struct
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.export import geoid
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError
from tests.joins.test_join_export import GEOREFERENCE, _tilted_export
from tests.support import analytic_field as af

CRS = GEOREFERENCE["crs"]               # EPSG:32632; its origin lies near 47.37 N, 8.54 E
FLAT_N = 47.25                          # metres: exact in float32, like every value written below
A, B, C = 30.0, 0.5, -0.25              # N = A + B lat + C lon


def write_gtx(path: Path, south: float, west: float, step: float, rows: int, cols: int, n_of) -> Path:
    """A GTX grid: header (south latitude, west longitude, latitude step, longitude step: float64;
    rows, columns: int32), big-endian, then rows x cols float32 N(lat, lon), south row first,
    each row west to east."""
    lat = south + step * np.arange(rows)
    lon = west + step * np.arange(cols)
    values = n_of(lat[:, None], lon[None, :]) + np.zeros((rows, cols))
    path.write_bytes(struct.pack(">4d2i", south, west, step, step, rows, cols) + values.astype(">f4").tobytes())
    return path


def write_geotiff(path: Path, south: float, west: float, step: float, rows: int, cols: int, n_of) -> Path:
    """The same grid as a GeoTIFF (tifffile, scikit-image's TIFF writer): float32 rows from north
    to south, ModelPixelScale (step, step, 0), ModelTiepoint pixel (0, 0) -> (west, north), and the
    GeoKeys: geographic model (1024 = 2), PixelIsPoint (1025 = 2), WGS 84 (2048 = 4326)."""
    import tifffile

    lat = south + step * np.arange(rows)
    lon = west + step * np.arange(cols)
    values = (n_of(lat[:, None], lon[None, :]) + np.zeros((rows, cols))).astype(np.float32)[::-1]
    keys = [1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 2, 2048, 0, 1, 4326]
    tifffile.imwrite(path, values, extratags=[
        (33550, "d", 3, (step, step, 0.0), False),
        (33922, "d", 6, (0.0, 0.0, 0.0, west, south + step * (rows - 1), 0.0), False),
        (34735, "H", len(keys), keys, False)])
    return path


def linear_n(lat, lon):
    return A + B * lat + C * lon


def site_grid(path: Path, n_of) -> Path:
    """A grid over 46.5-48.5 N, 7.5-9.5 E (the analytic tower's site), 0.25 degree steps."""
    return write_gtx(path, 46.5, 7.5, 0.25, 9, 9, n_of)


def lat_lon(points_crs: np.ndarray):
    """WGS 84 (latitude, longitude) of CRS points, by pyproj directly (the horizontal part)."""
    import pyproj

    lon, lat = pyproj.Transformer.from_crs(CRS, "EPSG:4326", always_xy=True).transform(points_crs[:, 0],
                                                                                       points_crs[:, 1])
    return np.asarray(lat), np.asarray(lon)


@pytest.mark.parametrize("writer, name", [(write_gtx, "linear.gtx"), (write_geotiff, "linear.tif")])
def test_orthometric_heights_of_a_linear_geoid_are_the_closed_form(tmp_path, writer, name):
    """H = h - (A + B lat + C lon) at 200 points spread over 20 km of the site, from a GTX grid
    and from a GeoTIFF one; eastings and northings untouched."""
    path = writer(tmp_path / name, 46.5, 7.5, 0.25, 9, 9, linear_n)
    rng = np.random.default_rng(0)
    points = np.asarray(GEOREFERENCE["origin"]) + rng.uniform([-1e4, -1e4, 300], [1e4, 1e4, 600], (200, 3))
    got, n = geoid.orthometric(points, CRS, geoid.open_grid(path), path)
    lat, lon = lat_lon(points)
    np.testing.assert_allclose(n, linear_n(lat, lon), atol=1e-5)
    np.testing.assert_allclose(got[:, 2], points[:, 2] - linear_n(lat, lon), atol=1e-5)
    np.testing.assert_array_equal(got[:, :2], points[:, :2])


def test_a_point_outside_the_grid_is_a_data_error_naming_the_grid(tmp_path):
    path = site_grid(tmp_path / "site.gtx", linear_n)
    far = np.asarray(GEOREFERENCE["origin"]) + [0.0, 3e5, 0.0]            # 300 km north: about 50 N
    with pytest.raises(DataError, match=r"site\.gtx: export\.geoid does not cover 1 of the 2 points"):
        geoid.orthometric(np.stack([np.asarray(GEOREFERENCE["origin"], float), far]), CRS, geoid.open_grid(path), path)



@pytest.mark.parametrize("source, reference", [("gps", "ellipsoidal (GPS heights as written)"),
                                               ("gps+gcp", geoid.AS_CONTROL_POINTS), ("gcp", geoid.AS_CONTROL_POINTS)])
def test_without_a_grid_the_heights_are_as_the_fit_took_them(source, reference):
    """GPS alone: the GPS's heights; with control points (whose weight rules the fit): their Z."""
    record = geoid.vertical_record(geo={**GEOREFERENCE, "source": source})
    assert record == {"reference": reference, "geoid_grid": None, "n_at_base_m": None, "n_range_m": None,
                      "vertical_crs": None}


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    """The analytic tower's export (GPS record, EPSG:32632) without a grid, with a flat grid
    (N = FLAT_N, named as EGM96 height: export.vertical_crs EPSG:5773) and with the linear one
    (no datum named): {name: (measurements, export folder, grid path)}."""
    out = {}
    for name, n_of, datum in (("plain", None, None), ("flat", lambda lat, lon: FLAT_N, "EPSG:5773"),
                              ("linear", linear_n, None)):
        root = tmp_path_factory.mktemp(name)
        path = site_grid(root / f"{name}.gtx", n_of) if n_of else None
        meas = _tilted_export(root, af.TILT, {"georeference": GEOREFERENCE}, geoid=path, vertical_crs=datum)
        out[name] = (meas, root / "run" / "export", path)
    return out


def _las(folder: Path) -> np.ndarray:
    import laspy

    las = laspy.read(folder / "tower_points.las")
    return np.column_stack([las.x, las.y, las.z])


def _mesh_crs(folder: Path) -> np.ndarray:
    import plyfile

    v = plyfile.PlyData.read(str(folder / "tower_mesh_crs.ply"))["vertex"]
    return np.column_stack([v["x"], v["y"], v["z"]])


def _relative(meas: dict) -> dict:
    """measurements.json less what may differ between two exports (times, folders) and the
    CRS heights the geoid changes."""
    skip = {"seconds", "timings", "peak_memory_mib", "run"}
    out = {k: v for k, v in meas.items() if k not in skip}
    out["survey"] = {k: v for k, v in meas["survey"].items() if k != "vertical"}
    out["survey"]["base_centre"] = {k: v for k, v in meas["survey"]["base_centre"].items() if k != "crs"}
    return out


def test_a_flat_geoid_lowers_every_crs_height_by_n_and_changes_no_measurement(exports):
    plain, plain_dir, _ = exports["plain"]
    flat, flat_dir, path = exports["flat"]
    assert _relative(flat) == _relative(plain)
    assert flat["height"] == plain["height"] and flat["cross_arms"] == plain["cross_arms"]
    las_plain, las_flat = _las(plain_dir), _las(flat_dir)
    assert len(las_flat) == len(las_plain) > 100
    np.testing.assert_array_equal(las_flat[:, :2], las_plain[:, :2])
    np.testing.assert_allclose(las_flat[:, 2], las_plain[:, 2] - FLAT_N, atol=1.01e-3)   # LAS steps of 1 mm
    mesh_plain, mesh_flat = _mesh_crs(plain_dir), _mesh_crs(flat_dir)
    np.testing.assert_array_equal(mesh_flat[:, :2], mesh_plain[:, :2])
    np.testing.assert_allclose(mesh_flat[:, 2], mesh_plain[:, 2] - FLAT_N, atol=1e-9)
    base_plain, base_flat = plain["survey"]["base_centre"]["crs"], flat["survey"]["base_centre"]["crs"]
    np.testing.assert_allclose(base_flat, np.asarray(base_plain) - [0, 0, FLAT_N], atol=1e-9)
    for name in ("tower_points.ply", "tower_mesh.ply"):                  # the local frame stays as it was
        np.testing.assert_array_equal(io.read_ply_points(flat_dir / name), io.read_ply_points(plain_dir / name))


def test_the_records_and_the_report_name_the_vertical_reference(exports):
    import laspy
    import pyproj

    plain, plain_dir, _ = exports["plain"]
    flat, flat_dir, path = exports["flat"]
    assert plain["survey"]["vertical"]["reference"] == "ellipsoidal (GPS heights as written)"
    vertical = flat["survey"]["vertical"]
    assert vertical["reference"] == (f"above the geoid of flat.gtx, N = {FLAT_N:.3f} m at the base "
                                     f"(EPSG:5773 EGM96 height)")
    assert vertical["vertical_crs"] == "EPSG:5773 EGM96 height"
    assert plain["survey"]["vertical"]["vertical_crs"] is None
    assert vertical["n_at_base_m"] == pytest.approx(FLAT_N, abs=1e-9)
    assert vertical["n_range_m"] == pytest.approx([FLAT_N, FLAT_N], abs=1e-9)
    assert io.read_json(flat_dir / "measurements.json")["survey"]["vertical"] == vertical
    report = (flat_dir.parent / "report.md").read_text()
    assert f"| {vertical['reference']} |" in report
    assert "| ellipsoidal (GPS heights as written) |" in (plain_dir.parent / "report.md").read_text()
    assert f"heights: {vertical['reference']}" in (flat_dir / "tower_mesh_crs.ply").read_bytes()[:2000].decode(
        "ascii", "replace")
    las_crs = laspy.read(flat_dir / "tower_points.las").header.parse_crs()   # the compound of the two
    assert las_crs.is_compound
    assert [c.to_epsg() for c in las_crs.sub_crs_list] == [32632, 5773]
    for name in ("plain", "linear"):                                        # no datum named: the horizontal alone
        assert laspy.read(exports[name][1] / "tower_points.las").header.parse_crs() == pyproj.CRS.from_epsg(32632)


def test_a_linear_geoid_gives_the_closed_form_at_every_las_point_and_the_base(exports):
    plain, plain_dir, _ = exports["plain"]
    linear, linear_dir, _ = exports["linear"]
    assert _relative(linear) == _relative(plain)
    las_plain, las_linear = _las(plain_dir), _las(linear_dir)
    lat, lon = lat_lon(las_plain)
    np.testing.assert_allclose(las_linear[:, 2], las_plain[:, 2] - linear_n(lat, lon), atol=1.5e-3)
    base = np.asarray(plain["survey"]["base_centre"]["crs"])
    lat, lon = lat_lon(base[None])
    n_base = float(linear_n(lat, lon)[0])
    assert linear["survey"]["vertical"]["n_at_base_m"] == pytest.approx(n_base, abs=1e-5)
    assert linear["survey"]["base_centre"]["crs"][2] == pytest.approx(base[2] - n_base, abs=1e-5)
    mesh_plain = _mesh_crs(plain_dir)
    lat, lon = lat_lon(mesh_plain)
    np.testing.assert_allclose(_mesh_crs(linear_dir)[:, 2], mesh_plain[:, 2] - linear_n(lat, lon), atol=1e-5)


def _refused(tmp_path, monkeypatch, meta: dict, grid, match: str) -> None:
    """export_run with `grid` fails with one line matching `match` before any view is rendered;
    nothing is written."""
    from jaxnerf_grid.export import run as export_run

    def not_before_the_checks(*args, **kwargs):
        raise AssertionError("views rendered before the geoid's checks")

    monkeypatch.setattr(export_run, "_render_cloud", not_before_the_checks)
    with pytest.raises(DataError, match=match) as err:
        _tilted_export(tmp_path, af.TILT, meta, geoid=grid)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "run" / "export").exists()


def test_a_missing_grid_file_is_refused_before_anything_is_written(tmp_path, monkeypatch):
    _refused(tmp_path, monkeypatch, {"georeference": GEOREFERENCE}, tmp_path / "egm96.gtx",
             r"egm96\.gtx: export\.geoid does not exist")


def test_a_file_proj_cannot_read_as_a_grid_is_refused(tmp_path, monkeypatch):
    bad = tmp_path / "notes.gtx"
    bad.write_text("not a grid\n")
    _refused(tmp_path, monkeypatch, {"georeference": GEOREFERENCE}, bad, r"notes\.gtx: export\.geoid: PROJ cannot read")


def test_a_dataset_without_a_crs_given_a_grid_is_refused(tmp_path, monkeypatch):
    """The analytic dataset states its normalisation (metres) but has no georeference: the
    refusal says which (export_run mutant 93: `_check_geoid_site` handed no units said "no
    metric scale")."""
    grid = site_grid(tmp_path / "site.gtx", linear_n)
    _refused(tmp_path, monkeypatch, {}, grid,
             r"site\.gtx: export\.geoid needs a dataset georeferenced .*; this one has metres but no CRS$")


def test_a_grid_that_does_not_cover_the_site_is_refused(tmp_path, monkeypatch):
    grid = write_gtx(tmp_path / "elsewhere.gtx", 10.0, 20.0, 0.25, 5, 5, linear_n)
    _refused(tmp_path, monkeypatch, {"georeference": GEOREFERENCE}, grid,
             r"elsewhere\.gtx: export\.geoid does not cover")


def test_the_command_line_names_the_flag_and_the_file_in_one_line(tmp_path, monkeypatch, capsys):
    """`jaxnerf-grid export --geoid MISSING`: exit 1, one line naming --geoid and the file."""
    from jaxnerf_grid.train import runs
    from tests.joins.test_join_truth import analytic_config

    monkeypatch.setattr(runs, "load_run", lambda run_dir: (analytic_config(), None))
    (tmp_path / "run").mkdir()
    rc = cli.main(["export", "--run", str(tmp_path / "run"), "--geoid", str(tmp_path / "egm96.gtx"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1
    assert "egm96.gtx: --geoid does not exist" in err
    assert not (tmp_path / "run" / "export").exists()


@pytest.mark.parametrize("with_grid, datum, match", [
    (False, "EPSG:5773", r"export\.vertical_crs = 'EPSG:5773' names the datum .* give export\.geoid"),
    (True, "EPSG:32632", r"export\.vertical_crs = 'EPSG:32632' is not a vertical CRS"),
    (True, "EPSG:999999", r"export\.vertical_crs = 'EPSG:999999': pyproj does not know it")])
def test_a_vertical_crs_without_a_grid_unknown_or_not_vertical_is_refused(tmp_path, monkeypatch, with_grid, datum,
                                                                           match):
    """Each a one-line DataError naming the key, before the dataset is read; nothing written."""
    from jaxnerf_grid.export import run as export_run

    def not_before_the_checks(*args, **kwargs):
        raise AssertionError("views rendered before the vertical CRS's check")

    monkeypatch.setattr(export_run, "_render_cloud", not_before_the_checks)
    grid = site_grid(tmp_path / "site.gtx", linear_n) if with_grid else None
    with pytest.raises(DataError, match=match) as err:
        _tilted_export(tmp_path, af.TILT, {"georeference": GEOREFERENCE}, geoid=grid, vertical_crs=datum)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "run" / "export").exists()
