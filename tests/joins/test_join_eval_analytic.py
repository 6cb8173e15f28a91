"""`evaluate.evaluate_run` (and its `_lift`, `_fit_left_half`) on the analytic tower
(tests/support/analytic_field.py), no training: `train.load_params` returns the closed-form field's
constants and `fields.apply` is the analytic field, as in test_join_export.py.

The dataset (4 frames of 24 x 16 on a ring, 2 train, 2 test) is rendered from the same field;
its clean images (the evaluation targets) are the float render plus a +-0.03 checkerboard (+0.03
on the black sky), so
each test view's PSNR is near 20 log10(1 / 0.03) = 30.5 dB and is recomputed here by hand from
the written render PNG; its images are the clean images turned inside out (1 - clean), so
scoring against the wrong target moves the PSNR by tens of dB. The semantics and depth are
test_join_eval's hand-painted frame (`expected_regions`). The tower cloud is checked in metres:
each point lies on the analytic tower or the ground's top, and the count is the opacity rule's,
counted here from the float renders."""

from pathlib import Path

import jax
import numpy as np
import pytest

from jaxnerf_grid.eval import evaluate
from jaxnerf_grid.nerf import fields
from jaxnerf_grid.render import clouds as clouds_lib
from jaxnerf_grid.render import views
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import runs
from jaxnerf_grid.util import io
from tests.joins.test_join_eval import H, W, _semantics_and_depth, expected_regions, psnr
from tests.joins.test_join_truth import analytic_config
from tests.support import analytic_field as af

FRAMES, TEST_IDS, TRAIN_IDS = 4, (1, 3), (0, 2)
CHECKER = 0.03


def _checker():
    yy, xx = np.mgrid[0:H, 0:W]
    return np.where((yy + xx) % 2, CHECKER, -CHECKER)[..., None]


def _dataset(root, cfg, params):
    """The analytic dataset: clean images = the float render + the checkerboard."""
    ds = af.dataset(frames=FRAMES, width=W, height=H)
    ds.root = root
    ds.split = {"train": np.array(TRAIN_IDS), "test": np.array(TEST_IDS)}
    renders = {i: views.render_view(params, cfg, ds, i) for i in range(FRAMES)}
    rgb = np.stack([np.clip(renders[i]["rgb"], 0, 1) for i in range(FRAMES)])
    clean = rgb + np.where(rgb < CHECKER, CHECKER, _checker())       # the black sky: +0.03
    assert clean.min() >= 0 and clean.max() <= 1            # no clipping: the checker is the error
    ds.clean_images = clean.astype(np.float32)
    ds.images = (1.0 - clean).astype(np.float32)
    sem, depth = _semantics_and_depth()
    ds.semantics = np.repeat(sem[None], FRAMES, 0)
    ds.depth = np.repeat(depth[None], FRAMES, 0)
    ds.distractor_masks = np.zeros((FRAMES, H, W), bool)
    ds.distractor_masks[:, 2:6, 3:9] = True
    return ds, renders


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """evaluate_run of the analytic run with one training view in the cloud: (metrics, run
    folder, dataset, the float renders {frame: view} made here)."""
    root = tmp_path_factory.mktemp("analytic_eval")
    cfg = analytic_config()
    params = af.params(cfg.model)
    af.clear_compiled()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fields, "apply", af.apply)
        ds, renders = _dataset(root, cfg, params)
    handed = {}
    result, run_dir = _evaluate(root, "run", cfg, ds, params, handed, progress=False, cloud_views=1,
                                distractor_views=1)
    # what evaluate_run hands the stand-ins: the run folder, the config's data, the call's own
    # dataset / progress / allow_other_data / full_size, the run's max_side
    assert handed["load_run"] == [run_dir]
    assert handed["dataset_of_run"] == [((run_dir, root / "dataset", ds, False, False),
                                         {"max_side": cfg.train.max_side, "full_size": False})]
    assert [(folder, c is cfg, d is ds) for folder, c, d in handed["load_params"]] == [(run_dir, True, True)]
    return result, run_dir, ds, renders


