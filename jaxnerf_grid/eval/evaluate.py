"""Evaluating a trained run: test-view metrics, per-region PSNR, distractor PSNR, tower geometry.

`evaluate_run(run_dir)` renders the test views, writes metrics.json, report.md, report.html
(`report_html`) and tower_points.ply into the run directory and returns the metrics.

Evaluation protocol (stored in metrics.json and the report):
  * targets are the clean images where the dataset has them (synthetic data), else the images;
  * NeRF-W with an appearance embedding: the embedding of each test image is fitted on its
    left half (network frozen) and the headline metrics are on the right half; every method
    also reports right-half metrics ("mean_right_half") so methods can be compared alike;
  * per-region PSNR with semantics: "tower" = classes 1 (tower) and 2 (conductor);
    "near_ground" = class 3 (ground); "far_background" = class 0 (sky) plus classes 4
    (vegetation) and 5 (building) whose ground-truth z-depth exceeds 100 m in metric units
    (normalised depth / scene scale); without a depth map only sky counts as far background;
  * "distractor_psnr": PSNR inside the distractor masks of (up to 4) training views against
    their clean images: how much of the passers-by the model burnt in (higher = cleaner);
  * LPIPS only with --lpips-weights, else "unavailable";
  * "geometry": the exported tower cloud (tower_points.ply) against a reference cloud, scored by
    `geometry.score_points` in normalised scene units (precision / recall / F-score at 0.01,
    0.02, 0.05 units and the Chamfer distance, both clouds cropped to the reference tower's box
    less a ground strip). The reference is --reference-ply (a user's survey cloud, already in the
    dataset's normalised units) or else the dataset's `tower_ply` (synthetic data; converted from
    the file's `scene_normalization` to the loaded dataset's normalisation); None without one.
  * "training_fit": the PSNR of the training batches over the last tenth of the run (`training_fit`,
    from metrics.jsonl: each logged batch's weighted MSE, averaged, then as PSNR): how well the
    model fits the photos it trained on, beside the held-out views' PSNR;
  * "export": when the run has been exported (`jaxnerf-grid export`, RUN/export/), its
    measurements and, with a reference, its score in the export's units (`eval.export_score`: F-score
    at 0.2, 0.4, 1.0 m, Chamfer, height error; docs/EXPORT.md).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import numpy as np

from jaxnerf_grid.config import budget as budget_lib
from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.eval import export_score as score
from jaxnerf_grid.eval import geometry, lpips, metrics
from jaxnerf_grid.masks import robust as robust_lib
from jaxnerf_grid.nerf import losses
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.render import clouds, views
from jaxnerf_grid.report import html as report_html
from jaxnerf_grid.report import markdown as report
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train.runs import bar, frame_name, load_run_and_dataset, write_view
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError

FAR_BACKGROUND_METRES = 100.0
TRAINING_FIT_TAIL = 0.1  # `training_fit`: the logged batches of the last tenth of the steps
REGION_DEFINITION = ("tower = classes 1-2 (tower, conductor); near_ground = class 3; far_background = "
                     "class 0 (sky) + classes 4-5 (vegetation, building) with ground-truth z-depth > "
                     f"{FAR_BACKGROUND_METRES:.0f} m")


def region_masks(ds, index: int) -> dict:
    """Boolean masks [H, W] of frame `index` for the per-region PSNR: {"tower", "near_ground",
    "far_background"} (REGION_DEFINITION); {} when the dataset has no semantics."""
    if ds.semantics is None:
        return {}
    sem = np.asarray(ds.semantics[index])
    far = sem == 0
    if ds.depth is not None:
        scale = float(ds.normalization.get("scale", 1.0))
        metric = np.asarray(ds.depth[index], np.float64) / max(scale, 1e-12)
        far = far | (np.isin(sem, (4, 5)) & ~(metric <= FAR_BACKGROUND_METRES))
    return {"tower": np.isin(sem, (1, 2)), "near_ground": sem == 3, "far_background": far}


def reference_cloud(ds, reference_ply=None) -> tuple[Path, dict | None] | None:
    """The reference tower cloud of an evaluation: (PLY path, the normalisation its points are
    stored in, None = already in the dataset's units), or None when there is none.

    reference_ply: a user's cloud in the dataset's normalised units (must exist); else the
    dataset's `tower_ply` (relative to the dataset root; in the units of the file's
    `scene_normalization`) when that file exists.
    """
    if reference_ply:
        path = Path(reference_ply)
        if not path.is_file():
            raise DataError(f"{path}: reference point cloud not found (eval.reference_ply)")
        return path, None
    name = ds.meta.get("tower_ply") if ds.meta else None
    if not name:
        return None
    path = Path(ds.root) / name
    if not path.is_file():
        return None
    return path, ds.meta.get("scene_normalization")


def score_geometry(ds, cloud: list, reference_ply=None) -> dict | None:
    """metrics.json["geometry"]: the exported cloud parts [(points [K, 3], colours [K, 3])]
    against `reference_cloud(ds, reference_ply)`; None without a reference."""
    ref = reference_cloud(ds, reference_ply)
    if ref is None:
        return None
    path, file_norm = ref
    return geometry.score_against_ply(cloud, path, file_normalization=file_norm,
                                      scene_normalization=ds.normalization if file_norm else None)


def export_section(ds, run_dir, reference_ply=None) -> dict | None:
    """metrics.json["export"] when the run has an export (RUN/export/measurements.json, written by
    `jaxnerf-grid export`): {"measurements", "image", "score"}, the score (`eval.export_score`, in
    the export's units) only with a reference tower; None without an export."""
    folder = Path(run_dir) / "export"
    if not (folder / "measurements.json").is_file():
        return None
    info = {"measurements": io.read_json(folder / "measurements.json"), "image": "export/export_views.png"}
    ref = reference_cloud(ds, reference_ply)
    if ref is not None:
        path, file_norm = ref
        points = score.reference_in_export_units(io.read_ply_points(path), file_norm, ds.normalization)
        info["score"] = score.score_export(folder, points, float(ds.normalization.get("scale", 1.0)))
    return info


METRIC_KEYS = ("psnr", "ssim", "ms_ssim", "lpips")


def _fit_left_half(params, cfg, ds, index: int, target: np.ndarray, rays) -> np.ndarray:
    """NeRF-W's test protocol: the appearance embedding [A] of a test image fitted on its left
    half (network frozen), from the mean of the training photos' rows (`held_out_appearance`).
    target: [H, W, 3]; rays: the view's Rays [H, W]."""
    half = ds.width // 2
    left = rays_lib.Rays(*(jax.numpy.asarray(np.asarray(x)[:, :half].reshape(-1, *np.asarray(x).shape[2:]))
                           for x in rays))
    return views.fit_appearance(params, cfg.model, cfg.train, left, target[:, :half].reshape(-1, 3),
                                jax.random.PRNGKey(index), start=views.held_out_appearance(params, cfg, ds, index))


def _right_half_metrics(rgb: np.ndarray, target: np.ndarray, lpips_params) -> dict:
    """PSNR / SSIM / MS-SSIM / LPIPS of the right halves of rgb, target [H, W, 3] (PSNR only
    when the half is smaller than the SSIM window)."""
    half = rgb.shape[1] // 2
    if min(rgb.shape[0], rgb.shape[1] - half) >= metrics.WIN_SIZE:
        right = metrics.evaluate_image(rgb[:, half:], target[:, half:], lpips_params)
    else:  # too small for the SSIM window: PSNR only
        right = {"psnr": float(metrics.psnr(rgb[:, half:], target[:, half:])), "ssim": None,
                 "ms_ssim": None, "lpips": None}
    return {k: right[k] for k in METRIC_KEYS}


def _region_psnr(rgb: np.ndarray, target: np.ndarray, masks: dict) -> dict:
    """{region: PSNR of rgb against target [H, W, 3] inside its mask [H, W], None if empty}."""
    return {region: float(metrics.psnr(rgb, target, mask.astype(np.float32))) if mask.any() else None
            for region, mask in masks.items()}


def _mean_of(key: str, rows: list[dict]) -> float | None:
    """Mean of the finite, non-None rows[...][key]; None when there is none."""
    vals = [r[key] for r in rows if r.get(key) is not None and np.isfinite(r[key])]
    return float(np.mean(vals)) if vals else None


def _means(per_view: list[dict]) -> tuple[dict, dict, dict]:
    """(mean, mean_right_half, regions_mean) over the per-view records."""
    mean = {k: _mean_of(k, per_view) for k in METRIC_KEYS}
    mean["ms_ssim_scales"] = per_view[0]["ms_ssim_scales"] if per_view else None
    mean_right = {k: _mean_of(k, [r["right_half"] for r in per_view]) for k in METRIC_KEYS}
    regions_mean = {}
    if per_view and per_view[0]["regions"]:
        for region in per_view[0]["regions"]:
            regions_mean[region] = _mean_of(region, [r["regions"] for r in per_view])
    return mean, mean_right, regions_mean


def _lift(ds, index: int, near: float, far: float, rgb: np.ndarray, view: dict):
    """The tower points of one rendered view: clouds.lift_view -> (points [K, 3], colours [K, 3])."""
    return clouds.lift_view(views.camera_rays(ds, index, near, far), rgb, view["depth"], view["opacity"])


def fits_left_half(cfg) -> bool:
    """Whether held-out views are scored by NeRF-W's protocol (the embedding fitted on the left
    half, the right half scored): a model with the appearance embedding and
    train.appearance_steps > 0; with 0 steps they render with the mean of the training photos'
    embeddings (`views.held_out_appearance`, no test pixel used) and whole views are scored."""
    return bool(cfg.model.use_appearance and cfg.train.appearance_steps > 0)


def _protocol(ds, cfg) -> str:
    protocol = ("targets are the clean images" if ds.clean_images is not None else "targets are the images")
    if fits_left_half(cfg):
        protocol += ("; NeRF-W: the appearance embedding of each test image is fitted on its left half "
                     "(network frozen) and the headline metrics are computed on the right half only")
    elif cfg.model.use_appearance:
        protocol += ("; each test image renders with the mean of the training photos' appearance embeddings "
                     "(no test pixel used, train.appearance_steps = 0)")
    return protocol + ("; rendering shows the static scene only" if cfg.model.use_transient else "")


def evaluate_run(run_dir, lpips_weights: str | None = None, progress: bool = True, dataset=None,
                 distractor_views: int = 4, extra_notes: Sequence[str] = (), reference_ply=None,
                 cloud_views: int = 0, allow_other_data: bool = False, full_size: bool = False,
                 cloud_pixels: int = 0, appearance_steps: int | None = None) -> dict:
    """Renders the test views, computes metrics.json and writes report.md. Returns the metrics.

    The views are rendered and scored at the run's working resolution (`train.max_side`,
    data/working.py), or at the photos' full size with `full_size`; metrics["resolution"] says which.

    reference_ply: a reference tower cloud (normalised scene units) for metrics["geometry"];
    default: the dataset's `tower_ply` when it has one.
    cloud_views: the tower cloud (tower_points.ply, and the geometry score) is lifted from the
    test views' depth and also from this many training views, evenly spaced (more sides of
    the tower); the images are not scored. cloud_pixels: when > 0, at most this many pixels of
    training views in all (`clouds.views_within`: at least 2 views), so large photos cost
    what small ones do.
    allow_other_data: score a dataset other than the run's (runs.check_fingerprint refuses it).
    appearance_steps: the test-time fit's steps instead of the run's train.appearance_steps (a
    model with the appearance embedding: 0 scores whole views rendered with the training
    photos' mean embedding, more NeRF-W's right halves; `fits_left_half`).
    Everything is checked (the dataset's fingerprint, --reference-ply, the LPIPS weights file)
    before anything is rendered or written.
    """
    start = time.perf_counter()
    for key, value in (("eval.distractor_views", distractor_views), ("eval.cloud_views", cloud_views)):
        config_lib.check_value(key, value, int, config_lib.NONNEGATIVE)
    run_dir = Path(run_dir)
    cfg, data, ds = load_run_and_dataset(run_dir, dataset, progress, allow_other_data, full_size)
    if appearance_steps is not None:
        config_lib.check_value("eval.appearance_steps", appearance_steps, int, config_lib.NONNEGATIVE)
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, appearance_steps=appearance_steps))
    ref = reference_cloud(ds, reference_ply)  # a missing or broken --reference-ply fails before rendering
    if reference_ply and ref is not None:
        geometry.read_reference_points(ref[0])
    if lpips_weights and not Path(lpips_weights).is_file():
        raise DataError(f"{lpips_weights}: LPIPS weights file not found (eval.lpips_weights)")
    params, step = train.load_params(run_dir, cfg, ds)
    lpips_params = lpips.load_lpips(lpips_weights) if lpips_weights else None
    targets = ds.clean_images if ds.clean_images is not None else ds.images
    fit_left = fits_left_half(cfg)
    near, far = config_lib.near_far(cfg.model, ds)
    per_view, figures, cloud = [], [], []
    for i in bar(np.asarray(ds.split["test"]), progress, "eval"):
        i = int(i)
        target = np.asarray(targets[i], np.float32)
        appearance = (_fit_left_half(params, cfg, ds, i, target, views.camera_rays(ds, i, near, far))
                      if fit_left else None)
        view = views.render_view(params, cfg, ds, i, appearance=appearance)
        name = frame_name(ds, i)
        write_view(run_dir, name, view)
        rgb = np.clip(view["rgb"], 0, 1)
        cloud.append(_lift(ds, i, near, far, rgb, view))
        per_view.append({"name": name, "index": i, **metrics.evaluate_image(rgb, target, lpips_params),
                         "right_half": _right_half_metrics(rgb, target, lpips_params),
                         "regions": _region_psnr(rgb, target, region_masks(ds, i))})
        figures.append({"name": name, "gt": target, "rgb": rgb, "depth": view["depth"],
                        "semantic": None if ds.semantics is None else np.asarray(ds.semantics[i])})
    mean, mean_right, regions_mean = _means(per_view)
    if cloud_pixels > 0:
        cloud_views = clouds.views_within(cloud_views, cloud_pixels, ds.width, ds.height)
    cloud_ids = clouds.cloud_view_ids(ds, cloud_views)
    for i in bar(cloud_ids, progress, "tower points"):
        view = views.render_view(params, cfg, ds, i)
        cloud.append(_lift(ds, i, near, far, np.clip(view["rgb"], 0, 1), view))
    distractor = distractor_psnr(params, cfg, ds, distractor_views, progress)
    if fit_left:
        mean = dict(mean_right, ms_ssim_scales=mean["ms_ssim_scales"])
    result = {"method": cfg.model.method, "step": step, "num_views": len(per_view),
              "target": "clean images" if ds.clean_images is not None else "images",
              "protocol": _protocol(ds, cfg), "mean": mean, "mean_right_half": mean_right,
              "regions_mean": regions_mean, "region_definition": REGION_DEFINITION if regions_mean else None,
              "distractor_psnr": distractor, "geometry": score_geometry(ds, cloud, reference_ply),
              "export": export_section(ds, run_dir, reference_ply),
              "cloud_views": {"test": [int(r["index"]) for r in per_view], "train": cloud_ids},
              "per_view": per_view, "lpips": "computed" if lpips_params is not None else "unavailable",
              "resolution": resolution_record(ds, cfg, full_size),
              "eval_seconds": time.perf_counter() - start}
    log = train.read_log(run_dir / "metrics.jsonl")
    result["training_fit"] = training_fit(log, cfg.train.max_steps)
    weights = training_weights(run_dir, ds)
    if weights is not None:
        late = robust_lib.late_ignored_share(log, cfg.train.max_steps)
        result["training_weights"] = {"mode": cfg.train.robust.mode, "ignored_share": weights["ignored_share"],
                                      "late_batch_ignored_share": late}
    chosen = read_budget(run_dir)
    if chosen is not None:
        result["budget"] = chosen
    depth_prior = read_depth_prior(run_dir)
    if depth_prior is not None:
        result["depth_prior"] = depth_prior
    io.write_json(run_dir / "metrics.json", result)
    clouds.write_point_cloud(run_dir / "tower_points.ply", cloud)
    notes = list(extra_notes)
    if chosen is not None:
        notes.append(budget_lib.report_line(chosen))
    notes.append(resolution_note(result["resolution"]))
    if depth_prior is not None:
        notes.append(depth_prior_note(depth_prior, cfg.train))
    if weights is not None:
        late = result["training_weights"]["late_batch_ignored_share"]
        late_text = "" if late is None else (f"{100 * late:.1f} % of the pixels of each batch in the last "
                                             "quarter of training, and ")
        notes.append(f"Photometric evidence (`train.robust.mode = {cfg.train.robust.mode}`): training ignored "
                     f"{late_text}{100 * weights['ignored_share']:.1f} % of the training pixels in its per-pixel "
                     "record (pixels never drawn count as used; weights in `weights/`, docs/ROBUST.md)."
                     + strict_note(cfg.train))
        notes += report.weights_figure(run_dir, weights["rows"])
    notes.append(f"Point cloud of the unit sphere (the tower region) lifted from the depth maps of the "
                 f"{len(per_view)} test views" + (f" and {len(cloud_ids)} training views" if cloud_ids else "")
                 + f" (opacity >= 0.5): `tower_points.ply`, {sum(len(p) for p, _ in cloud)} points, "
                 "normalised scene units.")
    lpips_note = (f"computed from {lpips_weights}" if lpips_params is not None
                  else "unavailable (no LPIPS weights given)")
    notes.append(f"LPIPS: {lpips_note}.")
    notes.append(f"Evaluation took {result['eval_seconds']:.0f} s.")
    report.write_report(run_dir, result, cfg, data, figures, notes)
    report_html.write_report_html(run_dir / "report.html", run_dir, ds, result, figures, run_dir / "export")
    return result


