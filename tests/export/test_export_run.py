"""The blocks of export/run.py around `export_run` (the checks
before anything is written, the ground of the dense cloud, the survey record, the geoid step, the
report's place), each against answers worked out by hand in the test, without an export."""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.export import run as export_run
from jaxnerf_grid.util import folders
from jaxnerf_grid.util.io import DataError

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
                with pytest.raises(ConfigError, match=r"^export\.box lies outside the scene: it does not meet the "
                                                      r"region of interest \(the unit sphere of the normalised "
                                                      r"scene, i\.e\. the tower's surroundings\); give it in the "
                                                      r"dataset's original units \(metres for the synthetic "
                                                      r"scenes\)$"):
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
        with pytest.raises(DataError, match=r"was not written by jaxnerf-grid export .* choose another export\.out$"):
            export_run.check_out(folder, data, overwrite=True)
    odd = _marked(tmp_path / "odd", ["tower_mesh.ply"])
    (odd / "measurements.json").mkdir()                                       # not a file
    assert not export_run._is_legacy_export(odd)


def test_parse_box_takes_six_numbers_and_names_what_is_wrong():
    """A box given as numbers (the Python API) and the three refusals' words."""
    np.testing.assert_array_equal(export_run.parse_box([0, 1, 2, 3, 4, 5]), [0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(export_run.parse_box((0.5, 1, 2, 3, 4, 5)), [0.5, 1.0, 2.0, 3.0, 4.0, 5.0])
    with pytest.raises(ConfigError, match=r"^export\.box: expected 'auto' or six numbers xmin,ymin,zmin,xmax,ymax,"
                                          r"zmax, got 'a,b,c,d,e,f'$"):
        export_run.parse_box("a,b,c,d,e,f")
    with pytest.raises(ConfigError, match=r"^export\.box: expected six finite numbers xmin,ymin,zmin,xmax,ymax,zmax, "
                                          r"got '1,2,3,4,5'$"):
        export_run.parse_box("1,2,3,4,5")
    with pytest.raises(ConfigError, match=r"^export\.box: the box is empty \(each max must exceed its min\): "
                                          r"'0,0,1,1,1,1'$"):
        export_run.parse_box("0,0,1,1,1,1")


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
    (about zero instead: MAD 0.008, clearance 3 x 1.4826 x 0.008 = 0.0356). Settled on the
    cloud (`ground.settle_on_cloud`) the plane moves to the median of the points within 0.025 of
    it: the 100 ground points (the 5 above and the roof lie 0.3 and 0.5 higher), median height
    0.092, so the offset is -0.092 and it moved 0.008 (then every residual, +0.02 or 0, is in
    the band and the median is 0: it stops)."""
    pts = _checkerboard(0.0)
    rows = np.repeat(np.arange(10), 10)                  # i of the 100 base points (5..104)
    pts[5:105, 2] = 0.1 + np.where(np.isin(rows, [0, 1, 8, 9]), 0.012, -0.008)
    g = export_run._ground(pts)
    assert g["offset"] == pytest.approx(-0.092, abs=1e-9) and g["inliers"] == 100
    assert g["settled_on"] == 100 and g["settled_shift"] == pytest.approx(-0.008, abs=1e-9)
    assert g["clearance"] == pytest.approx(0.02, abs=1e-12)


def test_ground_draws_the_1000_ransac_planes_docs_export_md_states(monkeypatch):
    """docs/EXPORT.md: "RANSAC (1000 three-point planes within 45 degrees of horizontal, inliers
    within 0.025 units)". On the checkerboard every count of draws finds the same plane, so the
    count is read where it is handed over: RANSAC itself (the real one, wrapped) is asked for
    1000 draws, an inlier distance of 0.025 and its 45-degree limit, and the plane is the one
    worked out by hand above."""
    from jaxnerf_grid.export import ground

    asked = []
    real = ground.fit_plane_ransac

    def recording(points, threshold, iterations=500, seed=0, max_tilt_deg=45.0):
        asked.append((threshold, iterations, seed, max_tilt_deg))
        return real(points, threshold, iterations=iterations, seed=seed, max_tilt_deg=max_tilt_deg)

    monkeypatch.setattr(ground, "fit_plane_ransac", recording)
    g = export_run._ground(_checkerboard(0.006))
    assert asked == [(0.025, 1000, 0, 45.0)]
    assert g["inliers"] == 100 and g["offset"] == pytest.approx(-0.1, abs=1e-9)


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
            "tilt": {"tilt_degrees": 1.2, "tilt_sigma_degrees": 0.1, "thickness_spread_degrees": 0.2,
                     "top_offset": 0.4, "top_offset_sigma": 0.05, "base": [10.0, 20.0, 50.0], "lowest_height": 6.0},
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
    sqrt(2 / 12); a cross-arm's height: hypot(0.1, slice / sqrt(12)); the tilt's: its fit 0.1 and
    thickness spread 0.2 degrees in quadrature, the top offset's that spread over the height 20
    added; the base centre: lever |base - centroid| = 5 (a 3-4-0 triangle), position 0.5 added,
    and the tilt's error over the 6 m the axis is extended below the lowest point; CRS = local + origin."""
    alignment = {"relative_scale": REL, "position_m": POS, "centroid": [13.0, 24.0, 50.0]}
    sv = export_run._survey(_meas(), GEO, alignment, VOXEL)
    g, vertex, ends = 0.1, VOXEL / math.sqrt(12), VOXEL * math.sqrt(2 / 12)
    angle = math.sqrt(0.1**2 + 0.2**2)
    reach = 6.0 * math.tan(math.radians(angle))
    want = {
        "alignment": alignment,
        "height": _fig(20.0, math.hypot(g, vertex)),
        "footprint": [_fig(4.0, ends), _fig(3.0, ends)],
        "cross_arm_heights": [_fig(15.0, math.hypot(g, 0.24 / math.sqrt(12))),
                              _fig(18.0, math.hypot(g, 0.24 / math.sqrt(12)))],
        "cross_arm_spans": [_fig(12.0, ends), _fig(8.0, ends)],
        "tilt_degrees": {"value": 1.2, "sigma": angle, "fit_sigma": angle},
        "top_offset": _fig(0.4, math.hypot(0.05, math.radians(0.2) * 20.0)),
        "conductor_clearance": _fig(12.0, math.hypot(g, VOXEL)),
        "base_centre": {"local": [10.0, 20.0, 50.0], "crs": [465010.0, 5247020.0, 150.0], "crs_name": "EPSG:32632",
                        "extrapolated": 6.0,
                        **{k: v for k, v in _fig(0.0, math.sqrt(vertex**2 + g**2 + reach**2), lever=5.0,
                                                 position=POS).items() if k != "value"}},
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
    tilt = {**_meas()["tilt"], "lowest_height": -0.3}            # a mesh reaching below the plane
    meas = {**_meas(), "ground": {}, "conductors": {"reconstructed": False}, "tilt": tilt}
    sv = export_run._survey(meas, None, {"relative_scale": REL}, VOXEL)
    vertex = VOXEL / math.sqrt(12)
    _close(sv["base_centre"], {"local": [10.0, 20.0, 50.0], "crs": None, "crs_name": None, "extrapolated": 0.0,
                               "sigma": vertex, "fit_sigma": vertex})
    assert sv["conductor_clearance"] is None
    _close(sv["height"], _fig(20.0, vertex))


def test_survey_record_of_a_tilt_without_its_spread_or_lowest_height_and_no_height():
    """A tilt record without `thickness_spread_degrees` and `lowest_height` counts them as 0: the
    tilt's sigma is its fit's 0.1 degrees alone, the top offset's its own 0.05, and the base
    centre is not extrapolated (reach 0: sqrt(vertex^2 + 0.1^2), lever 5, position 0.5). With the
    spread (0.2 degrees) but no height measured, the spread adds nothing to the top offset (0.2
    degrees over a height of 0): its sigma is 0.05 again, the tilt's hypot(0.1, 0.2)."""
    alignment = {"relative_scale": REL, "position_m": POS, "centroid": [13.0, 24.0, 50.0]}
    tilt = {k: v for k, v in _meas()["tilt"].items() if k not in ("thickness_spread_degrees", "lowest_height")}
    sv = export_run._survey({**_meas(), "tilt": tilt}, GEO, alignment, VOXEL)
    g, vertex = 0.1, VOXEL / math.sqrt(12)
    _close(sv["tilt_degrees"], {"value": 1.2, "sigma": 0.1, "fit_sigma": 0.1})
    _close(sv["top_offset"], _fig(0.4, 0.05))
    _close(sv["base_centre"], {"local": [10.0, 20.0, 50.0], "crs": [465010.0, 5247020.0, 150.0],
                               "crs_name": "EPSG:32632", "extrapolated": 0.0,
                               **{k: v for k, v in _fig(0.0, math.hypot(vertex, g), lever=5.0, position=POS).items()
                                  if k != "value"}})
    sv = export_run._survey({**_meas(), "height": None}, GEO, alignment, VOXEL)
    assert sv["height"] is None
    angle = math.hypot(0.1, 0.2)
    _close(sv["tilt_degrees"], {"value": 1.2, "sigma": angle, "fit_sigma": angle})
    _close(sv["top_offset"], _fig(0.4, 0.05))


# --------------------------------------------------------------------------- the geoid step and the report's place


def test_vertical_without_a_grid_records_the_heights_as_written():
    sv, pts, mesh = {}, np.ones((2, 3)), np.zeros((3, 3))
    got = export_run._vertical(sv, {"source": "gps+gcp"}, "EPSG:32632", None, None, pts, mesh)
    assert got[0] is pts and got[1] is mesh
    assert sv["vertical"]["reference"].startswith("as the control points' Z") and sv["vertical"]["geoid_grid"] is None


def test_vertical_with_a_linear_geoid_by_closed_form(tmp_path):
    """H = h - N, N = A + B lat + C lon (exact under bilinear interpolation) at each point, at
    the base centre (its N recorded), the range of N over the points and the mesh."""
    from jaxnerf_grid.export import geoid
    from tests.export.test_geoid import CRS, A, B, C, lat_lon, linear_n, site_grid

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


def test_vertical_names_the_grid_when_it_misses_a_point_the_mesh_or_the_base_and_records_the_datum(tmp_path):
    """A point 300 km north of the site (about 50 N) is outside the grid (46.5-48.5 N): the
    DataError names the grid file whether the point is in the cloud, the mesh or the base
    centre. With no point and no mesh vertex, no N range; a named datum is recorded."""
    import pyproj

    from jaxnerf_grid.export import geoid
    from tests.export.test_geoid import CRS, linear_n, site_grid

    path = site_grid(tmp_path / "site.gtx", linear_n)
    grid = geoid.open_grid(path)
    inside, far = np.array([[465000.0, 5247000.0, 300.0]]), np.array([[465000.0, 5547000.0, 300.0]])
    for pts, mesh, base in ((far, inside, inside[0]), (inside, far, inside[0]), (inside, inside, far[0])):
        sv = {"base_centre": {"crs": list(base)}}
        with pytest.raises(DataError, match=r"site\.gtx: export\.geoid does not cover 1 of the 1 points"):
            export_run._vertical(sv, GEO, CRS, grid, path, pts, mesh)
    sv = {"base_centre": None}
    got = export_run._vertical(sv, GEO, CRS, grid, path, np.zeros((0, 3)), np.zeros((0, 3)),
                               datum=pyproj.CRS.from_epsg(5773))
    assert got[0].shape == (0, 3) and got[1].shape == (0, 3)
    assert sv["vertical"]["n_range_m"] is None and sv["vertical"]["n_at_base_m"] is None
    assert sv["vertical"]["vertical_crs"] == "EPSG:5773 EGM96 height"


def test_check_geoid_site_needs_the_grid_to_cover_every_camera(tmp_path):
    """The cameras' centres, mapped to metres (x = x_norm / s - t with s = 0.5, t = (-10, 0, 0):
    x_norm (0, 0, 0) is 10 m east of the CRS origin) and to the CRS, must lie on the grid
    (46.5-48.5 N; the origin is near 47.37 N): a camera at x_norm y = 150 km (300 km north in
    metres, about 50 N) is refused naming the grid file; at 60 km (120 km, about 48.45 N) it
    passes, and 120 km without the scale undone would be 240 km (outside): the scale is undone."""
    from types import SimpleNamespace

    from jaxnerf_grid.export import geoid
    from tests.export.test_geoid import CRS, linear_n, site_grid

    path = site_grid(tmp_path / "site.gtx", linear_n)
    grid = geoid.open_grid(path)
    geo = {"units": "metres", "crs": CRS, "origin": [465000.0, 5247000.0, 300.0]}
    norm = {"scale": 0.5, "translation": [-10.0, 0.0, 0.0]}
    c2w = np.tile(np.eye(4), (2, 1, 1))
    export_run._check_geoid_site(path, grid, CRS, geo, SimpleNamespace(c2w=c2w), norm, "metres")
    c2w[1, 1, 3] = 0.5 * 3e5                               # 300 km north in metres: about 50 N
    with pytest.raises(DataError, match=r"site\.gtx: export\.geoid does not cover 1 of the 2 points"):
        export_run._check_geoid_site(path, grid, CRS, geo, SimpleNamespace(c2w=c2w), norm, "metres")
    c2w[1, 1, 3] = 0.5 * 1.2e5                             # 120 km north in metres: about 48.45 N, inside
    export_run._check_geoid_site(path, grid, CRS, geo, SimpleNamespace(c2w=c2w), norm, "metres")
    c2w[1, 1, 3] = 1.2e5                                   # the same without the scale: 240 km, outside
    with pytest.raises(DataError, match="does not cover 1 of the 2 points"):
        export_run._check_geoid_site(path, grid, CRS, geo, SimpleNamespace(c2w=c2w), norm, "metres")


def test_check_geoid_site_names_why_a_dataset_without_a_crs_is_refused(tmp_path):
    grid = tmp_path / "g.gtx"
    with pytest.raises(DataError, match=r"g\.gtx: export\.geoid needs a dataset georeferenced .* this one has "
                                        r"metres but no CRS$"):
        export_run._check_geoid_site(grid, None, None, None, None, None, "metres")
    with pytest.raises(DataError, match=r"this one has no metric scale$"):
        export_run._check_geoid_site(grid, None, None, None, None, None, "unknown")


@pytest.mark.parametrize("default", [True, False])
def test_update_report_writes_beside_the_run_or_the_export(tmp_path, monkeypatch, default):
    """RUN/export: RUN/report.md with the pictures at export/export_views.png and
    export/conductors_views.png; elsewhere: OUT/report.md with both beside it; report.html next
    to the report.md."""
    from jaxnerf_grid.report import html as report_html
    from jaxnerf_grid.report import markdown as report

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
    folder = "export/" if default else ""
    info = {"measurements": meas, "image": f"{folder}export_views.png",
            "conductors_image": f"{folder}conductors_views.png"}
    assert calls["section"] == (md, report.EXPORT_HEADING, ("lines", info))
    assert calls["html"] == (md.with_suffix(".html"), run_dir, ds, out)


# --------------------------------------------------------------------------- export/survey.py


class _Meta:
    def __init__(self, meta):
        self.meta = meta


def test_georeference_crs_and_to_crs_of_records_by_hand():
    from jaxnerf_grid.export import survey

    assert survey.georeference_of(object()) is None and survey.georeference_of(_Meta(None)) is None
    assert survey.units_of(object()) == "unknown"                                  # no meta at all
    assert survey.georeference_of(_Meta({"georeference": "EPSG:32632"})) is None
    assert survey.georeference_of(_Meta({"georeference": GEO})) is GEO
    name, origin = survey.crs_of(GEO)
    assert name == "EPSG:32632" and origin.dtype == np.float64
    np.testing.assert_array_equal(origin, [465000.0, 5247000.0, 100.0])
    name, origin = survey.crs_of({"units": "metres", "crs": "EPSG:2056"})          # no origin: 0
    assert name == "EPSG:2056"
    np.testing.assert_array_equal(origin, [0.0, 0.0, 0.0])
    for geo in (None, {}, {**GEO, "units": "unknown"}, {**GEO, "crs": ""}, {**GEO, "crs": None}):
        name, origin = survey.crs_of(geo)
        assert name is None
        np.testing.assert_array_equal(origin, [0.0, 0.0, 0.0])
    local = np.array([[1.5, -2.0, 3.25]], np.float32)
    got = survey.to_crs(local, GEO)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, [[465001.5, 5246998.0, 103.25]])
    np.testing.assert_array_equal(survey.to_crs(local, {**GEO, "units": "unknown"}), local)


def test_coordinate_and_weighted_scale_sigma_by_hand():
    from jaxnerf_grid.export import survey

    assert survey.coordinate_sigma(3.0, 1, 3) is None                   # 3n - p = 0
    assert survey.coordinate_sigma(3.0, 1, 2) == pytest.approx(3.0)     # sqrt(1 / 1)
    assert survey.coordinate_sigma(2.0, 4, 7) == pytest.approx(2.0 * math.sqrt(4 / 5))
    pos = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    sources = [(pos, 2, 1.0, 1.0)]
    assert survey.weighted_scale_sigma(sources, [None]) is None
    assert survey.weighted_scale_sigma([(np.ones((3, 3)), 3, 1.0, 1.0)], [0.5]) is None      # no spread
    # one source: S = n x mean |x - c|^2 = 2 x 1 = 2; s_rel = sqrt(w^2 s^2 S) / (w S) = s / sqrt(2)
    assert survey.weighted_scale_sigma(sources, [0.3]) == pytest.approx(0.3 / math.sqrt(2))
    # two sources, weights 1 and 4, n 2 and 1: centroid (1 x 2 x (1, 0, 0) + 4 x 1 x (4, 0, 0)) / 6 = (3, 0, 0);
    # S_1 = 2 x mean(9, 1) = 10, S_2 = 1 x 1 = 1; s_rel = sqrt(1 x 0.3^2 x 10 + 16 x 0.1^2 x 1) / (10 + 4)
    two = [(pos, 2, 1.0, 1.0), (np.array([[4.0, 0.0, 0.0]]), 1, 1.0, 4.0)]
    assert survey.weighted_scale_sigma(two, [0.3, 0.1]) == pytest.approx(math.sqrt(0.9 + 0.16) / 14)
    # the fit's parameters charged to the source of the larger w x n: (1 x 2) < (4 x 1)
    assert survey.source_sigmas([(pos, 2, 1.0, 1.0), (pos, 3, 1.0, 4.0)], 7) == pytest.approx(
        [1.0 * math.sqrt(2 / 6), 1.0 * math.sqrt(3 / 2)])
    assert survey.source_sigmas([(pos, 3, 1.0, 4.0), (pos, 2, 1.0, 1.0)], 7) == pytest.approx(
        [1.0 * math.sqrt(3 / 2), 1.0 * math.sqrt(2 / 6)])
    # w x n 6 against 4 (not w / n: 1/6 against 1): the first source rules
    assert survey.source_sigmas([(pos, 6, 1.0, 1.0), (pos, 2, 1.0, 2.0)], 7) == pytest.approx(
        [1.0 * math.sqrt(6 / 11), 1.0 * math.sqrt(2 / 6)])
    # a spread sum under 1 is still a spread: S = 2 x 0.01 = 0.02, s_rel = 0.3 / sqrt(0.02)
    small = [(np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]]), 2, 1.0, 1.0)]
    assert survey.weighted_scale_sigma(small, [0.3]) == pytest.approx(0.3 / math.sqrt(0.02))