def test_negative_or_fractional_view_counts_are_refused_before_the_run_loads(tmp_path, monkeypatch):
    """eval.distractor_views and eval.cloud_views must be integers >= 0, refused by name (the
    CLI shows the flag) before the run's config is read."""
    from jaxnerf_grid.config.schema import ConfigError

    def not_loaded(folder):
        raise AssertionError("the run was loaded before the checks")

    monkeypatch.setattr(runs, "load_run", not_loaded)
    for key, kwargs in (("eval.distractor_views", {"distractor_views": -1}), ("eval.cloud_views", {"cloud_views": -2})):
        with pytest.raises(ConfigError, match=rf"^{key} = -\d: must be an integer >= 0$"):
            evaluate.evaluate_run(tmp_path, progress=False, **kwargs)
    for key, kwargs in (("eval.distractor_views", {"distractor_views": 1.5}),
                        ("eval.cloud_views", {"cloud_views": 0.5})):
        with pytest.raises(ConfigError, match=rf"^{key} = "):
            evaluate.evaluate_run(tmp_path, progress=False, **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_defaults_are_the_documented_ones():
    """The defaults `jaxnerf-grid eval` relies on (jaxnerf_grid/cli/eval.py passes neither
    cloud_views nor cloud_pixels: the cloud is the test views'), and the module docstring's
    "up to 4" distractor views."""
    import inspect

    got = {k: v.default for k, v in inspect.signature(evaluate.evaluate_run).parameters.items()}
    assert got == {"run_dir": inspect.Parameter.empty, "lpips_weights": None, "progress": True, "dataset": None,
                   "distractor_views": 4, "extra_notes": (), "reference_ply": None, "cloud_views": 0,
                   "allow_other_data": False, "full_size": False, "cloud_pixels": 0,
                   "appearance_steps": None}  # None: the run's own train.appearance_steps


def test_metrics_json_is_the_returned_record_with_one_row_per_test_view(evaluated):
    """metrics.json holds what evaluate_run returned; one per-view row per test frame in order,
    named frame_NNNN, with its index; the step is load_params's, the target the clean images."""
    result, run_dir, ds, _ = evaluated
    written = io.read_json(run_dir / "metrics.json")
    assert {"method", "step", "num_views", "target", "protocol", "mean", "mean_right_half", "regions_mean",
            "region_definition", "distractor_psnr", "geometry", "export", "cloud_views", "per_view", "lpips",
            "resolution", "eval_seconds", "training_fit"} == set(written)
    assert written["step"] == result["step"] == 7
    assert written["num_views"] == 2 and written["target"] == "clean images"
    assert [r["index"] for r in written["per_view"]] == list(TEST_IDS)
    assert [r["name"] for r in written["per_view"]] == [f"frame_{i:04d}" for i in TEST_IDS]
    assert written["cloud_views"] == {"test": list(TEST_IDS), "train": [TRAIN_IDS[0]]}
    assert written["lpips"] == "unavailable" and written["export"] is None and written["geometry"] is None
    assert written["method"] == "ours" and written["region_definition"] == evaluate.REGION_DEFINITION
    assert written["resolution"] == {"width": W, "height": H, "native_width": W, "native_height": H,
                                     "max_side": int(analytic_config().train.max_side), "full_size": False}
    for key in ("psnr", "ssim"):
        assert written["mean"][key] == pytest.approx(result["mean"][key], rel=1e-12)
        assert written["per_view"][1][key] == pytest.approx(result["per_view"][1][key], rel=1e-12)


def test_written_renders_and_psnr_by_hand_against_the_clean_images(evaluated):
    """renders/, depth/, opacity/ hold each test view (the render PNG is the float render, the
    depth EXR its depth); each view's PSNR, right-half PSNR and region PSNRs are -10 log10 MSE
    by hand against the clean image (the 0.03 checker: about 30.5 dB; against the images it
    would be far lower); the means are the views' means."""
    result, run_dir, ds, renders = evaluated
    regions = expected_regions()
    for row, i in zip(result["per_view"], TEST_IDS):
        name = f"frame_{i:04d}"
        png = io.read_image(run_dir / "renders" / f"{name}.png")[..., :3]
        np.testing.assert_allclose(png, np.clip(renders[i]["rgb"], 0, 1), atol=0.5 / 255 + 1e-6)
        np.testing.assert_allclose(io.read_exr(run_dir / "depth" / f"{name}.exr"), renders[i]["depth"], atol=1e-4)
        opacity = io.read_image(run_dir / "opacity" / f"{name}.png")[..., 0]
        np.testing.assert_allclose(opacity, np.clip(renders[i]["opacity"], 0, 1), atol=0.5 / 255 + 1e-6)
        clean = ds.clean_images[i]
        assert psnr(png, clean) == pytest.approx(20 * np.log10(1 / CHECKER), abs=0.05)
        assert row["psnr"] == pytest.approx(psnr(png, clean), abs=0.05)
        assert row["psnr"] == pytest.approx(psnr(np.clip(renders[i]["rgb"], 0, 1), clean), abs=1e-3)
        right = np.zeros((H, W), bool)
        right[:, W // 2:] = True
        assert row["right_half"]["psnr"] == pytest.approx(psnr(np.clip(renders[i]["rgb"], 0, 1), clean, right),
                                                          abs=1e-3)
        for region, mask in regions.items():
            assert row["regions"][region] == pytest.approx(psnr(np.clip(renders[i]["rgb"], 0, 1), clean, mask),
                                                           abs=1e-3)
    assert result["mean"]["psnr"] == pytest.approx(np.mean([r["psnr"] for r in result["per_view"]]), rel=1e-9)
    for region in regions:
        assert result["regions_mean"][region] == pytest.approx(
            np.mean([r["regions"][region] for r in result["per_view"]]), rel=1e-9)


def test_distractor_psnr_of_the_first_training_view_by_hand(evaluated):
    """distractor_views=1: PSNR inside the first training view's distractor mask against its
    clean image (the checker again: about 30.5 dB)."""
    result, _, ds, renders = evaluated
    i = TRAIN_IDS[0]
    want = psnr(np.clip(renders[i]["rgb"], 0, 1), ds.clean_images[i], ds.distractor_masks[i])
    assert result["distractor_psnr"] == pytest.approx(want, abs=1e-3)


def _lift_by_hand(ds, i, view, near, far):
    """Rays of frame i by hand (pinhole, OpenGL axes: x right, y up, -z forward, pixel centres),
    lifted by the rule: t = z-depth / cos, opacity >= 0.5, |x| <= 1, t finite."""
    fx, fy, cx, cy = (float(v) for v in ds.intrinsics[i])
    c2w = np.asarray(ds.c2w[i], np.float64)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    cam = np.stack([(u - cx) / fx, -(v - cy) / fy, -np.ones_like(u)], -1)
    d = cam @ c2w[:3, :3].T
    cos = 1.0 / np.linalg.norm(cam, axis=-1)           # the unit direction's cosine to the axis
    t = np.asarray(view["depth"], np.float64) / cos
    x = c2w[:3, 3] + d / np.linalg.norm(d, axis=-1, keepdims=True) * t[..., None]
    keep = (np.asarray(view["opacity"]) >= 0.5) & (np.linalg.norm(x, axis=-1) <= 1.0) & np.isfinite(t)
    return x[keep], np.clip(view["rgb"], 0, 1)[keep]


def test_tower_points_are_the_opacity_rule_of_the_test_and_cloud_views_on_the_analytic_surface(evaluated):
    """tower_points.ply (`_lift` of the 2 test views, then of the 1 cloud training view): the
    points and colours lifted by hand from the float renders, in that order, their count the
    opacity rule's; in metres the points lie on the tower's surface or the ground's top (median
    distance under 0.25 m, every one within 1.25 coarse sample bins: the 24 x 16 views' edge
    pixels blend); tower points above the ground have the tower's colour."""
    result, run_dir, ds, renders = evaluated
    near, far = ds.near, ds.far
    parts = [_lift_by_hand(ds, i, renders[i], near, far) for i in (*TEST_IDS, TRAIN_IDS[0])]
    want_points = np.concatenate([p for p, _ in parts])
    want_colours = np.concatenate([c for _, c in parts])
    vertex = io.read_ply(run_dir / "tower_points.ply")
    points = np.column_stack([vertex[k] for k in "xyz"])
    colours = np.column_stack([vertex[k] for k in ("red", "green", "blue")]) / 255.0
    assert len(points) == len(want_points) > 100
    np.testing.assert_allclose(points, want_points, atol=2e-4)
    np.testing.assert_allclose(colours, want_colours, atol=0.5 / 255 + 1e-6)
    scale, rot = af.NORMALIZATION["scale"], np.asarray(af.NORMALIZATION["rotation"])
    metric = np.asarray(points, np.float64) @ rot / scale - np.asarray(af.NORMALIZATION["translation"])
    tower_frame = af.to_tower_frame(metric)
    dist = np.minimum(af.distance_to_tower_surface(tower_frame), np.abs(tower_frame[:, 2] - af.GROUND_Z))
    coarse_bin = (ds.far - ds.near) / 48 / scale                   # metres: 1.67 m
    assert np.median(dist) < 0.25 and dist.max() < 1.25 * coarse_bin  # measured: 0.07 m, 1.70 m of 422
    on_tower = af.distance_to_tower_surface(tower_frame) < 0.25
    assert on_tower.sum() > 20
    np.testing.assert_allclose(np.asarray(colours)[on_tower & (tower_frame[:, 2] > af.GROUND_Z + 0.5)],
                               np.tile(af.TOWER_RGB, ((on_tower & (tower_frame[:, 2] > af.GROUND_Z + 0.5)).sum(), 1)),
                               atol=0.02)
    assert (f"2 test views and 1 training views (opacity >= 0.5): `tower_points.ply`, {len(points)} points"
            in (run_dir / "report.md").read_text())


def test_lift_direct_call_is_lift_view_of_the_views_camera_rays():
    """`_lift(ds, i, near, far, rgb, view)` keeps, of a hand-made view, the pixels the rule keeps,
    at the depth along frame i's own rays (bounds near, far handed on)."""
    ds = af.dataset(frames=3, width=W, height=H)
    rng = np.random.default_rng(0)
    i = 2
    depth = rng.uniform(0.8, 3.0, (H, W)).astype(np.float32)
    opacity = rng.uniform(0, 1, (H, W)).astype(np.float32)
    opacity[0, 0], opacity[0, 1] = 0.5, np.nextafter(np.float32(0.5), np.float32(0))
    depth[0, :2] = 2.2                       # on the unit sphere's side of the camera at 2.46 from the origin
    rgb = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    view = {"depth": depth, "opacity": opacity}
    points, colours = evaluate._lift(ds, i, 0.5, 4.5, rgb, view)
    want_p, want_c = _lift_by_hand(ds, i, {"depth": depth, "opacity": opacity, "rgb": rgb}, 0.5, 4.5)
    assert len(want_p) > 10
    np.testing.assert_allclose(points, want_p, atol=1e-5)
    np.testing.assert_allclose(colours, want_c, atol=1e-7)


def test_fit_left_half_hands_fit_appearance_the_left_half_and_the_views_key(monkeypatch):
    """`_fit_left_half` (NeRF-W only; the analytic run is "ours", so a direct call with
    `views.fit_appearance` recorded): the rays and target pixels of columns < W // 2 in row-major
    order, the model and train configs, PRNGKey(index); returns what the fit returned."""
    ds = af.dataset(frames=3, width=W + 1, height=H)        # an odd width: half = W // 2 columns
    cfg = analytic_config()
    i = 1
    rays = views.camera_rays(ds, i, 0.5, 4.5)
    target = np.random.default_rng(1).uniform(0, 1, (H, W + 1, 3)).astype(np.float32)
    calls = []

    def fit(params, mcfg, tcfg, r, tgt, key, start=None):
        calls.append((params, mcfg, tcfg, r, np.asarray(tgt), np.asarray(key)))
        return np.arange(4.0)

    monkeypatch.setattr(views, "fit_appearance", fit)
    out = evaluate._fit_left_half("P", cfg, ds, i, target, rays)
    np.testing.assert_array_equal(out, np.arange(4.0))
    (params, mcfg, tcfg, r, tgt, key), = calls
    assert params == "P" and mcfg is cfg.model and tcfg is cfg.train
    half = (W + 1) // 2
    assert half == W // 2
    for got, full in zip(r, rays):
        full = np.asarray(full)
        want = full[:, :half].reshape(H * half, *full.shape[2:])
        np.testing.assert_array_equal(np.asarray(got), want)
    np.testing.assert_array_equal(tgt, target[:, :half].reshape(-1, 3))
    np.testing.assert_array_equal(key, np.asarray(jax.random.PRNGKey(i)))



def _evaluate(root, name, cfg, ds, params, handed, **kwargs):
    """evaluate_run of the analytic run in a new folder root/name with the analytic field in place;
    the stand-ins record in `handed` what they are given ("dataset_of_run": (args, kwargs),
    "load_params": (folder, cfg, ds), "load_run": folder) instead of asserting it."""
    run_dir = root / name
    run_dir.mkdir(exist_ok=True)

    def load_run(folder):
        handed.setdefault("load_run", []).append(Path(folder))
        return cfg, root / "dataset"

    def dataset_of_run(*args, **kw):
        handed.setdefault("dataset_of_run", []).append((args, kw))
        return ds

    def load_params(folder, cfg_, ds_):
        handed.setdefault("load_params", []).append((Path(folder), cfg_, ds_))
        return params, 7

    af.clear_compiled()
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(fields, "apply", af.apply)
            mp.setattr(runs, "load_run", load_run)
            mp.setattr(runs, "dataset_of_run", dataset_of_run)
            mp.setattr(train, "load_params", load_params)
            return evaluate.evaluate_run(run_dir, dataset=ds, **kwargs), run_dir
    finally:
        af.clear_compiled()


def test_a_call_with_the_defaults_on_a_robust_runs_folder(evaluated, tmp_path):
    """The defaults of the API (what `jaxnerf-grid eval` relies on: no cloud_views, no
    cloud_pixels, progress shown), with allow_other_data, full_size and a reference cloud, on the
    analytic dataset without clean images or semantics, in a run folder holding a robust run's
    weights/ (two training views' weight PNGs) and metrics.jsonl: the cloud is the 2 test views'
    alone; the loader is handed progress True and both flags; the targets are the images (1 -
    clean: far from the 30.5 dB of the clean ones), no distractor PSNR (it needs clean images),
    no regions; the geometry is the written cloud scored against the reference; the training
    weights' shares and the report's lines are worked out by hand."""
    import dataclasses
    import json
    import time

    from jaxnerf_grid.eval import geometry

    _, _, ds, renders = evaluated
    plain = dataclasses.replace(ds, clean_images=None, semantics=None)
    cfg = analytic_config()
    run_dir = tmp_path / "run"
    used = {TRAIN_IDS[0]: np.ones((H, W), np.float32), TRAIN_IDS[1]: np.ones((H, W), np.float32)}
    used[TRAIN_IDS[0]][2:6, 3:9] = 0.0                   # 24 of 384 pixels ignored: 0.0625
    used[TRAIN_IDS[1]][:3] = 0.0                         # 72 of 384: 0.1875; mean 0.125
    for i, w in used.items():
        io.write_png(run_dir / "weights" / f"{evaluate.frame_name(ds, i)}.png", w)
    steps = cfg.train.max_steps                          # the last quarter: 0.8 and 0.6, not the 0 at step 1
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in (
        {"step": 1, "robust_weight": 0.0}, {"step": int(0.9 * steps), "robust_weight": 0.6},
        {"step": steps, "robust_weight": 0.8})))
    scale, rot = af.NORMALIZATION["scale"], np.asarray(af.NORMALIZATION["rotation"])
    surface = (af.to_metric_frame(af.surface_samples(0.5)) + np.asarray(af.NORMALIZATION["translation"])) * scale
    reference = tmp_path / "reference.ply"
    clouds_lib.write_point_cloud(reference, [(surface @ rot.T, np.zeros_like(surface))])
    handed = {}
    start = time.perf_counter()
    result, _ = _evaluate(tmp_path, "run", cfg, plain, af.params(cfg.model), handed, allow_other_data=True,
                          full_size=True, reference_ply=reference)
    took = time.perf_counter() - start
    assert handed["load_run"] == [run_dir]
    assert handed["dataset_of_run"] == [((run_dir, tmp_path / "dataset", plain, True, True),
                                         {"max_side": cfg.train.max_side, "full_size": True})]
    assert result["cloud_views"] == {"test": list(TEST_IDS), "train": []}
    want = [_lift_by_hand(ds, i, renders[i], ds.near, ds.far)[0] for i in TEST_IDS]
    vertex = io.read_ply(run_dir / "tower_points.ply")
    count = len(vertex["x"])
    assert count == sum(len(p) for p in want) > 50
    assert result["target"] == "images" and result["distractor_psnr"] is None
    assert result["regions_mean"] == {} and result["region_definition"] is None
    assert result["resolution"]["full_size"] is True and 0 < result["eval_seconds"] <= took
    for row, i in zip(result["per_view"], TEST_IDS):
        want_psnr = psnr(np.clip(renders[i]["rgb"], 0, 1), ds.images[i])
        assert row["psnr"] == pytest.approx(want_psnr, abs=1e-3) and want_psnr < 20
    points = np.column_stack([vertex[k] for k in "xyz"])
    score = geometry.score_against_ply([(points, np.zeros_like(points))], reference)
    assert score["num_pred"] >= 20 and score["thresholds"]["0.05"]["precision"] > 0.5   # measured: 40, 0.9
    assert result["geometry"].keys() == score.keys()
    for key, value in score.items():
        assert result["geometry"][key] == (pytest.approx(value, rel=1e-4, abs=1e-6)
                                           if isinstance(value, float) else value), key
    weights = {"mode": cfg.train.robust.mode, "ignored_share": pytest.approx(0.125, abs=1e-6),
               "late_batch_ignored_share": pytest.approx(0.3, abs=1e-9)}
    assert result["training_weights"] == weights
    assert io.read_json(run_dir / "metrics.json")["training_weights"] == weights
    report = (run_dir / "report.md").read_text()
    for line in (f"Data: `{tmp_path / 'dataset'}`",
                 f"Resolution: test views rendered at the photos' full size, {W}x{H} (`--full-size`).",
                 f"Photometric evidence (`train.robust.mode = {cfg.train.robust.mode}`): training ignored 30.0 % "
                 "of the "
                 "pixels of each batch in the last quarter of training, and 12.5 % of the training pixels in its "
                 "per-pixel record (pixels never drawn count as used; weights in `weights/`, docs/ROBUST.md).",
                 "![training weights](report_weights.png)",
                 "Point cloud of the unit sphere (the tower region) lifted from the depth maps of the 2 test views "
                 f"(opacity >= 0.5): `tower_points.ply`, {count} points, normalised scene units.",
                 "LPIPS: unavailable (no LPIPS weights given)."):
        assert line in report, line
    assert (run_dir / "report_weights.png").is_file() and (run_dir / "report.html").is_file()