def training_fit(log: list[dict], max_steps: int, tail: float = TRAINING_FIT_TAIL) -> dict | None:
    """The training batches' PSNR late in a run: -10 log10 of the mean MSE (10^(-psnr / 10) of each
    record) of the metrics.jsonl records (`log`: {"step", "psnr", ...}) whose step is past
    (1 - tail) x max_steps. Each batch is a fresh draw of training pixels, so the mean estimates
    the fit over the training photos (their masked pixels left out, as the loss leaves them).
    Returns {"psnr", "batches", "from_step"}; None when no record lies there."""
    start = (1.0 - tail) * max_steps
    late = [float(r["psnr"]) for r in log if "psnr" in r and float(r.get("step", 0)) > start
            and np.isfinite(float(r["psnr"]))]
    if not late:
        return None
    mse = float(np.mean([10.0 ** (-v / 10.0) for v in late]))
    return {"psnr": -10.0 * float(np.log10(mse)), "batches": len(late), "from_step": int(start)}


def read_depth_prior(run_dir) -> dict | None:
    """The run's record of train.depth (RUN/depth_prior.json: {"used", "why", "rays"}); None when
    the run did not ask for it or the record does not parse."""
    path = Path(run_dir) / train.DEPTH_RECORD
    if not path.is_file():
        return None
    try:
        rec = io.read_json(path)
    except DataError:
        return None
    return rec if isinstance(rec, dict) and {"used", "why"} <= set(rec) else None


