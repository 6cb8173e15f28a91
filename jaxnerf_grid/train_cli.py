"""`jaxnerf-grid train | render | eval | demo`.

    jaxnerf-grid train --data DIR --method ours|nerf|nerfw [--config FILE] [--out RUN] [--steps N]
    jaxnerf-grid render --run RUN [--split test|train|all]
    jaxnerf-grid eval --run RUN [--lpips-weights FILE] [--reference-ply FILE]
    jaxnerf-grid demo [--out runs/demo] [--steps N] [--overwrite]

A run directory holds config.json ({"data", "model", "train"}), checkpoints/, metrics.jsonl
(training log), renders/ (PNG), depth/ (EXR, z-depth in normalised scene units), opacity/
(PNG), metrics.json and report.md (written by eval).

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
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from jaxnerf_grid import config as config_lib, io
from jaxnerf_grid.config import ConfigError
from jaxnerf_grid.io import DataError

FAR_BACKGROUND_METRES = 100.0
REGION_DEFINITION = ("tower = classes 1-2 (tower, conductor); near_ground = class 3; far_background = "
                     "class 0 (sky) + classes 4-5 (vegetation, building) with ground-truth z-depth > "
                     f"{FAR_BACKGROUND_METRES:.0f} m")


# --------------------------------------------------------------------------- config / run dir


def _read_overrides(path: str | None) -> dict:
    if not path:
        return {}
    data = io.read_json(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must hold a JSON object")
    data = dict(data)
    data.pop("data", None)
    return data


def run_config_dict(cfg, data_path) -> dict:
    return {"data": str(data_path), **config_lib.to_dict(cfg)}


def load_run(run_dir) -> tuple:
    """(RunConfig, data path) of a run directory."""
    from jaxnerf_grid import train

    run_dir = Path(run_dir)
    path = run_dir / "config.json"
    if not path.is_file():
        raise DataError(f"{path}: not a run directory (no config.json)")
    raw = dict(io.read_json(path))
    data = raw.pop("data", None)
    return config_lib.from_dict(train.RunConfig, raw, where=str(path)), data


def _load_dataset(path, downscale: float = 1, progress: bool = True):
    from jaxnerf_grid.data.formats import load_dataset

    return load_dataset(path, downscale=downscale, progress=progress)


def train_run(data: str, method: str, out, overrides: dict | None = None, steps: int | None = None,
              overwrite: bool = False, progress: bool = True, dataset=None):
    """Creates (or resumes) a run and trains it. Returns (run_dir, RunConfig, TrainResult)."""
    from jaxnerf_grid import train

    overrides = dict(overrides or {})
    if steps is not None:
        overrides.setdefault("train", {})
        overrides["train"] = {**overrides["train"], "max_steps": int(steps)}
    cfg = train.make_config(method, overrides)
    ds = dataset if dataset is not None else _load_dataset(data, progress=progress)
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_images=ds.num_frames))
    run_dir = Path(out)
    wanted = run_config_dict(cfg, Path(data).resolve())
    if run_dir.exists() and any(run_dir.iterdir()):
        existing = run_dir / "config.json"
        if overwrite:
            for sub in ("checkpoints", "renders", "depth", "opacity"):
                shutil.rmtree(run_dir / sub, ignore_errors=True)
            for f in ("metrics.jsonl", "metrics.json", "report.md", "config.json"):
                (run_dir / f).unlink(missing_ok=True)
        elif not existing.is_file():
            raise DataError(f"{run_dir}: exists and is not a run directory; pass --overwrite or another --out")
        else:
            old = io.read_json(existing)
            same = {k: v for k, v in old.items() if k != "train"} == {k: v for k, v in wanted.items() if k != "train"}
            if not same or {k: v for k, v in old["train"].items() if k != "max_steps"} != \
                    {k: v for k, v in wanted["train"].items() if k != "max_steps"}:
                raise ConfigError(f"{existing}: the run exists with a different config; pass --overwrite "
                                  "to start again or another --out")
            if old["train"]["max_steps"] != wanted["train"]["max_steps"]:
                raise ConfigError(f"{existing}: the run was configured for {old['train']['max_steps']} steps "
                                  "(the learning-rate schedule depends on it); pass --overwrite to change it")
    run_dir.mkdir(parents=True, exist_ok=True)
    io.write_json(run_dir / "config.json", wanted)
    result = train.train(ds, cfg, run_dir, progress=progress)
    return run_dir, cfg, result


# --------------------------------------------------------------------------- render / eval


def _frame_name(ds, index: int) -> str:
    if ds.frame_paths:
        return Path(ds.frame_paths[index]).stem
    return f"frame_{index:04d}"


def _region_masks(ds, index: int) -> dict:
    if ds.semantics is None:
        return {}
    sem = np.asarray(ds.semantics[index])
    far = sem == 0
    if ds.depth is not None:
        scale = float(ds.normalization.get("scale", 1.0))
        metric = np.asarray(ds.depth[index], np.float64) / max(scale, 1e-12)
        far = far | (np.isin(sem, (4, 5)) & ~(metric <= FAR_BACKGROUND_METRES))
    return {"tower": np.isin(sem, (1, 2)), "near_ground": sem == 3, "far_background": far}


def render_split(run_dir, split: str = "test", progress: bool = True, dataset=None, params=None) -> list[dict]:
    """Renders the frames of a split into renders/, depth/, opacity/. Returns per-view dicts."""
    from jaxnerf_grid import train

    run_dir = Path(run_dir)
    cfg, data = load_run(run_dir)
    ds = dataset if dataset is not None else _load_dataset(data, progress=progress)
    if params is None:
        params, _ = train.load_params(run_dir, cfg, ds.num_frames)
    ids = np.arange(ds.num_frames) if split == "all" else np.asarray(ds.split[split])
    out = []
    for i in _bar(ids, progress, f"render {split}"):
        view = train.render_view(params, cfg, ds, int(i))
        _write_view(run_dir, _frame_name(ds, int(i)), view)
        out.append({"index": int(i), **view})
    return out


def _bar(items, progress: bool, desc: str):
    from jaxnerf_grid import progress as progress_lib

    return progress_lib.bar(items, desc=desc, unit="view", enabled=progress)


def _write_view(run_dir: Path, name: str, view: dict) -> None:
    io.write_png(run_dir / "renders" / f"{name}.png", np.clip(view["rgb"], 0, 1))
    io.write_exr(run_dir / "depth" / f"{name}.exr", view["depth"])
    io.write_png(run_dir / "opacity" / f"{name}.png", np.clip(view["opacity"], 0, 1))


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
            raise DataError(f"{path}: reference point cloud not found (--reference-ply)")
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
    from jaxnerf_grid import geometry

    ref = reference_cloud(ds, reference_ply)
    if ref is None:
        return None
    path, file_norm = ref
    return geometry.score_against_ply(cloud, path, file_normalization=file_norm,
                                      scene_normalization=ds.normalization if file_norm else None)


def evaluate_run(run_dir, lpips_weights: str | None = None, progress: bool = True, dataset=None,
                 distractor_views: int = 4, extra_notes: list[str] = (), reference_ply=None,
                 cloud_views: int = 0) -> dict:
    """Renders the test views, computes metrics.json and writes report.md. Returns the metrics.

    reference_ply: a reference tower cloud (normalised scene units) for metrics["geometry"];
    default: the dataset's `tower_ply` when it has one.
    cloud_views: the tower cloud (tower_points.ply, and the geometry score) is lifted from the
    test views' depth and also from this many training views, evenly spaced (more sides of
    the tower); the images are not scored.
    """
    import jax

    from jaxnerf_grid import export, lpips, metrics, rays as rays_lib, report, train

    start = time.perf_counter()
    run_dir = Path(run_dir)
    cfg, data = load_run(run_dir)
    ds = dataset if dataset is not None else _load_dataset(data, progress=progress)
    reference_cloud(ds, reference_ply)  # a missing --reference-ply fails before rendering
    params, step = train.load_params(run_dir, cfg, ds.num_frames)
    lpips_params = lpips.load_lpips(lpips_weights) if lpips_weights else None
    targets = ds.clean_images if ds.clean_images is not None else ds.images
    fit_left = cfg.model.use_appearance
    near = float(cfg.model.near if cfg.model.near is not None else ds.near)
    far = float(cfg.model.far if cfg.model.far is not None else ds.far)
    per_view, figures, cloud = [], [], []
    for i in _bar(np.asarray(ds.split["test"]), progress, "eval"):
        i = int(i)
        target = np.asarray(targets[i], np.float32)
        appearance = None
        if fit_left:
            r = train.camera_rays(ds, i, near, far)
            half = ds.width // 2
            left = rays_lib.Rays(*(np.asarray(x)[:, :half].reshape(-1, *np.asarray(x).shape[2:]) for x in r))
            appearance = train.fit_appearance(params, dataclasses.replace(cfg.model), cfg.train,
                                              rays_lib.Rays(*(jax.numpy.asarray(x) for x in left)),
                                              target[:, :half].reshape(-1, 3), jax.random.PRNGKey(i))
        view = train.render_view(params, cfg, ds, i, appearance=appearance)
        name = _frame_name(ds, i)
        _write_view(run_dir, name, view)
        rgb = np.clip(view["rgb"], 0, 1)
        cloud.append(export.lift_view(train.camera_rays(ds, i, near, far), rgb, view["depth"], view["opacity"]))
        record = {"name": name, "index": i, **metrics.evaluate_image(rgb, target, lpips_params)}
        half = ds.width // 2
        if min(rgb.shape[0], rgb.shape[1] - half) >= metrics.WIN_SIZE:
            right = metrics.evaluate_image(rgb[:, half:], target[:, half:], lpips_params)
        else:  # too small for the SSIM window: PSNR only
            right = {"psnr": float(metrics.psnr(rgb[:, half:], target[:, half:])), "ssim": None,
                     "ms_ssim": None, "lpips": None}
        record["right_half"] = {k: right[k] for k in ("psnr", "ssim", "ms_ssim", "lpips")}
        regions = {}
        for region, mask in _region_masks(ds, i).items():
            regions[region] = float(metrics.psnr(rgb, target, mask.astype(np.float32))) if mask.any() else None
        record["regions"] = regions
        per_view.append(record)
        figures.append({"name": name, "gt": target, "rgb": rgb, "depth": view["depth"],
                        "semantic": None if ds.semantics is None else np.asarray(ds.semantics[i])})

    def mean_of(key, rows):
        vals = [r[key] for r in rows if r.get(key) is not None and np.isfinite(r[key])]
        return float(np.mean(vals)) if vals else None

    mean = {k: mean_of(k, per_view) for k in ("psnr", "ssim", "ms_ssim", "lpips")}
    mean["ms_ssim_scales"] = per_view[0]["ms_ssim_scales"] if per_view else None
    mean_right = {k: mean_of(k, [r["right_half"] for r in per_view]) for k in ("psnr", "ssim", "ms_ssim", "lpips")}
    regions_mean = {}
    if per_view and per_view[0]["regions"]:
        for region in per_view[0]["regions"]:
            regions_mean[region] = mean_of(region, [r["regions"] for r in per_view])
    train_ids = np.asarray(ds.split["train"])
    cloud_ids = [int(i) for i in train_ids[np.linspace(0, len(train_ids) - 1, min(cloud_views, len(train_ids)))
                                           .round().astype(int)]] if cloud_views > 0 and len(train_ids) else []
    for i in _bar(cloud_ids, progress, "tower points"):
        view = train.render_view(params, cfg, ds, i)
        cloud.append(export.lift_view(train.camera_rays(ds, i, near, far), np.clip(view["rgb"], 0, 1),
                                      view["depth"], view["opacity"]))
    distractor = _distractor_psnr(params, cfg, ds, distractor_views, progress)
    protocol = ("targets are the clean images" if ds.clean_images is not None else "targets are the images")
    if fit_left:
        protocol += ("; NeRF-W: the appearance embedding of each test image is fitted on its left half "
                     "(network frozen) and the headline metrics are computed on the right half only")
        mean, mean_right = dict(mean_right, ms_ssim_scales=mean["ms_ssim_scales"]), mean_right
    protocol += "; rendering shows the static scene only" if cfg.model.use_transient else ""
    result = {"method": cfg.model.method, "step": step, "num_views": len(per_view),
              "target": "clean images" if ds.clean_images is not None else "images",
              "protocol": protocol, "mean": mean, "mean_right_half": mean_right,
              "regions_mean": regions_mean, "region_definition": REGION_DEFINITION if regions_mean else None,
              "distractor_psnr": distractor, "geometry": score_geometry(ds, cloud, reference_ply),
              "cloud_views": {"test": [int(r["index"]) for r in per_view], "train": cloud_ids},
              "per_view": per_view, "lpips": "computed" if lpips_params is not None else "unavailable",
              "eval_seconds": time.perf_counter() - start}
    io.write_json(run_dir / "metrics.json", result)
    export.write_point_cloud(run_dir / "tower_points.ply", cloud)
    notes = list(extra_notes)
    notes.append(f"Point cloud of the unit sphere (the tower region) lifted from the depth maps of the "
                 f"{len(per_view)} test views" + (f" and {len(cloud_ids)} training views" if cloud_ids else "")
                 + f" (opacity >= 0.5): `tower_points.ply`, {sum(len(p) for p, _ in cloud)} points, "
                 "normalised scene units.")
    notes.append(f"LPIPS: {'computed from ' + str(lpips_weights) if lpips_params is not None else 'unavailable (no --lpips-weights)'}.")
    notes.append(f"Evaluation took {result['eval_seconds']:.0f} s.")
    report.write_report(run_dir, result, run_config_dict(cfg, data), figures, notes)
    return result


def _distractor_psnr(params, cfg, ds, max_views: int, progress: bool):
    from jaxnerf_grid import metrics, train

    if ds.distractor_masks is None or ds.clean_images is None or max_views <= 0:
        return None
    ids = [int(i) for i in ds.split["train"] if np.asarray(ds.distractor_masks[i]).any()][:max_views]
    if not ids:
        return None
    sq, count = 0.0, 0.0
    for i in _bar(ids, progress, "distractor regions"):
        view = train.render_view(params, cfg, ds, i)
        m = np.asarray(ds.distractor_masks[i], np.float64)
        err = np.mean((np.clip(view["rgb"], 0, 1) - ds.clean_images[i]) ** 2, axis=-1)
        sq += float(np.sum(err * m))
        count += float(np.sum(m))
    return train.psnr_of(sq / count) if count else None


# --------------------------------------------------------------------------- subcommands


def main_train(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="jaxnerf-grid train", description="train a NeRF on a dataset")
    p.add_argument("--data", required=True, help="dataset folder (transforms.json, COLMAP, LLFF, Blender)")
    p.add_argument("--method", choices=["ours", "nerf", "nerfw"], default="ours")
    p.add_argument("--config", default=None, help="JSON file overriding defaults ({'model': {...}, 'train': {...}})")
    p.add_argument("--out", default=None, help="run directory (default runs/<method>)")
    p.add_argument("--steps", type=int, default=None, help="override train.max_steps")
    p.add_argument("--overwrite", action="store_true", help="start the run again if it exists")
    p.add_argument("--eval", action="store_true", help="evaluate and write the report after training")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    args = p.parse_args(argv)
    out = args.out or f"runs/{args.method}"
    run_dir, cfg, result = train_run(args.data, args.method, out, _read_overrides(args.config), args.steps,
                                     args.overwrite, not args.quiet)
    print(f"trained {cfg.model.method} to step {result.step} in {result.seconds:.0f} s "
          f"(last loss {result.last_loss:.4f}, PSNR {result.last_psnr:.2f} dB, "
          f"{len(result.skipped_steps)} skipped steps): {run_dir}")
    if args.eval:
        m = evaluate_run(run_dir, progress=not args.quiet)
        print(f"test PSNR {m['mean']['psnr']:.2f} dB; report: {run_dir / 'report.md'}")
    return 0


def main_render(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="jaxnerf-grid render", description="render views of a trained run")
    p.add_argument("--run", required=True, help="run directory")
    p.add_argument("--split", choices=["test", "train", "all"], default="test")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    views = render_split(args.run, args.split, not args.quiet)
    print(f"rendered {len(views)} views into {Path(args.run) / 'renders'} (depth/, opacity/ alongside)")
    return 0


def main_eval(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="jaxnerf-grid eval", description="evaluate a trained run on its test views")
    p.add_argument("--run", required=True, help="run directory")
    p.add_argument("--lpips-weights", default=None, help="LPIPS weights .npz (else LPIPS is unavailable)")
    p.add_argument("--distractor-views", type=int, default=4)
    p.add_argument("--reference-ply", default=None,
                   help="reference tower point cloud (PLY, the dataset's normalised scene units) to score "
                        "tower_points.ply against (default: the dataset's tower_ply, if any)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    m = evaluate_run(args.run, args.lpips_weights, not args.quiet, distractor_views=args.distractor_views,
                     reference_ply=args.reference_ply)
    print(f"test PSNR {m['mean']['psnr']:.2f} dB, SSIM {m['mean']['ssim']:.4f}; "
          f"report: {Path(args.run) / 'report.md'}")
    geo = m.get("geometry")
    if geo:
        print("tower geometry: " + ", ".join(f"F@{tau} {row['fscore']:.3f}" for tau, row in geo["thresholds"].items())
              + (f", Chamfer {geo['chamfer']:.4f}" if geo["chamfer"] is not None else ", Chamfer n/a")
              + " (normalised scene units)")
    return 0


# The CPU recipe of the demo (docs/GRID.md): a hash-grid field on the contracted coordinates
# (fields/grid.py), one density-only proposal round of 64 samples stratified in s (disparity
# warp) feeding 32 samples of the main field, the interlevel and distortion losses (in s), an
# opaque far bin at 1000 units so the sky sits at infinity, and Instant-NGP's Adam settings.
# Each choice was measured at 1000 steps on tower-small (docs/GRID.md, "How the recipe was chosen").
DEMO_CONFIG = {
    "model": {"sampler": "proposal", "proposal_samples": [64], "num_fine": 32, "contract_radius": 2.0,
              "field": {"kind": "grid", "depth": 1, "width": 64, "view_depth": 2, "view_width": 64,
                        "dir_max_deg": 3, "density_activation": "exp", "density_bias": -4.0,
                        "grid": {"num_levels": 12, "features_per_level": 2, "log2_table_size": 17,
                                 "min_resolution": 16, "max_resolution": 1024}},
              "proposal_field": {"density_bias": -4.0},
              # The drone orbits 45-70 m (2.2-3.5 units) from the tower; with the dataset's near of
              # 0.5 the disparity warp puts 3/4 of the samples in the empty first 2 units. Rays
              # start at 1 unit (20 m): birds nearer than that are distractors, masked anyway.
              # They end at 1000 units (20 km) in an opaque bin: the sky, at the far sphere.
              "near": 1.0, "far": 1000.0, "opaque_far": True},
    "train": {"batch_rays": 1024, "max_steps": 2400, "lr_init": 2e-2, "lr_final": 2e-3, "warmup": 50,
              "adam_eps": 1e-15, "adam_b2": 0.99, "max_grad_norm": 0.0, "distortion_loss_weight": 0.002,
              "checkpoint_every": 300, "log_every": 50, "chunk": 4096},
}


# Training views whose depth also goes into the demo's tower cloud (evaluate_run's cloud_views).
DEMO_CLOUD_VIEWS = 16


def run_demo(data: str | Path | None, out: str | Path, steps: int | None = None, overwrite: bool = False,
             progress: bool = True) -> dict:
    """The demo recipe as a library call: (synth when data is None) -> mask (when the dataset
    has no masks) -> train "ours" with DEMO_CONFIG -> evaluate. Returns {"run_dir", "metrics",
    "timings" (s per stage), "total_seconds", "mask_source"}."""
    if steps is not None and steps < 1:
        raise ConfigError(f"--steps must be >= 1, got {steps}")
    start = time.perf_counter()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: --out exists and is not a folder")
    timings = {}
    if data is not None:
        data = Path(data)
        if not data.is_dir():
            raise DataError(f"{data}: --data is not a folder")
    else:
        data = out / "data"
        if not (data / "transforms.json").is_file():
            from jaxnerf_grid.data.synthetic.generate import generate_scene

            t = time.perf_counter()
            generate_scene("tower-small", data, seed=0, overwrite=True, progress=progress)
            timings["synth"] = time.perf_counter() - t
    meta = io.read_json(data / "transforms.json") if (data / "transforms.json").is_file() else {}
    has_masks = "mask_source" in meta or any(isinstance(f, dict) and (f.get("weight_path") or f.get("mask_path"))
                                             for f in meta.get("frames", []))
    if not has_masks:
        from jaxnerf_grid import mask_cli

        t = time.perf_counter()
        mask_args = ["--data", str(data)]
        if not mask_cli.BUILTIN.exists() and "distractor_mask_path" in json.dumps(meta.get("frames", [])):
            mask_args += ["--source", "gt"]
        if not progress:
            mask_args.append("--quiet")
        rc = mask_cli.main(mask_args)
        if rc:
            raise DataError(f"{data}: masking failed (exit code {rc})")
        timings["mask"] = time.perf_counter() - t
        meta = io.read_json(data / "transforms.json") if (data / "transforms.json").is_file() else {}
    mask_source = meta.get("mask_source", "unknown")
    t = time.perf_counter()
    run_dir, cfg, result = train_run(str(data), "ours", out / "run", DEMO_CONFIG, steps, overwrite, progress)
    timings["train"] = time.perf_counter() - t
    notes = []
    if mask_source == "dpt":
        notes.append("Masks: built-in DPT (`jaxnerf-grid mask`), weights 1 - M_w.")
    elif mask_source in ("gt", "ground-truth"):
        notes.append("Masks: **ground-truth stand-ins** (mask source `ground-truth`): `jaxnerf-grid mask "
                     "--source gt` built M from the synthetic distractor masks and D from the true depth.")
    else:
        notes.append(f"Masks: from the dataset (mask source `{mask_source}`).")
    t = time.perf_counter()
    notes.append("Timings so far (s): " + ", ".join(f"{k} {v:.0f}" for k, v in timings.items()))
    metrics_out = evaluate_run(run_dir, progress=progress, extra_notes=notes, distractor_views=2,
                               cloud_views=DEMO_CLOUD_VIEWS)
    timings["eval"] = time.perf_counter() - t
    return {"run_dir": run_dir, "metrics": metrics_out, "timings": timings,
            "total_seconds": time.perf_counter() - start, "mask_source": mask_source}


def demo_summary(result: dict) -> str:
    """One line: time per stage, test PSNR, tower PSNR and tower F-score at 0.02."""
    m = result["metrics"]
    geometry = m.get("geometry") or {}
    f002 = ((geometry.get("thresholds") or {}).get("0.02") or {}).get("fscore")
    tower = (m.get("regions_mean") or {}).get("tower")
    timings = result["timings"]
    return (f"demo done in {result['total_seconds'] / 60:.1f} min "
            f"({', '.join(f'{k} {v:.0f} s' for k, v in timings.items())}); test PSNR {m['mean']['psnr']:.2f} dB"
            + (f", tower {tower:.2f} dB" if tower is not None else "")
            + (f", tower F-score@0.02 {f002:.3f}" if f002 is not None else ""))


def main_demo(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="jaxnerf-grid demo",
                                description="tower-small scene (or --data DIR) -> masks -> train ours -> render -> report")
    p.add_argument("--data", default=None,
                   help="run the same recipe on this dataset instead of the synthetic tower (skips synth; "
                        "skips mask when the dataset already has masks)")
    p.add_argument("--out", default="runs/demo")
    p.add_argument("--steps", type=int, default=None,
                   help=f"training steps (default {DEMO_CONFIG['train']['max_steps']})")
    p.add_argument("--overwrite", action="store_true", help="retrain the run (the data are kept)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    result = run_demo(args.data, args.out, args.steps, args.overwrite, not args.quiet)
    print(demo_summary(result))
    print(f"report: {result['run_dir'] / 'report.md'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    table = {"train": main_train, "render": main_render, "eval": main_eval, "demo": main_demo}
    if not argv or argv[0] not in table:
        print("usage: python -m jaxnerf_grid.train_cli {train,render,eval,demo} ...", file=sys.stderr)
        return 2
    return table[argv[0]](argv[1:])