def test_nerfw_protocol_fits_each_test_views_appearance_on_its_left_half(evaluated, tmp_path, monkeypatch):
    """The analytic run as a NeRF-W run (`use_appearance`; the analytic field ignores the
    embedding): `views.fit_appearance` (recorded) is handed each test view's left-half rays and
    clean pixels, the run's params and configs, PRNGKey(index); the test view is rendered with
    the embedding it returned, the cloud and distractor views with none (the table); the
    headline means are the right-half means and the protocol says so. With a pixel budget
    (`cloud_pixels`, one view's worth) the one cloud view asked for is still lifted."""
    import dataclasses

    from jaxnerf_grid.config import schema as config_lib

    _, _, ds, _ = evaluated
    base = analytic_config()
    cfg = dataclasses.replace(base, model=dataclasses.replace(base.model, use_appearance=True, appearance_dim=3,
                                                              num_images=FRAMES))
    params = dict(af.params(cfg.model), appearance=np.zeros((FRAMES, 3), np.float32))
    fitted, rendered = [], []

    def fit(params_, mcfg, tcfg, r, tgt, key, start=None):
        fitted.append((params_, mcfg, tcfg, r, np.asarray(tgt), np.asarray(key)))
        return np.full(3, 0.25 * len(fitted), np.float32)

    real_render = views.render_view

    def render(params_, cfg_, ds_, index, appearance=None, progress=False):
        rendered.append((int(index), None if appearance is None else np.asarray(appearance).tolist()))
        return real_render(params_, cfg_, ds_, index, appearance=appearance, progress=progress)

    monkeypatch.setattr(views, "fit_appearance", fit)
    monkeypatch.setattr(views, "render_view", render)
    result, _ = _evaluate(tmp_path, "run", cfg, ds, params, {}, progress=False, cloud_views=1, distractor_views=1,
                          cloud_pixels=W * H)             # a budget of one view: still the 1 asked for
    near, far = config_lib.near_far(cfg.model, ds)
    half = W // 2
    assert len(fitted) == len(TEST_IDS)
    for (params_, mcfg, tcfg, r, tgt, key), i in zip(fitted, TEST_IDS):
        assert params_ is params and mcfg is cfg.model and tcfg is cfg.train
        for got, full in zip(r, views.camera_rays(ds, i, near, far)):
            full = np.asarray(full)
            np.testing.assert_array_equal(np.asarray(got), full[:, :half].reshape(H * half, *full.shape[2:]))
        np.testing.assert_array_equal(tgt, ds.clean_images[i][:, :half].reshape(-1, 3))
        np.testing.assert_array_equal(key, np.asarray(jax.random.PRNGKey(i)))
    assert rendered == [(1, [0.25] * 3), (3, [0.5] * 3), (TRAIN_IDS[0], None), (TRAIN_IDS[0], None)]
    assert result["cloud_views"]["train"] == [TRAIN_IDS[0]]
    right, full_ssim = result["mean_right_half"], np.mean([r["ssim"] for r in result["per_view"]])
    assert {k: result["mean"][k] for k in evaluate.METRIC_KEYS} == right
    assert result["mean"]["ms_ssim_scales"] == result["per_view"][0]["ms_ssim_scales"]
    assert abs(right["ssim"] - full_ssim) > 1e-3                  # the right half is not the whole view
    assert "NeRF-W" in result["protocol"] and "right half" in result["protocol"]