def depth_prior_note(rec: dict, tcfg) -> str:
    """report.md's line on the sparse points' depth prior."""
    if not rec["used"]:
        return f"Depth prior (`train.depth`): asked for but not used: {rec['why']}."
    d = tcfg.depth
    return (f"Depth prior (`train.depth.weight = {d.weight:g}`, decaying to {d.weight * d.decay:g}): "
            f"{rec['why']}; {d.rays} of them rendered each step (docs/RECIPES.md).")


def read_budget(run_dir) -> dict | None:
    """The training budget's record of a run (RUN/budget.json, `budget.apply`); None for a run
    without one (trained before the budget, or by a library call that gave none)."""
    path = Path(run_dir) / "budget.json"
    if not path.is_file():
        return None
    rec = io.read_json(path)
    if not isinstance(rec, dict) or not {"rule", "steps", "batch_rays", "epochs", "train_pixels"} <= set(rec):
        raise DataError(f"{path}: not a training budget record (an object with rule, steps, batch_rays, "
                        "epochs, train_pixels expected)")
    return rec


def resolution_record(ds, cfg, full_size: bool) -> dict:
    """What size the views were scored at: {"width", "height" (rendered), "native_width",
    "native_height" (the photos), "max_side" (the run's train.max_side), "full_size"}."""
    native = ds.meta.get("native_size") or [ds.width, ds.height]
    return {"width": ds.width, "height": ds.height, "native_width": int(native[0]),
            "native_height": int(native[1]), "max_side": int(cfg.train.max_side), "full_size": bool(full_size)}


