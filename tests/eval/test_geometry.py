"""geometry.py against brute-force nearest distances and closed-form F-score cases; io.read_ply."""

import numpy as np
import pytest

from jaxnerf_grid.eval import geometry
from jaxnerf_grid.util import io


def brute_nearest(a, b):
    """O(N M) loop: distance from each a_i to its nearest b_j."""
    out = np.empty(len(a))
    for i, p in enumerate(a):
        out[i] = min(np.sqrt(np.sum((p - q) ** 2)) for q in b)
    return out


def brute_prf(pred, ref, tau):
    d_pred, d_ref = brute_nearest(pred, ref), brute_nearest(ref, pred)
    p = sum(d <= tau for d in d_pred) / len(pred)
    r = sum(d <= tau for d in d_ref) / len(ref)
    return p, r, (2 * p * r / (p + r) if p + r else 0.0)


def test_nearest_distances_match_brute_force():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(37, 3)), rng.normal(size=(23, 3))
    np.testing.assert_allclose(geometry.nearest_distances(a, b), brute_nearest(a, b), rtol=1e-12)
    np.testing.assert_allclose(geometry.nearest_distances(b, a), brute_nearest(b, a), rtol=1e-12)


def test_prf_and_chamfer_match_brute_force():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0, 1, size=(40, 3))
    pred = np.concatenate([ref[:25] + rng.normal(scale=0.03, size=(25, 3)), rng.uniform(0, 1, size=(10, 3))])
    taus = (0.02, 0.05, 0.1)
    got = geometry.precision_recall_fscore(pred, ref, taus)
    for tau in taus:
        p, r, f = brute_prf(pred, ref, tau)
        assert got[tau]["precision"] == pytest.approx(p)
        assert got[tau]["recall"] == pytest.approx(r)
        assert got[tau]["fscore"] == pytest.approx(f)
    # 35 vs 40 points: precision and recall differ, so a swap would show
    assert got[0.05]["precision"] != pytest.approx(got[0.05]["recall"])
    want = 0.5 * (brute_nearest(pred, ref).mean() + brute_nearest(ref, pred).mean())
    assert geometry.chamfer(pred, ref) == pytest.approx(want)


def test_fscore_closed_forms():
    rng = np.random.default_rng(2)
    ref = rng.uniform(0, 1, size=(50, 3)) * [1, 1, 0]   # points on the plane z = 0
    tau = 0.01
    same = geometry.precision_recall_fscore(ref, ref, (tau,))[tau]
    assert same == {"precision": 1.0, "recall": 1.0, "fscore": 1.0}
    assert geometry.chamfer(ref, ref) == 0.0
    # shifted by 2 tau off the plane: every nearest distance is exactly 2 tau
    shifted = ref + [0, 0, 2 * tau]
    got = geometry.precision_recall_fscore(shifted, ref, (tau, 3 * tau))
    assert got[tau] == {"precision": 0.0, "recall": 0.0, "fscore": 0.0}
    assert got[3 * tau] == {"precision": 1.0, "recall": 1.0, "fscore": 1.0}
    assert geometry.chamfer(shifted, ref) == pytest.approx(2 * tau)
    # half the prediction on the reference, half far away: P = 1/2, R = 1, F = 2/3
    half = np.concatenate([ref, ref + 10.0])
    got = geometry.precision_recall_fscore(half, ref, (tau,))[tau]
    assert (got["precision"], got["recall"]) == (0.5, 1.0) and got["fscore"] == pytest.approx(2 / 3)


def test_empty_prediction_scores_zero():
    ref = np.random.default_rng(3).uniform(0, 1, size=(20, 3))
    got = geometry.precision_recall_fscore(np.zeros((0, 3)), ref, (0.1,))[0.1]
    assert got == {"precision": 0.0, "recall": 0.0, "fscore": 0.0}
    assert geometry.chamfer(np.zeros((0, 3)), ref) is None
    assert np.all(np.isinf(geometry.nearest_distances(ref, np.zeros((0, 3)))))
    res = geometry.score_points(np.zeros((0, 3)), ref, (0.1,), ground_strip=0.0)
    assert res["num_pred"] == 0 and res["num_ref"] == 20 and res["chamfer"] is None
    assert res["thresholds"]["0.1"] == {"precision": 0.0, "recall": 0.0, "fscore": 0.0}