def _square(shift=(100.0, 200.0, 30.0)):
    """4 centres (+-3, 0, 0), (0, +-4, 0) about `shift`: RMS distance from their mean sqrt(12.5)."""
    return np.array([[3.0, 0, 0], [-3.0, 0, 0], [0, 4.0, 0], [0, -4.0, 0]]) + np.asarray(shift)


@pytest.mark.parametrize("rotation, p", [("full", 7), ("about z only (one heading)", 5)])
def test_alignment_uncertainty_of_gps_by_hand(rotation, p):
    """10 GPS inliers, RMS 2 m: sigma = 2 sqrt(10 / (30 - p)); position sigma sqrt(3 / 10);
    s_rel = sigma / sqrt(S), S = 10 x 12.5 (the 4 centres stand for the 10 positions)."""
    from jaxnerf_grid.export import survey

    geo = {"units": "metres", "source": "gps", "rotation": rotation, "gps": {"inliers": 10, "rms_m": 2.0}}
    got = survey.alignment_uncertainty(geo, "metres", _square())
    sigma = 2.0 * math.sqrt(10 / (30 - p))
    _close(got, {"relative_scale": sigma / math.sqrt(125.0), "position_m": sigma * math.sqrt(0.3), "from": "gps",
                 "n": 10, "rms_m": 2.0, "spread_m": math.sqrt(12.5), "centroid": [100.0, 200.0, 30.0],
                 "sigma_per_coordinate_m": sigma})


