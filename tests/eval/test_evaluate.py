"""The blocks of evaluate.py that decide what metrics.json and report.md say, without training a
run (tests/joins/test_join_eval.py trains one): the means over views (`_mean_of`, `_means`), the
right-half and per-region PSNR, the pooled distractor PSNR (a renderer faked per view), the
protocol and resolution lines, the robust run's weights record, and where the reference cloud
and the export come from. Every answer is worked out by hand or in NumPy here."""

import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from jaxnerf_grid.eval import evaluate, metrics
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError


def _np_psnr(a, b, mask=None):
    """PSNR for data range 1 in float64; mask [H, W]: the mean over its pixels (channels averaged)."""
    err = np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2, axis=-1)
    mse = err.mean() if mask is None else err[mask].mean()
    return -10.0 * np.log10(mse)


# --------------------------------------------------------------------------- means


def test_mean_of_counts_only_finite_numbers():
    rows = [{"a": 1.0}, {"a": None}, {"a": float("inf")}, {"a": float("nan")}, {"a": 4.0}, {"b": 9.0}]
    assert evaluate._mean_of("a", rows) == 2.5
    assert evaluate._mean_of("b", rows) == 9.0
    assert evaluate._mean_of("a", [{"a": None}, {"a": float("-inf")}]) is None
    assert evaluate._mean_of("a", []) is None


def test_means_of_the_views_by_hand():
    """Two views: each metric averaged over the views that have it, the MS-SSIM scale count the
    first view's, the right halves likewise, each region over the views where it is not empty."""
    views = [
        {"psnr": 20.0, "ssim": 0.5, "ms_ssim": 0.25, "ms_ssim_scales": 3, "lpips": None,
         "right_half": {"psnr": 10.0, "ssim": None, "ms_ssim": None, "lpips": None},
         "regions": {"tower": 12.0, "near_ground": None, "far_background": 30.0}},
        {"psnr": 30.0, "ssim": None, "ms_ssim": 0.75, "ms_ssim_scales": 2, "lpips": None,
         "right_half": {"psnr": 16.0, "ssim": 0.4, "ms_ssim": None, "lpips": 0.1},
         "regions": {"tower": 18.0, "near_ground": None, "far_background": float("inf")}},
    ]
    mean, right, regions = evaluate._means(views)
    assert mean == {"psnr": 25.0, "ssim": 0.5, "ms_ssim": 0.5, "lpips": None, "ms_ssim_scales": 3}
    assert right == {"psnr": 13.0, "ssim": 0.4, "ms_ssim": None, "lpips": 0.1}
    assert regions == {"tower": 15.0, "near_ground": None, "far_background": 30.0}
    one = evaluate._means(views[:1])                                  # one view: its own numbers
    assert one[0]["psnr"] == 20.0 and one[2] == {"tower": 12.0, "near_ground": None, "far_background": 30.0}
    no_regions = [dict(v, regions={}) for v in views]
    assert evaluate._means(no_regions)[2] == {}
    assert evaluate._means([]) == ({"psnr": None, "ssim": None, "ms_ssim": None, "lpips": None,
                                    "ms_ssim_scales": None}, dict.fromkeys(evaluate.METRIC_KEYS), {})


# --------------------------------------------------------------------------- halves and regions


