"""Run directories: create or resume a run and train it, load one back, render its views.

A run directory holds config.json ({"data", "model", "train"}), checkpoints/, metrics.jsonl
(training log), renders/ (PNG), depth/ (EXR, z-depth in normalised scene units), opacity/
(PNG), and, once evaluated (`evaluate.evaluate_run`), metrics.json, report.md and
tower_points.ply.

config.json stores the config as made by `run_config.make_config` with `model.num_images` set from
the dataset; `model.near` / `model.far` stay as configured (None = the dataset's), see
`config.resolve`. A run trains at the working resolution of `train.max_side` (data/working.py)
and its views are rendered at that size unless `full_size`; a config.json without
`train.max_side` (a run made before it existed) was trained at full size and reads as 0.

What keeps a run and its dataset safe (docs/RELIABILITY.md):
  * `.jaxnerf-grid-run` (RUN_MARKER) is the first file a run writes; `--overwrite` clears only a
    folder holding it, and then only the run's own outputs (RUN_OUTPUT_DIRS, RUN_OUTPUT_FILES);
  * `check_run` validates the config, the dataset's cameras and the batch's memory before
    anything is written or deleted;
  * dataset.json (FINGERPRINT_FILE) is the dataset's fingerprint (`dataset_fingerprint`);
    resume, `render_split` and `evaluate.evaluate_run` refuse another dataset unless
    `allow_other_data`.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np

from jaxnerf_grid.capture import poses
from jaxnerf_grid.config import build
from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.run_config import RunConfig, make_config, upgrade_run_dict
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data import formats
from jaxnerf_grid.data.dataset import check_camera_centres
from jaxnerf_grid.data.formats import working_dataset
from jaxnerf_grid.masks import write as masking
from jaxnerf_grid.nerf import fields
from jaxnerf_grid.render import views
from jaxnerf_grid.report import progress_page as progress_page_lib
from jaxnerf_grid.train import distributed, ray_pool
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.util import folders, io
from jaxnerf_grid.util import progress as progress_lib
from jaxnerf_grid.util.io import DataError

RUN_MARKER = folders.marker("train")
FINGERPRINT_FILE = "dataset.json"
RUN_OUTPUT_DIRS = ("checkpoints", "renders", "depth", "opacity", "videos")
RUN_OUTPUT_FILES = ("metrics.jsonl", "metrics.json", "report.md", "report.html", "progress.html", "report_views.png",
                    "report_crops.png", "tower_points.ply", "config.json", FINGERPRINT_FILE, "timings.json",
                    "budget.json")


def run_config_dict(cfg, data_path=None) -> dict:
    """config.json's content, `to_dict` of the RunConfig: {"data", "model", "train"}; data_path,
    when given, replaces cfg.data."""
    if data_path is not None:
        cfg = dataclasses.replace(cfg, data=str(data_path))
    return config_lib.to_dict(cfg)


def load_run(run_dir) -> tuple:
    """(RunConfig, its data path `cfg.data`) of a run directory."""
    run_dir = Path(run_dir)
    path = run_dir / "config.json"
    if not run_dir.is_dir():
        raise DataError(f"{run_dir}: no such run directory")
    if not path.is_file():
        raise DataError(f"{path}: not a run directory (no config.json)")
    raw = io.read_json(path)
    if not isinstance(raw, dict):
        raise DataError(f"{path}: a run's config.json must hold a JSON object")
    if isinstance(raw.get("train"), dict) and "max_side" not in raw["train"]:
        raw = {**raw, "train": {**raw["train"], "max_side": 0}}  # made before max_side: trained at full size
    cfg = config_lib.from_dict(RunConfig, raw, where=str(path))
    try:
        config_lib.validate(cfg)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    return cfg, cfg.data


# --------------------------------------------------------------------------- the dataset's fingerprint


def dataset_fingerprint(ds) -> dict:
    """What identifies a dataset to a run: {"frames": N, "height": H, "width": W, "digest": sha256
    of the frame names, the image size, the intrinsics [N, 4] and the poses [N, 4, 4] (rounded to
    1e-5 normalised units / pixels), "names": sha256 of the frame names}. Masks, weights and
    pixel values are not part of it (re-masking a dataset keeps it the same dataset)."""
    names = "\n".join(str(p) for p in ds.frame_paths) if ds.frame_paths else str(ds.num_frames)
    h = hashlib.sha256()
    h.update(names.encode("utf-8"))
    h.update(np.asarray([ds.num_frames, ds.height, ds.width], np.int64).tobytes())
    for arr in (ds.intrinsics, ds.c2w):
        h.update(np.round(np.asarray(arr, np.float64), 5).tobytes())
    return {"frames": int(ds.num_frames), "height": int(ds.height), "width": int(ds.width),
            "names": hashlib.sha256(names.encode("utf-8")).hexdigest(), "digest": h.hexdigest()}


def _describe(fp: dict) -> str:
    return f"{fp.get('frames')} frames of {fp.get('width')}x{fp.get('height')}"


def check_fingerprint(run_dir, ds, allow_other_data: bool = False) -> None:
    """Refuses (DataError naming run_dir/dataset.json) a dataset whose fingerprint differs from
    the one the run was trained on; a run without a fingerprint (made before it existed) and
    `allow_other_data` pass."""
    path = Path(run_dir) / FINGERPRINT_FILE
    if allow_other_data or not path.is_file():
        return
    old = io.read_json(path)
    new = dataset_fingerprint(ds)
    if not isinstance(old, dict) or not isinstance(old.get("digest"), str):
        raise DataError(f"{path}: not a dataset fingerprint (a JSON object with \"digest\" expected), so the "
                        "dataset cannot be checked; pass allow_other_data=True to go on without the check")
    if old.get("digest") == new["digest"]:
        return
    if (old.get("frames"), old.get("height"), old.get("width")) != (new["frames"], new["height"], new["width"]):
        what = f"{_describe(old)}, this one has {_describe(new)}"
    elif old.get("names") != new["names"]:
        what = f"other frame names ({_describe(new)} both)"
    else:
        what = f"the same frames with other cameras ({_describe(new)})"
    raise DataError(f"{path}: the run was trained on another dataset than {ds.root} ({what}); "
                    "pass allow_other_data=True to use it anyway")


def load_run_and_dataset(run_dir, dataset=None, progress: bool = True, allow_other_data: bool = False,
                         full_size: bool = False) -> tuple:
    """(cfg, data path, dataset) of a trained run: its config (load_run), its dataset (`dataset`
    when given, else loaded from the run's data path) at the run's working resolution
    (`train.max_side`), or at full size with `full_size`; refused when the dataset is not the one
    the run was trained on (check_fingerprint), unless `allow_other_data`."""
    cfg, data = load_run(run_dir)
    return cfg, data, dataset_of_run(run_dir, data, dataset, progress, allow_other_data,
                                     max_side=cfg.train.max_side, full_size=full_size)


def dataset_of_run(run_dir, data, dataset=None, progress: bool = True, allow_other_data: bool = False,
                   max_side: int = 0, full_size: bool = False):
    """The dataset of a run whose config is already loaded (`data`: its `cfg.data`): `dataset` when
    given, else loaded from `data`, at the working resolution of `max_side` (the run's
    `train.max_side`; data/working.py) or at full size with `full_size`; refused when it is not
    the one the run was trained on (check_fingerprint on the working resolution), unless
    `allow_other_data`."""
    side = 0 if full_size else max_side
    ds = dataset if dataset is not None else load_dataset(data, progress=progress, max_side=side)
    ds = working_dataset(ds, side) if side else ds
    if side == max_side or allow_other_data or not (Path(run_dir) / FINGERPRINT_FILE).is_file():
        check_fingerprint(run_dir, ds, allow_other_data)
    else:  # full size: the run's fingerprint is of its working resolution (from the cache: cheap)
        trained = working_dataset(dataset, max_side) if dataset is not None else \
            load_dataset(data, progress=progress, max_side=max_side)
        check_fingerprint(run_dir, trained, allow_other_data)
    return ds


# --------------------------------------------------------------------------- creating a run


def check_run(cfg, ds, num_devices: int | None = None) -> None:
    """The checks of a run before anything is written or deleted: the config's types and ranges
    (config.validate), the ray bounds on this dataset (config.resolve), the camera centres
    (data.dataset.check_camera_centres), the device count and the batch's memory
    (train.check_batch), train.robust's patches and masks (train.check_robust)."""
    config_lib.validate(cfg)
    settled = config_lib.resolve(cfg, ds)
    check_camera_centres(ds)
    n = train.step_devices(cfg.train) if num_devices is None else num_devices
    train.check_batch(settled, n)
    train.check_robust(settled.train, n, ds)
    check_weights(settled, ds)


def check_weights(cfg, ds) -> None:
    """DataError naming the dataset when it has no training frames or, with train.robust off,
    every training pixel has loss weight 0 (all-zero weight maps): train would refuse it
    only after the run folder was made."""
    train_ids = np.asarray(ds.split["train"], np.int64)
    if train_ids.size == 0:
        raise DataError(f"{ds.root}: the dataset has no training frames")
    t = cfg.train
    if t.robust.mode != "off" or not t.use_masks or ds.weights is None:
        return  # every pixel has weight 1 (or the evidence sets the weights)
    # frame by frame: the weights of every frame at once are 4 bytes a pixel
    if not any(np.any(ray_pool.frame_weights(ds.weights[f], None if ds.masks is None else ds.masks[f], True,
                                             t.mask_weight_floor, (ds.height, ds.width)) > 0) for f in train_ids):
        raise DataError(f"{ds.root}: every training pixel has loss weight 0 (check the masks / weights)")


def load_dataset(path, downscale: float = 1, progress: bool = True, max_side: int = 0, uint8_images: bool = False):
    """The dataset of a folder (formats.load_dataset; `max_side`: its working resolution,
    data/working.py, 0 = full size), after finishing any `mask` run that was killed while
    swapping its new masks in (masking.recover), so the masks are one set, and any `poses` run
    killed while swapping a new dataset in (data.poses.recover). uint8_images: images as uint8
    (value / 255), what training holds (ray_pool)."""
    if Path(path).is_dir():
        poses.recover(path)
        masking.recover(path)

    return formats.load_dataset(path, downscale=downscale, progress=progress, max_side=max_side,
                                uint8_images=uint8_images)


def _without(d: dict, key: str) -> dict:
    return {k: v for k, v in d.items() if k != key}


def is_run_dir(run_dir) -> bool:
    """True when run_dir holds the marker a run writes first (RUN_MARKER)."""
    return (Path(run_dir) / RUN_MARKER).is_file()


def _is_legacy_run(run_dir: Path) -> bool:
    """A run made before the marker existed: config.json with "model" and "train", and checkpoints/."""
    try:
        raw = io.read_json(run_dir / "config.json")
    except DataError:
        return False
    return isinstance(raw, dict) and {"model", "train"} <= set(raw) and (run_dir / "checkpoints").is_dir()


def check_out(run_dir: Path, data=None) -> None:
    """Refuses a run folder (run.out) that is a file, or that is the dataset folder or inside it
    (links resolved; `folders.check_outside`)."""
    folders.check_folder(run_dir, "run.out")
    folders.check_outside(run_dir, data, "run.out")


def _field_of_its_kind(field):
    """A field dict without the keys of other kinds that older runs wrote (fields/base.py)."""
    if isinstance(field, dict) and field.get("kind") in fields.KINDS:
        return fields.base.drop_other_kinds(field, field["kind"])
    return field


def fields_upgraded(model):
    """A config.json's model dict with its fields (model.field, the proposal sampler's field) as
    `to_dict` of the current config writes them; the input is not changed."""
    if not isinstance(model, dict):
        return model
    out = dict(model)
    if "field" in out:
        out["field"] = _field_of_its_kind(out["field"])
    if isinstance(out.get("sampler"), dict) and "field" in out["sampler"]:
        out["sampler"] = dict(out["sampler"], field=_field_of_its_kind(out["sampler"]["field"]))
    return out


def check_existing(run_dir: Path, wanted: dict, overwrite: bool) -> None:
    """Makes run_dir ready for a run of config `wanted` (run_config_dict): with `overwrite`
    clears a previous run's outputs (only in a folder holding RUN_MARKER, and only the files a
    run writes); else an existing run must have the same config (the step count included: the
    learning-rate schedule depends on it), so it is resumed. A non-empty folder that is not a
    run is never touched."""
    if not (run_dir.exists() and any(run_dir.iterdir())):
        return
    existing = run_dir / "config.json"
    marked = is_run_dir(run_dir)
    if not marked and not (not overwrite and _is_legacy_run(run_dir)):
        raise DataError(f"{run_dir}: exists, is not empty and is not a jaxnerf-grid run (no {RUN_MARKER}); "
                        "nothing was changed: choose another run.out")
    if overwrite:  # a symlinked checkpoints/ is refused, never skipped (`folders.check_clearable`)
        folders.clear_outputs(run_dir, "train", RUN_OUTPUT_DIRS + RUN_OUTPUT_FILES, "run.out")
    elif not existing.is_file():
        return  # a marked run that was stopped before its config.json was written: start it
    else:
        old = io.read_json(existing)
        if not isinstance(old, dict) or not isinstance(old.get("train"), dict):
            raise DataError(f"{existing}: not a run's config (expected an object with \"train\")")
        old = upgrade_run_dict(old)  # a run from before model.sampler / train.robust: its flat keys
        old = dict(old, model=fields_upgraded(old.get("model")))
        if _without(old, "train") != _without(wanted, "train") or \
                _without(old["train"], "max_steps") != _without(wanted["train"], "max_steps"):
            raise ConfigError(f"{existing}: the run exists with a different config; pass overwrite=True "
                              "to start again or another run.out")
        if old["train"]["max_steps"] != wanted["train"]["max_steps"]:
            raise ConfigError(f"{existing}: the run was configured for {old['train']['max_steps']} steps "
                              "(the learning-rate schedule depends on it); pass overwrite=True to change it")


def train_run(data: str, method: str, out, overrides: dict | None = None, steps: int | None = None,
              overwrite: bool = False, progress: bool = True, dataset=None, allow_other_data: bool = False,
              progress_page: int = 0, budget: dict | None = None):
    """Creates (or resumes) a run and trains it. Returns (run_dir, RunConfig, TrainResult).

    data: the dataset folder (loaded unless `dataset` is given); method: ours | nerf | nerfw;
    overrides: nested dict over the method's defaults; steps: train.max_steps;
    allow_other_data: resume a run on a dataset whose fingerprint differs;
    progress_page: rewrite RUN/progress.html every that many steps (`progress_page`; 0 = never);
    budget: the training budget's record (`budget.apply`), written to RUN/budget.json.
    Everything is checked (`check_run`, `check_out`, the fingerprint) before the run folder is
    created, cleared or written.
    """
    run_dir = Path(out)
    check_out(run_dir, data)
    config_lib.check_value("run.progress_page", progress_page, int, config_lib.NONNEGATIVE)
    cfg = make_config(method, build.with_steps(overrides, steps))
    side = cfg.train.max_side  # the working resolution (data/working.py)
    # training holds the frames as 8 bits (ray_pool): loaded so, they reach the devices without a copy
    ds = working_dataset(dataset, side) if dataset is not None else load_dataset(data, progress=progress,
                                                                                 max_side=side, uint8_images=True)
    cfg = dataclasses.replace(config_lib.resolve(cfg, ds, bounds=False), data=str(Path(data).resolve()))
    check_run(cfg, ds)
    wanted = run_config_dict(cfg)
    if distributed.is_main():  # in a multi-process run only process 0 writes the run folder
        if not overwrite and is_run_dir(run_dir):
            check_fingerprint(run_dir, ds, allow_other_data)
        check_existing(run_dir, wanted, overwrite)
        folders.write_marker(run_dir, "train")
        io.write_json(run_dir / FINGERPRINT_FILE, dataset_fingerprint(ds))
        io.write_json(run_dir / "config.json", wanted)
        if budget is not None:
            io.write_json(run_dir / "budget.json", budget)
    distributed.barrier("jaxnerf_grid.train.runs.train_run")
    on_step = (progress_page_lib.watcher(run_dir, ds, cfg, progress_page)
               if progress_page and distributed.is_main() else None)
    result = train.train(ds, cfg, run_dir, progress=progress, on_step=on_step)
    return run_dir, cfg, result


# --------------------------------------------------------------------------- views of a run


def frame_name(ds, index: int) -> str:
    """A frame's file stem (frame_0007 when the dataset has no paths)."""
    if ds.frame_paths:
        return Path(ds.frame_paths[index]).stem
    return f"frame_{index:04d}"


def bar(items, progress: bool, desc: str):
    """A progress bar over views (progress.bar, off when not `progress`)."""
    return progress_lib.bar(items, desc=desc, unit="view", enabled=progress)


def write_view(run_dir: Path, name: str, view: dict) -> None:
    """renders/<name>.png (rgb [H, W, 3]), depth/<name>.exr ([H, W]), opacity/<name>.png ([H, W])."""
    io.write_png(run_dir / "renders" / f"{name}.png", np.clip(view["rgb"], 0, 1))
    io.write_exr(run_dir / "depth" / f"{name}.exr", view["depth"])
    io.write_png(run_dir / "opacity" / f"{name}.png", np.clip(view["opacity"], 0, 1))


def render_split(run_dir, split: str = "test", progress: bool = True, dataset=None, params=None,
                 allow_other_data: bool = False, full_size: bool = False) -> list[dict]:
    """Renders the frames of a split (test | train | all) into renders/, depth/, opacity/, at the
    run's working resolution (`train.max_side`), or at the photos' full size with `full_size`.
    Returns per-view dicts {"index", "rgb", "depth", "expected_depth", "opacity"}.
    A dataset other than the run's (its fingerprint) is refused unless `allow_other_data`."""
    run_dir = Path(run_dir)
    cfg, _, ds = load_run_and_dataset(run_dir, dataset, progress, allow_other_data, full_size)
    if params is None:
        params, _ = train.load_params(run_dir, cfg, ds)
    ids = np.arange(ds.num_frames) if split == "all" else np.asarray(ds.split[split])
    out = []
    for i in bar(ids, progress, f"render {split}"):
        view = views.render_view(params, cfg, ds, int(i))
        write_view(run_dir, frame_name(ds, int(i)), view)
        out.append({"index": int(i), **view})
    return out