def test_crop_and_ground_strip():
    pts = np.array([[0, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5], [1.01, 0.5, 0.5], [0.5, -0.01, 0.5]])
    np.testing.assert_array_equal(geometry.crop_to_box(pts, [0, 0, 0], [1, 1, 1]), pts[:3])
    ref = np.array([[0.0, 0.0, -0.75], [0.2, 0.1, 0.75], [0.1, -0.3, 0.0]])
    lo, hi = geometry.tower_box(ref, ground_strip=0.05)
    np.testing.assert_allclose(lo, [0.0, -0.3, -0.70])      # z (up) raised by the strip only
    np.testing.assert_allclose(hi, [0.2, 0.1, 0.75])
    with pytest.raises(ValueError):
        geometry.tower_box(ref, ground_strip=2.0)


def test_score_points_crops_both_clouds():
    """A tower (vertical segment) on a ground plane: the ground in the prediction and the
    reference's own foot are cut by the strip; the points outside the box are not scored."""
    z = np.linspace(0.0, 1.0, 101)
    tower = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=-1)            # 0.01 spacing
    g = np.arange(-10, 11) * 0.05                                                 # holds 0.0 exactly
    ground = np.stack(np.meshgrid(g, g, [0.0]), -1).reshape(-1, 3)               # the plane z = 0
    floater = np.array([[0.0, 0.0, 5.0]])                                         # above the box
    pred = np.concatenate([tower, ground, floater])
    res = geometry.score_points(pred, tower, thresholds=(0.001,), ground_strip=0.05)
    # the crop keeps exactly the tower points with z >= 0.05 in both clouds -> F = 1
    assert res["num_ref"] == res["num_pred"] == int(np.sum(z >= 0.05))
    assert res["thresholds"]["0.001"] == {"precision": 1.0, "recall": 1.0, "fscore": 1.0}
    assert res["chamfer"] == 0.0 and res["box"]["min"][2] == pytest.approx(0.05)
    # without the strip the ground's centre point (on the tower's foot) is in the box too
    assert geometry.score_points(pred, tower, (0.001,), ground_strip=0.0)["num_pred"] == len(tower) + 1


def test_reference_units_conversion():
    """A tower.ply stored in one normalisation is mapped into the dataset's (composed) one."""
    from jaxnerf_grid.data.normalize import apply_normalization_to_points, compose_normalization

    metric = np.random.default_rng(4).uniform(-5, 30, size=(10, 3))
    file_norm = {"scale": 0.05, "translation": [0.0, 0.0, -15.0]}
    scene_norm = compose_normalization(file_norm, {"scale": 1.7, "translation": [0.1, -0.2, 0.3]})
    stored = apply_normalization_to_points(metric, file_norm)
    np.testing.assert_allclose(geometry.reference_to_scene(stored, file_norm, scene_norm),
                               apply_normalization_to_points(metric, scene_norm), atol=1e-9)
    np.testing.assert_array_equal(geometry.reference_to_scene(stored, file_norm, dict(file_norm)), stored)
    np.testing.assert_array_equal(geometry.reference_to_scene(stored, None, scene_norm), stored)
    # records with a rotation (x_norm = s R (x + t)): the formula written out
    rot = np.array([[0.0, -1.0, 0.0], [0.6, 0.0, 0.8], [-0.8, 0.0, 0.6]])
    rotated = {"scale": 0.2, "translation": [1.0, 2.0, -3.0], "rotation": rot.tolist()}
    expect = np.stack([0.2 * rot @ (x + [1.0, 2.0, -3.0]) for x in metric])
    np.testing.assert_allclose(geometry.reference_to_scene(stored, file_norm, rotated), expect, atol=1e-9)
    np.testing.assert_allclose(geometry.reference_to_scene(expect, rotated, file_norm), stored, atol=1e-9)


