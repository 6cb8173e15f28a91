"""report.py's blocks without training a run: the figures, the tower box,
the number formats, the geometry / export / survey sections, the training-weights figure,
`set_section` and `write_report`'s tables, each against answers built in the test by hand
(NumPy, OpenCV, f-strings of the hand-written metrics). Each test takes well under a second."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jaxnerf_grid.config.run_config import make_config
from jaxnerf_grid.report import markdown as report
from jaxnerf_grid.util import io

H, W = 12, 16


def _turbo(depth, lo=None, hi=None):
    """The depth colours by hand: 1 / max(depth, 1e-6), scaled between the 2nd and 98th
    percentiles of the finite values (or lo / hi), rounded to 8 bits, TURBO, BGR -> RGB."""
    inv = 1.0 / np.maximum(np.asarray(depth, np.float64), 1e-6)
    fin = inv[np.isfinite(inv)]
    lo = np.percentile(fin, 2) if lo is None else lo
    hi = np.percentile(fin, 98) if hi is None else hi
    idx = np.round(np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1) * 255).astype(np.uint8)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    return lut[idx].astype(np.float32) / 255.0


def _image(seed, h=H, w=W):
    """An [h, w, 3] image of 8-bit values (exact through a PNG)."""
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3)).astype(np.float32) / 255.0


def _depth(h=H, w=W):
    """A depth map 1..h*w (distinct values, so the percentiles are known)."""
    return np.arange(1, h * w + 1, dtype=np.float64).reshape(h, w)


def test_colourise_depth_is_turbo_of_inverse_depth_between_percentiles():
    d = _depth()
    out = report.colourise_depth(d)
    assert out.shape == (H, W, 3) and out.dtype == np.float32
    np.testing.assert_array_equal(out, _turbo(d))
    # near = warm: the nearest pixel is the map's top colour, the farthest its bottom one
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1] / 255.0
    np.testing.assert_allclose(out[0, 0], lut[255], atol=1e-7)
    np.testing.assert_allclose(out[-1, -1], lut[0], atol=1e-7)
    # lo / hi given: 1/d = 0.25 halfway between 0 and 0.5 -> index round(127.5) = 128
    got = report.colourise_depth(np.full((2, 2), 4.0), lo=0.0, hi=0.5)
    np.testing.assert_allclose(got[0, 0], lut[128], atol=1e-7)
    got = report.colourise_depth(np.array([[4.0, 2.0]]), lo=0.0, hi=0.25)
    np.testing.assert_allclose(got[0, 1], lut[255], atol=1e-7)  # 0.5 clipped to 1
    # lo == hi: no division by zero; zero depth is 1e-6
    np.testing.assert_array_equal(report.colourise_depth(np.array([[0.0, 1.0]]), lo=1.0, hi=1.0),
                                  _turbo(np.array([[0.0, 1.0]]), 1.0, 1.0))
    # an infinite depth (inverse 0) is kept; the percentiles are of the finite inverses
    d2 = d.copy()
    d2[0, 0] = np.inf
    np.testing.assert_array_equal(report.colourise_depth(d2), _turbo(d2))


def test_colourise_depth_percentiles_are_the_2nd_and_98th():
    """A depth whose inverses are 0..99: 2nd and 98th percentiles 1.98 and 97.02 by hand."""
    inv = np.arange(100, dtype=np.float64)
    d = 1.0 / np.maximum(inv, 1e-300)
    d[0] = 1e9  # inverse 1e-9 (not 0; clipped at 1e-6 only for depth below it)
    out = report.colourise_depth(d.reshape(10, 10))
    lo, hi = 1.98, 97.02
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1] / 255.0
    for k in (1, 2, 3, 50, 97, 98):
        idx = int(np.round(np.clip((k - lo) / (hi - lo), 0, 1) * 255))
        np.testing.assert_allclose(out.reshape(100, 3)[k], lut[idx], atol=1e-7)
    assert int(np.round((3 - lo) / (hi - lo) * 255)) == 3 and int(np.round((50 - lo) / (hi - lo) * 255)) == 129


def test_side_by_side_layout_by_hand():
    a, b, c = _image(1), _image(2), _image(3)
    d, e, f = _image(4, 5, 7), _image(5, 5, 7), _image(6, 5, 7)
    out = report.side_by_side([(a, b, c), (d, e, f)])
    assert out.shape == (H + 2 + 5, 3 * W + 4, 3) and out.dtype == np.float32
    np.testing.assert_array_equal(out[:H, :W], a)
    np.testing.assert_array_equal(out[:H, W + 2:2 * W + 2], b)
    np.testing.assert_array_equal(out[:H, 2 * W + 4:], c)
    assert np.all(out[:H, W:W + 2] == 1) and np.all(out[:H, 2 * W + 2:2 * W + 4] == 1) and np.all(out[H:H + 2] == 1)
    r = H + 2
    np.testing.assert_array_equal(out[r:, :7], d)
    np.testing.assert_array_equal(out[r:, 9:16], e)
    np.testing.assert_array_equal(out[r:, 18:25], f)
    assert np.all(out[r:, 7:9] == 1) and np.all(out[r:, 16:18] == 1) and np.all(out[r:, 25:] == 1)
    # gap 3, one row: no gap below the last row
    one = report.side_by_side([(a, b, c)], gap=3)
    assert one.shape == (H, 3 * W + 6, 3)
    np.testing.assert_array_equal(one[:, W + 3:2 * W + 3], b)
    np.testing.assert_array_equal(report.side_by_side([(a, b, c)]), np.concatenate(
        [a, np.ones((H, 2, 3)), b, np.ones((H, 2, 3)), c], axis=1).astype(np.float32))


def test_tower_box_by_hand():
    sem = np.zeros((20, 30), np.uint8)
    assert report.tower_box(sem) is None
    sem[:, 0] = 2                       # conductors: not the tower
    assert report.tower_box(sem) is None
    sem[6, 10] = sem[9, 13] = 1
    assert report.tower_box(sem) == (slice(2, 14), slice(6, 18))
    assert report.tower_box(sem, margin=0) == (slice(6, 10), slice(10, 14))
    assert report.tower_box(sem, margin=7) == (slice(0, 17), slice(3, 21))
    sem[19, 29] = 1                     # clipped at the far edges
    assert report.tower_box(sem, margin=1) == (slice(5, 20), slice(9, 30))
    one = np.zeros((20, 30), np.uint8)
    one[0, 0] = 1
    assert report.tower_box(one) == (slice(0, 5), slice(0, 5))


def test_fmt_by_hand():
    f = report._fmt
    assert f(None) == "unavailable" and f(float("nan")) == "n/a" and f(float("inf")) == "n/a"
    assert f(3.14159) == "3.14" and f(3.14159, 4) == "3.1416" and f(2.0, 0) == "2"
    assert f(7) == "7" and f("x") == "x" and f(True) == "True"
    assert report._xyz([1.0, 2.5, -3.0]) == "(1.00, 2.50, -3.00)"
    assert report._xyz([1.0, 2.0], 3) == "(1.000, 2.000)" and report._xyz(None) == "n/a"
    assert report._pm(None, "m") == "unavailable" and report._pm({}, "m") == "unavailable"
    assert report._pm({"value": 12.345, "sigma": 0.051}, "m") == "12.35 m +- 0.05 m"
    assert report._pm({"value": 12.345, "sigma": None}, "m", 3) == "12.345 m +- (not estimated)"
    assert report._pm({"value": 1.0}, "deg") == "1.00 deg +- (not estimated)"
    assert report._pm({"value": 1.0, "sigma": 0.0}, "m") == "1.00 m +- 0.00 m"
    assert report._pm({"value": 1.0, "sigma": 0.0123}, "m", 3) == "1.000 m +- 0.012 m"   # sigma to the same digits


def test_samples_and_field_lines_name_the_config():
    grid = make_config("ours", {"model": {"field": {"kind": "grid"}}}).model
    line = report._samples_line(grid)
    from jaxnerf_grid.nerf import models

    assert line == f"sampling in s: {models.describe(grid)}, {models.samples_per_ray(grid)} samples per ray" + (
        ", opaque far bin" if grid.opaque_far else "")
    import dataclasses

    assert report._samples_line(dataclasses.replace(grid, opaque_far=True)).endswith(" samples per ray, opaque far bin")
    assert not report._samples_line(dataclasses.replace(grid, opaque_far=False)).endswith("bin")
    f = grid.field
    g = f.grid
    assert f.kind == "grid"
    assert report._field_line(f) == (
        f"hash grid, {g.num_levels} levels x {g.features_per_level} features, table 2^{g.log2_table_size}, "
        f"resolution {g.min_resolution}-{g.max_resolution}; MLPs {f.depth} x {f.width} (density), "
        f"{f.view_depth} x {f.view_width} (colour)")
    mlp = make_config("nerf").model.field
    assert mlp.kind != "grid"
    assert report._field_line(mlp) == (f"MLP {mlp.depth} x {mlp.width} (skip after {mlp.skip}), PE "
                                       f"{mlp.pos_max_deg} octaves, view dirs {mlp.use_viewdirs}")


GEOMETRY = {"reference": "tower.ply", "units": "metres", "ground_strip": 0.25, "num_pred": 120, "num_ref": 300,
            "thresholds": {"0.05": {"precision": 0.123456, "recall": 0.5, "fscore": 0.19806},
                           "0.1": {"precision": 1.0, "recall": None, "fscore": float("nan")}},
            "chamfer": 0.03125}


def test_geometry_lines_by_hand():
    assert report.geometry_lines(None) == [] and report.geometry_lines({}) == []
    assert report.geometry_lines(GEOMETRY) == [
        "## Tower geometry", "",
        "`tower_points.ply` against `tower.ply`, metres; both clouds cropped to the reference tower's box less a "
        "0.250-unit ground strip (120 predicted, 300 reference points).", "",
        "| threshold | precision | recall | F-score |", "|---|---|---|---|",
        "| 0.05 | 0.1235 | 0.5000 | 0.1981 |",
        "| 0.1 | 1.0000 | unavailable | n/a |",
        "", "Chamfer distance (mean of the two mean nearest-neighbour distances): 0.0312", ""]
    bare = report.geometry_lines({"chamfer": 1.0})
    assert bare[2] == ("`tower_points.ply` against `the reference cloud`, normalised scene units; both clouds cropped "
                       "to the reference tower's box less a unavailable-unit ground strip (? predicted, ? reference "
                       "points).")
    assert bare[4:] == ["| threshold | precision | recall | F-score |", "|---|---|---|---|", "",
                        "Chamfer distance (mean of the two mean nearest-neighbour distances): 1.0000", ""]


def _fig(v, s):
    return {"value": v, "sigma": s}


MEASUREMENTS = {
    "units": "metres", "height": 21.456,
    "footprint": {"width_a": 3.214, "width_b": 2.5},
    "cross_arms": {"levels": [{"height": 15.04, "span": 6.26}, {"height": 19.96, "span": 4.0}]},
    "survey": {"height": _fig(21.456, 0.031), "footprint": [_fig(3.214, 0.02), _fig(2.5, None)],
               "cross_arm_heights": [_fig(15.04, 0.1), _fig(19.95, 0.2)],
               "cross_arm_spans": [_fig(6.26, 0.05), None],
               "tilt_degrees": _fig(0.5, 0.25), "top_offset": _fig(0.19, 0.01),
               "base_centre": {"crs": [500000.0, 4649776.25, 12.5], "crs_name": "EPSG:32633",
                               "local": [0.0, 1.0, 2.0], "sigma": 0.0123},
               "vertical": {"reference": "ellipsoidal (WGS 84)"},
               "conductor_clearance": _fig(11.0, 0.5)},
    "conductors": {"reconstructed": True},
    "ground": {"normal": [0.0, 0.1, 0.99498744], "offset": -0.1234, "tilt_degrees": 5.7392},
    "mesh": {"vertices": 100, "faces": 196, "kept_face_fraction": 0.98765, "closed": False},
    "points": {"count": 4321},
    "box": {"source": "auto", "min": [-1.0, -2.0, 0.0], "max": [1.0, 2.0, 22.0]},
    "voxel_size": 0.05, "threshold": {"density": 12.34, "opacity_per_voxel": 0.456},
}

SCORE = {"reference_points": 999, "ground_strip": 0.5,
         "mesh": {"thresholds": {"0.1": {"fscore": 0.81234}, "0.2": {"fscore": 0.9}}, "chamfer": 0.04567},
         "points": {"thresholds": {"0.1": {"fscore": 0.7}, "0.2": {"fscore": 0.75}}, "chamfer": 0.05},
         "height": {"export": 21.456, "reference": 21.0, "error": 0.456, "error_percent": 2.1714}}


def test_export_lines_with_survey_and_score_by_hand():
    got = report.export_lines({"measurements": MEASUREMENTS, "image": "export/views.png", "score": SCORE})
    assert got == [
        "## Tower model (export)", "",
        "`jaxnerf-grid export`: `tower_mesh.ply`, `tower_points.ply`, `box.json`, `measurements.json`; metres.", "",
        "| measurement | value |", "|---|---|",
        "| tower height above the fitted ground | 21.46 m |",
        "| base footprint (minimum-area rectangle of the lowest band) | 3.21 x 2.50 m |",
        "| cross-arm levels (height: span, heuristic) | 15.0: 6.3; 20.0: 4.0 m |",
        "| height with its 1-sigma uncertainty | 21.46 m +- 0.03 m |",
        "| base footprint widths | 3.21 m +- 0.02 m x 2.50 m +- (not estimated) |",
        "| cross-arm heights above the ground (spans) | 15.04 m +- 0.10 m (6.26 m +- 0.05 m); 19.95 m +- 0.20 m |",
        "| tilt of the tower's axis from vertical | 0.50 deg +- 0.25 deg; top offset 0.19 m +- 0.01 m |",
        "| base centre | (500000.000, 4649776.250, 12.500) in EPSG:32633 +- 0.01 m |",
        "| heights of the CRS coordinates (base centre, tower_points.las, tower_mesh_crs.ply) | ellipsoidal (WGS 84) |",
        "| conductors' lowest reconstructed point above the ground | 11.00 m +- 0.50 m |",
        "| ground plane n . x + d = 0 | n = (0.0000, 0.1000, 0.9950), d = -0.123 (tilt 5.74 deg) |",
        "| mesh | 100 vertices, 196 faces, 98.8 % of the faces kept after removing small components, closed: False |",
        "| fused points | 4321 |",
        "| box (auto) | (-1.00, -2.00, 0.00) - (1.00, 2.00, 22.00) m |",
        "| voxel, threshold | 0.050 m, density 12.3 per normalised unit (one voxel 0.46 opaque) |", "",
        "Against the reference tower (999 points; both cropped to its box less a 0.50 m ground strip):", "",
        "| cloud | F@0.1 | F@0.2 | Chamfer |", "|---|---|---|---|",
        "| mesh vertices | 0.812 | 0.900 | 0.046 |",
        "| fused points | 0.700 | 0.750 | 0.050 |", "",
        "Height: 21.46 against 21.00 m, error 0.46 m (2.17 %).", "",
        "![front | side | top](export/views.png)", ""]


def test_export_lines_without_metres_survey_or_score():
    assert report.export_lines(None) == [] and report.export_lines({}) == []
    assert report.export_lines({"measurements": {}}) == [] and report.export_lines({"score": SCORE}) == []
    got = report.export_lines({"measurements": {"units": "unknown", "height": 2.0}})
    assert got == [
        "## Tower model (export)", "",
        "`jaxnerf-grid export`: `tower_mesh.ply`, `tower_points.ply`, `box.json`, `measurements.json`; "
        "**units unknown** (the dataset has no metric scale: its original units).", "",
        "| measurement | value |", "|---|---|",
        "| tower height above the fitted ground | 2.00 units |",
        "| mesh | ? vertices, ? faces, n/a % of the faces kept after removing small components, closed: None |",
        "| fused points | ? |", "| box (?) | n/a - n/a units |",
        "| voxel, threshold | unavailable units, density unavailable per normalised unit (one voxel unavailable "
        "opaque) |", ""]
    # a score of points only: the F columns from the points; no height line
    got = report.export_lines({"measurements": {"units": "metres", "height": 2.0},
                               "score": {"points": {"thresholds": {"0.3": {"fscore": 0.5}}, "chamfer": 0.1}}})
    i = got.index("| cloud | F@0.3 | Chamfer |")
    assert got[i - 2].startswith("Against the reference tower (? points; both cropped to its box less a unavailable m")
    assert got[i:] == ["| cloud | F@0.3 | Chamfer |", "|---|---|---|", "| fused points | 0.500 | 0.100 |", ""]
    # a score of the mesh only: the F columns from the mesh
    got = report.export_lines({"measurements": {"units": "metres", "height": 2.0},
                               "score": {"mesh": {"thresholds": {"0.4": {"fscore": 0.25}}, "chamfer": 0.2}}})
    i = got.index("| cloud | F@0.4 | Chamfer |")
    assert got[i:] == ["| cloud | F@0.4 | Chamfer |", "|---|---|---|", "| mesh vertices | 0.250 | 0.200 |", ""]
    # a score with neither cloud: a table of no rows, no F columns
    got = report.export_lines({"measurements": {"units": "metres", "height": 2.0}, "score": {"reference_points": 5}})
    i = len(got) - 1 - got[::-1].index("|---|---|")   # the score table's separator (the last)
    assert got[i - 3].startswith("Against the reference tower (5 points;") and "F@" not in got[i - 1]
    assert got[i - 1].startswith("| cloud |") and got[i + 1:] == [""]


def test_survey_lines_local_base_and_conductors_not_reconstructed():
    m = {"survey": {"height": _fig(3.0, None),
                    "cross_arm_heights": [_fig(1.0, 0.1), _fig(2.0, 0.1)],
                    "base_centre": {"crs": None, "local": [1.0, 2.0, 3.0], "sigma": None}},
         "conductors": {"reconstructed": False, "why": "no wire left the box"}}
    assert report._survey_lines(m, "units") == [
        "| height with its 1-sigma uncertainty | 3.00 units +- (not estimated) |",
        "| cross-arm heights above the ground (spans) | 1.00 units +- 0.10 units; 2.00 units +- 0.10 units |",
        "| base centre | (1.000, 2.000, 3.000) (the dataset's frame) +- (not estimated) |",
        "| conductors | not reconstructed: no wire left the box |"]
    assert report._survey_lines({}, "m") == [] and report._survey_lines({"survey": None}, "m") == []
    assert report._survey_lines({"survey": {"height": _fig(1.0, 0.5)}, "conductors": {"why": "x"}}, "m") == [
        "| height with its 1-sigma uncertainty | 1.00 m +- 0.50 m |", "| conductors | not reconstructed: x |"]
    assert report._survey_lines({"survey": {"height": _fig(1.0, 0.5)}, "conductors": {"reconstructed": False}},
                                "m")[1] == "| conductors | not reconstructed:  |"


def test_survey_lines_say_when_the_lower_part_is_missing():
    """The base extrapolated 11.08 m on a 30.49 m tower (more than 5 % of it): one row saying so;
    1.0 m (3.3 %) or exactly 5 %: none; without a height: none."""
    def lines(low, height):
        base = {"crs": None, "local": [1.0, 2.0, 3.0], "sigma": 0.5, "extrapolated": low}
        return report._survey_lines({"height": height, "survey": {"base_centre": base}}, "m")

    got = lines(11.08, 30.49)
    assert got[1] == "| base centre | (1.000, 2.000, 3.000) (the dataset's frame) +- 0.50 m |"
    assert len(got) == 3 and got[2].startswith("| **lower part missing** | the model's tower begins 11.08 m above the "
                                               "ground: its legs were not reconstructed there")
    assert len(lines(1.0, 30.49)) == 2 and len(lines(0.05 * 40.0, 40.0)) == 2 and len(lines(11.08, None)) == 2


def test_lower_part_missing_by_hand_and_its_row_word_for_word():
    """lower_part_missing: the base's `extrapolated` when it is more than 5 % of a positive
    height: 0.6 on a 10 m tower (5 % = 0.5) is, 0.5 and 0.4 are not; a base without
    `extrapolated`, none, no survey or no height: None (nothing to say). The row in full, in the
    export's units."""
    def m(low, height=10.0):
        base = {"crs": None, "local": [1.0, 2.0, 3.0], "sigma": 0.5}
        if low is not None:
            base["extrapolated"] = low
        return {"height": height, "survey": {"base_centre": base}}

    assert report.lower_part_missing(m(0.6)) == 0.6 and type(report.lower_part_missing(m(0.6))) is float
    assert report.lower_part_missing(m(0.5)) is None and report.lower_part_missing(m(0.4)) is None
    assert report.lower_part_missing(m(None)) is None and report.lower_part_missing(m(0.6, None)) is None
    assert report.lower_part_missing({}) is None and report.lower_part_missing({"height": 10.0}) is None
    assert report.lower_part_missing({"height": 10.0, "survey": {"base_centre": None}}) is None
    assert report._survey_lines(m(0.6), "units")[-1] == (
        "| **lower part missing** | the model's tower begins 0.60 units above the ground: its legs were not "
        "reconstructed there, so the base centre and the tilt come from the axis extended down that far (train "
        "longer, or add low oblique photos) |")