def test_alignment_uncertainty_of_gps_and_control_points_by_hand():
    """GPS (10 inliers, RMS 2 m, weight 1/9) and 4 control points (RMS 0.04 m, weight 400):
    the control points rule (400 x 4 > 10 / 9), so the 7 parameters are charged to them:
    sigma_c = 0.04 sqrt(4 / 5), sigma_g = 2 sqrt(10 / 30); position from the control points,
    sigma_c sqrt(3 / 4); s_rel by the weighted formula, worked out here."""
    from jaxnerf_grid.export import survey

    ctrl = np.array([[100.0, 200.0, 20.0], [106.0, 200.0, 20.0], [100.0, 208.0, 20.0], [104.0, 204.0, 23.0]])
    geo = {"units": "metres", "source": "gps+gcp", "rotation": "full", "gps": {"inliers": 10, "rms_m": 2.0},
           "gcp": {"control": {"rms_m": 0.04, "residuals": [{}] * 4, "points_m": ctrl.tolist()}}}
    got = survey.alignment_uncertainty(geo, "metres", _square())
    sg, sc = 2.0 * math.sqrt(10 / 30), 0.04 * math.sqrt(4 / 5)
    wg, wc = 1 / 9.0, 1 / 0.05**2
    centroid = (wg * 10 * np.array([100.0, 200.0, 30.0]) + wc * 4 * ctrl.mean(0)) / (wg * 10 + wc * 4)
    s_g = 10 * np.mean(np.sum((_square() - centroid) ** 2, axis=1))
    s_c = 4 * np.mean(np.sum((ctrl - centroid) ** 2, axis=1))
    rel = math.sqrt(wg**2 * sg**2 * s_g + wc**2 * sc**2 * s_c) / (wg * s_g + wc * s_c)
    _close(got, {"relative_scale": rel, "position_m": sc * math.sqrt(3 / 4), "from": "gps+gcp", "n": 10,
                 "rms_m": 2.0, "spread_m": math.sqrt(12.5), "centroid": [100.0, 200.0, 30.0],
                 "sigma_per_coordinate_m": sg, "control_points": 4})
    # control points without residuals, points or an RMS are no source; GPS without inliers,
    # an RMS or centres neither
    for control in ({"rms_m": 0.04, "residuals": [], "points_m": ctrl.tolist()},
                    {"rms_m": 0.04, "residuals": [{}] * 4, "points_m": []},
                    {"rms_m": None, "residuals": [{}] * 4, "points_m": ctrl.tolist()}):
        got = survey.alignment_uncertainty({**geo, "gcp": {"control": control}}, "metres", _square())
        assert "control_points" not in got
        assert got["position_m"] == pytest.approx(2.0 * math.sqrt(10 / 23) * math.sqrt(0.3))
    for gps, centres in (({"inliers": 0, "rms_m": 2.0}, _square()), ({"inliers": 10, "rms_m": None}, _square()),
                         ({"inliers": 10, "rms_m": 2.0}, np.zeros((0, 3)))):
        got = survey.alignment_uncertainty({**geo, "gps": gps}, "metres", centres)
        assert "n" not in got and "sigma_per_coordinate_m" not in got
        sc7 = 0.04 * math.sqrt(4 / 5)
        assert got["position_m"] == pytest.approx(sc7 * math.sqrt(3 / 4)) and got["control_points"] == 4
        # control points alone: s_rel = sigma / sqrt(S), S about their own mean
        s_c = 4 * np.mean(np.sum((ctrl - ctrl.mean(0)) ** 2, axis=1))
        assert got["relative_scale"] == pytest.approx(sc7 / math.sqrt(s_c))


def test_alignment_uncertainty_of_the_other_records():
    from jaxnerf_grid.export import survey

    assert survey.alignment_uncertainty(GEO, "unknown", _square()) == {"relative_scale": None, "position_m": None,
                                                                      "from": "units unknown"}
    assert survey.alignment_uncertainty(None, "metres", _square()) == {
        "relative_scale": 0.0, "position_m": 0.0, "from": "the dataset's recorded metric scale (exact)"}
    bar = {"units": "metres", "source": "scale_bar", "scale_bar": {"relative_sigma": 0.002}}
    assert survey.alignment_uncertainty(bar, "metres", _square()) == {"relative_scale": 0.002, "position_m": None,
                                                                     "from": "scale_bar"}
    assert survey.alignment_uncertainty({**bar, "scale_bar": None}, "metres", _square())["relative_scale"] is None
    # a record with no usable source: nothing known, the centres' spread still recorded
    got = survey.alignment_uncertainty({"units": "metres", "source": "gps", "gps": {}}, "metres", _square())
    assert got == {"relative_scale": None, "position_m": None, "from": "gps", "centroid": [100.0, 200.0, 30.0]}
    assert "centroid" not in survey.alignment_uncertainty({"units": "metres", "source": "gps"}, "metres",
                                                          np.zeros((0, 3)))
    # one camera centre is a source too (no spread: no scale error known; the position is)
    one = survey.alignment_uncertainty({"units": "metres", "source": "gps", "gps": {"inliers": 10, "rms_m": 2.0}},
                                       "metres", np.array([[1.0, 2.0, 3.0]]))
    assert one["n"] == 10 and one["spread_m"] == 0.0 and one["relative_scale"] is None
    assert one["position_m"] == pytest.approx(2.0 * math.sqrt(10 / 23) * math.sqrt(0.3))


def test_with_sigma_by_hand():
    from jaxnerf_grid.export import survey

    al = {"relative_scale": 0.01, "position_m": 0.6}
    assert survey.with_sigma(None, 0.1, al) is None
    assert survey.with_sigma(-30.0, 0.4, al) == pytest.approx({"value": -30.0, "sigma": 0.5, "fit_sigma": 0.4})
    assert survey.with_sigma(30.0, 0.4, al, lever=40.0) == pytest.approx(
        {"value": 30.0, "sigma": math.sqrt(0.16 + 0.16), "fit_sigma": 0.4})
    assert survey.with_sigma(30.0, 0.4, al, position=True)["sigma"] == pytest.approx(math.sqrt(0.09 + 0.16 + 0.36))
    for missing in ({"relative_scale": 0.01}, {"relative_scale": 0.01, "position_m": None}):
        assert survey.with_sigma(30.0, 0.4, missing, position=True)["sigma"] == pytest.approx(0.5)
    got = survey.with_sigma(np.float32(2.5), np.float32(0.25), {"relative_scale": None})
    assert got == {"value": 2.5, "sigma": None, "fit_sigma": 0.25} and type(got["value"]) is float
    assert type(got["fit_sigma"]) is float