def test_a_missing_or_empty_reference_or_missing_lpips_weights_is_refused_before_the_params_load(evaluated,
                                                                                                  tmp_path):
    """--reference-ply missing or empty, --lpips-weights missing: DataError naming the file, before
    the parameters are loaded or anything is written in the run folder."""
    import re

    from jaxnerf_grid.util.io import DataError

    _, _, ds, _ = evaluated
    cfg = analytic_config()
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n")
    missing, weights = tmp_path / "missing.ply", tmp_path / "alex.npz"
    for name, kwargs, message in (
            ("missing", {"reference_ply": missing}, f"{missing}: reference point cloud not found (eval.reference_ply)"),
            ("empty", {"reference_ply": empty}, f"{empty}: the reference point cloud is empty"),
            ("lpips", {"lpips_weights": str(weights)},
             f"{weights}: LPIPS weights file not found (eval.lpips_weights)")):
        handed = {}
        with pytest.raises(DataError, match=f"^{re.escape(message)}$"):
            _evaluate(tmp_path, name, cfg, ds, af.params(cfg.model), handed, progress=False, **kwargs)
        assert "load_params" not in handed and list((tmp_path / name).iterdir()) == []


# --------------------------------------------------------------------------- what each block is handed


def test_lpips_from_a_weights_file_scores_each_view_and_its_right_half(evaluated, tmp_path, monkeypatch):
    """With --lpips-weights (a file that exists; `lpips.load_lpips` and the network are stand-ins
    here: the "distance" is the mean absolute difference, worked out by hand from the float
    renders and the clean images): each test view's LPIPS and its right half's are that distance,
    the record says "computed" and the report names the file (evaluate_run mutants 51, 52, 54:
    the weights never loaded or loaded from None; 160, 163, 168: not handed to the metrics; 340,
    342, 343: the record's word)."""
    from jaxnerf_grid.eval import lpips as lpips_lib

    _, _, ds, renders = evaluated
    cfg = analytic_config()
    weights = tmp_path / "alex.npz"
    weights.write_bytes(b"stand-in")
    loaded = []

    def load(path):
        loaded.append(path)
        return {"stand-in": np.ones(1)}

    monkeypatch.setattr(lpips_lib, "load_lpips", load)
    monkeypatch.setattr(lpips_lib, "lpips_jit", lambda params, pred, target: float(np.mean(np.abs(
        np.asarray(pred, np.float64) - np.asarray(target, np.float64)))) + 1000.0 * float(params["stand-in"][0]))
    result, run_dir = _evaluate(tmp_path, "run", cfg, ds, af.params(cfg.model), {}, progress=False,
                                lpips_weights=str(weights))
    assert loaded == [str(weights)]
    assert result["lpips"] == "computed"
    for row, i in zip(result["per_view"], TEST_IDS):
        rgb, clean = np.clip(renders[i]["rgb"], 0, 1).astype(np.float64), ds.clean_images[i].astype(np.float64)
        assert row["lpips"] == pytest.approx(1000.0 + np.mean(np.abs(rgb - clean)), abs=1e-5)
        half = W // 2
        assert row["right_half"]["lpips"] == pytest.approx(1000.0 + np.mean(np.abs(rgb[:, half:] - clean[:, half:])),
                                                           abs=1e-5)
    assert f"LPIPS: computed from {weights}." in (run_dir / "report.md").read_text()