def test_tilt_doubtful_past_three_degrees_and_its_row_word_for_word():
    """tilt_doubtful: the survey's tilt when over 3 degrees (7.25, a ghost of a model's; 3.01), not
    at 3 or 1.74 (the most a sound export measured); no tilt: None. The row in full."""
    def m(tilt):
        return {"height": 21.76, "survey": {"height": _fig(21.76, 0.39),
                                            "tilt_degrees": None if tilt is None else _fig(tilt, 0.4)}}

    assert report.tilt_doubtful(m(7.25)) == 7.25 and report.tilt_doubtful(m(3.01)) == 3.01
    assert report.tilt_doubtful(m(3.0)) is None and report.tilt_doubtful(m(1.74)) is None
    assert report.tilt_doubtful(m(None)) is None and report.tilt_doubtful({}) is None
    assert report._survey_lines(m(7.25), "m")[-1] == (
        "| **tilt doubtful** | the tower's axis leans 7.25 deg from vertical: a standing lattice tower leans under "
        "2 degrees in every export measured here: either this one leans, or the model's tower is incomplete or "
        "misplaced (look at report_views.png), and its height, cross-arm levels and the conductors' clearance are "
        "doubtful |")
    assert not any("tilt doubtful" in line for line in report._survey_lines(m(1.74), "m"))