def test_pyproj_crs_names_the_key_and_the_crs():
    from jaxnerf_grid.export import survey

    assert survey.pyproj_crs("EPSG:32632").to_epsg() == 32632
    with pytest.raises(DataError, match=r"^georeference\.crs = 'EPSG:999999': pyproj does not know it \("):
        survey.pyproj_crs("EPSG:999999")


def test_las_header_offsets_scales_colours_and_compound_crs(tmp_path):
    """Offsets = the points' minimum floored to the metre, scales 1 mm, colours x 65535 rounded
    (clipped to [0, 1]), the compound CRS named 'horizontal + vertical'; no temporary file left."""
    import laspy
    import pyproj

    from jaxnerf_grid.export import survey

    pts = np.array([[465000.7, 5247000.2, -3.5], [465010.25, 5247003.0, 12.0]])
    cols = np.array([[-0.5, 0.5, 1.5], [0.25, 1.0, 0.0]])
    survey.write_las(tmp_path / "p.las", pts, cols, "EPSG:32632", pyproj.CRS.from_epsg(5773))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.las"]
    las = laspy.read(tmp_path / "p.las")
    np.testing.assert_array_equal(las.header.offsets, [465000.0, 5247000.0, -4.0])
    np.testing.assert_array_equal(las.header.scales, [0.001, 0.001, 0.001])
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), pts, atol=5e-4 + 1e-9)
    np.testing.assert_array_equal(np.column_stack([las.red, las.green, las.blue]),
                                  [[0, 32768, 65535], [16384, 65535, 0]])
    crs = las.header.parse_crs()
    assert crs.is_compound and crs.name == "WGS 84 / UTM zone 32N + EGM96 height"
    assert [c.to_epsg() for c in crs.sub_crs_list] == [32632, 5773]
    assert str(las.header.version) == "1.4" and las.header.point_format.id == 7
    # float32 colours (what export hands on) rounded in doubles: 0.6700618 x 65535 = 43912.5... -> 43913
    # (in float32 arithmetic 43912)
    c32 = np.array([[0.6700618, 0.5923629, 0.54545665]], np.float32)
    survey.write_las(tmp_path / "c.las", pts[:1], c32)
    got = laspy.read(tmp_path / "c.las")
    assert [int(got.red[0]), int(got.green[0]), int(got.blue[0])] == [round(float(v) * 65535) for v in c32[0]]
    assert [round(float(v) * 65535) for v in c32[0]] == [43913, 38821, 35747]
    survey.write_las(tmp_path / "e.las", np.zeros((0, 3)), np.zeros((0, 3)))
    empty = laspy.read(tmp_path / "e.las")
    assert len(empty.points) == 0
    np.testing.assert_array_equal(empty.header.offsets, [0.0, 0.0, 0.0])


def test_ply_double_holds_the_doubles_colours_faces_and_comments(tmp_path):
    import plyfile

    from jaxnerf_grid.export import survey

    pts = np.array([[465000.123456, 5247000.654321, 401.0009], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    cols = np.array([[-0.1, 0.5, 1.2], [0.2, 0.0, 1.0], [1.0, 1.0, 1.0]])
    survey.write_ply_double(tmp_path / "m.ply", pts, cols, np.array([[0, 1, 2], [2, 1, 0]]),
                            comments=("crs:  EPSG:32632\nline two", "T\u00fcr"))
    ply = plyfile.PlyData.read(str(tmp_path / "m.ply"))
    assert ply.comments == ["crs: EPSG:32632 line two", "T\\xfcr"]
    assert ply.text is False and ply.byte_order == "<"
    v = ply["vertex"]
    assert [p.name for p in v.properties] == ["x", "y", "z", "red", "green", "blue"]
    assert v["x"].dtype == np.float64
    np.testing.assert_array_equal(np.column_stack([v["x"], v["y"], v["z"]]), pts)
    np.testing.assert_array_equal(np.column_stack([v["red"], v["green"], v["blue"]]),
                                  [[0, 128, 255], [51, 0, 255], [255, 255, 255]])
    assert [list(f) for f in ply["face"]["vertex_indices"]] == [[0, 1, 2], [2, 1, 0]]
    # float32 colours rounded in doubles: 0.6098039 x 255 = 155.499... -> 155 (156 in float32 arithmetic)
    survey.write_ply_double(tmp_path / "c.ply", pts[:1], np.array([[0.6098039, 0.8686274, 0.76666665]], np.float32),
                            np.zeros((0, 3)))
    v = plyfile.PlyData.read(str(tmp_path / "c.ply"))["vertex"]
    assert [int(v["red"][0]), int(v["green"][0]), int(v["blue"][0])] == [155, 221, 195]


# --------------------------------------------------------------------------- export/fuse.py


def test_project_by_hand_for_an_upright_and_a_turned_camera():
    """Camera at c = (1, 2, 3) looking down -z (c2w = [I | c], 3 x 4): the point c + (0.5, 0.25,
    -2) is 2 ahead, u = cx + fx 0.25 = 10 + 8 x 0.25, v = cy - fy 0.125 = 6 - 12 x 0.125.
    Turned 90 degrees about y (its -z axis along world -x): c + (-2, 0.5, 0.25) is 2 ahead at
    camera (x, y) = (-0.25, 0.5) -> u = 10 - 8 x 0.125 = 9, v = 6 - 12 x 0.25 = 3; a point behind
    gets z < 0."""
    from jaxnerf_grid.export import fuse

    intr = (8.0, 12.0, 10.0, 6.0)
    c2w = np.hstack([np.eye(3), [[1.0], [2.0], [3.0]]])
    u, v, z = fuse.project(np.array([[1.5, 2.25, 1.0], [1.0, 2.0, 5.0]]), c2w, intr)
    np.testing.assert_allclose(u[:1], [12.0])
    np.testing.assert_allclose(v[:1], [4.5])
    np.testing.assert_allclose(z, [2.0, -2.0])
    turn = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])   # columns: the camera's axes
    c2w4 = np.eye(4)
    c2w4[:3, :3], c2w4[:3, 3] = turn, [1.0, 2.0, 3.0]
    u, v, z = fuse.project(np.array([[-1.0, 2.5, 3.25]]), c2w4, intr)
    np.testing.assert_allclose([u[0], v[0], z[0]], [9.0, 3.0, 2.0])


def _one_camera(depth, opacity, fx=4.0):
    """A 3 x 4 (rows x columns) camera at the origin looking down -z, fx = `fx`, fy = 2 fx,
    principal point (2, 1.5): the pixel (row r, column c) holds the points x = (c + 0.5 - 2) z / fx,
    y = -(r + 0.5 - 1.5) z / (2 fx), at z-depth z."""
    return {"c2w": np.eye(4), "intrinsics": (fx, 2 * fx, 2.0, 1.5), "depth": np.asarray(depth, np.float32),
            "opacity": np.asarray(opacity, np.float32)}


def _at(r, c, z, fx=4.0):
    return [(c + 0.5 - 2.0) * z / fx, -(r + 0.5 - 1.5) * z / (2 * fx), -z]


def test_confirmations_counted_by_hand_at_each_boundary():
    """One confirming camera (index 1) of depth 2.5 everywhere; the tolerance is 1 pixel at the
    point's depth z, z / fx (fx = 4, not fy = 8). Points (source 0): on the surface (1); at z = 2:
    |d - z| = 0.5 = tol exactly (1; 0 with fy's 0.25); at z = 1.99: 0.51 > 0.4975 (0); in the last
    column and row (1), a column or row past the image on either side (0), behind the camera (0),
    on a pixel of opacity exactly 0.5 (1) and 0.49 (0), on a pixel of depth nan (0); from the
    camera's own view (source 1) (0)."""
    from jaxnerf_grid.export import fuse

    depth = np.full((3, 4), 2.5)
    opacity = np.ones((3, 4))
    opacity[0, 0], opacity[0, 1] = 0.5, 0.49
    depth[2, 0] = np.nan
    cams = [_one_camera(np.zeros((3, 4)), np.zeros((3, 4))), _one_camera(depth, opacity)]
    pts = [_at(1, 1, 2.5), _at(1, 1, 2.0), _at(1, 1, 1.99), _at(2, 3, 2.5), _at(1, 4, 2.5), _at(3, 1, 2.5),
           _at(-1, 1, 2.5), _at(1, -1, 2.5), [0.0, 0.0, 2.5], _at(0, 0, 2.5), _at(0, 1, 2.5), _at(2, 0, 2.5),
           _at(1, 2, 2.5)]
    source = [0] * 12 + [1]
    counts = fuse.confirmations(np.array(pts), np.array(source), cams)
    np.testing.assert_array_equal(counts, [1, 1, 0, 1, 0, 0, 0, 0, 0, 1, 0, 0, 0])
    # a wider tolerance (2 pixels: 0.995) takes the point at 1.99; a stricter opacity drops 0.5
    counts = fuse.confirmations(np.array(pts), np.array(source), cams, min_opacity=0.6, tol_pixels=2.0)
    np.testing.assert_array_equal(counts, [1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0])
    assert counts.dtype.kind == "i"
    # a surface nearer than one unit (the normalised scene's cameras are 2-4 units away): counted
    near = [_one_camera(np.zeros((3, 4)), np.zeros((3, 4))), _one_camera(np.full((3, 4), 0.5), np.ones((3, 4)))]
    np.testing.assert_array_equal(fuse.confirmations(np.array([_at(1, 1, 0.5), _at(2, 2, 0.25)]), np.array([0, 0]),
                                                     near), [1, 0])