def test_cloud_views_by_a_pixel_budget_the_distractor_default_and_the_semantic_figures(evaluated, tmp_path,
                                                                                          monkeypatch):
    """All 4 frames as training views (the test views 1 and 3 among them): cloud_views 3 without a
    budget lifts training views 0, 2, 3 (evenly spaced over 4: positions 0, 1.5, 3 rounded); with
    a budget of 1 pixel, the floor of 2 views, 0 and 3. Without distractor_views, the distractor
    PSNR is asked of at most 4 views (the signature's documented default, docs/USAGE.md's eval).
    The report's figures carry each test view's semantics, the dataset's own (evaluate_run
    mutants 2; 6, 203, 204: the budget 1 by default, applied at 0, not at 1; 195, 196, 198: the
    figures' "semantic" renamed or None)."""
    import dataclasses

    from jaxnerf_grid.report import markdown as report

    _, _, ds, _ = evaluated
    four = dataclasses.replace(ds, split={"train": np.arange(FRAMES), "test": np.array(TEST_IDS)})
    cfg = analytic_config()
    asked, figures = [], []
    real_distractor, real_report = evaluate.distractor_psnr, report.write_report

    def distractor(params, cfg_, ds_, max_views, progress=False):
        asked.append(max_views)
        return real_distractor(params, cfg_, ds_, max_views, progress)

    def write_report(run_dir, metrics, cfg_, data, views_, extra_lines=()):
        figures.append(views_)
        return real_report(run_dir, metrics, cfg_, data, views_, extra_lines)

    monkeypatch.setattr(evaluate, "distractor_psnr", distractor)
    monkeypatch.setattr(report, "write_report", write_report)
    result, _ = _evaluate(tmp_path, "all", cfg, four, af.params(cfg.model), {}, progress=False, cloud_views=3)
    assert result["cloud_views"] == {"test": list(TEST_IDS), "train": [0, 2, 3]}
    assert asked == [4]
    (shown,) = figures
    assert [f["name"] for f in shown] == [evaluate.frame_name(ds, i) for i in TEST_IDS]
    for fig, i in zip(shown, TEST_IDS):
        np.testing.assert_array_equal(fig["semantic"], ds.semantics[i])
    result, _ = _evaluate(tmp_path, "budget", cfg, four, af.params(cfg.model), {}, progress=False, cloud_views=3,
                          cloud_pixels=1, distractor_views=1)
    assert result["cloud_views"]["train"] == [0, 3]