def _doubt_spans(*seen):
    """measurements.json's conductor_spans with a span (side + then -) per `ground_seen` record."""
    spans = [{**_span_row(), "side": 1 if i % 2 == 0 else -1, "clearance": {"ground": 6.9, "ground_seen": s}}
             for i, s in enumerate(seen)]
    return {"units": "metres", "conductor_spans": {"found": len(spans), "photos": 40, "spans": spans}}


NOT_SEEN = {"radius": 16.0, "count": 3, "min_count": 10, "median_height": 0.05, "tolerance": 0.2, "doubtful": True,
            "reason": "too few ground points"}
OFF_PLANE = {"radius": 16.0, "count": 812, "min_count": 10, "median_height": -2.0, "tolerance": 0.2,
             "doubtful": True, "reason": "ground off the plane"}
SEEN = {"radius": 16.0, "count": 812, "min_count": 10, "median_height": 0.0, "tolerance": 0.2, "doubtful": False,
        "reason": None}


def test_clearance_doubtful_names_the_doubtful_spans_grouped_by_their_words_and_the_rows_word_for_word():
    """clearance_doubtful: the spans whose `ground_seen` is doubtful, by the conductors' table's
    number and side; a sound span, a span without the record (none measured) and an export without
    spans: nothing. The rows in full in the export section's table, in the export's units."""
    m = _doubt_spans(NOT_SEEN, SEEN, None, OFF_PLANE)
    got = report.clearance_doubtful(m, "m")
    assert [span for span, _ in got] == ["span 1 (side +)", "span 4 (side -)"]
    assert report.clearance_doubtful(_doubt_spans(SEEN, None), "m") == []
    assert report.clearance_doubtful({}, "m") == [] and report.clearance_doubtful({"conductor_spans": None}, "m") == []
    lines = report.export_lines({"measurements": m})
    rows = [line for line in lines if "clearance doubtful" in line]
    assert rows == [
        "| **clearance doubtful** | span 1 (side +): only 3 ground points of the cloud within 16.00 m of the point "
        "beneath the lowest point (at least 10 needed): the ground there is not seen, and the clearance over the "
        "ground is the fitted plane's extrapolation |",
        "| **clearance doubtful** | span 4 (side -): the cloud's ground within 16.00 m of the point beneath the "
        "lowest point has a median height of -2.00 m above the fitted plane (beyond +- 0.20 m): the plane does not "
        "fit the ground there, and the clearance over the ground is off by about that much |"]
    # spans with the same words share one entry, their numbers as runs
    same = report.clearance_doubtful(_doubt_spans(NOT_SEEN, NOT_SEEN, SEEN, NOT_SEEN, OFF_PLANE, NOT_SEEN), "m")
    assert [span for span, _ in same] == ["4 spans (1-2, 4, 6)", "span 5 (side +)"]
    assert same[0][1] == got[0][1]
    assert not any("clearance doubtful" in line for line in report.export_lines({"measurements": _doubt_spans(SEEN)}))
    # the spans' table marks the figure
    table = report.conductor_lines({"conductor_spans": {"found": 2, "photos": 40, "spans": [
        {**_span_row(), "clearance": {"ground": 6.9, "ground_sigma": 0.01, "ground_seen": NOT_SEEN}},
        {**_span_row(), "clearance": {"ground": 6.9, "ground_sigma": 0.01, "ground_seen": SEEN}}]}}, "m")
    assert [line.split(" | ")[5] for line in table if line.startswith("| 1 |") or line.startswith("| 2 |")] == \
        ["6.90 +- 0.01 (doubtful)", "6.90 +- 0.01"]


