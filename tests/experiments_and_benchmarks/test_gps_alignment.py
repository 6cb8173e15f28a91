"""benchmarks/gps_alignment.py's score of a trained model's export against the synthetic truth,
on hand-made files: a reference tower 30 m tall at 0.05 units per metre, measurements with known
errors."""

import numpy as np
import pytest

from benchmarks import gps_alignment
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError


def _truth(tmp_path):
    syn = tmp_path / "syn"
    syn.mkdir()
    rng = np.random.default_rng(0)
    tower = rng.uniform([-0.2, -0.2, -0.75], [0.2, 0.2, 0.75], (500, 3))  # 1.5 units = 30 m
    tower[0, 2], tower[1, 2] = -0.75, 0.75
    io.write_ply(syn / "tower.ply", tower.astype(np.float32))
    io.write_json(syn / "gps_truth.json", {"scene_units_per_metre": 0.05,
                                            "tower_base_crs": [465000.0, 5247000.0, 410.0]})
    return syn


def _export(tmp_path, height, base_crs, units="metres"):
    out = tmp_path / "export"
    out.mkdir(exist_ok=True)
    survey = {"height": {"value": height, "sigma": 0.4, "fit_sigma": 0.1},
              "base_centre": None if base_crs is None else {"crs": base_crs, "sigma": 1.2}}
    io.write_json(out / "measurements.json", {"units": units, "survey": survey})
    return out


def test_height_and_base_errors_against_the_truth(tmp_path):
    syn = _truth(tmp_path)
    got = gps_alignment.score_export(syn, _export(tmp_path, 30.6, [465003.0, 5246996.0, 412.0]))
    assert got["true_height_m"] == pytest.approx(30.0, abs=1e-3)
    assert got["height_error_m"] == pytest.approx(0.6, abs=1e-3)
    assert got["height_error_percent"] == pytest.approx(2.0, abs=1e-3)
    assert got["base_error_horizontal_m"] == pytest.approx(5.0, abs=1e-3)
    assert got["base_error_m"] == pytest.approx(np.sqrt(29.0), abs=1e-3)
    assert got["height_sigma_m"] == 0.4 and got["base_sigma_m"] == 1.2
    no_axis = gps_alignment.score_export(syn, _export(tmp_path, 29.7, None))
    assert no_axis["base_error_m"] is None and no_axis["height_error_percent"] == pytest.approx(-1.0, abs=1e-3)


def test_an_export_without_metres_is_refused(tmp_path):
    syn = _truth(tmp_path)
    with pytest.raises(DataError, match="not in metres"):
        gps_alignment.score_export(syn, _export(tmp_path, 30.0, None, units="unknown"))


def test_export_moved_through_another_alignment_by_hand(tmp_path):
    """`moved_export` (--realign with --export): the export made under one alignment (CRS = local
    + O1) moved through sim = (1.01, a quarter turn about z, (1, 2, 3)) to CRS = local + O2. By
    hand: height 30.0 m -> 30.3 m (+1 %); the base (465003, 5246996, 412) -> local (3, -4, 412)
    -> turned (4, 3, 412) -> x 1.01 (4.04, 3.03, 416.12) -> + t (5.04, 5.03, 419.12) -> + O2
    (465005.04, 5247005.03, 410.0): 5.04 m east and 5.03 m north of the true base."""
    syn = _truth(tmp_path)
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    got = gps_alignment.moved_export(syn, _export(tmp_path, 30.0, [465003.0, 5246996.0, 412.0]),
                                     (1.01, quarter, np.array([1.0, 2.0, 3.0])),
                                     np.array([465000.0, 5247000.0, 0.0]), np.array([465000.0, 5247000.0, -9.12]))
    assert got["height_m"] == pytest.approx(30.3, abs=1e-3)
    assert got["height_error_percent"] == pytest.approx(1.0, abs=1e-3)
    assert got["base_error_horizontal_m"] == pytest.approx(np.hypot(5.04, 5.03), abs=1e-3)
    assert got["base_error_m"] == pytest.approx(np.hypot(5.04, 5.03), abs=1e-3)