def test_a_robust_runs_report_without_a_late_share_says_the_record_alone(evaluated, tmp_path):
    """A robust run whose metrics.jsonl has no `robust_weight` in its last quarter: the report's
    sentence gives the per-pixel record's share alone, 12.5 % (24 and 72 of 384 pixels black
    in the two weight PNGs, by hand), and metrics.json's late share is None (evaluate_run
    mutants 411, 413: the late text for a missing share)."""
    import json

    _, _, ds, _ = evaluated
    cfg = analytic_config()
    run_dir = tmp_path / "run"
    used = {TRAIN_IDS[0]: np.ones((H, W), np.float32), TRAIN_IDS[1]: np.ones((H, W), np.float32)}
    used[TRAIN_IDS[0]][2:6, 3:9] = 0.0
    used[TRAIN_IDS[1]][:3] = 0.0
    for i, w in used.items():
        io.write_png(run_dir / "weights" / f"{evaluate.frame_name(ds, i)}.png", w)
    (run_dir / "metrics.jsonl").write_text(json.dumps({"step": cfg.train.max_steps, "loss": 0.1}) + "\n")
    result, _ = _evaluate(tmp_path, "run", cfg, ds, af.params(cfg.model), {}, progress=False)
    assert result["training_weights"]["late_batch_ignored_share"] is None
    assert (f"Photometric evidence (`train.robust.mode = {cfg.train.robust.mode}`): training ignored 12.5 % "
            "of the training "
            "pixels in its per-pixel record (pixels never drawn count as used; weights in `weights/`, "
            "docs/ROBUST.md).") in (run_dir / "report.md").read_text()