def test_the_conductors_lowest_reconstructed_point_marked_doubtful_with_its_row_word_for_word():
    """measurements.json's heuristic `conductors` with a `ground_seen` record: doubtful (no ground
    seen within 2.50 m), its figure in the survey rows marked "(doubtful)" and a "clearance
    doubtful" row naming it; sound, without the record, or not reconstructed: no mark, no row."""
    seen = {**NOT_SEEN, "radius": 2.5, "count": 0, "median_height": None}

    def rows(cond):
        return [line for line in report.export_lines({"measurements": {**MEASUREMENTS, "conductors": cond}})
                if "lowest reconstructed point" in line]

    assert rows({"reconstructed": True, "ground_seen": seen}) == [
        "| conductors' lowest reconstructed point above the ground | 11.00 m +- 0.50 m (doubtful) |",
        "| **clearance doubtful** | the conductors' lowest reconstructed point: only 0 ground points of the cloud "
        "within 2.50 m of the point beneath the lowest point (at least 10 needed): the ground there is not seen, and "
        "the clearance over the ground is the fitted plane's extrapolation |"]
    sound = ["| conductors' lowest reconstructed point above the ground | 11.00 m +- 0.50 m |"]
    assert rows({"reconstructed": True, "ground_seen": SEEN}) == sound
    assert rows({"reconstructed": True}) == rows({"reconstructed": True, "ground_seen": None}) == sound
    assert rows({"reconstructed": False, "why": "none", "ground_seen": seen}) == []