def test_fuse_keeps_points_confirmed_by_min_views_and_their_colours():
    """Three cameras at the origin (the same view), depth 2: a point of view 0 on the surface is
    confirmed by views 1 and 2 (2), one of view 1 off it by none; min_views 2 keeps the first
    only, 3 none, 0 both; colours follow their points; float32 out."""
    from jaxnerf_grid.export import fuse

    cams = [_one_camera(np.full((3, 4), 2.0), np.ones((3, 4))) for _ in range(3)]
    parts = [(np.array([_at(1, 1, 2.0)]), np.array([[0.1, 0.2, 0.3]])),
             (np.array([_at(1, 2, 3.0)]), np.array([[0.4, 0.5, 0.6]])), (np.zeros((0, 3)), np.zeros((0, 3)))]
    pts, cols, stats = fuse.fuse(parts, cams, min_views=2)
    assert pts.dtype == np.float32 and cols.dtype == np.float32
    np.testing.assert_allclose(pts, [_at(1, 1, 2.0)], rtol=1e-6)
    np.testing.assert_allclose(cols, [[0.1, 0.2, 0.3]], rtol=1e-6)
    assert stats == {"lifted": 2, "kept": 1}
    assert fuse.fuse(parts, cams, min_views=3)[2] == {"lifted": 2, "kept": 0}
    pts, cols, stats = fuse.fuse(parts, cams, min_views=0)
    assert stats == {"lifted": 2, "kept": 2}
    np.testing.assert_allclose(cols, [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], rtol=1e-6)
    # options handed on: a 0.49-opaque surface confirms nothing at min_opacity 0.5, all at 0.4
    dim = [_one_camera(np.full((3, 4), 2.0), np.full((3, 4), 0.49)) for _ in range(3)]
    assert fuse.fuse(parts, dim, min_views=1)[2]["kept"] == 0
    assert fuse.fuse(parts, dim, min_views=1, min_opacity=0.4)[2]["kept"] == 1
    # the tolerance handed on: z = 2.7 is 0.7 from the surface, past 1 pixel (0.675), within 2 (1.35)
    far = [(np.array([_at(1, 1, 2.7)]), np.zeros((1, 3)))] + parts[1:]
    assert fuse.fuse(far, cams, min_views=1)[2]["kept"] == 0
    # (and view 1's point at z = 3, 1 from the surface: within 2 pixels there, 1.5)
    assert fuse.fuse(far, cams, min_views=1, tol_pixels=2.0)[2]["kept"] == 2
    empty = fuse.fuse([], cams)
    assert empty[0].shape == (0, 3) and empty[1].shape == (0, 3) and empty[2] == {"lifted": 0, "kept": 0}
    assert empty[0].dtype == np.float32 and empty[1].dtype == np.float32


# --------------------------------------------------------------------------- export/mesh.py


def test_grid_spec_by_hand():
    """Box [0, 0, 0]-[1, 0.3, 0.25] at resolution 4: h = 0.25; voxels ceil(4, 1.2, 1) = (4, 2, 1)
    (0.25 / 0.25 is exactly 1: no extra voxel), nodes (5, 3, 2); origin = centre - h voxels / 2 =
    (0, 0.15 - 0.25, 0.125 - 0.125) = (0, -0.1, 0). A flat or inverted box, resolution 1: refused."""
    from jaxnerf_grid.export import mesh

    origin, h, shape = mesh.grid_spec([0.0, 0.0, 0.0], [1.0, 0.3, 0.25], 4)
    assert h == 0.25 and shape == (5, 3, 2) and all(type(v) is int for v in shape)
    np.testing.assert_allclose(origin, [0.0, -0.1, 0.0], atol=1e-15)
    origin, h, shape = mesh.grid_spec([0.0, 0.0, 0.0], [2.0, 2.0, 2.0], 2)
    assert h == 1.0 and shape == (3, 3, 3)
    for lo, hi, res in (([0, 0, 0], [1, 1, 0], 4), ([0, 0, 0], [1, -1, 1], 4), ([0, 0, 0], [1, 1, 1], 1)):
        with pytest.raises(ValueError, match="grid_spec: need resolution >= 2 and a box of positive size"):
            mesh.grid_spec(lo, hi, res)


def test_grid_points_are_ij_indexed_float32():
    from jaxnerf_grid.export import mesh

    p = mesh.grid_points([1.0, 2.0, 3.0], 0.5, (2, 3, 4))
    assert p.shape == (2, 3, 4, 3) and p.dtype == np.float32
    np.testing.assert_array_equal(p[1, 2, 3], [1.5, 3.0, 4.5])
    np.testing.assert_array_equal(p[0, 1, 0], [1.0, 2.5, 3.0])


def test_density_threshold_refuses_an_opacity_outside_0_1():
    from jaxnerf_grid.export import mesh

    for bad in (0.0, 1.0, -0.1, 1.5):
        with pytest.raises(ValueError, match=r"^opacity must be in \(0, 1\), got "):
            mesh.density_threshold(0.1, bad)
    assert mesh.density_threshold(2.0, 0.75) == pytest.approx(math.log(4.0) / 2.0)


def _cube_density():
    """A 4 x 4 x 4 node grid, density 1 at the 2 x 2 x 2 inner nodes, 0 elsewhere."""
    d = np.zeros((4, 4, 4), np.float32)
    d[1:3, 1:3, 1:3] = 1.0
    return d


def test_extract_mesh_of_a_cube_by_hand():
    """Level 0.5 on the inner 2 x 2 x 2 nodes of a grid at origin (10, 20, 30), h = 2: the surface
    lies halfway between nodes 0 and 1 and between 2 and 3, at 10 + 2 x (0.5, 2.5) along x: every
    vertex coordinate is in {11, 15} x {21, 25} x {31, 35} on at least one axis, all within
    [11, 15] x [21, 25] x [31, 35]; the faces are wound counter-clockwise seen from outside (the
    signed volume is positive) and the normals point out of the cube's centre (13, 23, 33)."""
    from jaxnerf_grid.export import mesh

    verts, faces, normals = mesh.extract_mesh(_cube_density(), 0.5, [10.0, 20.0, 30.0], 2.0)
    assert faces.dtype == np.int64 and verts.dtype == np.float64 and normals.dtype == np.float64
    np.testing.assert_allclose(verts.min(0), [11.0, 21.0, 31.0], atol=1e-9)
    np.testing.assert_allclose(verts.max(0), [15.0, 25.0, 35.0], atol=1e-9)
    tri = verts[faces] - [13.0, 23.0, 33.0]
    volume = np.sum(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))) / 6
    assert volume > 0
    assert np.all(np.sum(normals * (verts - [13.0, 23.0, 33.0]), axis=1) > 0)
    assert mesh.is_closed(faces)


def test_extract_mesh_at_the_grids_border_nan_inf_and_no_surface():
    """Dense nodes on the grid's border are closed by the zero padding (the surface half a voxel
    outside the first node: origin - h / 2); nan counts as empty, +inf as dense; a level at or
    above the maximum or not finite gives empty arrays (at the maximum, skimage raised a
    RuntimeError before: export_run's "no surface in the box" never came)."""
    from jaxnerf_grid.export import mesh

    d = np.ones((3, 3, 3), np.float32)
    verts, faces, _ = mesh.extract_mesh(d, 0.5, [0.0, 0.0, 0.0], 1.0)
    np.testing.assert_allclose(verts.min(0), [-0.5, -0.5, -0.5], atol=1e-9)
    np.testing.assert_allclose(verts.max(0), [2.5, 2.5, 2.5], atol=1e-9)
    assert mesh.is_closed(faces)
    d = _cube_density()
    d[1, 1, 1], d[2, 2, 2] = np.nan, np.inf
    verts, faces, _ = mesh.extract_mesh(d, 0.25, [0.0, 0.0, 0.0], 1.0)
    assert np.isfinite(verts).all() and len(faces) > 0
    # at level 0.25 the nan node, empty, has the surface a quarter voxel from it, on its edges
    # towards its dense neighbours (0 -> 1 crosses 0.25 at t = 0.25); dense, three quarters
    near_nan = np.linalg.norm(verts - [1.0, 1.0, 1.0], axis=1)
    assert near_nan.min() == pytest.approx(0.25, abs=1e-6)
    for level in (1.5, 1.0, np.nan, np.inf):       # 1.0: exactly the maximum, no crossing
        v, f, n = mesh.extract_mesh(_cube_density(), level, [0.0, 0.0, 0.0], 1.0)
        assert v.shape == (0, 3) and f.shape == (0, 3) and n.shape == (0, 3) and f.dtype == np.int64
    v, f, _ = mesh.extract_mesh(_cube_density(), 0.999, [0.0, 0.0, 0.0], 1.0)
    assert len(f) > 0