def test_an_exported_run_gets_its_export_section_and_report_html_shows_its_measurements(evaluated, tmp_path,
                                                                                           monkeypatch):
    """A run folder holding an export (export/measurements.json, written here) evaluated with a
    reference cloud (normalised units): metrics.json's "export" is the measurements, the picture's
    path and the export's score against the reference moved to the export's units by hand, x =
    R^T x_norm / s - t (`score.score_export` is a stand-in recording what it is handed); report.html
    shows the measurements table, its height and footprint rows written out (evaluate_run mutants
    321, 323, 326: the export section without the dataset or the reference; 474, 480, 485, 486:
    report.html not shown the export folder)."""
    from jaxnerf_grid.eval import export_score as score

    _, _, ds, _ = evaluated
    cfg = analytic_config()
    run_dir = tmp_path / "run"
    meas = {"units": "metres", "height": 19.87, "box": {"min": [98.0, 198.0, 50.0], "max": [102.0, 202.0, 70.0]},
            "footprint": {"width_a": 4.01, "width_b": 3.99}, "cross_arms": {"levels": []}}
    io.write_json(run_dir / "export" / "measurements.json", meas)
    reference = tmp_path / "reference.ply"
    ref_points = np.array([[0.1, -0.2, 0.05], [0.0, 0.3, -0.1], [-0.25, 0.1, 0.2]])
    clouds_lib.write_point_cloud(reference, [(ref_points, np.zeros_like(ref_points))])
    handed = []

    def score_export(folder, points, scale):
        handed.append((Path(folder), np.asarray(points, np.float64), scale))
        return {"stand-in": True}

    monkeypatch.setattr(score, "score_export", score_export)
    result, _ = _evaluate(tmp_path, "run", cfg, ds, af.params(cfg.model), {}, progress=False, reference_ply=reference)
    assert result["export"] == {"measurements": meas, "image": "export/export_views.png", "score": {"stand-in": True}}
    (folder, points, scale), = handed
    s, rot, t = af.NORMALIZATION["scale"], np.asarray(af.NORMALIZATION["rotation"]), np.asarray(
        af.NORMALIZATION["translation"])
    assert folder == run_dir / "export" and scale == s
    np.testing.assert_allclose(points, ref_points @ rot / s - t, atol=1e-4)
    page = (run_dir / "report.html").read_text()
    assert "<h2>Measurements (export)</h2>" in page
    assert "<tr><td>height above the fitted ground</td><td>19.87 m</td></tr>" in page
    assert "<tr><td>base footprint</td><td>4.01 x 3.99 m</td></tr>" in page