def _span_row() -> dict:
    """The figures of a conductors' table row the marker test does not look at."""
    fig = _fig(1.0, 0.1)
    return {"side": 1, "attachment": _fig([0.0, 0.0, 14.9], [0.0, 0.0, 0.01]), "sag": fig, "catenary_parameter": fig}


def test_weights_figure_panels_by_hand(tmp_path):
    assert report.weights_figure(tmp_path, []) == [] and not (tmp_path / "report_weights.png").exists()
    photo = _image(7)
    rng = np.random.default_rng(8)
    prior = rng.integers(0, 256, (H, W)) / 255.0
    used = rng.integers(0, 256, (H, W)) / 255.0
    lines = report.weights_figure(str(tmp_path), [(photo, prior, used), (photo[::-1], used, prior)])
    assert lines == ["Training weights (photo | DPT weight 1 - M_w | weight training used; black = ignored): "
                     "![training weights](report_weights.png)"]
    fig = io.read_image(tmp_path / "report_weights.png")
    assert fig.shape == (2 * H + 2, 3 * W + 4, 3)
    np.testing.assert_array_equal(fig[:H, :W], photo)
    for c in range(3):
        np.testing.assert_allclose(fig[:H, W + 2:2 * W + 2, c], prior, atol=1e-7)
        np.testing.assert_allclose(fig[:H, 2 * W + 4:, c], used, atol=1e-7)
        np.testing.assert_allclose(fig[H + 2:, W + 2:2 * W + 2, c], used, atol=1e-7)
    np.testing.assert_array_equal(fig[H + 2:, :W], photo[::-1])


