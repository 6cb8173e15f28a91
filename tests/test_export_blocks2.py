"""Issue 43, mutation round seven: the blocks of export/run.py around `export_run` (the checks
before anything is written, the ground of the dense cloud, the survey record, the geoid step, the
report's place), each against answers worked out by hand in the test, without an export."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid import folders
from jaxnerf_grid.config import ConfigError
from jaxnerf_grid.export import run as export_run
from jaxnerf_grid.io import DataError

sys.path.insert(0, str(Path(__file__).parent))


# --------------------------------------------------------------------------- the checks


def test_check_resolution_bounds_and_the_largest_that_fits():
    """8 is the least resolution; (r + 1)^3 x 32 bytes must fit. 1023: 1024^3 x 32 = 32 GiB
    against 16 GiB (2^34 bytes): the largest r with (r + 1)^3 x 32 <= 2^34 is 811 (812^3 =
    535,387,328 <= 2^29 = 536,870,912 < 813^3 = 537,367,797), counted here by brute force."""
    export_run.check_resolution(8, available=10**9)
    for bad in (7, 0, 8.0, True, "64"):
        with pytest.raises(ConfigError, match=r"^export\.resolution = "):
            export_run.check_resolution(bad, available=10**9)
    with pytest.raises(ConfigError, match=r"^export\.resolution = 7: must be an integer >= 8$"):
        export_run.check_resolution(7, available=10**9)
    fits = max(r for r in range(8, 2000) if (r + 1) ** 3 * 32 <= 2**34)
    assert fits == 811
    with pytest.raises(ConfigError) as err:
        export_run.check_resolution(1023, available=2**34)
    assert str(err.value) == ("export.resolution = 1023: its grid needs about 32.0 GiB, more than the 16.0 GiB of "
                              "memory here; use at most 811")
    export_run.check_resolution(811, available=2**34)
    with pytest.raises(ConfigError, match="use at most 811"):
        export_run.check_resolution(812, available=2**34)
    # exactly the need fits: 64^3 x 32 bytes for resolution 63
    export_run.check_resolution(63, available=64**3 * 32)
    with pytest.raises(ConfigError):
        export_run.check_resolution(63, available=64**3 * 32 - 1)


def test_check_resolution_reads_the_hosts_memory_by_default():
    """Without `available`, the host's RAM (MemTotal of /proc/meminfo, within 5 %) is the limit."""
    export_run.check_resolution(8)
    with pytest.raises(ConfigError) as err:
        export_run.check_resolution(100_000)
    meminfo = Path("/proc/meminfo")
    if meminfo.is_file():
        total_kib = next(int(line.split()[1]) for line in meminfo.read_text().splitlines()
                         if line.startswith("MemTotal:"))
        shown = float(str(err.value).split("more than the ")[1].split(" GiB")[0])
        assert shown == pytest.approx(total_kib / 2**20, rel=0.05)


def test_check_views_bounds():
    export_run.check_views(1, 0)
    with pytest.raises(ConfigError, match=r"^export\.views = 0: must be an integer >= 1$"):
        export_run.check_views(0, 0)
    with pytest.raises(ConfigError, match=r"^export\.views = "):
        export_run.check_views(2.0, 0)
    with pytest.raises(ConfigError, match=r"^export\.min_views = -1: must be an integer >= 0$"):
        export_run.check_views(1, -1)
    with pytest.raises(ConfigError, match=r"^export\.min_views = "):
        export_run.check_views(1, 1.0)


def test_check_box_in_scene_at_the_cubes_faces():
    """The box must meet the open cube (-1, 1)^3 on every axis: a box touching a face from
    outside (hi = -1 or lo = 1 on one axis) is refused; one reaching 0.001 inside is taken."""
    lo, hi = np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.5])
    export_run.check_box_in_scene(lo, hi)
    for axis in range(3):
        for (a, b), refused in (((-3.0, -1.0), True), ((-3.0, -0.999), False), ((1.0, 3.0), True),
                                ((0.999, 3.0), False)):
            l2, h2 = lo.copy(), hi.copy()
            l2[axis], h2[axis] = a, b
            if refused:
                with pytest.raises(ConfigError, match="^export.box lies outside the scene"):
                    export_run.check_box_in_scene(l2, h2)
            else:
                export_run.check_box_in_scene(l2, h2)