def test_score_against_ply(tmp_path):
    """The function evaluate_run calls: exported cloud parts vs a PLY; equal clouds score F = 1."""
    rng = np.random.default_rng(5)
    ref = rng.uniform(-0.3, 0.3, size=(200, 3)).astype(np.float32)
    io.write_ply(tmp_path / "tower.ply", ref)
    parts = [(ref[:120], np.ones((120, 3))), (ref[120:], np.ones((80, 3)))]
    res = geometry.score_against_ply(parts, tmp_path / "tower.ply", ground_strip=0.0)
    assert set(res) >= {"thresholds", "chamfer", "num_pred", "num_ref", "box", "reference", "units"}
    assert set(res["thresholds"]) == {"0.01", "0.02", "0.05"}
    assert all(v["fscore"] == 1.0 for v in res["thresholds"].values()) and res["chamfer"] == 0.0
    empty = geometry.score_against_ply([], tmp_path / "tower.ply")
    assert empty["num_pred"] == 0 and empty["chamfer"] is None
    assert all(v["fscore"] == 0.0 for v in empty["thresholds"].values())


def test_read_reference_points_returns_the_vertices_and_refuses_empty_or_non_finite_word_for_word(tmp_path):
    """The vertices of a written cloud as written (float32: 0.5, -1.25, 3.0 are exact); one point
    is enough; no point, or one coordinate nan, +inf or -inf among finite ones, is a DataError
    whose whole message names the file and says which."""
    pts = np.array([[0.5, -1.25, 3.0], [1.0, 2.0, -7.5]], np.float32)
    io.write_ply(tmp_path / "two.ply", pts)
    np.testing.assert_array_equal(geometry.read_reference_points(tmp_path / "two.ply"), pts)
    io.write_ply(tmp_path / "one.ply", pts[:1])
    np.testing.assert_array_equal(geometry.read_reference_points(tmp_path / "one.ply"), pts[:1])
    io.write_ply(tmp_path / "empty.ply", np.zeros((0, 3), np.float32))
    with pytest.raises(io.DataError) as err:
        geometry.read_reference_points(tmp_path / "empty.ply")
    assert str(err.value) == f"{tmp_path / 'empty.ply'}: the reference point cloud is empty"
    for bad in (np.nan, np.inf, -np.inf):
        broken = pts.copy()
        broken[1, 2] = bad
        io.write_ply(tmp_path / "bad.ply", broken)
        with pytest.raises(io.DataError) as err:
            geometry.read_reference_points(tmp_path / "bad.ply")
        assert str(err.value) == (f"{tmp_path / 'bad.ply'}: the reference point cloud has coordinates that are "
                                  "not finite numbers")


def test_report_geometry_section():
    from jaxnerf_grid.report import markdown as report

    res = geometry.score_points(np.eye(3), np.eye(3), ground_strip=0.0)
    text = "\n".join(report.geometry_lines({**res, "reference": "tower.ply"}))
    assert "## Tower geometry" in text and "| 0.02 | 1.0000 | 1.0000 | 1.0000 |" in text
    assert "Chamfer distance" in text
    assert report.geometry_lines(None) == []


# --------------------------------------------------------------------------- io.read_ply


def test_read_ply_round_trips_write_ply(tmp_path):
    pts = np.random.default_rng(6).normal(size=(15, 3)).astype(np.float32)
    cols = np.random.default_rng(7).uniform(size=(15, 3))
    io.write_ply(tmp_path / "p.ply", pts, cols, faces=np.array([[0, 1, 2]]))
    v = io.read_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], -1), pts)
    np.testing.assert_array_equal(v["red"], np.round(cols[:, 0] * 255).astype(np.uint8))
    np.testing.assert_array_equal(io.read_ply_points(tmp_path / "p.ply"), pts)


