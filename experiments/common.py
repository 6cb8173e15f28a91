"""Shared machinery of the paper's experiments (Section 4) and the sampling-scheme benchmark.

Every table script does the same things, so they live here:
  * `scene(...)`: a synthetic dataset generated once per (preset, seed, size, views,
    distractors) under the cache (default experiments/.cache/scenes/);
  * `mask_variant(...)`: a copy of a scene's transforms.json in its own folder whose image
    paths point back at the scene's files (no image is copied) and whose masks / weights are
    written by `masking.write_masks` (what `jaxnerf-grid mask` runs: ground truth with or
    without Eq. 7's depth weighting, or a DPT); `clean_variant(...)`: the same with the clean
    images as training targets;
  * `run_condition(...)`: train + evaluate one (dataset, method, overrides, seed) in a run
    directory named by a hash of all of it; a run whose metrics.json exists is skipped, one
    that was killed resumes from its last checkpoint (so a table can be re-launched);
  * `aggregate(...)`, `write_results(...)`: mean / standard deviation over seeds into
    results/<name>.json and results/<name>.md with the command, settings, machine and wall time.

Settings come in three sizes:
  * "quick": CI's smoke setting (an MLP 3x64, 200 steps, 80x60 scenes; no run resolves the tower);
  * "standard": the paper's tables on the 2-core CPU. Every method uses the demo's grid field and
    proposal sampling (`demo.DEMO_CONFIG`) with the same steps, rays and samples per ray; the
    methods differ only in what defines them (contraction and warp, masks, NeRF-W's embeddings;
    `method_overrides`). 1200 steps x 1024 rays on the demo's 160x120 scenes: ours resolves the
    tower there (docs/GRID.md, experiments/README.md);
  * "full": 3 seeds, larger scenes and more steps of the MLP, for a GPU machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import re
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")

ROOT = Path(__file__).resolve().parents[1]

import numpy as np  # noqa: E402

from jaxnerf_grid import io  # noqa: E402
from jaxnerf_grid.config import merge  # noqa: E402

EXPERIMENTS = Path(__file__).resolve().parent
RESULTS = EXPERIMENTS / "results"
BENCH_RESULTS = ROOT / "benchmarks" / "results"
CACHE = EXPERIMENTS / ".cache"

# Scene sizes: (width, height, num_train, num_test, supersample) per preset and setting.
SCENE_SIZES = {
    "quick": {"tower-small": (80, 60, 20, 3, 1), "ttpla-like": (96, 54, 20, 3, 1), "plad-like": (84, 56, 20, 3, 1)},
    "standard": {"tower-small": (160, 120, 40, 8, 2), "ttpla-like": (192, 108, 40, 8, 2),
                 "plad-like": (180, 120, 40, 8, 2)},
    "full": {"tower-small": (160, 120, 40, 8, 2), "ttpla-like": (320, 180, 60, 8, 2),
             "plad-like": (300, 200, 60, 8, 2)},
}


def _standard_overrides() -> dict:
    """The demo's recipe (grid field, proposal sampling in s, opaque far bin) without its step count."""
    from jaxnerf_grid.demo import DEMO_CONFIG
    from jaxnerf_grid.samplers.legacy import flat_model

    recipe = json.loads(json.dumps(DEMO_CONFIG))
    recipe["model"] = flat_model(recipe["model"])  # the settings' layers are flat (their run keys hash that)
    recipe["train"].pop("max_steps", None)
    return recipe

# Model / optimiser settings shared by every table (a method's own flags come on top).
TRAIN_SETTINGS = {
    "quick": {"steps": 200, "seeds": 1, "distractor_views": 2, "overrides": {
        "model": {"field": {"depth": 3, "width": 64, "skip": 0, "pos_max_deg": 7, "dir_max_deg": 2,
                            "view_width": 32},
                  "num_coarse": 16, "num_fine": 16},
        "train": {"batch_rays": 256, "lr_init": 4e-3, "lr_final": 3e-4, "warmup": 20, "checkpoint_every": 100,
                  "log_every": 20, "chunk": 4096, "appearance_steps": 20}}},
    "standard": {"steps": 1200, "seeds": 3, "distractor_views": 4, "cloud_views": 16,
                 "overrides": _standard_overrides()},
    "full": {"steps": 5000, "seeds": 3, "distractor_views": 4, "overrides": {
        "model": {"field": {"depth": 6, "width": 128, "skip": 3, "pos_max_deg": 10, "dir_max_deg": 4,
                            "view_width": 64},
                  "num_coarse": 48, "num_fine": 48},
        "train": {"batch_rays": 2048, "lr_init": 2e-3, "lr_final": 5e-5, "warmup": 200, "checkpoint_every": 1000,
                  "log_every": 50, "chunk": 8192}}},
}


# Without contraction a grid field must cover every sample point: at `standard` NeRF and NeRF-W
# sample linearly from 1 to the far plane at 40 units (800 m, past the tree line and buildings;
# the sky is the opaque far bin), and their grid spans +-44 units: the far plane plus the
# farthest camera (3.7 units). That is NeRF's bounded parameterisation; contraction is what
# "ours" has and they lack.
NERF_FAR = 40.0
NERF_GRID_HALF_WIDTH = 44.0