def test_set_section_replaces_appends_and_keeps_bytes(tmp_path):
    p = tmp_path / "r.md"
    assert report.set_section(p, "## B", ["## B", "new"]) == p
    assert p.read_bytes() == b"## B\nnew"
    p.write_bytes(b"# T\n\n## A\na\n## B\nold\nold2\n## C\nc\xe9\n")
    report.set_section(str(p), "## B", ["## B", "b"])
    assert p.read_bytes() == b"# T\n\n## A\na\n## B\nb\n## C\nc\xe9\n"
    report.set_section(p, "## C", ["## C", "z"])     # the last section: up to the end
    assert p.read_bytes() == b"# T\n\n## A\na\n## B\nb\n## C\nz"
    report.set_section(p, "## D", ["## D", "d"])     # appended after one blank line
    assert p.read_bytes() == b"# T\n\n## A\na\n## B\nb\n## C\nz\n\n## D\nd"
    p.write_bytes(b"x\n")
    report.set_section(p, "## E", ["## E"])          # the file ends with a newline: one blank line, not two
    assert p.read_bytes() == b"x\n\n## E"
    p.write_bytes(b"## A\n## B\nb\n")                # the next section right under the heading
    report.set_section(p, "## A", ["## A", "a"])
    assert p.read_bytes() == b"## A\na\n## B\nb\n"
    p.write_bytes(b"## A\n### sub\n## Ab\n")         # "### " is not a section end; "## Ab" is
    report.set_section(p, "## A", ["## A", "n"])
    assert p.read_bytes() == b"## A\nn\n## Ab\n"
    p.write_bytes(b"")
    report.set_section(p, "## F", ["## F"])          # an empty file reads as one empty line
    assert p.read_bytes() == b"\n## F"