def test_read_ply_ascii_and_big_endian_double(tmp_path):
    pts = np.array([[0.5, -1.25, 3.0], [1e-3, 2.0, -7.5]])
    ascii_ply = ("ply\r\nformat ascii 1.0\r\ncomment survey export\r\nelement vertex 2\r\n"
                 "property double x\r\nproperty double y\r\nproperty double z\r\nproperty uchar red\r\n"
                 "element face 0\r\nproperty list uchar int vertex_indices\r\nend_header\r\n"
                 "0.5 -1.25 3.0 10\r\n0.001 2.0 -7.5 20\r\n")
    (tmp_path / "a.ply").write_bytes(ascii_ply.encode("ascii"))
    np.testing.assert_allclose(io.read_ply_points(tmp_path / "a.ply"), pts.astype(np.float32))
    header = ("ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
              "property double z\nend_header\n").encode("ascii")
    (tmp_path / "b.ply").write_bytes(header + pts.astype(">f8").tobytes())
    np.testing.assert_allclose(io.read_ply_points(tmp_path / "b.ply"), pts.astype(np.float32))
    (tmp_path / "c.ply").write_bytes(header + pts.astype(">f8").tobytes()[:20])
    with pytest.raises(io.DataError, match="c.ply"):
        io.read_ply_points(tmp_path / "c.ply")


def test_score_geometry_of_a_dataset(tmp_path):
    """evaluate.score_geometry (what evaluate_run stores as metrics["geometry"]): the dataset's
    tower_ply, stored in the file's normalisation, against a cloud in the dataset's (re-normalised)
    frame; --reference-ply instead; None without a reference."""
    from types import SimpleNamespace

    from jaxnerf_grid.data.normalize import apply_normalization_to_points, compose_normalization
    from jaxnerf_grid.eval import evaluate

    metric = np.random.default_rng(8).uniform([-4, -4, 0], [4, 4, 30], size=(300, 3))
    file_norm = {"scale": 0.05, "translation": [0.0, 0.0, -15.0]}
    scene_norm = compose_normalization(file_norm, {"scale": 0.8, "translation": [0.05, 0.0, 0.1]})
    io.write_ply(tmp_path / "tower.ply", apply_normalization_to_points(metric, file_norm))
    ds = SimpleNamespace(root=tmp_path, normalization=scene_norm,
                         meta={"tower_ply": "tower.ply", "scene_normalization": file_norm})
    # the reference in the scene's frame (checked against the metric points; bit-equal to what
    # score_geometry computes, so no point sits a rounding error outside the crop box)
    pred = geometry.reference_to_scene(io.read_ply_points(tmp_path / "tower.ply"), file_norm, scene_norm)
    np.testing.assert_allclose(pred, apply_normalization_to_points(metric, scene_norm), atol=1e-5)
    cloud = [(pred[:100], np.zeros((100, 3))), (pred[100:], np.zeros((200, 3)))]
    res = evaluate.score_geometry(ds, cloud)
    assert res["reference"] == str(tmp_path / "tower.ply") and res["num_pred"] == res["num_ref"] > 250
    assert all(v["fscore"] == 1.0 for v in res["thresholds"].values()) and res["chamfer"] == 0.0
    # the same points read as if already in the scene's units would be off: F < 1
    off = evaluate.score_geometry(ds, cloud, reference_ply=tmp_path / "tower.ply")
    assert off["thresholds"]["0.01"]["fscore"] < 0.5
    assert evaluate.score_geometry(SimpleNamespace(root=tmp_path, normalization=scene_norm, meta={}), cloud) is None
    ds.meta["tower_ply"] = "missing.ply"
    assert evaluate.score_geometry(ds, cloud) is None
    with pytest.raises(io.DataError, match="missing.ply"):
        evaluate.score_geometry(ds, cloud, reference_ply=tmp_path / "missing.ply")
