"""benchmarks/conductors.py's `score`: a fitted span is matched with the true span it runs along,
whatever its own side label, and its curve RMS is taken against the truth's closed-form catenary."""

import math

import numpy as np

from benchmarks import conductors as bench
from jaxnerf_grid.export import catenary

L, A, ATTACH = 320.0, 1600.0, np.array([5.0, 0.0, 20.0])   # span, catenary parameter, shared attachment


def _true_span(side: int) -> dict:
    """A level span from ATTACH to +-L along y (side +1: +y), its points from the closed form
    z(s) = z_a + A (cosh((s - L/2) / A) - cosh(L / (2 A)))."""
    s = np.linspace(0.0, L, 4000)
    z = ATTACH[2] + A * (np.cosh((s - L / 2) / A) - math.cosh(L / (2 * A)))
    pts = np.stack([np.full_like(s, ATTACH[0]), side * s, z], axis=1)
    return {"wire": 0, "earth": False, "side": side, "attachment": ATTACH, "far": pts[-1], "sag": float(z[0] - z.min()),
            "lowest_z": float(z.min()), "points": pts}


def _record(psi: float, side_label: int) -> dict:
    """A fitted span along azimuth psi from ATTACH with the true curvature (theta = across offset,
    attachment height, psi, slope at the attachment, 1 / A; centre at the origin), labelled
    side_label."""
    kappa = 1.0 / A
    theta = [0.0, ATTACH[2], psi, -math.sinh(L * kappa / 2), kappa]
    _, across, _ = catenary.line_axes(psi)
    theta[0] = float(ATTACH @ across)
    fig = catenary.derived(theta, [0.0, 0.0, 0.0])
    return {"theta": theta, "centre": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0], "side": side_label,
            "attachment": {"value": list(fig["attachment"])}, "far_attachment": {"value": list(fig["far_attachment"])},
            "lowest_point": {"value": list(fig["lowest_point"])}, "sag": {"value": fig["sag"], "sigma": 0.01},
            "inlier_share": 1.0, "observed_stations": [0.0, 80.0]}


def test_a_span_labelled_the_other_side_is_matched_with_the_true_span_it_runs_along():
    """Records along -y labelled +1 and along +y labelled -1 (the export's line direction the
    opposite of the generator's): each true span is found with an RMS under 2 cm (the sampling) and its
    sag within 1e-6; matched by label instead, the curves would lie 100 m and more apart."""
    truth = [_true_span(+1), _true_span(-1)]
    records = [_record(-math.pi / 2, +1), _record(+math.pi / 2, -1)]
    out = bench.score(records, truth)
    assert out["found"] == 2 and out["invented"] == 0
    assert out["worst_rms"] < 0.02          # the fitted polyline's points lie 0.04 m apart
    assert out["worst_sag_error_rel"] < 1e-6


def test_a_shifted_record_is_the_same_curve_moved_by_the_shift():
    """`shifted` by t = (3, -2, 1.5): the record's curve at every station is the original's + t, and
    its attachment, far attachment and lowest point are the original's + t."""
    record = _record(-math.pi / 2, +1)
    t = np.array([3.0, -2.0, 1.5])
    moved = bench.shifted(record, t)
    s = np.linspace(0.0, L, 50)
    before = catenary.curve_points(record["theta"], record["centre"], s, record["up"])
    after = catenary.curve_points(moved["theta"], moved["centre"], s, moved["up"])
    np.testing.assert_allclose(after, before + t, atol=1e-9)
    for key in ("attachment", "far_attachment", "lowest_point"):
        np.testing.assert_allclose(moved[key]["value"], np.asarray(record[key]["value"]) + t, atol=1e-9)


def test_gps_shift_is_the_export_origin_less_the_tower_base(tmp_path):
    """An export whose base centre is at local (1, 2, 3), CRS (501, 1002, 403) (origin (500, 1000,
    400)), a scene whose tower base is at CRS (499, 1001, 401): the shift is (1, -1, -1); no
    gps_truth.json, or no CRS in the export: None."""
    meas = {"survey": {"base_centre": {"local": [1.0, 2.0, 3.0], "crs": [501.0, 1002.0, 403.0]}}}
    assert bench.gps_shift(meas, tmp_path) is None
    (tmp_path / "gps_truth.json").write_text('{"tower_base_crs": [499.0, 1001.0, 401.0]}')
    np.testing.assert_allclose(bench.gps_shift(meas, tmp_path), [1.0, -1.0, -1.0])
    assert bench.gps_shift({"survey": {"base_centre": {"local": [1.0, 2.0, 3.0], "crs": None}}}, tmp_path) is None