def test_distractor_psnr_shows_its_progress_only_when_asked(evaluated, capsys):
    """distractor_psnr is quiet by default and with progress False; with progress True it
    prints one line (stderr is not a terminal here): "distractor regions: 1/1 view (100%), ..."
    (evaluate.distractor_psnr mutants 1, 18, 19, 23, 24: the default, the bar's flag, its label)."""
    import re

    _, _, ds, _ = evaluated
    cfg = analytic_config()
    params = af.params(cfg.model)
    af.clear_compiled()
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(fields, "apply", af.apply)
            capsys.readouterr()
            quiet = evaluate.distractor_psnr(params, cfg, ds, 1)
            assert capsys.readouterr().err == ""
            evaluate.distractor_psnr(params, cfg, ds, 1, False)
            assert capsys.readouterr().err == ""
            shown = evaluate.distractor_psnr(params, cfg, ds, 1, True)
            assert re.fullmatch(r"distractor regions: 1/1 view \(100%\), \d+\.\d s\n", capsys.readouterr().err)
    finally:
        af.clear_compiled()
    assert quiet == shown and quiet is not None


def test_evaluate_run_shows_the_progress_of_each_loop_when_asked(evaluated, tmp_path, capsys):
    """progress=True (stderr not a terminal: one final line a bar): the test views, the training
    views of the cloud and the distractor views each end with their line, written out here:
    "eval: 2/2 views (100%), ...", "tower points: 1/1 view (100%), ...", "distractor regions: 1/1
    view (100%), ..." (evaluate_run mutants 67, 68, 75, 76, 220, 221, 225, 226, 264, 269: a bar's
    flag or label, or distractor_psnr not handed the flag)."""
    import re

    _, _, ds, _ = evaluated
    cfg = analytic_config()
    capsys.readouterr()
    _evaluate(tmp_path, "run", cfg, ds, af.params(cfg.model), {}, progress=True, cloud_views=1, distractor_views=1)
    lines = capsys.readouterr().err.splitlines()
    for pattern in (r"eval: 2/2 views \(100%\), \d+\.\d s", r"tower points: 1/1 view \(100%\), \d+\.\d s",
                    r"distractor regions: 1/1 view \(100%\), \d+\.\d s"):
        assert sum(bool(re.fullmatch(pattern, line)) for line in lines) == 1, (pattern, lines)