def space_overrides(setting: str, method: str, overrides: dict | None = None) -> dict:
    """The bounded space of a run without contraction. At `standard` the demo's recipe is ours
    (near 1, far 1000, contracted); a run without contraction (NeRF, NeRF-W, Table 2's rows
    without it) keeps its field, sampler, samples, steps and rays, in a bounded space instead
    (far NERF_FAR, the grid over +-NERF_GRID_HALF_WIDTH). `overrides`: the condition's own."""
    from jaxnerf_grid import models

    if setting != "standard":
        return {}
    own = (overrides or {}).get("model", {})
    if own.get("use_contraction", models.method_defaults(method).get("use_contraction", False)):
        return {}
    return {"model": {"far": NERF_FAR, "encoding_scale": NERF_GRID_HALF_WIDTH}}


# --------------------------------------------------------------------------- setup / provenance


def enable_compile_cache(path: Path = CACHE / "jax_cache") -> None:
    """Persistent XLA compilation cache: runs that differ only in the seed share compilations."""
    import jax

    path.mkdir(parents=True, exist_ok=True)
    try:
        jax.config.update("jax_compilation_cache_dir", str(path))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    except Exception as exc:  # an older/newer jax without these options: just slower
        print(f"(no persistent compilation cache: {exc})", file=sys.stderr)