def test_extract_mesh_drops_degenerate_triangles():
    """Densities 0, 1, 2 at level 1 put vertices exactly on nodes, where marching cubes makes
    triangles with two corners at one point (skimage keeps them unless asked not to): none of
    the returned faces has two vertices at the same position (checked here by brute force)."""
    from jaxnerf_grid.export import mesh

    d = np.random.default_rng(0).integers(0, 3, (6, 6, 6)).astype(np.float32)
    verts, faces, _ = mesh.extract_mesh(d, 1.0, [0.0, 0.0, 0.0], 1.0)
    t = verts[faces]
    same = [np.array_equal(a, b) or np.array_equal(b, c) or np.array_equal(a, c) for a, b, c in t]
    assert len(faces) > 100 and not any(same)


def _tetra(offset=0):
    """A closed tetrahedron's faces (4), its vertices numbered from `offset`."""
    return np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]]) + offset


def test_face_components_and_is_closed_by_hand():
    from jaxnerf_grid.export import mesh

    faces = np.vstack([_tetra(0), _tetra(4), [[8, 9, 10]]])
    labels = mesh.face_components(faces, 11)
    assert len(np.unique(labels)) == 3
    assert len(set(labels[:4])) == 1 and len(set(labels[4:8])) == 1 and labels[0] != labels[4] != labels[8]
    # a chain joined only through each face's last vertex: 0-1-2, 2-3-4 share vertex 2
    assert len(set(mesh.face_components(np.array([[0, 1, 2], [2, 3, 4], [5, 6, 4]]), 7))) == 1
    assert len(set(mesh.face_components(np.array([[0, 1, 2], [3, 4, 0]]), 5))) == 1
    empty = mesh.face_components(np.zeros((0, 3), np.int64), 0)
    assert empty.shape == (0,) and empty.dtype.kind == "i"
    np.testing.assert_array_equal(mesh.face_components(np.array([[0, 1, 2]]), 3), [0])      # one face
    assert mesh.is_closed(_tetra()) and mesh.is_closed(np.vstack([_tetra(0), _tetra(4)]))
    assert not mesh.is_closed(_tetra()[:3]) and not mesh.is_closed(np.zeros((0, 3)))
    assert not mesh.is_closed(np.vstack([_tetra(), _tetra()[:1]]))   # an edge shared by three faces


def test_remove_small_components_by_hand():
    """A tetrahedron (4 faces), a second one (4) and a lone triangle (1): F = 9. min_fraction
    4 / 9 keeps both tetrahedra (4 >= 4), drops the triangle; 4.01 / 9 keeps nothing. The
    kept vertices are renumbered in order; the per-vertex extras follow."""
    from jaxnerf_grid.export import mesh

    verts = np.arange(33, dtype=np.float64).reshape(11, 3)
    faces = np.vstack([_tetra(0), [[8, 9, 10]], _tetra(4)])
    extra = np.arange(11) * 10
    v, f, (e,), stats = mesh.remove_small_components(verts, faces, 4 / 9, (extra,))
    np.testing.assert_array_equal(v, verts[:8])
    np.testing.assert_array_equal(f, np.vstack([_tetra(0), _tetra(4)]))
    np.testing.assert_array_equal(e, extra[:8])
    assert stats == {"components": 3, "kept_components": 2, "kept_face_fraction": pytest.approx(8 / 9),
                     "kept_vertex_fraction": pytest.approx(8 / 11)}
    # the first tetrahedron's vertices unused (a floater of its own): the kept ones renumbered from 0
    v, f, _, stats = mesh.remove_small_components(verts, np.vstack([_tetra(4), _tetra(0)[:1]]), 0.5)
    np.testing.assert_array_equal(f, _tetra(0))
    np.testing.assert_array_equal(v, verts[4:8])
    assert stats["kept_components"] == 1 and stats["kept_vertex_fraction"] == pytest.approx(4 / 11)
    _, f, _, stats = mesh.remove_small_components(verts, faces, 4.01 / 9)
    assert len(f) == 0 and stats["kept_components"] == 0 and stats["kept_face_fraction"] == 0.0
    v, f, extra_out, stats = mesh.remove_small_components(verts, np.zeros((0, 3)), 0.5, (extra,))
    assert v is verts and f.shape == (0, 3) and extra_out[0] is extra
    assert stats == {"components": 0, "kept_components": 0, "kept_face_fraction": 1.0, "kept_vertex_fraction": 1.0}


# --------------------------------------------------------------------------- export/geoid.py


def test_as_written_and_the_pipeline_text():
    from jaxnerf_grid.export import geoid

    assert geoid.as_written(None) == geoid.as_written({}) == geoid.as_written({"source": "gps"}) == \
        "ellipsoidal (GPS heights as written)"
    for source in ("gcp", "gps+gcp"):
        assert geoid.as_written({"source": source}) == "as the control points' Z (the GCP file's heights as written)"
    assert geoid.pipeline_text(Path("/g/egm.gtx")) == (
        '+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad +step +proj=vgridshift '
        '+grids="/g/egm.gtx" +multiplier=-1 +step +proj=unitconvert +xy_in=rad +xy_out=deg')


def test_open_grid_refusals_name_the_file(tmp_path):
    from jaxnerf_grid.export import geoid

    with pytest.raises(DataError, match=r"missing\.gtx: export\.geoid does not exist \(a geoid grid PROJ reads"):
        geoid.open_grid(tmp_path / "missing.gtx")
    (tmp_path / "folder.gtx").mkdir()
    with pytest.raises(DataError, match=r"folder\.gtx: export\.geoid is not a file \(a geoid grid"):
        geoid.open_grid(tmp_path / "folder.gtx")
    quoted = tmp_path / 'a"b.gtx'
    quoted.write_bytes(b"x")
    with pytest.raises(DataError, match=r'a"b\.gtx: export\.geoid: a path with a double quote cannot be passed'):
        geoid.open_grid(quoted)
    bad = tmp_path / "notes.gtx"
    bad.write_text("not a grid\n")
    with pytest.raises(DataError, match=r"notes\.gtx: export\.geoid: PROJ cannot read this file as a geoid grid "
                                        r"\(GTX or GeoTIFF\)$"):
        geoid.open_grid(bad)


def test_open_grid_takes_a_relative_path_and_undulation_names_the_first_point_outside(tmp_path, monkeypatch):
    """A path relative to the working folder is made absolute (PROJ would look it up in its
    own search path); N of the linear grid at (47, 8): A + 47 B + 8 C = 51.5; two of three
    points outside: the first outside named, to 6 places."""
    from jaxnerf_grid.export import geoid
    from tests.export.test_geoid import linear_n, site_grid

    site_grid(tmp_path / "site.gtx", linear_n)
    monkeypatch.chdir(tmp_path)
    grid = geoid.open_grid("site.gtx")
    np.testing.assert_allclose(geoid.undulation(grid, "site.gtx", np.array([47.0, 48.0]), np.array([8.0, 9.0])),
                               [30 + 0.5 * 47 - 0.25 * 8, 30 + 0.5 * 48 - 0.25 * 9], atol=1e-5)
    assert geoid.undulation(grid, "site.gtx", 47.0, 8.0).shape == (1,)
    with pytest.raises(DataError) as err:
        geoid.undulation(grid, "site.gtx", np.array([47.0, 60.1234567, 61.0]), np.array([8.0, 8.5, 8.5]))
    assert str(err.value) == ("site.gtx: export.geoid does not cover 2 of the 3 points (e.g. latitude 60.123457, "
                              "longitude 8.500000); use a grid that covers the site")


def test_orthometric_of_no_points_and_leaves_its_input(tmp_path):
    from jaxnerf_grid.export import geoid
    from tests.export.test_geoid import CRS, linear_n, site_grid

    path = site_grid(tmp_path / "site.gtx", linear_n)
    grid = geoid.open_grid(path)
    p, n = geoid.orthometric(np.zeros((0, 3)), CRS, grid, path)
    assert p.shape == (0, 3) and n.shape == (0,)
    points = np.array([[465000.0, 5247000.0, 400.0]])
    got, n = geoid.orthometric(points, CRS, grid, path)
    assert points[0, 2] == 400.0 and got[0, 2] == pytest.approx(400.0 - n[0])
    # whole-metre coordinates given as integers: the heights still become H = h - N (floats)
    got_int, n_int = geoid.orthometric(np.array([[465000, 5247000, 400]]), CRS, grid, path)
    assert got_int.dtype == np.float64 and got_int[0, 2] == pytest.approx(400.0 - n[0]) and n_int[0] == n[0]