def _marked(folder: Path, names=()) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_text("x")
    return folder


def test_check_out_empty_occupied_marked_legacy_and_foreign(tmp_path):
    data = _marked(tmp_path / "data", ["transforms.json"])
    export_run.check_out(tmp_path / "new", data, overwrite=False)            # absent
    export_run.check_out(_marked(tmp_path / "empty"), data, overwrite=False)
    with pytest.raises(DataError, match="export.out is the dataset folder"):
        export_run.check_out(data / "export", data, overwrite=True)
    (tmp_path / "file").write_text("x")
    with pytest.raises(DataError, match="export.out exists and is not a folder"):
        export_run.check_out(tmp_path / "file", data, overwrite=True)
    marked = _marked(tmp_path / "marked", ["tower_mesh.ply"])
    folders.write_marker(marked, "export")
    with pytest.raises(DataError, match="already exists and is not empty; pass overwrite=True"):
        export_run.check_out(marked, data, overwrite=False)
    export_run.check_out(marked, data, overwrite=True)
    # an export from before the marker: measurements.json and only export's files
    legacy = _marked(tmp_path / "legacy", ["measurements.json", "tower_mesh.ply", "report.md"])
    assert export_run._is_legacy_export(legacy)
    export_run.check_out(legacy, data, overwrite=True)
    for name, files in (("foreign", ["measurements.json", "notes.txt"]), ("no_record", ["tower_mesh.ply"])):
        folder = _marked(tmp_path / name, files)
        assert not export_run._is_legacy_export(folder)
        with pytest.raises(DataError, match="was not written by jaxnerf-grid export"):
            export_run.check_out(folder, data, overwrite=True)
    odd = _marked(tmp_path / "odd", ["tower_mesh.ply"])
    (odd / "measurements.json").mkdir()                                       # not a file
    assert not export_run._is_legacy_export(odd)


def test_inside_is_the_closed_box():
    p = np.array([[0, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5], [1.0001, 0.5, 0.5], [0.5, -1e-4, 0.5], [0.5, 0.5, 1.01]])
    np.testing.assert_array_equal(export_run._inside(p, np.zeros(3), np.ones(3)),
                                  [True, True, True, False, False, False])


# --------------------------------------------------------------------------- the ground of the dense cloud


def _checkerboard(e: float):
    """One point per 0.02 column on 10 x 10 columns (cell centres), heights 0.1 +- e in a
    checkerboard (orthogonal to 1, x and y: the least-squares plane is z = 0.1, every residual
    +- e, their median 0 and MAD e), plus 5 points above those columns (not lowest) and 4
    roof points in columns of their own at z = 0.6."""
    i, j = np.meshgrid(np.arange(10), np.arange(10), indexing="ij")
    x, y = 0.02 * i.ravel() + 0.01, 0.02 * j.ravel() + 0.01
    z = 0.1 + e * np.where((i + j).ravel() % 2 == 0, 1.0, -1.0)
    base = np.column_stack([x, y, z])
    above = base[:5] + [0.0, 0.0, 0.3]
    roof = np.array([[0.41, 0.41, 0.6], [0.43, 0.41, 0.6], [0.45, 0.41, 0.6], [0.47, 0.41, 0.6]])
    return np.vstack([above, base, roof])