METRICS = {"step": 321, "num_views": 3, "target": "clean_images",
           "mean": {"psnr": 23.456789, "ssim": 0.812345, "ms_ssim": 0.912345, "lpips": float("nan"),
                    "ms_ssim_scales": 4},
           "mean_right_half": {"psnr": 21.0049, "ssim": 0.70005},
           "regions_mean": {"tower": 19.87654, "near_ground": 25.0, "far_background": None},
           "distractor_psnr": 14.255, "protocol": "left half fitted", "region_definition": "by depth",
           "geometry": GEOMETRY, "export": {"measurements": {"units": "metres", "height": 2.0}}}


def _views():
    sem = np.zeros((H, W), np.uint8)
    sem[5, 6] = sem[7, 9] = 1
    rgb = _image(11)                                   # the render clipped to [0, 1]
    rgb[:2, :3] = -0.5
    rgb[6:, 5:] = 1.5
    return [{"name": "a", "gt": _image(10), "rgb": rgb, "depth": _depth(), "semantic": sem},
            {"name": "b", "gt": _image(12), "rgb": _image(13), "depth": _depth()[::-1].copy(), "semantic": None},
            {"name": "c", "gt": _image(14), "rgb": _image(15), "depth": _depth() ** 2,
             "semantic": np.zeros((H, W), np.uint8)}]


def test_write_report_tables_and_sections_by_hand(tmp_path):
    cfg = make_config("ours", {"train": {"use_masks": True, "mask_weight_floor": 0.3}})
    path = report.write_report(str(tmp_path), METRICS, cfg, "DATA/tower", _views(), ["note one", "note two"])
    assert path == tmp_path / "report.md"
    text = path.read_text()
    lines = text.split("\n")
    t, m = cfg.train, cfg.model
    assert lines[:6] == [f"# Run report: {m.method}", "", "Data: `DATA/tower`  ", "Trained steps: 321  ",
                         "Evaluated views: 3 (clean_images)", ""]
    i = lines.index("## Metrics (mean over test views)")
    assert lines[i:i + 17] == [
        "## Metrics (mean over test views)", "", "| metric | value |", "|---|---|",
        "| PSNR | 23.46 |", "| SSIM | 0.8123 |", "| MS-SSIM | 0.9123 |", "| LPIPS | n/a |",
        "| MS-SSIM scales | 4 |", "| PSNR, right half | 21.00 |", "| SSIM, right half | 0.7000 |",
        "| PSNR, tower | 19.88 |", "| PSNR, near ground | 25.00 |", "| PSNR, far background | unavailable |",
        "| PSNR inside distractors (train views vs clean) | 14.26 |", "", "Protocol: left half fitted"]
    assert lines[i + 17:i + 20] == ["", "Regions: by depth", ""]
    g = lines.index("## Tower geometry")
    assert lines[g:g + len(report.geometry_lines(GEOMETRY))] == report.geometry_lines(GEOMETRY)
    e = lines.index("## Tower model (export)")
    assert e > g and lines[e:e + 12] == report.export_lines(METRICS["export"])
    c = lines.index("## Method and configuration")
    assert lines[c:c + 9] == [
        "## Method and configuration", "",
        f"- method `{m.method}`: contraction {m.use_contraction} (R = {m.contract_radius}), warp `{m.warp}`, "
        + report._samples_line(m),
        f"- field: {report._field_line(m.field)}",
        f"- NeRF-W: appearance {m.use_appearance}, transient {m.use_transient}",
        "- loss weights from masks: True (floor 0.3)",
        f"- photometric evidence (train.robust.mode): {t.robust.mode}",
        f"- batch {t.batch_rays} rays, {t.max_steps} steps, lr {t.lr_init} -> {t.lr_final} (warm-up {t.warmup}), "
        f"clip {t.max_grad_norm}", ""]
    v = lines.index("## Views (ground truth | render | depth)")
    assert lines[v:v + 6] == ["## Views (ground truth | render | depth)", "",
                              "![ground truth | render | depth](report_views.png)", "",
                              "Tower crops (2x): ![tower crops](report_crops.png)", ""]
    assert lines[v + 6:] == ["## Notes", "", "note one", "note two", ""]
    assert c < v


