"""Run directories: create or resume a run and train it, load one back, render its views.

A run directory holds config.json ({"data", "model", "train"}), checkpoints/, metrics.jsonl
(training log), renders/ (PNG), depth/ (EXR, z-depth in normalised scene units), opacity/
(PNG), and, once evaluated (`evaluate.evaluate_run`), metrics.json, report.md and
tower_points.ply.

config.json stores the config as made by `train.make_config` with `model.num_images` set from
the dataset; `model.near` / `model.far` stay as configured (None = the dataset's), see
`config.resolve`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid import config as config_lib, io
from jaxnerf_grid.config import ConfigError
from jaxnerf_grid.io import DataError

RUN_OUTPUT_DIRS = ("checkpoints", "renders", "depth", "opacity")
RUN_OUTPUT_FILES = ("metrics.jsonl", "metrics.json", "report.md", "config.json")


def read_overrides(path: str | None) -> dict:
    """The override dict of a --config JSON file ({} without one); its "data" key is dropped."""
    if not path:
        return {}
    data = io.read_json(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must hold a JSON object")
    data = dict(data)
    data.pop("data", None)
    return data


def run_config_dict(cfg, data_path) -> dict:
    """config.json's content: {"data": str(data_path), "model": {...}, "train": {...}}."""
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


def load_dataset(path, downscale: float = 1, progress: bool = True):
    """The dataset of a folder (formats.load_dataset)."""
    from jaxnerf_grid.data.formats import load_dataset as load

    return load(path, downscale=downscale, progress=progress)


def _with_steps(overrides: dict | None, steps: int | None) -> dict:
    """overrides with train.max_steps = steps (when given); the input is not changed."""
    overrides = dict(overrides or {})
    if steps is not None:
        overrides["train"] = {**overrides.get("train", {}), "max_steps": int(steps)}
    return overrides


def _without(d: dict, key: str) -> dict:
    return {k: v for k, v in d.items() if k != key}


def check_existing(run_dir: Path, wanted: dict, overwrite: bool) -> None:
    """Makes run_dir ready for a run of config `wanted` (run_config_dict): with `overwrite`
    clears a previous run's outputs; else an existing run must have the same config (the
    step count included: the learning-rate schedule depends on it), so it is resumed."""
    if not (run_dir.exists() and any(run_dir.iterdir())):
        return
    existing = run_dir / "config.json"
    if overwrite:
        import shutil

        for sub in RUN_OUTPUT_DIRS:
            shutil.rmtree(run_dir / sub, ignore_errors=True)
        for f in RUN_OUTPUT_FILES:
            (run_dir / f).unlink(missing_ok=True)
    elif not existing.is_file():
        raise DataError(f"{run_dir}: exists and is not a run directory; pass --overwrite or another --out")
    else:
        old = io.read_json(existing)
        if _without(old, "train") != _without(wanted, "train") or \
                _without(old["train"], "max_steps") != _without(wanted["train"], "max_steps"):
            raise ConfigError(f"{existing}: the run exists with a different config; pass --overwrite "
                              "to start again or another --out")
        if old["train"]["max_steps"] != wanted["train"]["max_steps"]:
            raise ConfigError(f"{existing}: the run was configured for {old['train']['max_steps']} steps "
                              "(the learning-rate schedule depends on it); pass --overwrite to change it")


def train_run(data: str, method: str, out, overrides: dict | None = None, steps: int | None = None,
              overwrite: bool = False, progress: bool = True, dataset=None):
    """Creates (or resumes) a run and trains it. Returns (run_dir, RunConfig, TrainResult).

    data: the dataset folder (loaded unless `dataset` is given); method: ours | nerf | nerfw;
    overrides: nested dict over the method's defaults; steps: train.max_steps.
    """
    from jaxnerf_grid import train

    cfg = train.make_config(method, _with_steps(overrides, steps))
    ds = dataset if dataset is not None else load_dataset(data, progress=progress)
    cfg = config_lib.resolve(cfg, ds, bounds=False)
    run_dir = Path(out)
    wanted = run_config_dict(cfg, Path(data).resolve())
    check_existing(run_dir, wanted, overwrite)
    run_dir.mkdir(parents=True, exist_ok=True)
    io.write_json(run_dir / "config.json", wanted)
    result = train.train(ds, cfg, run_dir, progress=progress)
    return run_dir, cfg, result


# --------------------------------------------------------------------------- views of a run


def frame_name(ds, index: int) -> str:
    """A frame's file stem (frame_0007 when the dataset has no paths)."""
    if ds.frame_paths:
        return Path(ds.frame_paths[index]).stem
    return f"frame_{index:04d}"


def bar(items, progress: bool, desc: str):
    """A progress bar over views (progress.bar, off when not `progress`)."""
    from jaxnerf_grid import progress as progress_lib

    return progress_lib.bar(items, desc=desc, unit="view", enabled=progress)


def write_view(run_dir: Path, name: str, view: dict) -> None:
    """renders/<name>.png (rgb [H, W, 3]), depth/<name>.exr ([H, W]), opacity/<name>.png ([H, W])."""
    io.write_png(run_dir / "renders" / f"{name}.png", np.clip(view["rgb"], 0, 1))
    io.write_exr(run_dir / "depth" / f"{name}.exr", view["depth"])
    io.write_png(run_dir / "opacity" / f"{name}.png", np.clip(view["opacity"], 0, 1))


def render_split(run_dir, split: str = "test", progress: bool = True, dataset=None, params=None) -> list[dict]:
    """Renders the frames of a split (test | train | all) into renders/, depth/, opacity/.
    Returns per-view dicts {"index", "rgb", "depth", "expected_depth", "opacity"}."""
    from jaxnerf_grid import train, views

    run_dir = Path(run_dir)
    cfg, data = load_run(run_dir)
    ds = dataset if dataset is not None else load_dataset(data, progress=progress)
    if params is None:
        params, _ = train.load_params(run_dir, cfg, ds)
    ids = np.arange(ds.num_frames) if split == "all" else np.asarray(ds.split[split])
    out = []
    for i in bar(ids, progress, f"render {split}"):
        view = views.render_view(params, cfg, ds, int(i))
        write_view(run_dir, frame_name(ds, int(i)), view)
        out.append({"index": int(i), **view})
    return out