def test_right_half_metrics_score_the_right_half_only():
    """8 x 21: the right half is columns 10..20 (11 wide) but only 8 high, under the 11-pixel
    SSIM window: PSNR alone, in NumPy; 12 x 20 (a 10-wide half): PSNR alone. 12 x 23 (12 x 12
    right half) and 11 x 22 (exactly the window): all four metrics, those of
    `metrics.evaluate_image` on the right halves. The left halves differ wildly (a mutant that
    scores them, or the whole image, is far off)."""
    rng = np.random.default_rng(0)
    for h, w in ((8, 21), (12, 20), (12, 23), (11, 22)):
        target = rng.uniform(size=(h, w, 3)).astype(np.float32)
        rgb = np.clip(target + rng.normal(scale=0.05, size=target.shape), 0, 1).astype(np.float32)
        rgb[:, : w // 2] = 1.0 - target[:, : w // 2]
        got = evaluate._right_half_metrics(rgb, target, None)
        assert list(got) == ["psnr", "ssim", "ms_ssim", "lpips"]
        assert got["psnr"] == pytest.approx(_np_psnr(rgb[:, w // 2:], target[:, w // 2:]), abs=1e-4)
        assert got["psnr"] > _np_psnr(rgb, target) + 5
        if min(h, w - w // 2) < 11:
            assert got["ssim"] is None and got["ms_ssim"] is None and got["lpips"] is None
        else:
            ref = metrics.evaluate_image(rgb[:, w // 2:], target[:, w // 2:])
            assert got == {k: ref[k] for k in evaluate.METRIC_KEYS} and 0 < got["ssim"] < 1


def test_right_half_metrics_hand_the_lpips_weights_on(monkeypatch):
    """The LPIPS parameters reach `metrics.evaluate_image` (else a run given --lpips-weights
    reports no right-half LPIPS)."""
    seen = []
    monkeypatch.setattr(evaluate.metrics, "evaluate_image", lambda a, b, lp: seen.append((a.shape, lp)) or {
        "psnr": 1.0, "ssim": 2.0, "ms_ssim": 3.0, "ms_ssim_scales": 1, "lpips": 4.0})
    lp = {"lpips": "weights"}
    got = evaluate._right_half_metrics(np.zeros((12, 24, 3)), np.zeros((12, 24, 3)), lp)
    assert got == {"psnr": 1.0, "ssim": 2.0, "ms_ssim": 3.0, "lpips": 4.0} and seen == [((12, 12, 3), lp)]


def test_region_psnr_inside_each_mask_and_none_for_an_empty_one():
    rng = np.random.default_rng(1)
    target = rng.uniform(size=(5, 6, 3)).astype(np.float32)
    rgb = rng.uniform(size=(5, 6, 3)).astype(np.float32)
    a = np.zeros((5, 6), bool)
    a[1, 2] = a[3, 4] = True
    got = evaluate._region_psnr(rgb, target, {"a": a, "b": np.zeros((5, 6), bool), "all": np.ones((5, 6), bool)})
    assert got["b"] is None and list(got) == ["a", "b", "all"]
    assert got["a"] == pytest.approx(_np_psnr(rgb, target, a), abs=1e-4)
    assert got["all"] == pytest.approx(_np_psnr(rgb, target), abs=1e-4)


# --------------------------------------------------------------------------- distractor PSNR


def test_distractor_psnr_pools_the_masked_pixels_of_the_first_views(monkeypatch):
    """Clean images 0.2 everywhere; renders 0.95 outside the masks (never counted) and inside:
    view 1 0.3 (2 masked pixels: squared error 0.01 each), view 2 0.5 (1 pixel: 0.09), view 3
    1.5 and -0.8 (clipped to 1 and 0: 0.64 and 0.04); view 0 has an empty mask and is skipped.
    max_views 2: views 1 and 2 pooled, MSE (0.02 + 0.09) / 3 = 0.036667, PSNR 14.357 dB (the mean
    of the two views' MSEs, 0.05, would be 13.010); max_views 1: view 1 alone, 20 dB; max_views
    3: (0.02 + 0.09 + 0.64 + 0.04) / 5 = 0.158, 8.013 dB."""
    n, h, w = 4, 3, 4
    masks = np.zeros((n, h, w), np.float32)
    masks[1, 0, :2] = 1
    masks[2, 2, 3] = 1
    masks[3, 1, 1:3] = 1
    inside = {1: [0.3, 0.3], 2: [0.5], 3: [1.5, -0.8]}
    ds = SimpleNamespace(distractor_masks=masks, clean_images=np.full((n, h, w, 3), 0.2, np.float32),
                         split={"train": np.arange(n)})
    params, cfg = object(), object()
    rendered = []

    def render_view(params_, cfg_, ds_, i):
        assert params_ is params and cfg_ is cfg and ds_ is ds
        rendered.append(i)
        rgb = np.full((h, w, 3), 0.95, np.float32)
        rgb[masks[i] > 0] = np.asarray(inside[i], np.float32)[:, None]
        return {"rgb": rgb}

    monkeypatch.setattr(evaluate.views, "render_view", render_view)
    assert evaluate.distractor_psnr(params, cfg, ds, 2) == pytest.approx(-10 * np.log10(0.11 / 3), abs=1e-4)
    assert rendered == [1, 2]
    assert evaluate.distractor_psnr(params, cfg, ds, 1) == pytest.approx(20.0, abs=1e-4)
    assert evaluate.distractor_psnr(params, cfg, ds, 3) == pytest.approx(-10 * np.log10(0.79 / 5), abs=1e-4)
    assert round(-10 * np.log10(0.11 / 3), 3) == 14.357 and round(-10 * np.log10(0.79 / 5), 3) == 8.013
    # nothing to score: no masks, no clean images, no views asked, or every mask empty
    rendered.clear()
    assert evaluate.distractor_psnr(params, cfg, SimpleNamespace(**{**vars(ds), "distractor_masks": None}), 2) is None
    assert evaluate.distractor_psnr(params, cfg, SimpleNamespace(**{**vars(ds), "clean_images": None}), 2) is None
    assert evaluate.distractor_psnr(params, cfg, ds, 0) is None
    empty = SimpleNamespace(**{**vars(ds), "distractor_masks": np.zeros_like(masks)})
    assert evaluate.distractor_psnr(params, cfg, empty, 2) is None and rendered == []


# --------------------------------------------------------------------------- words


def _cfg(appearance=False, transient=False, max_side=800, appearance_steps=30):
    return SimpleNamespace(model=SimpleNamespace(use_appearance=appearance, use_transient=transient),
                           train=SimpleNamespace(max_side=max_side, appearance_steps=appearance_steps))


def test_protocol_in_words():
    clean, plain = SimpleNamespace(clean_images=np.zeros(1)), SimpleNamespace(clean_images=None)
    nerfw = ("; NeRF-W: the appearance embedding of each test image is fitted on its left half (network frozen) "
             "and the headline metrics are computed on the right half only")
    assert evaluate._protocol(clean, _cfg()) == "targets are the clean images"
    assert evaluate._protocol(plain, _cfg()) == "targets are the images"
    assert evaluate._protocol(clean, _cfg(appearance=True)) == "targets are the clean images" + nerfw
    assert evaluate._protocol(plain, _cfg(transient=True)) == ("targets are the images; rendering shows the static "
                                                               "scene only")
    assert evaluate._protocol(plain, _cfg(True, True)) == ("targets are the images" + nerfw
                                                           + "; rendering shows the static scene only")
    assert evaluate._protocol(plain, _cfg(True, appearance_steps=0)) == (
        "targets are the images; each test image renders with the mean of the training photos' appearance "
        "embeddings (no test pixel used, train.appearance_steps = 0)")


def test_resolution_record_and_its_line():
    ds = SimpleNamespace(width=200, height=150, meta={"native_size": [4000.0, 3000.0]})
    res = evaluate.resolution_record(ds, _cfg(max_side=200), False)
    assert res == {"width": 200, "height": 150, "native_width": 4000, "native_height": 3000, "max_side": 200,
                   "full_size": False}
    assert type(res["native_width"]) is int and type(res["max_side"]) is int
    assert evaluate.resolution_note(res) == (
        "Resolution: trained and rendered at 200x150, the working resolution of the 4000x3000 photos "
        "(`train.max_side` 200; `eval --full-size` for full size).")
    assert evaluate.resolution_note({**res, "full_size": True}) == (
        "Resolution: test views rendered at the photos' full size, 200x150 (`--full-size`).")
    for meta in ({}, {"native_size": None}):      # no record: the photos are the size trained at
        res = evaluate.resolution_record(SimpleNamespace(width=64, height=48, meta=meta), _cfg(), 1)
        assert res == {"width": 64, "height": 48, "native_width": 64, "native_height": 48, "max_side": 800,
                       "full_size": True}
        assert evaluate.resolution_note({**res, "full_size": False}) == ("Resolution: trained and rendered at "
                                                                         "the photos' size, 64x48.")
    # the same width, another height is not the photos' size
    res = {"width": 64, "height": 48, "native_width": 64, "native_height": 96, "max_side": 9, "full_size": False}
    assert evaluate.resolution_note(res).startswith("Resolution: trained and rendered at 64x48, the working")


# --------------------------------------------------------------------------- a robust run's weights


def test_training_weights_read_back_by_hand(tmp_path):
    """Training views 0, 2, 3, 5 of 6; weights written for 0 (all 1), 2 (all 0) and 5 (0.2 on
    half the pixels, 1 on the rest: mean 0.6), none for 3. ignored_share is the mean over the
    three of 1 - mean: (0 + 1 + 0.4) / 3. Three panels at positions linspace(0, 3, 3) = 0, 1.5, 3,
    rounded to 0, 2, 3: views 0, 3, 5; 3 has no weights, so rows for 0 and 5, each (photo, the
    DPT weight or ones without one, the weight used)."""
    n, h, w = 6, 4, 6
    images = np.random.default_rng(2).uniform(size=(n, h, w, 3)).astype(np.float32)
    ds = SimpleNamespace(split={"train": np.array([0, 2, 3, 5])}, frame_paths=[f"images/v{i}.png" for i in range(n)],
                         images=images, weights=None)
    assert evaluate.training_weights(tmp_path, ds) is None                       # no weights/ folder
    (tmp_path / "weights").mkdir()
    io.write_png(tmp_path / "weights/other.png", np.ones((h, w), np.float32))
    assert evaluate.training_weights(tmp_path, ds) is None                       # none of a training view
    half = np.ones((h, w), np.float32)
    half[:, :3] = 51 / 255                                                       # 0.2, exact in 8 bits
    for i, wmap in ((0, np.ones((h, w))), (2, np.zeros((h, w))), (5, half)):
        io.write_png(tmp_path / f"weights/v{i}.png", wmap)
    got = evaluate.training_weights(tmp_path, ds)
    assert got["ignored_share"] == pytest.approx((0 + 1 + 0.4) / 3, abs=1e-6)
    assert len(got["rows"]) == 2
    for row, i in zip(got["rows"], (0, 5)):
        np.testing.assert_array_equal(row[0], images[i])
    np.testing.assert_array_equal(got["rows"][0][1], np.ones((h, w), np.float32))
    np.testing.assert_allclose(got["rows"][1][2], half, atol=1e-6)
    np.testing.assert_array_equal(got["rows"][0][2], np.ones((h, w), np.float32))
    prior = np.random.default_rng(3).uniform(size=(n, h, w)).astype(np.float32)
    got = evaluate.training_weights(tmp_path, SimpleNamespace(**{**vars(ds), "weights": prior}), panels=2)
    assert len(got["rows"]) == 2                                                 # panels 0 and 3: views 0, 5
    for row, i in zip(got["rows"], (0, 5)):
        np.testing.assert_array_equal(row[1], prior[i])


# --------------------------------------------------------------------------- the reference cloud, the export


def test_reference_cloud_a_users_file_or_the_datasets_tower(tmp_path):
    ply = tmp_path / "ref.ply"
    io.write_ply(ply, np.zeros((3, 3)))
    norm = {"scale": 0.5}
    ds = SimpleNamespace(root=tmp_path, meta={"tower_ply": "ref.ply", "scene_normalization": norm})
    assert evaluate.reference_cloud(ds, str(ply)) == (ply, None)
    assert evaluate.reference_cloud(ds) == (tmp_path / "ref.ply", norm)
    assert evaluate.reference_cloud(SimpleNamespace(root=tmp_path, meta={"tower_ply": "ref.ply"})) == (ply, None)
    for meta in (None, {}, {"tower_ply": ""}, {"tower_ply": "gone.ply"}):
        assert evaluate.reference_cloud(SimpleNamespace(root=tmp_path, meta=meta)) is None
    with pytest.raises(DataError, match="^" + re.escape(f"{tmp_path / 'gone.ply'}: reference point cloud not found "
                                                        "(eval.reference_ply)") + "$"):
        evaluate.reference_cloud(ds, tmp_path / "gone.ply")


def test_score_geometry_and_the_export_section_hand_on_the_normalisations(tmp_path, monkeypatch):
    """The reference in the file's own normalisation: geometry scores with both the file's and the
    dataset's; a user's cloud (already in the dataset's units): neither. The export section reads
    measurements.json, names the picture, and scores only with a reference, with the dataset's
    scale (1.0 without one)."""
    calls = []
    monkeypatch.setattr(evaluate.geometry, "score_against_ply",
                        lambda cloud, path, **kw: calls.append((cloud, path, kw)) or {"f": 1})
    monkeypatch.setattr(evaluate.score, "reference_in_export_units",
                        lambda points, file_norm, scene_norm: calls.append((len(points), file_norm, scene_norm)) or "P")
    monkeypatch.setattr(evaluate.score, "score_export", lambda folder, points, scale: calls.append(
        (folder, points, scale)) or {"s": 2})
    ply = tmp_path / "ref.ply"
    io.write_ply(ply, np.zeros((3, 3)))
    file_norm, scene_norm = {"scale": 0.5}, {"scale": 4.0}
    ds = SimpleNamespace(root=tmp_path, meta={"tower_ply": "ref.ply", "scene_normalization": file_norm},
                         normalization=scene_norm)
    assert evaluate.score_geometry(ds, ["cloud"]) == {"f": 1}
    assert calls.pop() == (["cloud"], ply, {"file_normalization": file_norm, "scene_normalization": scene_norm})
    assert evaluate.score_geometry(ds, ["cloud"], str(ply)) == {"f": 1}
    assert calls.pop() == (["cloud"], ply, {"file_normalization": None, "scene_normalization": None})
    assert evaluate.score_geometry(SimpleNamespace(root=tmp_path, meta={}, normalization=scene_norm), []) is None
    assert calls == []

    run = tmp_path / "run"
    assert evaluate.export_section(ds, run) is None
    io.write_json(run / "export/measurements.json", {"height": 30.0})
    bare = SimpleNamespace(root=tmp_path, meta={}, normalization={})
    assert evaluate.export_section(bare, run) == {"measurements": {"height": 30.0},
                                                  "image": "export/export_views.png"}
    assert calls == []
    assert evaluate.export_section(ds, str(run)) == {"measurements": {"height": 30.0},
                                                     "image": "export/export_views.png", "score": {"s": 2}}
    assert calls == [(3, file_norm, scene_norm), (Path(run) / "export", "P", 4.0)]
    calls.clear()
    evaluate.export_section(SimpleNamespace(**{**vars(bare), "meta": None}), run, str(ply))
    assert calls == [(3, None, {}), (Path(run) / "export", "P", 1.0)]


def test_region_masks_at_exactly_100_metres():
    """Far background is vegetation or building *beyond* 100 m: at scale 0.5 (exact in binary) a
    normalised depth of 50.0 is exactly 100 m (not far), 50.01 is 100.02 m (far), 49.99 is
    99.98 m (not); sky is far at any depth; tower = classes 1-2, near ground = class 3."""
    sem = np.array([[4, 4, 4, 5, 5, 5, 0, 1, 2, 3]], np.uint8)
    depth = np.array([[49.99, 50.0, 50.01, 49.99, 50.0, 50.01, 1.0, 60.0, 60.0, 60.0]], np.float32)
    ds = SimpleNamespace(semantics=sem[None], depth=depth[None], normalization={"scale": 0.5})
    got = evaluate.region_masks(ds, 0)
    assert {k: v.astype(int).tolist() for k, v in got.items()} == {
        "tower": [[0, 0, 0, 0, 0, 0, 0, 1, 1, 0]], "near_ground": [[0, 0, 0, 0, 0, 0, 0, 0, 0, 1]],
        "far_background": [[0, 0, 1, 0, 0, 1, 1, 0, 0, 0]]}
    assert evaluate.region_masks(SimpleNamespace(semantics=None), 0) == {}


def test_training_fit_averages_the_late_batches_mse_not_their_psnr():
    """Two late batches at 20 and 30 dB are MSEs 0.01 and 0.001: their mean 0.0055 is 22.60 dB
    (the mean of the PSNRs would say 25); earlier records, records without a PSNR and a
    non-finite one are left out; none late: None."""
    log = [{"step": 50, "psnr": 10.0}, {"step": 90, "psnr": 40.0}, {"step": 91, "psnr": 20.0},
           {"step": 95, "loss": 0.1}, {"step": 98, "psnr": float("nan")}, {"step": 100, "psnr": 30.0}]
    fit = evaluate.training_fit(log, 100)
    assert fit == {"psnr": pytest.approx(-10 * np.log10(0.0055), abs=1e-12), "batches": 2, "from_step": 90}
    assert evaluate.training_fit(log, 100, tail=0.6)["batches"] == 4   # from step 40: 10, 40, 20 and 30 dB
    assert evaluate.training_fit(log[:1], 100) is None and evaluate.training_fit([], 10) is None