def resolution_note(res: dict) -> str:
    """The report's line on the resolution of the scored views."""
    size = f"{res['width']}x{res['height']}"
    if res["full_size"]:
        return f"Resolution: test views rendered at the photos' full size, {size} (`--full-size`)."
    if (res["width"], res["height"]) == (res["native_width"], res["native_height"]):
        return f"Resolution: trained and rendered at the photos' size, {size}."
    return (f"Resolution: trained and rendered at {size}, the working resolution of the "
            f"{res['native_width']}x{res['native_height']} photos (`train.max_side` {res['max_side']}; "
            "`eval --full-size` for full size).")


def strict_note(train_cfg) -> str:
    """The report's sentence on how dpt+robust re-admitted the pixels its prior flagged
    (train.robust.strict_readmit as the run settled it: config.strict_readmit_auto); "" for
    other modes or a run recorded before the key existed."""
    strict = train_cfg.robust.strict_readmit
    if train_cfg.robust.mode != "dpt+robust" or strict is None:
        return ""
    if strict:
        return (" A pixel the DPT flagged was re-admitted only when its residual was an inlier and a "
                "neighbouring photo confirmed it (`train.robust.strict_readmit` on; on by default unless `mask` "
                "judged the masks out of their domain).")
    return (" A pixel the DPT flagged was re-admitted when its residual was an inlier or a neighbouring "
            "photo confirmed it (`train.robust.strict_readmit` off; off by default only where `mask` judged "
            "the masks out of their domain).")