@pytest.mark.parametrize("e, clearance", [(0.006, 3 * 1.4826 * 0.006), (0.001, 0.02)])
def test_ground_of_a_checkerboard_by_hand(e, clearance):
    """clearance = max(0.02, 3 x 1.4826 MAD): 0.0266868 for MAD 0.006, the cell 0.02 for MAD
    0.001; the plane z = 0.1 (normal up, offset -0.1); 100 inliers of 104 candidates (the
    lowest point of each of 104 columns)."""
    g = export_run._ground(_checkerboard(e))
    assert g["candidates"] == 104 and g["inliers"] == 100
    assert isinstance(g["candidates"], int) and isinstance(g["inliers"], int)
    np.testing.assert_allclose(g["normal"], [0, 0, 1], atol=1e-9)
    assert g["offset"] == pytest.approx(-0.1, abs=1e-9)
    assert g["clearance"] == pytest.approx(clearance, rel=1e-9)


def test_ground_spread_is_about_the_median_not_zero():
    """Rows 0, 1, 8, 9 of the columns at 0.1 + 0.012 and rows 2-7 at 0.1 - 0.008 (mean 0 and
    symmetric about the grid's centre: the least-squares plane is z = 0.1): the median residual
    is -0.008, every |res - median| is 0 (60) or 0.02 (40): MAD 0, clearance the cell 0.02
    (about zero instead: MAD 0.008, clearance 3 x 1.4826 x 0.008 = 0.0356)."""
    pts = _checkerboard(0.0)
    rows = np.repeat(np.arange(10), 10)                  # i of the 100 base points (5..104)
    pts[5:105, 2] = 0.1 + np.where(np.isin(rows, [0, 1, 8, 9]), 0.012, -0.008)
    g = export_run._ground(pts)
    assert g["offset"] == pytest.approx(-0.1, abs=1e-9) and g["inliers"] == 100
    assert g["clearance"] == pytest.approx(0.02, abs=1e-12)


def test_ground_of_too_few_points_is_none():
    assert export_run._ground(np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.0]])) is None
    assert export_run._ground(np.zeros((0, 3))) is None


# --------------------------------------------------------------------------- the survey record

VOXEL, REL, POS = 0.12, 0.01, 0.5
GEO = {"units": "metres", "crs": "EPSG:32632", "origin": [465000.0, 5247000.0, 100.0]}


def _meas() -> dict:
    return {"ground": {"clearance": 0.3}, "footprint": {"width_a": 4.0, "width_b": 3.0}, "height": 20.0,
            "cross_arms": {"slice_height": 0.24, "levels": [{"height": 15.0, "span": 12.0},
                                                              {"height": 18.0, "span": 8.0}]},
            "tilt": {"tilt_degrees": 1.2, "tilt_sigma_degrees": 0.1, "top_offset": 0.4, "top_offset_sigma": 0.05,
                     "base": [10.0, 20.0, 50.0]},
            "conductors": {"reconstructed": True, "lowest_height": 12.0}}


def _fig(value, fit, lever=None, position=0.0):
    """A figure by the formula of docs/EXPORT.md: sigma = sqrt((L s_rel)^2 + fit^2 (+ pos^2))."""
    lever = abs(value) if lever is None else lever
    return {"value": value, "sigma": math.sqrt((lever * REL) ** 2 + fit**2 + position**2), "fit_sigma": fit}


def _close(got, want, where="") -> None:
    """got == want, floats within 1e-12 relative, through dicts and lists (same keys, lengths)."""
    if isinstance(want, dict):
        assert isinstance(got, dict) and got.keys() == want.keys(), where
        for k in want:
            _close(got[k], want[k], f"{where}.{k}")
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), where
        for k, (g, w) in enumerate(zip(got, want)):
            _close(g, w, f"{where}[{k}]")
    elif isinstance(want, float):
        assert got == pytest.approx(want, rel=1e-12, abs=1e-15), where
    else:
        assert got == want, where


