"""benchmarks/gps_alignment.py's score of a trained model's export against the synthetic truth,
on hand-made files: a reference tower 30 m tall at 0.05 units per metre, measurements with known
errors."""

import numpy as np
import pytest

from benchmarks import gps_alignment
from jaxnerf_grid import io
from jaxnerf_grid.io import DataError


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