def training_weights(run_dir, ds, panels: int = 3) -> dict | None:
    """The weights a train.robust run used (run_dir/weights/NAME.png, written by training),
    or None without them: {"ignored_share": mean of 1 - weight over every training pixel,
    "rows": [(photo, DPT weight 1 - M_w (ones without masks), weight used)] for `panels`
    training frames evenly spaced}."""
    folder = Path(run_dir) / "weights"
    if not folder.is_dir():
        return None
    train_ids = [int(i) for i in ds.split["train"]]
    used = {i: io.read_image(folder / f"{frame_name(ds, i)}.png")[..., 0] for i in train_ids
            if (folder / f"{frame_name(ds, i)}.png").is_file()}
    if not used:
        return None
    shown = [train_ids[k] for k in np.unique(np.linspace(0, len(train_ids) - 1, panels).round().astype(int))]
    prior = lambda i: np.ones(ds.images.shape[1:3], np.float32) if ds.weights is None else ds.weights[i]  # noqa: E731
    return {"ignored_share": float(np.mean([1.0 - w.mean() for w in used.values()])),
            "rows": [(ds.images[i], prior(i), used[i]) for i in shown if i in used]}


def distractor_psnr(params, cfg, ds, max_views: int, progress: bool = False) -> float | None:
    """PSNR inside the distractor masks of (up to max_views) training views against their clean
    images, pooled over the views (how much of the passers-by the model burnt in); None
    without distractor masks or clean images."""
    if ds.distractor_masks is None or ds.clean_images is None or max_views <= 0:
        return None
    ids = [int(i) for i in ds.split["train"] if np.asarray(ds.distractor_masks[i]).any()][:max_views]
    if not ids:
        return None
    sq, count = 0.0, 0.0
    for i in bar(ids, progress, "distractor regions"):
        view = views.render_view(params, cfg, ds, i)
        m = np.asarray(ds.distractor_masks[i], np.float64)
        err = np.mean((np.clip(view["rgb"], 0, 1) - ds.clean_images[i]) ** 2, axis=-1)
        sq += float(np.sum(err * m))
        count += float(np.sum(m))
    return float(losses.mse_to_psnr(sq / count)) if count else None