def test_vertical_record_and_crs_label_by_hand():
    import pyproj

    from jaxnerf_grid.export import geoid

    datum = pyproj.CRS.from_epsg(5773)
    assert geoid.crs_label(datum) == "EPSG:5773 EGM96 height"
    local = pyproj.crs.VerticalCRS(name="Site height", datum="EGM96 geoid")       # no EPSG code
    assert local.to_epsg() is None and geoid.crs_label(local) == "Site height"
    assert geoid.vertical_record(Path("/g/egm.gtx"), 47.25, (47.0, 47.5), datum=datum) == {
        "reference": "above the geoid of egm.gtx, N = 47.250 m at the base (EPSG:5773 EGM96 height)",
        "geoid_grid": str(Path("/g/egm.gtx")), "n_at_base_m": 47.25, "n_range_m": [47.0, 47.5],
        "vertical_crs": "EPSG:5773 EGM96 height"}
    assert geoid.vertical_record("/g/egm.gtx") == {"reference": "above the geoid of egm.gtx",
                                                  "geoid_grid": "/g/egm.gtx", "n_at_base_m": None,
                                                  "n_range_m": None, "vertical_crs": None}
    rec = geoid.vertical_record("/g/egm.gtx", np.float32(1.5), np.array([1.0, 2.0]))
    assert type(rec["n_at_base_m"]) is float and all(type(v) is float for v in rec["n_range_m"])


def test_vertical_crs_refusals_and_the_datum():
    from jaxnerf_grid.export import geoid

    assert geoid.vertical_crs(None, None) is None and geoid.vertical_crs(None, "g.gtx") is None
    assert geoid.vertical_crs("EPSG:5773", "g.gtx").to_epsg() == 5773
    with pytest.raises(DataError, match=r"^export\.vertical_crs = 'EPSG:5773' names the datum of heights above a "
                                        r"geoid: give export\.geoid \(the grid\) too$"):
        geoid.vertical_crs("EPSG:5773", None)
    with pytest.raises(DataError, match=r"^export\.vertical_crs = 'EPSG:999999': pyproj does not know it "
                                        r"\(e\.g\. EPSG:5773, EGM96 height\)$"):
        geoid.vertical_crs("EPSG:999999", "g.gtx")
    with pytest.raises(DataError, match=r"^export\.vertical_crs = 'EPSG:32632' is not a vertical CRS "
                                        r"\(WGS 84 / UTM zone 32N\); e\.g\. EPSG:5773, EGM96 height$"):
        geoid.vertical_crs("EPSG:32632", "g.gtx")