def test_write_report_figures_by_hand(tmp_path):
    views = _views() + [{"name": "d", "gt": _image(16), "rgb": _image(17), "depth": _depth() + 3},
                        {"name": "e", "gt": _image(18), "rgb": _image(19), "depth": _depth()}]  # only 4 shown
    report.write_report(tmp_path, METRICS, make_config("nerf"), "d", views)
    fig = io.read_image(tmp_path / "report_views.png")
    assert fig.shape == (4 * H + 3 * 2, 3 * W + 4, 3)
    for k, v in enumerate(views[:4]):
        r = k * (H + 2)
        np.testing.assert_array_equal(fig[r:r + H, :W], v["gt"])
        np.testing.assert_array_equal(fig[r:r + H, W + 2:2 * W + 2], np.clip(v["rgb"], 0, 1))
        np.testing.assert_array_equal(fig[r:r + H, 2 * W + 4:], _turbo(v["depth"]))
    # the crop: only view a has tower pixels: rows 5..7, cols 6..9, margin 4 -> rows 1..11, cols 2..13, doubled
    crops = io.read_image(tmp_path / "report_crops.png")
    box = (slice(1, 12), slice(2, 14))
    up = lambda a: np.repeat(np.repeat(a[box], 2, axis=0), 2, axis=1)  # noqa: E731
    a = views[0]
    assert crops.shape == (22, 3 * 24 + 4, 3)
    np.testing.assert_array_equal(crops[:, :24], up(a["gt"]))
    np.testing.assert_array_equal(crops[:, 26:50], up(np.clip(a["rgb"], 0, 1)))
    np.testing.assert_array_equal(crops[:, 52:], up(_turbo(a["depth"])))
    text = (tmp_path / "report.md").read_text()
    assert "## Notes" not in text and text.endswith("Tower crops (2x): ![tower crops](report_crops.png)\n")


def test_write_report_of_no_views_and_bare_metrics(tmp_path):
    cfg = make_config("nerf")
    report.write_report(tmp_path, {}, cfg, "d", [{"name": "x", "gt": _image(1), "rgb": _image(2), "depth": _depth(),
                                                   "semantic": np.zeros((H, W))}])
    assert (tmp_path / "report_views.png").exists() and not (tmp_path / "report_crops.png").exists()
    text = (tmp_path / "report.md").read_text()
    assert "Tower crops" not in text and "![ground truth | render | depth](report_views.png)\n" in text
    (tmp_path / "report_views.png").unlink()
    report.write_report(tmp_path, {}, cfg, "d", [])
    assert not (tmp_path / "report_views.png").exists()
    lines = (tmp_path / "report.md").read_text().split("\n")
    assert lines[:6] == [f"# Run report: {cfg.model.method}", "", "Data: `d`  ", "Trained steps: ?  ",
                         "Evaluated views: ? (images)", ""]
    i = lines.index("## Metrics (mean over test views)")
    assert lines[i + 4:i + 11] == ["| PSNR | unavailable |", "| SSIM | unavailable |", "| MS-SSIM | unavailable |",
                                   "| LPIPS | unavailable |", "", "Protocol: ", ""]
    assert lines[i + 11] == "## Method and configuration"
    assert "## Views (ground truth | render | depth)" not in lines and "## Notes" not in lines
    assert lines[-1] == "" and lines[-2].startswith("- batch ")
    assert f"- loss weights from masks: {cfg.train.use_masks} (floor {cfg.train.mask_weight_floor})" in lines


@pytest.mark.parametrize("robust", ["off", "dpt+robust"])
def test_write_report_names_the_robust_setting(tmp_path, robust):
    cfg = make_config("ours", {"train": {"robust": robust}})
    report.write_report(tmp_path, {}, cfg, "d", [])
    assert f"- photometric evidence (train.robust.mode): {robust}" in (tmp_path / "report.md").read_text().split("\n")


def test_write_report_of_a_config_from_before_robust_says_off(tmp_path):
    """A config whose train section predates train.robust (no such attribute): "off"."""
    import dataclasses
    import types

    cfg = make_config("ours")
    old_train = types.SimpleNamespace(**{k: v for k, v in dataclasses.asdict(cfg.train).items() if k != "robust"})
    report.write_report(tmp_path, {}, types.SimpleNamespace(model=cfg.model, train=old_train), "d", [])
    assert "- photometric evidence (train.robust.mode): off" in (tmp_path / "report.md").read_text().split("\n")


def test_colourise_depth_of_a_half_float_depth():
    """A float16 depth map (a half EXR) is coloured from its inverse in float64."""
    d = (np.arange(1, 201, dtype=np.float64).reshape(10, 20) * 0.37).astype(np.float16)
    np.testing.assert_array_equal(report.colourise_depth(d), _turbo(d.astype(np.float64)))


def test_number_ranges_joins_consecutive_numbers_into_runs():
    assert report.number_ranges([8, 1, 2, 3, 5, 7]) == "1-3, 5, 7-8"
    assert report.number_ranges([4]) == "4" and report.number_ranges([]) == ""
    assert report.number_ranges(list(range(1, 17))) == "1-16"


def test_the_training_fit_row_and_its_reading_appear_only_with_the_figure(tmp_path):
    """report.md's metrics table gets the training batches' PSNR and the words that tell a reader
    what its distance from the held-out PSNR means; without the figure, neither."""
    cfg = make_config("ours")
    metrics = {"mean": {"psnr": 19.4, "ssim": 0.5}, "step": 10, "num_views": 1}
    report.write_report(tmp_path, {**metrics, "training_fit": {"psnr": 27.315, "batches": 3, "from_step": 9}},
                        cfg, "DATA", [], [])
    text = (tmp_path / "report.md").read_text()
    assert "| PSNR of the training batches, last tenth of the run | 27.32 |" in text
    assert report.FIT_WORDS in text and report.FIT_WORDS.startswith("The training batches' PSNR is how well")
    report.write_report(tmp_path, metrics, cfg, "DATA", [], [])
    text = (tmp_path / "report.md").read_text()
    assert "training batches" not in text
