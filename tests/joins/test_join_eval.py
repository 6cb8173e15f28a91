"""Where rendering joins evaluation and the report: `evaluate.evaluate_run` on a tiny trained
run whose dataset is built here, so every region and every target is known by construction.

* The clean images (the evaluation targets, docs/DATASET.md) differ from the training images by
  a different offset in each region, so evaluating against the wrong target, or a region
  against another region's pixels, moves the numbers by decibels.
* The reference for every number is computed here: the float render of the test view
  (`views.render_view`, the renderer tested in test_models / test_train), the regions of
  `evaluate.REGION_DEFINITION` painted by hand, PSNR as -10 log10(MSE) in NumPy, SSIM from
  scikit-image. The written render PNG is checked to be that float render rounded to 8 bits,
  so the float numbers can be compared to 1e-3 dB instead of what rounding would blur.
* NeRF-W (docs: `evaluate.py`'s protocol): the appearance embedding is fitted on the left half
  of the test image and the headline metrics are the right half's.
* report.md's tables are read back and compared with metrics.json; its figures are cut into
  their panels and compared with the ground truth, the render PNG and the depth EXR.
"""

import json
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from jaxnerf_grid.data.formats import save_transforms_json
from jaxnerf_grid.eval import evaluate
from jaxnerf_grid.render import views
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import runs
from jaxnerf_grid.util import io
from tests.train.test_loop import TINY_FIELD, tiny_dataset

H, W = 16, 24          # the right half (12 px) is wide enough for SSIM's 11-px window
TEST = 4               # tiny_dataset's test frame
SCALE = 0.05           # metric -> normalised (x_norm = SCALE * x_metric), as the synthetic scenes
NEAR_M, FAR_M = 40.0, 200.0


def _semantics_and_depth():
    """One frame's classes and z-depth (normalised units), by construction:
    rows 0-3 sky; rows 4-5 vegetation, cols 0-7 far / 8-15 near, building cols 16-23 far;
    rows 6-9 a conductor (cols 0-5), near vegetation (6-9), the tower (10-13), near building
    (14-17), far vegetation (18-23); rows 10-15 ground."""
    sem = np.zeros((H, W), np.uint8)
    depth = np.full((H, W), NEAR_M * SCALE, np.float32)
    sem[4:6, :16], sem[4:6, 16:] = 4, 5
    depth[4:6, :8], depth[4:6, 16:] = FAR_M * SCALE, FAR_M * SCALE
    sem[6:10, 0:6], sem[6:10, 6:10], sem[6:10, 10:14], sem[6:10, 14:18], sem[6:10, 18:] = 2, 4, 1, 5, 4
    depth[6:10, 18:] = FAR_M * SCALE
    sem[10:] = 3
    depth[:4] = np.inf
    return sem, depth


def expected_regions():
    """REGION_DEFINITION's masks of the frame above, written out by hand."""
    tower = np.zeros((H, W), bool)
    tower[6:10, 0:6] = tower[6:10, 10:14] = True
    near = np.zeros((H, W), bool)
    near[10:] = True
    far = np.zeros((H, W), bool)
    far[:4] = True
    far[4:6, :8] = far[4:6, 16:] = far[6:10, 18:] = True
    return {"tower": tower, "near_ground": near, "far_background": far}


# Added to the training image to make the clean target, per region: big, and different everywhere.
OFFSETS = {"tower": 0.30, "near_ground": -0.12, "far_background": 0.06}
# and a checkerboard on the left half (no appearance embedding can fit it), so whole-image and
# right-half scores differ
LEFT_OFFSET = 0.25


def _quantise(x):
    return np.round(np.clip(x, 0, 1) * 255) / 255