def test_export_cli_warns_in_one_line_when_the_model_lacks_the_lower_part(monkeypatch, tmp_path, capsys):
    """`jaxnerf-grid export` on a run whose mesh begins 10.79 m above the ground of a 30.53 m
    tower (more than 5 %): one warning naming the height (the CLI prints it as one line); at
    1.0 m none. The
    export itself is a stand-in returning measurements.json's keys the CLI reads."""
    from jaxnerf_grid import cli
    from jaxnerf_grid.export import run as run_lib

    def fake(low):
        return lambda *a, **k: {"units": "metres", "height": 30.53, "tilt": {"tilt_degrees": 0.77},
                                "survey": {"height": {"sigma": 0.29}, "base_centre": {"extrapolated": low}},
                                "mesh": {"vertices": 3, "faces": 1}, "points": {"count": 5}, "seconds": 1.0}

    monkeypatch.setattr(run_lib, "export_run", fake(10.79))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert cli.main(["export", "--run", str(tmp_path), "--quiet"]) == 0
    assert [str(w.message)[:52] for w in caught] == ["the model's tower begins 10.79 m above the ground (i"]
    monkeypatch.setattr(run_lib, "export_run", fake(1.0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert cli.main(["export", "--run", str(tmp_path), "--quiet"]) == 0
    assert caught == [] and "tower height 30.53 m +- 0.29 m" in capsys.readouterr().out


def test_project_of_a_point_in_the_cameras_plane_warns_nothing():
    """A camera at the origin looking down -z (c2w the identity), fx = fy = 10, centre (5, 4): a
    point at z-depth 2 projects by hand to (5 + 10 x 1 / 2, 4 - 10 x (-1) / 2) = (10, 9); points
    in the camera's plane (z-depth 0: x / 0 and 0 / 0) give inf and nan without a NumPy warning,
    which a user would see printed once per export (fuse mutants 22-25: np.errstate's arguments)."""
    import warnings

    from jaxnerf_grid.export import fuse

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        u, v, z = fuse.project(np.array([[1.0, -1.0, -2.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), np.eye(4),
                               (10.0, 10.0, 5.0, 4.0))
    np.testing.assert_array_equal(z, [2.0, 0.0, 0.0])
    assert (u[0], v[0]) == (10.0, 9.0)
    assert np.isinf(u[1]) and np.isnan(v[1]) and np.isnan(u[2]) and np.isnan(v[2])


def test_export_cli_passes_the_span_length_and_refuses_a_non_positive_one_in_one_line(monkeypatch, tmp_path, capsys):
    """`jaxnerf-grid export --span-length 320` hands 320.0 to the export; without it None. 0, -5
    and nan are refused with one line naming the flag, before the run folder is read (tmp_path
    holds no run: a refusal that came later would name the missing config instead)."""
    from jaxnerf_grid import cli
    from jaxnerf_grid.export import run as run_lib

    for bad in ("0", "-5", "nan"):
        assert cli.main(["export", "--run", str(tmp_path), "--quiet", "--span-length", bad]) == 1
        err = capsys.readouterr().err
        assert err == (f"jaxnerf-grid export: error: --span-length must be a positive number (export units), "
                       f"got {float(bad)!r}\n")
    seen = []

    def fake(*a, **k):
        seen.append(k.get("span_length"))
        return {"units": "metres", "height": 30.0, "mesh": {"vertices": 3, "faces": 1}, "points": {"count": 5},
                "seconds": 1.0}

    monkeypatch.setattr(run_lib, "export_run", fake)
    assert cli.main(["export", "--run", str(tmp_path), "--quiet", "--span-length", "320"]) == 0
    assert cli.main(["export", "--run", str(tmp_path), "--quiet"]) == 0
    assert seen == [320.0, None]


def test_arm_seeds_are_the_cross_arm_ends_across_the_line_by_hand():
    """A line along +y (psi = pi / 2: e_across = up x e_line = -x), the axis at (1, 2, 0): a level
    whose ends are (9.45, 2, 21.5) and (-7.45, 2, 21.5) gives the seeds (-8.45, 21.5) and
    (8.45, 21.5); a level without ends gives none."""
    levels = [{"height": 21.5, "span": 16.9, "axis": "a", "ends": [[9.45, 2.0, 21.5], [-7.45, 2.0, 21.5]]},
              {"height": 25.0, "span": 0.0, "axis": "a"}]
    seeds = export_run.arm_seeds(levels, [1.0, 2.0, 0.0], math.pi / 2, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(seeds, [[-8.45, 21.5], [8.45, 21.5]], atol=1e-12)


def _dark_line_photos():
    """Four 64 x 48 photos with a dark line across (so that detections exist), looking down -z
    from 15 m along y: a stand-in dataset for `_conductors`."""
    from types import SimpleNamespace

    images = np.full((4, 48, 64, 3), 0.8, np.float32)
    images[:, 20, 5:60] = 0.2
    c2w = np.tile(np.eye(4), (4, 1, 1))
    c2w[:, :3, 3] = [[0.0, -60.0 + 5 * k, 15.0] for k in range(4)]
    return SimpleNamespace(images=images, c2w=c2w, intrinsics=np.tile([50.0, 50.0, 32.0, 24.0], (4, 1)),
                           normalization=None)


def test_conductor_step_hands_the_span_length_and_the_arm_tips_to_find_spans_and_records_them(monkeypatch):
    """`_conductors` on four 64 x 48 photos with a dark line (so that detections exist), the
    spans' search replaced by a recorder: it receives span_length 320, the cross-arm ends as
    seeds by hand (line along +y, axis at the origin: e_across = -x) and the window SEED_WINDOW x
    the tower's height; measurements.json's record carries the span length and the seeds."""

    from jaxnerf_grid.export import conductors as cond

    ds = _dark_line_photos()
    meas = {"ground": {"normal": [0.0, 0.0, 1.0], "offset": 0.0, "clearance": 0.1}, "height": 30.0,
            # a diagonal footprint (two lowest legs): the line's direction comes from the arms' axes
            "footprint": {"axis_a": [0.6, 0.8, 0.0], "axis_b": [-0.8, 0.6, 0.0]}, "tilt": {"base": [0.0, 0.0, 0.0]},
            "cross_arms": {"axis_a": [1.0, 0.0, 0.0], "axis_b": [0.0, 1.0, 0.0],
                           "levels": [{"height": 17.5, "span": 14.0, "axis": "a",
                                       "ends": [[7.0, 0.0, 17.5], [-7.0, 0.0, 17.5]]}]}}
    calls = []

    def recorder(*args, **kwargs):
        calls.append(kwargs)
        return []

    monkeypatch.setattr(cond, "find_spans", recorder)
    swept = []
    monkeypatch.setattr(export_run.next_tower_lib, "next_tower", lambda *args: swept.append(args))
    out = export_run._conductors(ds, np.arange(4), meas, np.zeros((0, 3)), [-5.0, -5.0, 0.0], [5.0, 5.0, 31.0],
                                 "metres", None, False, span_length=320.0)
    assert len(calls) == 1
    assert calls[0]["span_length"] == 320.0 and calls[0]["next_tower"] is None   # a given span: no search
    np.testing.assert_allclose(calls[0]["seeds"], [[-7.0, 17.5], [7.0, 17.5]], atol=1e-12)
    np.testing.assert_allclose(calls[0]["seed_window"], np.array(export_run.SEED_WINDOW) * 30.0)
    assert out["span_length"] == 320.0 and out["seeds"] == [[-7.0, 17.5], [7.0, 17.5]]
    # the ground 2 m above the frame's zero at the axis
    meas["ground"] = {**meas["ground"], "offset": -2.0}
    out = export_run._conductors(ds, np.arange(4), meas, np.zeros((0, 3)), [-5.0, -5.0, 0.0], [5.0, 5.0, 31.0],
                                 "metres", None, False)
    assert calls[1]["span_length"] is None and out["span_length"] is None
    # the next tower's search gets the photos high-passed, the cameras, the ground at the axis, the
    # tower's height and the cross-arms' half span, then the side's azimuth and window
    calls[1]["next_tower"](0.25, (300.0, 340.0))
    images, c2w, intr, centre, up, ground, height, half_width, psi, window = swept[0]
    assert images.shape == (4, 48, 64) and abs(float(images.mean())) < 1.0
    np.testing.assert_allclose(c2w, cond.metric_cameras(np.asarray(ds.c2w)[:4], ds.normalization))
    np.testing.assert_allclose(centre, [0.0, 0.0, 0.0])
    assert (ground, height, half_width, psi, window) == (2.0, 30.0, 7.0, 0.25, (300.0, 340.0))


def test_export_cli_warns_when_the_towers_axis_leans_past_three_degrees(monkeypatch, tmp_path):
    """A model's tower leaning 7.25 deg (a ghost of a model measured so): one warning naming the
    angle; 1.74 deg (the most a sound export measured) and exactly 3: none. The export is a
    stand-in returning the keys the CLI reads."""
    from jaxnerf_grid import cli
    from jaxnerf_grid.export import run as run_lib

    def fake(tilt):
        return lambda *a, **k: {"units": "metres", "height": 21.76, "tilt": {"tilt_degrees": tilt},
                                "survey": {"height": {"sigma": 0.39}, "tilt_degrees": {"value": tilt, "sigma": 0.4}},
                                "mesh": {"vertices": 3, "faces": 1}, "points": {"count": 5}, "seconds": 1.0}

    for tilt, expected in ((7.25, ["the tower's axis leans 7.25 deg from vertical: a standing lattice"]),
                           (1.74, []), (3.0, [])):
        monkeypatch.setattr(run_lib, "export_run", fake(tilt))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert cli.main(["export", "--run", str(tmp_path), "--quiet"]) == 0
        assert [str(w.message)[:65] for w in caught] == expected


def test_conductor_step_records_whether_the_ground_beneath_each_span_is_seen(monkeypatch):
    """`_conductors` with the spans' search replaced by one known span (line along +y from the
    axis at the origin, its lowest point 160 m out: a 320 m level span): its clearance carries
    `ground_seen` with the radius 5 % of the span (16 m) and the cloud's ground within the
    ground's band (0.1): a cloud whose ground reaches 20 m from the tower gives none there,
    doubtful; the same ground all along the span gives its points, on the plane, sound."""

    from jaxnerf_grid.export import clearance as clearance_lib
    from jaxnerf_grid.export import conductors as cond

    ds = _dark_line_photos()
    meas = {"ground": {"normal": [0.0, 0.0, 1.0], "offset": 0.0, "clearance": 0.1}, "height": 30.0,
            "tilt": {"base": [0.0, 0.0, 0.0]},
            "cross_arms": {"axis_a": [1.0, 0.0, 0.0], "axis_b": [0.0, 1.0, 0.0],
                           "levels": [{"height": 17.5, "span": 14.0, "axis": "a",
                                       "ends": [[7.0, 0.0, 17.5], [-7.0, 0.0, 17.5]]}]}}
    a, xv = 1600.0, 160.0
    fit = {"theta": np.array([-7.6, 14.9, math.pi / 2, -math.sinh(xv / a), 1.0 / a]),
           "cov": np.diag([1e-4, 1e-4, 1e-8, 1e-8, 1e-14]), "image_cov": np.diag([1e-4, 1e-4, 1e-8, 1e-8, 1e-14]),
           "side": 1, "sigma_px": 0.5, "inlier_share": 0.9,
           "residuals": 100, "seen": 110, "stations": np.array([4.5, 320.0])}
    monkeypatch.setattr(cond, "find_spans", lambda *a, **k: [fit])

    def ground(y_hi: float) -> np.ndarray:
        xy = np.stack(np.meshgrid(np.arange(-20.0, 20.5, 1.0), np.arange(-20.0, y_hi + 1.0, 2.0)), -1).reshape(-1, 2)
        return np.concatenate([xy, np.zeros((len(xy), 1))], 1)

    def seen(cloud: np.ndarray) -> dict:
        out = export_run._conductors(ds, np.arange(4), meas, cloud, [-5.0, -5.0, 0.0], [5.0, 5.0, 31.0], "metres",
                                     None, False)
        assert out["found"] == 1
        return out["spans"][0]["clearance"]["ground_seen"]

    near_tower = seen(ground(20.0))
    assert near_tower["radius"] == pytest.approx(16.0, abs=1e-6)
    assert (near_tower["count"], near_tower["doubtful"], near_tower["reason"]) == (0, True, clearance_lib.NOT_SEEN)
    assert near_tower["tolerance"] == pytest.approx(2 * 0.1 / 3, abs=1e-12)
    along = seen(ground(320.0))
    assert along["count"] > 300 and along["median_height"] == 0.0 and along["doubtful"] is False


def test_export_cli_warns_when_the_ground_beneath_the_lowest_reconstructed_conductor_point_is_doubtful(
        monkeypatch, tmp_path):
    """The heuristic `conductors` record with its `ground_seen` doubtful (no ground within 2.5 m):
    one warning naming that point and the reason, in the export's units; sound, not reconstructed:
    none. The export is a stand-in returning the keys the CLI reads."""
    from jaxnerf_grid import cli
    from jaxnerf_grid.export import run as run_lib

    not_seen = {"radius": 2.5, "count": 0, "min_count": 10, "median_height": None, "tolerance": 0.2,
                "doubtful": True, "reason": "too few ground points"}
    sound = {**not_seen, "count": 80, "median_height": 0.0, "doubtful": False, "reason": None}

    def fake(seen, reconstructed=True):
        return lambda *a, **k: {"units": "metres", "height": 30.0, "mesh": {"vertices": 3, "faces": 1},
                                "points": {"count": 5}, "seconds": 1.0,
                                "conductors": {"reconstructed": reconstructed, "ground_seen": seen}}

    for seen, reconstructed, expected in (
            (not_seen, True, ["the clearance of the conductors' lowest reconstructed point is doubtful: only 0 "
                              "ground points of the cloud within 2.50 m of the point beneath the lowest point (at "
                              "least 10 needed): the ground there is not seen, and the clearance over the ground "
                              "is the fitted plane's extrapolation"]),
            (sound, True, []), (not_seen, False, [])):
        monkeypatch.setattr(run_lib, "export_run", fake(seen, reconstructed))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert cli.main(["export", "--run", str(tmp_path), "--quiet"]) == 0
        assert [str(w.message) for w in caught] == expected


def test_export_cli_warns_for_the_spans_whose_ground_clearance_is_doubtful(monkeypatch, tmp_path):
    """Two spans, the first doubtful (no ground seen beneath it), the second sound: one warning
    naming the first span and its reason, in the export's units; both sound: none. The export is a
    stand-in returning the keys the CLI reads."""
    from jaxnerf_grid import cli
    from jaxnerf_grid.export import run as run_lib

    not_seen = {"radius": 16.0, "count": 0, "min_count": 10, "median_height": None, "tolerance": 0.2,
                "doubtful": True, "reason": "too few ground points"}
    sound = {**not_seen, "count": 500, "median_height": 0.01, "doubtful": False, "reason": None}

    def fake(first, units="metres"):
        spans = [{"side": 1, "clearance": {"ground_seen": first}}, {"side": -1, "clearance": {"ground_seen": sound}}]
        return lambda *a, **k: {"units": units, "height": 30.0, "mesh": {"vertices": 3, "faces": 1},
                                "points": {"count": 5}, "seconds": 1.0, "conductor_spans": {"spans": spans}}

    for first, units, expected in (
            (not_seen, "metres", ["the clearance over the ground of span 1 (side +) is doubtful: only 0 ground "
                                  "points of the cloud within 16.00 m of the point beneath the lowest point (at "
                                  "least 10 needed): the ground there is not seen, and the clearance over the "
                                  "ground is the fitted plane's extrapolation"]),
            (not_seen, "unknown", ["the clearance over the ground of span 1 (side +) is doubtful: only 0 ground "
                                   "points of the cloud within 16.00 units of"]),
            (sound, "metres", [])):
        monkeypatch.setattr(run_lib, "export_run", fake(first, units))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert cli.main(["export", "--run", str(tmp_path), "--quiet"]) == 0
        assert [str(w.message)[:len(e)] for w, e in zip(caught, expected)] == expected and len(caught) == len(expected)