def test_survey_record_of_a_full_measurement_by_hand():
    """ground sigma = clearance / 3 = 0.1; a vertex's = voxel / sqrt(12); two ends' = voxel
    sqrt(2 / 12); a cross-arm's height: hypot(0.1, slice / sqrt(12)); the base centre: lever
    |base - centroid| = 5 (a 3-4-0 triangle), position 0.5 added; CRS = local + origin."""
    alignment = {"relative_scale": REL, "position_m": POS, "centroid": [13.0, 24.0, 50.0]}
    sv = export_run._survey(_meas(), GEO, alignment, VOXEL)
    g, vertex, ends = 0.1, VOXEL / math.sqrt(12), VOXEL * math.sqrt(2 / 12)
    want = {
        "alignment": alignment,
        "height": _fig(20.0, math.hypot(g, vertex)),
        "footprint": [_fig(4.0, ends), _fig(3.0, ends)],
        "cross_arm_heights": [_fig(15.0, math.hypot(g, 0.24 / math.sqrt(12))),
                              _fig(18.0, math.hypot(g, 0.24 / math.sqrt(12)))],
        "cross_arm_spans": [_fig(12.0, ends), _fig(8.0, ends)],
        "tilt_degrees": {"value": 1.2, "sigma": 0.1, "fit_sigma": 0.1},
        "top_offset": _fig(0.4, 0.05),
        "conductor_clearance": _fig(12.0, math.hypot(g, VOXEL)),
        "base_centre": {"local": [10.0, 20.0, 50.0], "crs": [465010.0, 5247020.0, 150.0], "crs_name": "EPSG:32632",
                        **{k: v for k, v in _fig(0.0, math.hypot(vertex, g), lever=5.0, position=POS).items()
                           if k != "value"}},
        "vertical": None}
    assert sv.keys() == want.keys()
    for key, value in want.items():
        _close(sv[key], value, key)


def test_survey_record_without_a_ground_a_crs_or_a_centroid():
    """No ground: nothing measured, every figure None or empty. A tilt without a CRS and an
    alignment without a centroid: the base's lever is 0, its CRS None; conductors not
    reconstructed: None; the ground's clearance missing counts as 0."""
    sv = export_run._survey({"ground": None, "footprint": None, "height": None, "cross_arms": None, "tilt": None,
                             "conductors": None}, None, {"relative_scale": REL}, VOXEL)
    assert sv == {"alignment": {"relative_scale": REL}, "height": None, "cross_arm_heights": [],
                  "cross_arm_spans": [], "footprint": None, "tilt_degrees": None, "top_offset": None,
                  "conductor_clearance": None, "base_centre": None, "vertical": None}
    meas = {**_meas(), "ground": {}, "conductors": {"reconstructed": False}}
    sv = export_run._survey(meas, None, {"relative_scale": REL}, VOXEL)
    vertex = VOXEL / math.sqrt(12)
    _close(sv["base_centre"], {"local": [10.0, 20.0, 50.0], "crs": None, "crs_name": None, "sigma": vertex,
                               "fit_sigma": vertex})
    assert sv["conductor_clearance"] is None
    _close(sv["height"], _fig(20.0, vertex))


# --------------------------------------------------------------------------- the geoid step and the report's place


def test_vertical_without_a_grid_records_the_heights_as_written():
    sv, pts, mesh = {}, np.ones((2, 3)), np.zeros((3, 3))
    got = export_run._vertical(sv, {"source": "gps+gcp"}, "EPSG:32632", None, None, pts, mesh)
    assert got[0] is pts and got[1] is mesh
    assert sv["vertical"]["reference"].startswith("as the control points' Z") and sv["vertical"]["geoid_grid"] is None