def machine_info() -> dict:
    import jax

    info = {"date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "python": platform.python_version(),
            "platform": platform.platform(), "cpu_count": os.cpu_count(), "jax": jax.__version__,
            "backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()]}
    try:
        info["load_avg_1min"] = os.getloadavg()[0]
    except OSError:
        pass
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu_model"] = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return info


def machine_line(info: dict) -> str:
    cpu = info.get("cpu_model", "CPU")
    load = f", 1-min load average {info['load_avg_1min']:.1f} at the start" if "load_avg_1min" in info else ""
    return (f"{info['cpu_count']} x {cpu}, JAX {info['jax']} on {info['backend']} "
            f"({len(info['devices'])} devices){load}, {info['date_utc']}")


def base_parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--quick", dest="setting", action="store_const", const="quick",
                   help="small scenes and short training (2-core CPU; default)")
    g.add_argument("--standard", dest="setting", action="store_const", const="standard",
                   help="the grid field and proposal sampling for every method, sized to resolve the tower on "
                        "the 2-core CPU (about 5 min per run)")
    g.add_argument("--full", dest="setting", action="store_const", const="full",
                   help="the issue's setting: 3 seeds, larger scenes, more steps (GPU machine)")
    p.set_defaults(setting="quick")
    p.add_argument("--seeds", type=int, default=None, help="number of seeds (default: 1 quick, 3 full)")
    p.add_argument("--steps", type=int, default=None, help="training steps per run (default: by setting)")
    p.add_argument("--cache", default=str(CACHE), help="scenes, mask variants and runs (default experiments/.cache)")
    p.add_argument("--results", default=None,
                   help="where <table>.json / .md / .png go (default experiments/results/ for --quick, "
                        "experiments/results/<setting>/ otherwise)")
    p.add_argument("--budget-min", type=float, default=None,
                   help="stop launching new runs after this many minutes; missing rows are marked 'not run'")
    p.add_argument("--train-only", default=None, metavar="REGEX",
                   help="train only the runs whose 'LABEL seed N' matches this regular expression (re.search); "
                        "the others come from the cache or are marked 'not run' (to queue runs in a chosen order)")
    p.add_argument("--ignore-recorded", action="store_true",
                   help="train runs that are missing from the cache even when a committed results file records "
                        "them (by default such a run is read back from the results file: `recorded_runs`)")
    p.add_argument("--lpips-weights", default=None, help="LPIPS weights .npz (else LPIPS is reported unavailable)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


@dataclasses.dataclass
class Context:
    """What one table invocation needs: setting, paths, budget, and what has been run."""

    setting: str
    seeds: int
    steps: int
    cache: Path
    results: Path
    budget_s: float | None
    lpips_weights: str | None
    progress: bool
    command: str
    start: float = dataclasses.field(default_factory=time.perf_counter)
    machine: dict = dataclasses.field(default_factory=dict)
    not_run: list = dataclasses.field(default_factory=list)  # "LABEL seed N": over budget or not --train-only
    run_seconds: dict = dataclasses.field(default_factory=dict)  # run dir -> recorded train + eval wall s
    train_only: str | None = None  # regex on "LABEL seed N": runs that may be trained; None = all
    recorded: dict | None = None  # (seed, run key) -> a run read back from committed results (`recorded_runs`)
    restored: list = dataclasses.field(default_factory=list)  # run dirs taken from `recorded` in this invocation

    def may_train(self, name: str) -> bool:
        """Whether the run called `name` ("LABEL seed N") may be trained in this invocation."""
        return self.train_only is None or re.search(self.train_only, name) is not None

    @property
    def overrides(self) -> dict:
        return json.loads(json.dumps(TRAIN_SETTINGS[self.setting]["overrides"]))

    @property
    def distractor_views(self) -> int:
        return TRAIN_SETTINGS[self.setting]["distractor_views"]

    @property
    def cloud_views(self) -> int:
        """Training views whose depth joins the test views' in the tower cloud (eval's geometry_f)."""
        return TRAIN_SETTINGS[self.setting].get("cloud_views", 0)

    def out_of_budget(self) -> bool:
        return self.budget_s is not None and time.perf_counter() - self.start > self.budget_s


def results_folder(root: Path, setting: str) -> Path:
    """Where a setting's results go by default: `root` for quick (CI's smoke setting, whose files
    came first), root/<setting>/ for the others, so a table at one setting never overwrites another's."""
    return Path(root) if setting == "quick" else Path(root) / setting


def make_context(args, script: str) -> Context:
    setting = args.setting
    seeds = args.seeds or TRAIN_SETTINGS[setting]["seeds"]
    steps = args.steps or TRAIN_SETTINGS[setting]["steps"]
    flags = [f"--{setting}"] + [a for a in sys.argv[1:] if a not in ("--quick", "--standard", "--full")]
    command = f"JAX_PLATFORMS=cpu python -m experiments.{Path(script).stem} " + " ".join(flags)
    results = Path(args.results) if args.results else results_folder(RESULTS, setting)
    ctx = Context(setting, seeds, steps, Path(args.cache), results,
                  None if args.budget_min is None else args.budget_min * 60, args.lpips_weights, not args.quiet,
                  command.strip(), train_only=args.train_only)
    ctx.cache.mkdir(parents=True, exist_ok=True)
    ctx.results.mkdir(parents=True, exist_ok=True)
    enable_compile_cache(ctx.cache / "jax_cache")
    ctx.machine = machine_info()
    if not getattr(args, "ignore_recorded", False):
        folders = {ctx.results, results_folder(RESULTS, setting), results_folder(BENCH_RESULTS, setting)}
        ctx.recorded = recorded_runs(sorted(folders))
    return ctx


# --------------------------------------------------------------------------- scenes and masks


def scene(ctx: Context, preset: str, seed: int, distractors: str | None = None, size: tuple | None = None) -> Path:
    """Dataset folder of a synthetic scene (generated on first use). size: (w, h, train, test, ss)."""
    from jaxnerf_grid.data.synthetic.generate import generate_scene

    w, h, n_train, n_test, ss = size or SCENE_SIZES[ctx.setting][preset]
    name = f"{preset}_s{seed}_{w}x{h}_{n_train}+{n_test}_ss{ss}_{distractors or 'preset'}_g{generator_digest()}"
    out = ctx.cache / "scenes" / name
    if not (out / "transforms.json").is_file():
        print(f"[scene] generating {name}", flush=True)
        generate_scene(preset, out, seed=seed, distractors=distractors, overwrite=True, progress=ctx.progress,
                       width=w, height=h, num_train=n_train, num_test=n_test, supersample=ss,
                       workers=min(2, os.cpu_count() or 1) if w * h * (n_train + n_test) > 100_000 else 1)
    return out


def generator_digest() -> str:
    """Short SHA-1 of the synthetic generator's source: a cached scene made by other code is not reused."""
    from jaxnerf_grid.data import synthetic

    h = hashlib.sha1()
    for f in sorted(Path(synthetic.__file__).parent.glob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:6]


def _relink(scene_dir: Path, variant_dir: Path, meta: dict, keys=("file_path", "clean_file_path",
                                                                    "depth_file_path", "semantic_file_path",
                                                                    "distractor_mask_path", "shadow_mask_path")) -> dict:
    """transforms.json `meta` of scene_dir with every per-frame path rewritten relative to variant_dir."""
    meta = json.loads(json.dumps(meta))
    rel = os.path.relpath(scene_dir, variant_dir)
    for frame in meta["frames"]:
        for k in keys:
            if k in frame:
                frame[k] = f"{rel}/{frame[k]}"
        for k in ("mask_path", "weight_path", "dpt_depth_path", "overlay_path"):
            frame.pop(k, None)
    for k in ("mask_source", "mask_params"):
        meta.pop(k, None)
    if "tower_ply" in meta:
        meta["tower_ply"] = f"{rel}/{meta['tower_ply']}"
    return meta


def weights_digest(folder: Path) -> str:
    """Short SHA-1 of every file in a weights folder (names and bytes), for cache keys."""
    h = hashlib.sha1()
    for f in sorted(Path(folder).iterdir()):
        if f.is_file():
            h.update(f.name.encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:8]


def mask_variant(ctx: Context, scene_dir: Path, name: str, source: str = "gt", floor: float = 0.0,
                 weights: str | None = None, max_side: int = 160, dilate: int = 0) -> Path:
    """A folder whose transforms.json points at scene_dir's images, with masks from `masking.write_masks`.

    source "gt": ground-truth distractor masks and depth (floor 0 = Eq. 7, floor 1 = binary
    masks, every masked pixel excluded); "dpt": a DPT (`weights` folder, default built-in).
    dilate: pixels of `mask --dilate` (M and M_w grown by a disc); 0 keeps the folder name of old.
    """
    from jaxnerf_grid import masking

    if source == "dpt":  # any DPT can be retrained (the built-in; Table 4's crossover models): key the
        # cached masks, and so the run key of every run on them, on the weights' bytes
        name = f"{name}_{weights_digest(Path(weights) if weights else masking.BUILTIN)}"
    out = ctx.cache / "variants" / f"{scene_dir.name}__{name}"
    meta_path = out / "transforms.json"
    if meta_path.is_file() and "mask_source" in io.read_json(meta_path):
        return out
    out.mkdir(parents=True, exist_ok=True)
    io.write_json(meta_path, _relink(scene_dir, out, io.read_json(scene_dir / "transforms.json")))
    settings = {"source": source, "floor": floor, "overwrite": True, "max_side": max_side,
                "weights": str(weights) if weights else None, "dilate": dilate}
    print(f"[mask] {out.name}: masking.write_masks {settings}", flush=True)
    masking.write_masks(out, progress=ctx.progress, **settings)
    return out


def clean_variant(ctx: Context, scene_dir: Path) -> Path:
    """A folder whose training targets are the scene's clean (distractor-free) images: the upper bound."""
    out = ctx.cache / "variants" / f"{scene_dir.name}__clean"
    meta_path = out / "transforms.json"
    if not meta_path.is_file():
        out.mkdir(parents=True, exist_ok=True)
        meta = _relink(scene_dir, out, io.read_json(scene_dir / "transforms.json"))
        for frame in meta["frames"]:
            if "clean_file_path" in frame:
                frame["file_path"] = frame["clean_file_path"]
        io.write_json(meta_path, meta)
    return out


def mask_iou(variant_dir: Path, split: str = "train") -> dict:
    """IoU / precision / recall of a variant's masks M against the synthetic distractor masks (bit 0),
    pooled over the frames of `split`."""
    import cv2

    meta = io.read_json(variant_dir / "transforms.json")
    tp = fp = fn = 0.0
    for f in meta["frames"]:
        if f.get("split", "train") != split or "mask_path" not in f or "distractor_mask_path" not in f:
            continue
        pred = io.read_mask(variant_dir / f["mask_path"]) > 0.5
        raw = cv2.imread(str(variant_dir / f["distractor_mask_path"]), cv2.IMREAD_UNCHANGED)
        gt = (raw.astype(np.int64) & 1).astype(bool)
        tp += float(np.sum(pred & gt))
        fp += float(np.sum(pred & ~gt))
        fn += float(np.sum(~pred & gt))
    return {"iou": tp / max(tp + fp + fn, 1.0), "precision": tp / max(tp + fp, 1.0),
            "recall": tp / max(tp + fn, 1.0), "gt_pixels": tp + fn}


# --------------------------------------------------------------------------- runs


def run_key(data_dir: Path, method: str, overrides: dict, steps: int) -> str:
    """Hash of the dataset folder's name, the fully resolved RunConfig and the step count."""
    from jaxnerf_grid import config as config_lib, train
    from jaxnerf_grid.samplers.legacy import flat_keys

    with_steps = config_lib.merge(overrides, {"train": {"max_steps": int(steps)}})
    cfg = config_lib.to_dict(train.make_config(method, with_steps))
    cfg["model"] = {**{k: v for k, v in cfg["model"].items() if k != "sampler"},  # the flat sampler keys, as
                    **flat_keys(with_steps.get("model", {}))}  # before model.sampler: runs keep their keys
    blob = json.dumps({"data": Path(data_dir).name, "config": cfg}, sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:10]


def run_condition(ctx: Context, data_dir: Path, method: str, seed: int, label: str,
                  overrides: dict | None = None, steps: int | None = None) -> dict | None:
    """Trains and evaluates one condition (skipped when its metrics.json exists).

    Returns {"metrics": metrics.json, "run_dir", "train_seconds", "seconds_per_step", "cached"},
    or None when the time budget is spent before the run starts.
    """
    from jaxnerf_grid import evaluate, models, runs

    steps = int(steps or ctx.steps)
    ov = merge(merge(ctx.overrides, space_overrides(ctx.setting, method, overrides)), overrides or {})
    ov = merge(ov, {"train": {"seed": int(seed)}})
    key = run_key(data_dir, method, ov, steps)
    run_dir = ctx.cache / "runs" / f"{label}-s{seed}-{key}"
    same = sorted((ctx.cache / "runs").glob(f"*-s{seed}-{key}"))
    if not run_dir.exists() and same:  # the identical run made by another table
        run_dir = same[0]
    done = run_dir / "metrics.json"
    info_path = run_dir / "experiment.json"
    if done.is_file() and info_path.is_file():
        info = io.read_json(info_path)
        ctx.run_seconds[str(run_dir)] = info["train_wall_s"] + info["eval_wall_s"]
        return {**info, "wall_s": ctx.run_seconds[str(run_dir)], "metrics": io.read_json(done), "cached": True}
    restored = (ctx.recorded or {}).get((int(seed), key))
    if restored is not None:
        ctx.restored.append(restored["run_dir"])
        if restored.get("wall_s") is not None:
            ctx.run_seconds[restored["run_dir"]] = restored["wall_s"]
        print(f"[recorded] {label} seed {seed}: from {restored['recorded_in']}", flush=True)
        return restored
    if ctx.out_of_budget() or not ctx.may_train(f"{label} seed {seed}"):
        ctx.not_run.append(f"{label} seed {seed}")
        print(f"[not run] {label} seed {seed} (time budget, or not chosen by --train-only)", flush=True)
        return None
    print(f"[run] {label} seed {seed} ({method}, {steps} steps) -> {run_dir}", flush=True)
    t0 = time.perf_counter()
    from jaxnerf_grid.data.formats import load_dataset

    ds = load_dataset(data_dir, progress=ctx.progress)
    _, cfg, result = runs.train_run(str(data_dir), method, run_dir, ov, steps, progress=ctx.progress, dataset=ds)
    t_train = time.perf_counter() - t0
    t1 = time.perf_counter()
    metrics = evaluate.evaluate_run(run_dir, ctx.lpips_weights, progress=ctx.progress, dataset=ds,
                                    distractor_views=ctx.distractor_views, cloud_views=ctx.cloud_views)
    t_eval = time.perf_counter() - t1
    info = {"label": label, "seed": seed, "method": method, "steps": steps, "data": str(data_dir),
            "run_dir": str(run_dir), "overrides": ov, "train_wall_s": t_train, "eval_wall_s": t_eval,
            "seconds_per_step": seconds_per_step(run_dir, cfg.train.batch_rays),
            "samples_per_ray": models.samples_per_ray(cfg.model)}
    io.write_json(info_path, info)
    ctx.run_seconds[str(run_dir)] = t_train + t_eval
    print(f"[done] {label} seed {seed}: test PSNR {metrics['mean']['psnr']:.2f} dB "
          f"(train {t_train:.0f} s, eval {t_eval:.0f} s)", flush=True)
    return {**info, "wall_s": t_train + t_eval, "metrics": metrics, "cached": False}


def seconds_per_step(run_dir: Path, batch_rays: int) -> float | None:
    """Median seconds per step over the logged windows after the first (which holds the compilation)."""
    path = Path(run_dir) / "metrics.jsonl"
    if not path.is_file():
        return None
    rates = [json.loads(line)["rays_per_s"] for line in path.read_text().splitlines() if line.strip()]
    rates = rates[1:] or rates
    return float(batch_rays / np.median(rates)) if rates else None


# --------------------------------------------------------------------------- aggregation / output

METRIC_PATHS = {
    "psnr": ("metrics", "mean", "psnr"),
    "ssim": ("metrics", "mean", "ssim"),
    "ms_ssim": ("metrics", "mean", "ms_ssim"),
    "lpips": ("metrics", "mean", "lpips"),
    "psnr_tower": ("metrics", "regions_mean", "tower"),
    "psnr_near_ground": ("metrics", "regions_mean", "near_ground"),
    "psnr_far_background": ("metrics", "regions_mean", "far_background"),
    "distractor_psnr": ("metrics", "distractor_psnr"),
    "psnr_right_half": ("metrics", "mean_right_half", "psnr"),
    "seconds_per_step": ("seconds_per_step",),
    "geometry_f": ("metrics", "geometry", "thresholds", "0.02", "fscore"),
    "wall_s": ("wall_s",),  # train + eval wall seconds when the run ran (what `recorded_runs` reads back)
}


def _get(d, path):
    for k in path:
        if not isinstance(d, dict) or d.get(k) is None:
            return None
        d = d[k]
    return d


def aggregate(records: list[dict | None], extra: dict | None = None) -> dict:
    """Mean / standard deviation (ddof 0) / values over the seeds of one condition.

    records: run_condition results (None = not run). extra: {name: [value per record]}.
    """
    done = [r for r in records if r is not None]
    out = {"n": len(done), "seeds": [r["seed"] for r in done], "runs": [r["run_dir"] for r in done]}
    columns = {k: [_get(r, p) for r in done] for k, p in METRIC_PATHS.items()}
    for k, vals in (extra or {}).items():
        columns[k] = [v for v, r in zip(vals, records) if r is not None]
    for k, vals in columns.items():
        vals = [float(v) for v in vals if v is not None and np.isfinite(v)]
        out[k] = ({"mean": float(np.mean(vals)), "std": float(np.std(vals)), "values": vals} if vals else None)
    return out


RUN_DIR_NAME = re.compile(r"-s(\d+)-([0-9a-f]{10})$")  # LABEL-sSEED-KEY, as run_condition names run folders


def _put(tree: dict, path: tuple, value) -> None:
    for k in path[:-1]:
        tree = tree.setdefault(k, {})
    tree[path[-1]] = value


def _aggregates(obj):
    """Every aggregate (a dict with aligned "seeds" and "runs" lists) anywhere inside a results JSON."""
    if isinstance(obj, dict):
        if isinstance(obj.get("runs"), list) and isinstance(obj.get("seeds"), list) \
                and len(obj["runs"]) == len(obj["seeds"]):
            yield obj
        for v in obj.values():
            yield from _aggregates(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _aggregates(v)


def recorded_runs(folders) -> dict:
    """Finished runs as the committed results files record them: {(seed, run key): record}.

    The cache (experiments/.cache) is git-ignored, so a fresh clone has no finished run; the
    results files have every run's numbers. Each aggregate in each *.json directly under `folders`
    lists its run folders (LABEL-sSEED-KEY, KEY = `run_key`: the dataset folder's name, the fully
    resolved config and the step count, so an equal key is the identical run) and, per metric of
    METRIC_PATHS, the values in the same order. A record is shaped like run_condition's return
    (each metric at its METRIC_PATHS place, "recorded_in" the file); a metric is taken only where
    its values line up one-to-one with the runs (aggregate drops missing values, so a shorter list
    cannot be assigned). Where two files record one run differently (a table assembled before the
    run was evaluated again), the newest file (machine.date_utc) wins, with a warning.
    """
    files = [f for folder in folders if Path(folder).is_dir() for f in sorted(Path(folder).glob("*.json"))]
    loaded = []
    for f in files:
        try:
            loaded.append((f, json.loads(f.read_text())))
        except (OSError, ValueError) as exc:
            print(f"(results file {f} not read as a record of runs: {exc})", file=sys.stderr)
    loaded.sort(key=lambda fd: str((fd[1].get("machine") or {}).get("date_utc", "")) if isinstance(fd[1], dict) else "",
                reverse=True)
    out: dict = {}
    for f, data in loaded:
        where = str(portable(str(f.resolve())))
        for agg in _aggregates(data):
            aligned = {k: agg[k]["values"] for k in METRIC_PATHS
                       if isinstance(agg.get(k), dict) and len(agg[k].get("values", [])) == len(agg["runs"])}
            for i, (seed, run) in enumerate(zip(agg["seeds"], agg["runs"])):
                m = RUN_DIR_NAME.search(Path(str(run)).name)
                if m is None or int(m.group(1)) != int(seed):
                    continue
                rec = out.setdefault((int(seed), m.group(2)), {"seed": int(seed), "run_dir": str(run),
                                                              "label": Path(str(run)).name[:m.start()],
                                                              "cached": True, "recorded_in": where})
                for k, vals in aligned.items():
                    old = _get(rec, METRIC_PATHS[k])
                    if old is None:
                        _put(rec, METRIC_PATHS[k], vals[i])
                    elif abs(float(old) - float(vals[i])) > 1e-9 * max(1.0, abs(float(old))):
                        print(f"(run {Path(str(run)).name}: {k} is {old} in {rec['recorded_in']} but {vals[i]} in "
                              f"{where}; the newer file's is kept)", file=sys.stderr)
    return out


def values_by_seed(agg: dict, key: str = "psnr") -> dict:
    """{seed: value} from agg["seeds"] and agg[key]["values"], or {} when they are not one value per seed."""
    seeds, values = agg["seeds"], agg[key]["values"]
    return dict(zip(seeds, values)) if len(seeds) == len(values) else {}


def add_paired_delta(agg: dict | None, base: dict | None, key: str = "psnr", name: str = "delta_psnr") -> None:
    """agg[name] = mean / std of (agg - base) over the seeds both have (a paired difference: the
    scene-to-scene spread that dominates the per-row std cancels). Nothing when no seed is shared."""
    if not agg or not base or not agg.get(key) or not base.get(key):
        return
    a, b = values_by_seed(agg, key), values_by_seed(base, key)
    d = [a[s] - b[s] for s in sorted(set(a) & set(b))]
    if d:
        agg[name] = {"mean": float(np.mean(d)), "std": float(np.std(d)), "values": d}


VERDICT_RULE = ("Verdict on a paired effect (dB) over seeds: 'reproduced' when every seed's effect is positive and "
                "the mean is at least half the paper's figure; 'partly' when the mean is positive and at least two "
                "thirds of the seeds are, but the mean is below half the paper's figure or a seed is not positive; "
                "'not reproduced' otherwise (the mean is not positive, or the seeds disagree).")


def verdict(effect: dict | None, paper: float) -> str:
    """'reproduced' | 'partly' | 'not reproduced' | 'not run' for a paired effect {mean, std, values}
    against the paper's figure `paper` (same sign convention: positive = the paper's method is better).
    The rule is VERDICT_RULE."""
    if not effect or not effect.get("values"):
        return "not run"
    values = np.asarray(effect["values"], np.float64)
    mean, positive = float(values.mean()), float(np.mean(values > 0))
    if positive == 1.0 and mean >= 0.5 * paper:
        return "reproduced"
    if mean > 0 and positive >= 2 / 3:
        return "partly"
    return "not reproduced"


def claim_line(name: str, effect: dict | None, paper: float) -> str:
    """One markdown line: the claim, the paper's figure, ours (mean ± std, n) and the verdict."""
    if not effect or not effect.get("values"):
        return f"- {name}: paper {paper:+.2f} dB; ours not run."
    return (f"- {name}: paper {paper:+.2f} dB; ours {effect['mean']:+.2f} ± {effect['std']:.2f} dB over "
            f"{len(effect['values'])} seed(s) (values {', '.join(f'{v:+.2f}' for v in effect['values'])}): "
            f"**{verdict(effect, paper)}**.")


def fmt(cell: dict | None, digits: int = 2) -> str:
    if cell is None:
        return "n/a"
    if len(cell["values"]) == 1:
        return f"{cell['mean']:.{digits}f}"
    return f"{cell['mean']:.{digits}f} ± {cell['std']:.{digits}f}"


def markdown_table(rows: list[tuple[str, dict]], columns: list[tuple[str, str, int]]) -> list[str]:
    """rows: (label, aggregate); columns: (aggregate key, header, digits). Missing rows: 'not run'."""
    lines = ["| condition | n | " + " | ".join(h for _, h, _ in columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    for label, agg in rows:
        if agg is None or agg["n"] == 0:
            lines.append(f"| {label} | 0 | " + " | ".join("not run" for _ in columns) + " |")
        else:
            lines.append(f"| {label} | {agg['n']} | " + " | ".join(fmt(agg.get(k), d) for k, _, d in columns) + " |")
    return lines


def field_summary(model: dict) -> str:
    """One phrase for a setting's field and sampler, e.g. 'MLP 3x64, 16+16 samples per ray'."""
    field = model["field"]
    if field.get("kind") == "grid":
        g = field["grid"]
        text = (f"hash-grid field ({g['num_levels']} levels, 2^{g['log2_table_size']} entries, resolution "
                f"{g['min_resolution']}-{g['max_resolution']}) with a {field['depth']}x{field['width']} MLP")
    else:
        text = f"MLP {field['depth']}x{field['width']}"
    from jaxnerf_grid.samplers.legacy import upgrade_flat_model

    sampler = upgrade_flat_model(model)["sampler"]
    if sampler["kind"] == "proposal":
        return text + f", proposal sampling {'+'.join(map(str, sampler['samples']))} -> {sampler['main_samples']} samples"
    return text + f", {'+'.join(map(str, sampler['samples']))} samples per ray"


def settings_summary(ctx: Context) -> dict:
    return {"setting": ctx.setting, "seeds": ctx.seeds, "steps": ctx.steps, "overrides": ctx.overrides,
            "scene_sizes": {k: dict(zip(("width", "height", "num_train", "num_test", "supersample"), v))
                            for k, v in SCENE_SIZES[ctx.setting].items()}}


def portable(obj):
    """`obj` (JSON-able) with every string path inside the repository made relative to its root,
    so committed results name no machine's folders."""
    if isinstance(obj, dict):
        return {k: portable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [portable(v) for v in obj]
    if isinstance(obj, str):
        return obj.replace(str(ROOT) + os.sep, "")
    return obj


def not_run_text(entries: list[str]) -> str:
    """"LABEL seed N" entries, each label once, grouped by the seeds it misses:
    ["a seed 0", "b seed 0", "a seed 1"] -> "seeds 0, 1: a; seed 0: b"."""
    seeds_of: dict[str, list[int]] = {}
    for e in entries:
        label, _, seed = e.rpartition(" seed ")
        seeds_of.setdefault(label, []).append(int(seed))
    groups: dict[tuple, list[str]] = {}
    for label, seeds in seeds_of.items():
        groups.setdefault(tuple(sorted(seeds)), []).append(label)
    order = sorted(groups, key=lambda k: (-len(k), k))
    return "; ".join(f"seed{'s' if len(k) > 1 else ''} {', '.join(map(str, k))}: {', '.join(groups[k])}" for k in order)


def write_results(ctx: Context, name: str, title: str, body: dict, md_lines: list[str], notes: list[str]) -> Path:
    """results/<name>.json (body + provenance) and results/<name>.md (title, command, machine, tables, notes).
    Paths inside the repository are written relative to its root (`portable`)."""
    wall = time.perf_counter() - ctx.start
    lpips_note = ("LPIPS computed from " + ctx.lpips_weights) if ctx.lpips_weights else \
        "LPIPS unavailable (no --lpips-weights given); never a made-up number"
    restored = set(ctx.restored)
    num_runs = len(set(ctx.run_seconds) | restored)
    payload = {"table": name, "title": title, "command": ctx.command, "machine": ctx.machine,
               "settings": settings_summary(ctx), "wall_seconds": wall,
               "runs_seconds": sum(ctx.run_seconds.values()), "num_runs": num_runs, "lpips": lpips_note,
               "not_run_for_budget": ctx.not_run, "runs_from_results_files": sorted(restored),
               **body, "notes": notes}
    io.write_json(ctx.results / f"{name}.json", portable(payload))
    o = TRAIN_SETTINGS[ctx.setting]["overrides"]
    untimed = (f"; {len(restored)} of them read back from the committed results files, "
               f"{len(restored - set(ctx.run_seconds))} of those with no recorded wall time, not counted") if restored else ""
    head = [f"# {title}", "", f"Command: `{ctx.command}`", "",
            f"Machine: {machine_line(ctx.machine)}. The table's {num_runs} NeRF runs took "
            f"{sum(ctx.run_seconds.values()) / 60:.1f} min of train + eval wall time as recorded when each ran "
            f"(runs shared with another table counted in both{untimed}); this invocation took {wall / 60:.1f} min "
            "(runs already done in the cache are not re-run).", "",
            f"Setting `{ctx.setting}`: {ctx.seeds} seed(s), {ctx.steps} steps per run, "
            f"{o['train']['batch_rays']} rays per step, {field_summary(o['model'])} unless stated; "
            "scenes " + ", ".join(f"{k} {v[0]}x{v[1]} ({v[2]} train / {v[3]} test views)"
                                  for k, v in SCENE_SIZES[ctx.setting].items()) + ".",
            "Cells: mean ± standard deviation over seeds (one value when n = 1). " + lpips_note + ".", ""]
    tail = [""] + [f"- {n}" for n in notes]
    if ctx.not_run:
        tail.append(f"- Not run (time budget, or not chosen by --train-only; {len(ctx.not_run)} runs): "
                    f"{not_run_text(ctx.not_run)}.")
    text = portable("\n".join(head + md_lines + tail) + "\n")
    (ctx.results / f"{name}.md").write_text(text)
    print(text)
    return ctx.results / f"{name}.md"


# --------------------------------------------------------------------------- figures (no matplotlib)


def label_image(img: np.ndarray, text: str, height: int = 14) -> np.ndarray:
    """img [H, W, 3] float -> [H + height, W, 3] with `text` above it on white."""
    import cv2

    bar = np.full((height, img.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, text, (2, height - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([bar.astype(np.float32) / 255.0, img.astype(np.float32)], axis=0)


def _stack(images: list[np.ndarray], axis: int, gap: int) -> np.ndarray:
    """Concatenates [h, w, 3] images along `axis` (1: side by side, 0: top to bottom), padding the
    other extent with white and putting a white gap between neighbours."""
    other = 1 - axis
    size = max(i.shape[other] for i in images)
    out = []
    for k, im in enumerate(images):
        pad = [(0, 0), (0, 0), (0, 0)]
        pad[other] = (0, size - im.shape[other])
        if k:
            gap_shape = [0, 0, 3]
            gap_shape[axis], gap_shape[other] = gap, size
            out.append(np.ones(gap_shape, np.float32))
        out.append(np.pad(im, pad, constant_values=1.0))
    return np.concatenate(out, axis=axis)


def hstack(images: list[np.ndarray], gap: int = 3) -> np.ndarray:
    return _stack(images, 1, gap)


def vstack(images: list[np.ndarray], gap: int = 3) -> np.ndarray:
    return _stack(images, 0, gap)


PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


def line_plot(series: list[dict], xlabel: str, ylabel: str, title: str, size=(760, 480), log2_x: bool = True) -> np.ndarray:
    """A line plot drawn with OpenCV. series: [{"label", "x": [...], "y": [...], "dashed": bool,
    optional "colour_index", optional "err": [...] (error bars, +- err)}].
    Returns an RGB float image [H, W, 3] in [0, 1]."""
    import cv2

    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 60, 200, 30, 50
    xs = [x for s in series for x in s["x"]]
    ys = [y for s in series for y in s["y"] if y is not None]
    if not xs or not ys:
        return img.astype(np.float32) / 255
    tx = (lambda v: np.log2(v)) if log2_x else (lambda v: v)
    x0, x1 = tx(min(xs)), tx(max(xs))
    x1 = x1 if x1 > x0 else x0 + 1
    errs = [e for s in series for e in (s.get("err") or []) if e is not None]
    pad = max(0.08 * (max(ys) - min(ys)), 0.1) + (max(errs) if errs else 0.0)
    y0, y1 = min(ys) - pad, max(ys) + pad
    step = next(v for v in (0.05, 0.1, 0.2, 0.25, 0.5, 1, 2, 5, 10, 20, 50) if (y1 - y0) / v <= 8)
    y0, y1 = np.floor(y0 / step) * step, np.ceil(y1 / step) * step

    def px(x, y):
        return (int(left + (tx(x) - x0) / (x1 - x0) * (w - left - right)),
                int(h - bottom - (y - y0) / (y1 - y0) * (h - top - bottom)))

    black, grey = (0, 0, 0), (200, 200, 200)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for x in sorted(set(xs)):
        p = px(x, y0)
        cv2.line(img, (p[0], top), (p[0], h - bottom), grey, 1)
        cv2.putText(img, f"{x:g}", (p[0] - 8, h - bottom + 16), font, 0.4, black, 1, cv2.LINE_AA)
    for y in np.arange(y0, y1 + step / 2, step):
        p = px(min(xs), y)
        cv2.line(img, (left, p[1]), (w - right, p[1]), grey, 1)
        cv2.putText(img, f"{round(y, 2):g}", (8, p[1] + 4), font, 0.4, black, 1, cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (w - right, h - bottom), black, 1)
    cv2.putText(img, xlabel, (left + (w - left - right) // 2 - 60, h - 12), font, 0.45, black, 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (8, top - 10), font, 0.45, black, 1, cv2.LINE_AA)
    cv2.putText(img, title, (left + 120, top - 10), font, 0.45, black, 1, cv2.LINE_AA)
    for i, s in enumerate(series):
        colour = PALETTE[s.get("colour_index", i) % len(PALETTE)][::-1]
        pts = [px(x, y) for x, y in zip(s["x"], s["y"]) if y is not None]
        for a, b in zip(pts, pts[1:]):
            if s.get("dashed"):
                n = 8
                for k in range(0, n, 2):
                    pa = (int(a[0] + (b[0] - a[0]) * k / n), int(a[1] + (b[1] - a[1]) * k / n))
                    pb = (int(a[0] + (b[0] - a[0]) * (k + 1) / n), int(a[1] + (b[1] - a[1]) * (k + 1) / n))
                    cv2.line(img, pa, pb, colour, 2, cv2.LINE_AA)
            else:
                cv2.line(img, a, b, colour, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 3, colour, -1, cv2.LINE_AA)
        for x, y, e in zip(s["x"], s["y"], s.get("err") or []):  # error bars (+- e)
            if y is not None and e:
                (xa, ya), (_, yb) = px(x, y - e), px(x, y + e)
                xa += (i % 8 - 3.5) * 1.5  # spread overlapping bars a little
                cv2.line(img, (int(xa), ya), (int(xa), yb), colour, 1, cv2.LINE_AA)
        ly = top + 10 + 18 * i
        lx = w - right + 10
        if s.get("dashed"):
            cv2.line(img, (lx, ly), (lx + 8, ly), colour, 2)
            cv2.line(img, (lx + 14, ly), (lx + 22, ly), colour, 2)
        else:
            cv2.line(img, (lx, ly), (lx + 22, ly), colour, 2)
        cv2.putText(img, s["label"], (lx + 28, ly + 4), font, 0.4, black, 1, cv2.LINE_AA)
    return np.ascontiguousarray(img[..., ::-1]).astype(np.float32) / 255.0


def write_figure(ctx: Context, name: str, image: np.ndarray) -> Path:
    path = ctx.results / f"{name}.png"
    io.write_png(path, np.clip(image, 0, 1))
    return path