def region_dataset():
    ds = tiny_dataset(width=W, height=H)
    ds.images = _quantise(ds.images).astype(np.float32)
    sem, depth = _semantics_and_depth()
    n = ds.num_frames
    ds.semantics = np.repeat(sem[None], n, 0)
    ds.depth = np.repeat(depth[None], n, 0)
    clean = ds.images.copy()
    for region, mask in expected_regions().items():
        clean[:, mask] += OFFSETS[region]
    yy, xx = np.mgrid[0:H, 0: W // 2]
    clean[:, :, : W // 2] += LEFT_OFFSET * np.where((yy + xx) % 2, 1.0, -1.0)[..., None]
    ds.clean_images = _quantise(clean).astype(np.float32)
    ds.distractor_masks = np.zeros((n, H, W), bool)
    ds.distractor_masks[:, 1:3, 1:4] = True
    ds.normalization = {"scale": SCALE, "translation": [0.0, 0.0, 0.0]}
    ds.frame_paths = [f"images/frame_{i:03d}.png" for i in range(n)]
    return ds


def tiny_overrides(method):
    model = {"field": TINY_FIELD, "num_coarse": 8, "num_fine": 8}
    if method == "nerfw":
        model.update(appearance_dim=4, transient_dim=4)
    return {"model": model,
            "train": {"batch_rays": 64, "max_steps": 12, "checkpoint_every": 12, "log_every": 6, "warmup": 2,
                      "lr_init": 5e-3, "lr_final": 1e-3, "chunk": 256, "num_devices": 2,
                      "appearance_steps": 10, "appearance_rays": 96}}


def psnr(a, b, mask=None):
    """-10 log10 of the mean squared error over the pixels of `mask` (all), channels averaged."""
    sq = np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2, axis=-1)
    return float(-10 * np.log10(sq[mask].mean() if mask is not None else sq.mean()))


def ssim(a, b):
    return structural_similarity(np.asarray(a, np.float64), np.asarray(b, np.float64), gaussian_weights=True,
                                 sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)


def _train_and_evaluate(root: Path, method: str, spy=None):
    save_transforms_json(region_dataset(), root / "data")
    run, _, _ = runs.train_run(str(root / "data"), method, root / "run", tiny_overrides(method), progress=False)
    metrics = evaluate.evaluate_run(run, progress=False)
    cfg, data = runs.load_run(run)
    ds = runs.load_dataset(data, progress=False)
    params, _ = train.load_params(run, cfg, ds)
    return {"run": Path(run), "metrics": metrics, "cfg": cfg, "ds": ds, "params": params}


@pytest.fixture(scope="module")
def ours(tmp_path_factory):
    return _train_and_evaluate(tmp_path_factory.mktemp("eval_ours"), "ours")


class _FitSpy:
    """Wraps views.fit_appearance: records what it was given and what it returned."""

    def __init__(self, real):
        self.real, self.calls = real, []

    def __call__(self, params, mcfg, tcfg, r, target, key, start=None):
        emb = self.real(params, mcfg, tcfg, r, target, key, start=start)
        self.calls.append({"rays": r, "target": np.asarray(target), "emb": np.asarray(emb)})
        return emb


@pytest.fixture(scope="module")
def nerfw(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    spy = _FitSpy(views.fit_appearance)
    mp.setattr(views, "fit_appearance", spy)
    try:
        out = _train_and_evaluate(tmp_path_factory.mktemp("eval_nerfw"), "nerfw")
    finally:
        mp.undo()
    out["spy"] = spy
    return out


def _float_render(r, appearance=None):
    """The test view rendered in float by the renderer alone, checked to be the written PNG
    rounded to 8 bits (so the PNG is what was scored)."""
    rgb = np.clip(views.render_view(r["params"], r["cfg"], r["ds"], TEST, appearance=appearance)["rgb"], 0, 1)
    png = io.read_image(r["run"] / "renders" / f"{runs.frame_name(r['ds'], TEST)}.png")
    assert np.abs(png - rgb).max() <= 0.5 / 255 + 1e-6
    return rgb


def test_region_masks_are_the_regions_painted_by_hand():
    ds = region_dataset()
    got = evaluate.region_masks(ds, TEST)
    assert set(got) == set(expected_regions())
    for name, mask in expected_regions().items():
        np.testing.assert_array_equal(got[name], mask, err_msg=name)
    # a normalisation without a scale: the depth is taken as metres (found by mutation testing)
    far_px = ds.depth[TEST] == FAR_M * SCALE
    ds.normalization = {"translation": [0.0, 0.0, 0.0]}
    ds.depth = np.where(far_px, 150.0, 60.0).astype(np.float32)[None].repeat(ds.num_frames, 0)
    for name, mask in expected_regions().items():
        np.testing.assert_array_equal(evaluate.region_masks(ds, TEST)[name], mask, err_msg=name)
    # an empty region scores None, not nan (found by mutation testing)
    assert evaluate._region_psnr(ds.images[TEST], ds.clean_images[TEST], {"tower": np.zeros((H, W), bool)}) == {
        "tower": None}
    # without depth only the sky is far background
    ds.depth = None
    sky = np.zeros((H, W), bool)
    sky[:4] = True
    np.testing.assert_array_equal(evaluate.region_masks(ds, TEST)["far_background"], sky)


def test_eval_scores_the_clean_targets_and_each_region(ours):
    m, ds = ours["metrics"], ours["ds"]
    clean, images = ds.clean_images[TEST], ds.images[TEST]
    assert m["target"] == "clean images" and np.abs(clean - images).max() > 0.1
    rgb = _float_render(ours)
    view = m["per_view"][0]
    assert view["index"] == TEST and m["num_views"] == 1
    assert abs(view["psnr"] - psnr(rgb, clean)) < 1e-3
    assert abs(view["ssim"] - ssim(rgb, clean)) < 1e-4
    assert abs(psnr(rgb, images) - psnr(rgb, clean)) > 0.5          # the wrong target would show
    assert abs(m["mean"]["psnr"] - view["psnr"]) < 1e-9 and abs(m["mean"]["ssim"] - view["ssim"]) < 1e-9
    half = W // 2
    assert abs(view["right_half"]["psnr"] - psnr(rgb[:, half:], clean[:, half:])) < 1e-3
    assert abs(m["mean_right_half"]["ssim"] - ssim(rgb[:, half:], clean[:, half:])) < 1e-4
    refs = {name: psnr(rgb, clean, mask) for name, mask in expected_regions().items()}
    assert min(abs(a - b) for a in refs.values() for b in refs.values() if a != b) > 0.1   # swaps would show
    for name, ref in refs.items():
        assert abs(view["regions"][name] - ref) < 1e-3, name
        assert abs(m["regions_mean"][name] - ref) < 1e-3, name
    # distractor PSNR: training views' distractor pixels against their clean images, pooled
    sq, count = 0.0, 0
    for i in ds.split["train"][:4]:
        r = np.clip(views.render_view(ours["params"], ours["cfg"], ds, int(i))["rgb"], 0, 1)
        err = np.mean((r.astype(np.float64) - ds.clean_images[i]) ** 2, -1)[ds.distractor_masks[i]]
        sq, count = sq + err.sum(), count + err.size
    assert abs(m["distractor_psnr"] - (-10 * np.log10(sq / count))) < 1e-3


def test_nerfw_eval_fits_appearance_on_the_left_half_and_scores_the_right(nerfw):
    m, ds, spy = nerfw["metrics"], nerfw["ds"], nerfw["spy"]
    clean = ds.clean_images[TEST]
    half = W // 2
    assert len(spy.calls) == 1
    call = spy.calls[0]
    # fitted on the left half of the clean target, with the left half's rays
    np.testing.assert_array_equal(call["target"], clean[:, :half].reshape(-1, 3))
    cam = views.camera_rays(ds, TEST, *evaluate.config_lib.near_far(nerfw["cfg"].model, ds))
    np.testing.assert_allclose(np.asarray(call["rays"].origins), np.asarray(cam.origins)[:, :half].reshape(-1, 3))
    np.testing.assert_allclose(np.asarray(call["rays"].directions),
                               np.asarray(cam.directions)[:, :half].reshape(-1, 3))
    # the render scored is the one with the fitted embedding, and the headline is the right half
    rgb = _float_render(nerfw, appearance=call["emb"])
    right = psnr(rgb[:, half:], clean[:, half:])
    assert abs(m["mean"]["psnr"] - right) < 1e-3 and abs(m["mean_right_half"]["psnr"] - right) < 1e-3
    assert abs(m["mean"]["ssim"] - ssim(rgb[:, half:], clean[:, half:])) < 1e-4
    assert abs(m["per_view"][0]["psnr"] - psnr(rgb, clean)) < 1e-3        # per view: the whole image
    assert abs(psnr(rgb, clean) - right) > 0.5                           # so the two are told apart
    assert "left half" in m["protocol"] and "right half" in m["protocol"]
    # the embedding was fitted (not the starting mean of the training embeddings)
    assert np.abs(call["emb"] - np.asarray(nerfw["params"]["appearance"]).mean(0)).max() > 1e-4


def _table(report: str) -> dict:
    """report.md's "| name | value |" rows -> {name: value string}."""
    return {a.strip(): b.strip() for a, b in re.findall(r"^\|([^|]+)\|([^|]+)\|$", report, re.M)}


def test_report_tables_match_metrics_json(ours, nerfw):
    for r in (ours, nerfw):
        m = io.read_json(r["run"] / "metrics.json")
        rows = _table((r["run"] / "report.md").read_text())
        assert rows["PSNR"] == f"{m['mean']['psnr']:.2f}" and rows["SSIM"] == f"{m['mean']['ssim']:.4f}"
        assert rows["MS-SSIM"] == f"{m['mean']['ms_ssim']:.4f}" and rows["LPIPS"] == "unavailable"
        scales = m["per_view"][0]["ms_ssim_scales"]         # the scales MS-SSIM used, carried to the mean
        assert scales and m["mean"]["ms_ssim_scales"] == scales and rows["MS-SSIM scales"] == str(scales)
        assert rows["PSNR, right half"] == f"{m['mean_right_half']['psnr']:.2f}"
        assert rows["SSIM, right half"] == f"{m['mean_right_half']['ssim']:.4f}"
        for name in ("tower", "near_ground", "far_background"):
            assert rows[f"PSNR, {name.replace('_', ' ')}"] == f"{m['regions_mean'][name]:.2f}"
        assert rows["PSNR inside distractors (train views vs clean)"] == f"{m['distractor_psnr']:.2f}"
        assert f"Trained steps: {m['step']}" in (r["run"] / "report.md").read_text()
        # the training batches of the last tenth of the run, from metrics.jsonl by hand: their MSEs averaged
        log = [json.loads(line) for line in (r["run"] / "metrics.jsonl").read_text().splitlines()]
        late = [rec["psnr"] for rec in log if rec["step"] > 0.9 * r["cfg"].train.max_steps]
        assert late and m["training_fit"]["batches"] == len(late)
        want = -10 * math.log10(sum(10 ** (-v / 10) for v in late) / len(late))
        assert m["training_fit"]["psnr"] == pytest.approx(want, abs=1e-9)
        assert rows["PSNR of the training batches, last tenth of the run"] == f"{want:.2f}"


def _turbo_of_inverse_depth(depth):
    """report_views' depth panel, by hand: 1 / depth scaled between its 2nd and 98th percentiles,
    through OpenCV's TURBO map (docs: report.py)."""
    inv = 1.0 / np.maximum(depth.astype(np.float64), 1e-6)
    lo, hi = np.percentile(inv, 2), np.percentile(inv, 98)
    unit = np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1)
    return cv2.applyColorMap(np.round(unit * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1] / 255.0


def _panels(img, width, gap=2):
    """Cuts a side-by-side row into its three panels of `width` pixels separated by `gap`."""
    return [img[:, k * (width + gap): k * (width + gap) + width] for k in range(3)]


def check_report_figures(run: Path, name: str, target: np.ndarray, semantic: np.ndarray | None) -> None:
    """report_views.png = target | render PNG | depth colours; report_crops.png = the same cropped
    to the tower's box (class 1, margin 4) and doubled. target: [H, W, 3] 8-bit values."""
    render = io.read_image(run / "renders" / f"{name}.png")
    depth = io.read_exr(run / "depth" / f"{name}.exr")
    h, w = target.shape[:2]
    fig = io.read_image(run / "report_views.png")
    assert fig.shape == (h, 3 * w + 4, 3)
    gt_p, render_p, depth_p = _panels(fig, w)
    np.testing.assert_array_equal(gt_p, target)
    np.testing.assert_array_equal(render_p, render)
    assert np.abs(depth_p - _turbo_of_inverse_depth(depth)).max() <= 0.06      # one TURBO step at most
    assert np.mean(np.abs(depth_p - _turbo_of_inverse_depth(depth)) > 1e-6) < 0.05
    assert np.all(fig[:, w:w + 2] == 1.0) and np.all(fig[:, 2 * w + 2:2 * w + 4] == 1.0)
    if semantic is None:
        return
    ys, xs = np.nonzero(semantic == 1)
    box = (slice(max(ys.min() - 4, 0), min(ys.max() + 5, h)), slice(max(xs.min() - 4, 0), min(xs.max() + 5, w)))
    up = lambda a: np.repeat(np.repeat(a[box], 2, 0), 2, 1)  # noqa: E731
    crops = io.read_image(run / "report_crops.png")
    cw = 2 * (box[1].stop - box[1].start)
    assert crops.shape == (2 * (box[0].stop - box[0].start), 3 * cw + 4, 3)
    gt_c, render_c, _ = _panels(crops, cw)
    np.testing.assert_array_equal(gt_c, up(target))
    np.testing.assert_array_equal(render_c, up(render))


def test_report_figures_are_the_target_render_and_depth(ours):
    ds = ours["ds"]
    check_report_figures(ours["run"], runs.frame_name(ds, TEST), ds.clean_images[TEST], ds.semantics[TEST])


def test_tower_box_of_one_pixel_and_of_none():
    """The crop box: class-1 pixels' bounding box grown by the margin, clipped to the frame; None
    without tower pixels (found by mutation testing: one pixel gave no crop, none crashed)."""
    from jaxnerf_grid.report import markdown as report

    sem = np.zeros((H, W), np.uint8)
    assert report.tower_box(sem) is None
    sem[2, 20] = 1
    assert report.tower_box(sem, margin=4) == (slice(0, 7), slice(16, 24))


def test_a_robust_run_reports_the_weights_training_used(tmp_path):
    """train.robust writes weights/NAME.png per training frame; eval's report shows, for 3
    training frames, photo | DPT weight 1 - M_w | the weight used, and metrics.json the share
    of training pixels ignored (recomputed here from the PNGs)."""
    ds = region_dataset()
    save_transforms_json(ds, tmp_path / "data")
    overrides = tiny_overrides("ours")
    overrides["train"].update(robust="dpt+robust", robust_patch=4)
    run, _, _ = runs.train_run(str(tmp_path / "data"), "ours", tmp_path / "run", overrides, progress=False)
    metrics = evaluate.evaluate_run(run, progress=False)
    loaded = runs.load_dataset(str(tmp_path / "data"), progress=False)
    names = [Path(loaded.frame_paths[i]).stem for i in range(4)]   # the training frames' file stems
    used = [cv2.imread(str(Path(run) / "weights" / f"{name}.png"), cv2.IMREAD_GRAYSCALE) / 255.0 for name in names]
    assert all(u.shape == (H, W) for u in used)
    assert metrics["training_weights"]["mode"] == "dpt+robust"
    assert metrics["training_weights"]["ignored_share"] == pytest.approx(np.mean([1 - u.mean() for u in used]))
    cfg_steps = overrides["train"]["max_steps"]
    logged = [r["robust_weight"] for r in map(json.loads, (Path(run) / "metrics.jsonl").read_text().splitlines())
              if "robust_weight" in r and r["step"] > 0.75 * cfg_steps]
    assert logged
    assert metrics["training_weights"]["late_batch_ignored_share"] == pytest.approx(1 - np.mean(logged))
    assert "report_weights.png" in (Path(run) / "report.md").read_text()
    figure = io.read_image(Path(run) / "report_weights.png")
    assert figure.shape == (3 * H + 2 * 2, 3 * W + 2 * 2, 3)
    for row, frame in enumerate([0, 2, 3]):            # evenly spaced over the 4 training frames
        top = row * (H + 2)
        photo, prior, weight = (figure[top:top + H, k * (W + 2):k * (W + 2) + W] for k in range(3))
        np.testing.assert_allclose(photo, loaded.images[frame], atol=1 / 255 + 1e-6)
        np.testing.assert_allclose(prior[..., 0], loaded.weights[frame], atol=1 / 255 + 1e-6)
        np.testing.assert_allclose(weight[..., 0], used[frame], atol=1e-6)


def test_metrics_json_records_the_run_and_the_views_it_lifted(ours, tmp_path, monkeypatch):
    """metrics.json as written: the method, the steps trained (tiny_overrides: 12), the one test
    view scored, no training views lifted by default, no LPIPS, geometry or export, the region
    definition, the resolution (the photos' own size). Then a copy of the run evaluated again
    with cloud_views = 2 and no distractor views: the training views lifted are the first and the
    last of the split (evenly spaced, by hand), and no distractor PSNR is computed. The tiny run
    is too faint to lift any point (opacity < 0.5 everywhere), so the lifting is replaced by one
    that keeps each view's camera centre: tower_points.ply must then hold the centres of the
    test view and of those two, in that order (read from the dataset's poses)."""
    import shutil

    m, ds, cfg = io.read_json(ours["run"] / "metrics.json"), ours["ds"], ours["cfg"]
    assert m["method"] == "ours" and m["step"] == 12 and m["num_views"] == 1
    assert m["cloud_views"] == {"test": [TEST], "train": []}
    assert m["lpips"] == "unavailable" and m["geometry"] is None and m["export"] is None
    assert m["region_definition"] == evaluate.REGION_DEFINITION and "training_weights" not in m
    assert m["resolution"] == {"width": W, "height": H, "native_width": W, "native_height": H,
                               "max_side": cfg.train.max_side, "full_size": False}
    assert m["target"] == "clean images" and m["protocol"] == "targets are the clean images"

    def centre_only(rays, rgb, depth, opacity):
        return np.asarray(rays.origins)[:1, 0].astype(np.float32), np.asarray(rgb)[:1, 0].astype(np.float32)

    monkeypatch.setattr(evaluate.clouds, "lift_view", centre_only)
    run = tmp_path / "run"
    shutil.copytree(ours["run"], run)
    m2 = evaluate.evaluate_run(run, progress=False, cloud_views=2, distractor_views=0)
    train_ids = [int(i) for i in ds.split["train"]]
    assert len(train_ids) > 2 and m2["cloud_views"] == {"test": [TEST], "train": [train_ids[0], train_ids[-1]]}
    assert m2["distractor_psnr"] is None and io.read_json(run / "metrics.json")["cloud_views"] == m2["cloud_views"]
    centres = np.asarray(ds.c2w)[[TEST, train_ids[0], train_ids[-1]], :3, 3]
    assert np.linalg.norm(centres[1:] - centres[:-1], axis=-1).min() > 0.1
    np.testing.assert_allclose(io.read_ply_points(run / "tower_points.ply"), centres, atol=1e-5)