def test_vertical_with_a_linear_geoid_by_closed_form(tmp_path):
    """H = h - N, N = A + B lat + C lon (exact under bilinear interpolation) at each point, at
    the base centre (its N recorded), the range of N over the points and the mesh."""
    from test_export_geoid import A, B, C, CRS, lat_lon, linear_n, site_grid

    from jaxnerf_grid.export import geoid

    path = site_grid(tmp_path / "linear.gtx", linear_n)
    grid = geoid.open_grid(path)
    pts = np.array([[465000.0, 5247000.0, 300.0], [466000.0, 5249000.0, 310.0]])
    mesh = np.array([[464000.0, 5245000.0, 305.0], [465500.0, 5247500.0, 320.0], [467000.0, 5251000.0, 330.0]])
    base = [465100.0, 5247200.0, 301.0]
    sv = {"base_centre": {"crs": list(base)}}
    got_pts, got_mesh = export_run._vertical(sv, GEO, CRS, grid, path, pts, mesh)

    def n_at(p):
        lat, lon = lat_lon(np.asarray(p, np.float64).reshape(-1, 3))
        return A + B * lat + C * lon

    np.testing.assert_allclose(got_pts[:, 2], pts[:, 2] - n_at(pts), atol=1e-3)
    np.testing.assert_allclose(got_mesh[:, 2], mesh[:, 2] - n_at(mesh), atol=1e-3)
    np.testing.assert_allclose(got_pts[:, :2], pts[:, :2])
    n_base = float(n_at(base)[0])
    assert sv["base_centre"]["crs"] == pytest.approx([base[0], base[1], base[2] - n_base], abs=1e-3)
    n_all = np.concatenate([n_at(pts), n_at(mesh)])
    v = sv["vertical"]
    assert v["n_at_base_m"] == pytest.approx(n_base, abs=1e-3)
    assert v["n_range_m"] == pytest.approx([n_all.min(), n_all.max()], abs=1e-3)
    assert v["geoid_grid"] == str(path) and v["vertical_crs"] is None
    assert v["reference"] == f"above the geoid of linear.gtx, N = {n_base:.3f} m at the base"
    # no base centre in the CRS: no N at the base
    sv = {"base_centre": {"crs": None}}
    export_run._vertical(sv, GEO, CRS, grid, path, pts, mesh)
    assert sv["vertical"]["n_at_base_m"] is None and sv["base_centre"]["crs"] is None
    assert sv["vertical"]["reference"] == "above the geoid of linear.gtx"


def test_check_geoid_site_names_why_a_dataset_without_a_crs_is_refused(tmp_path):
    grid = tmp_path / "g.gtx"
    with pytest.raises(DataError, match=r"g\.gtx: export\.geoid needs a dataset georeferenced .* this one has "
                                        r"metres but no CRS$"):
        export_run._check_geoid_site(grid, None, None, None, None, None, "metres")
    with pytest.raises(DataError, match=r"this one has no metric scale$"):
        export_run._check_geoid_site(grid, None, None, None, None, None, "unknown")


@pytest.mark.parametrize("default", [True, False])
def test_update_report_writes_beside_the_run_or_the_export(tmp_path, monkeypatch, default):
    """RUN/export: RUN/report.md with the picture at export/export_views.png; elsewhere:
    OUT/report.md with export_views.png beside it; report.html next to the report.md."""
    from jaxnerf_grid import report, report_html

    calls = {}
    monkeypatch.setattr(report, "set_section", lambda path, heading, lines: calls.update(
        section=(path, heading, lines)))
    monkeypatch.setattr(report, "export_lines", lambda info: ("lines", info))
    monkeypatch.setattr(report_html, "write_report_html", lambda path, run_dir, ds, export_dir=None: calls.update(
        html=(path, run_dir, ds, export_dir)))
    run_dir = tmp_path / "run"
    out = run_dir / "export" if default else tmp_path / "elsewhere"
    meas, ds = {"height": 1.0}, object()
    export_run._update_report(run_dir, out, meas, ds)
    md = run_dir / "report.md" if default else out / "report.md"
    image = "export/export_views.png" if default else "export_views.png"
    assert calls["section"] == (md, report.EXPORT_HEADING, ("lines", {"measurements": meas, "image": image}))
    assert calls["html"] == (md.with_suffix(".html"), run_dir, ds, out)
