"""The demo: the CPU recipe (`DEMO_CONFIG`) end to end, as library calls.

`run_demo(data, out)`: synthetic tower-small (when no data is given) -> masks (when the dataset
has none; `masking.write_masks`) -> train the demo's recipe (DEMO_CONFIG; `runs.train_run`, at the
working resolution of `train.max_side`, data/working.py; near, far and contract_radius from the
dataset's `scene_bounds` when it records them, `data.bounds`) -> evaluate (`evaluate.evaluate_run`)
-> a short low-resolution fly-around video (`write_demo_video`: `videos.render_video`'s orbit,
DEMO_VIDEO_FRAMES frames DEMO_VIDEO_WIDTH px wide, into RUN/videos/; docs/VIDEOS.md), linked from
report.md and report.html. `demo_summary(result)` is its one-line summary. The seconds of each
stage (STAGES: poses when the dataset was made by `jaxnerf-grid poses`, from its record; synth,
mask, train, eval, video) go into RUN/timings.json and a "Time per stage" table at the end of
RUN/report.md (`timings_lines`).

Which masks train (`masks`, `demo --masks`; docs/MASKS.md): "auto" trusts the DPT's masks only
where the DPT is in its domain (`masking.domain_verdict`, recorded in transforms.json as
`mask_domain`), else trains with `train.robust = "robust"` (photometric evidence, no masks);
"dpt", "robust", "dpt+robust" and "none" force a mode. `mask_plan` makes the choice.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxnerf_grid.capture import camera_set
from jaxnerf_grid.capture.bounds import bounds_line, bounds_warning
from jaxnerf_grid.config import budget as budget_lib
from jaxnerf_grid.config import build, recipes
from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.run_config import make_config
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data.formats import colmap_model
from jaxnerf_grid.data.formats.frames import default_split
from jaxnerf_grid.data.formats.transforms_json import read_meta
from jaxnerf_grid.data.synthetic import generate as synth_generate
from jaxnerf_grid.eval import evaluate
from jaxnerf_grid.masks import write as masking
from jaxnerf_grid.render import videos
from jaxnerf_grid.report import html as report_html
from jaxnerf_grid.train import distributed, runs, sparse_depth, speed
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.util import folders, io
from jaxnerf_grid.util.io import DataError

# The demo's recipe: `recipes.overrides("ours-lean")` (docs/GRID.md, docs/RECIPES.md): `ours`, the
# recipe that resolves the tower (a hash grid on the contracted coordinates, one proposal round of
# 64 samples stratified in s feeding the main field, an opaque far bin at 1000 units), with a
# smaller proposal field, a leaner main field (24 samples a ray, 8 hash levels, one colour layer)
# and 1600 steps instead of 2400: the demo's figures on tower-small within 0.2 dB, each step about
# 2x faster than ours' (docs/GRID.md).
DEMO_RECIPE = "ours-lean"
DEMO_CONFIG = recipes.overrides(DEMO_RECIPE)


# Training views whose depth also goes into the demo's tower cloud (evaluate_run's cloud_views).
DEMO_CLOUD_VIEWS = 16
# ... within this many pixels in all: all 16 at tower-small's 160x120 (307 200 px), 4 at a real
# capture's 614x410 working size, where each view costs 10-15 s to render on two cores.
DEMO_CLOUD_PIXELS = 2 ** 20

# The demo's fly-around video (`write_demo_video`, docs/VIDEOS.md): an orbit of this many frames,
# this many pixels wide (the photos' aspect), played at DEMO_VIDEO_FPS. Chosen to cost well under a
# tenth of the demo's time on the 2-core CPU machine (the measurements in docs/VIDEOS.md).
DEMO_VIDEO_FRAMES = 32
DEMO_VIDEO_WIDTH = 80
DEMO_VIDEO_FPS = 8.0

# The stages of a demo, in order, as timings.json and the report name them.
STAGES = {"poses": "poses (`jaxnerf-grid poses`, before the demo; from the dataset's record)",
          "synth": "synthetic scene", "mask": "masks", "train": "training", "eval": "evaluation",
          "video": "fly-around video"}


def poses_seconds(data: Path) -> float | None:
    """The seconds `jaxnerf-grid poses` took to make the dataset (transforms.json's
    poses.seconds); None for a dataset it did not make."""
    poses = read_meta(data).get("poses")
    seconds = poses.get("seconds") if isinstance(poses, dict) else None
    return float(seconds) if isinstance(seconds, (int, float)) and not isinstance(seconds, bool) else None


def timings_lines(timings: dict) -> list[str]:
    """The report's "Time per stage" section: a Markdown table of timings {stage: seconds} in
    STAGES order (unknown stages after them), with the total of the demo's own stages."""
    order = [k for k in STAGES if k in timings] + [k for k in timings if k not in STAGES]
    lines = ["## Time per stage", "", "| stage | seconds |", "|---|---|"]
    lines += [f"| {STAGES.get(k, k)} | {timings[k]:.1f} |" for k in order]
    demo_total = sum(v for k, v in timings.items() if k != "poses")
    lines += [f"| total of the demo (poses excluded) | {demo_total:.1f} |", ""]
    return lines


def record_timings(run_dir: Path, timings: dict, lines: Sequence[str] = ()) -> None:
    """Writes RUN/timings.json ({stage: seconds}) and appends `lines` (Markdown) and the "Time per
    stage" table to RUN/report.md (written just before by evaluate_run)."""
    io.write_json(run_dir / "timings.json", {k: round(float(v), 2) for k, v in timings.items()})
    report = run_dir / "report.md"
    if report.is_file():
        text = (report.read_text(encoding="utf-8").rstrip("\n") + "\n\n"
                + "\n".join([*lines, *timings_lines(timings)]))
        io.atomic_write_bytes(report, text.encode("utf-8"))


def check_video_frames(frames) -> None:
    """ConfigError naming demo.video_frames unless it is an integer >= 0 (0: no video)."""
    config_lib.check_value("demo.video_frames", frames, int, config_lib.NONNEGATIVE)


def write_demo_video(run_dir: Path, frames: int = DEMO_VIDEO_FRAMES, progress: bool = True) -> dict:
    """The demo's fly-around: `videos.render_video`'s orbit of `frames` frames, DEMO_VIDEO_WIDTH
    px wide, at DEMO_VIDEO_FPS, into RUN/videos/orbit.mp4 and orbit_depth.mp4; then report.html is
    written again so that it links them (`report_html.write_report_html` lists RUN/videos/).
    Returns render_video's {"video", "depth_video", "frames", "width", "height", "fps"}."""
    run_dir = Path(run_dir)
    _, _, ds = runs.load_run_and_dataset(run_dir, progress=False)
    done = videos.render_video(run_dir, frames=frames, fps=DEMO_VIDEO_FPS, width=DEMO_VIDEO_WIDTH,
                               progress=progress, dataset=ds)
    report_html.write_report_html(run_dir / "report.html", run_dir, ds, export_dir=run_dir / "export")
    return done


def video_lines(done: dict, run_dir: Path, seconds: float) -> list[str]:
    """The report.md section on the demo's video (`write_demo_video`'s `done`), links relative to
    RUN."""
    colour, depth = (Path(done[k]).relative_to(run_dir).as_posix() for k in ("video", "depth_video"))
    return ["## Fly-around video", "",
            f"[{colour}]({colour}) (colour) and [{depth}]({depth}) (depth): an orbit of {done['frames']} frames "
            f"at {done['width']}x{done['height']} px, {done['fps']:g} frames per second, rendered in {seconds:.1f} s "
            "(`jaxnerf-grid render` renders longer and larger ones, docs/VIDEOS.md).", ""]


def demo_video_step(run_dir: Path, frames: int, progress: bool, timings: dict) -> tuple[dict | None, list[str]]:
    """The demo's last stage: `write_demo_video` (its seconds into timings["video"]) and its
    report lines. The video is an extra: when it cannot be written (a codec, a full disk) the
    demo still ends with its report, and a one-line warning says why. Returns (render_video's
    dict or None, report.md lines)."""
    if not frames:
        return None, []
    t = time.perf_counter()
    try:
        video = write_demo_video(run_dir, frames, progress)
    except (DataError, OSError) as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"warning: the fly-around video was not written: {reason}", flush=True)
        timings["video"] = time.perf_counter() - t
        return None, ["## Fly-around video", "", f"Not written: {reason}", ""]
    timings["video"] = time.perf_counter() - t
    return video, video_lines(video, run_dir, timings["video"])


def _dataset_folder(data, out: Path, progress: bool, timings: dict) -> Path:
    """The demo's dataset: `data` (must be a folder), else tower-small synthesised into
    out/data once (its seconds into timings["synth"])."""
    if data is not None:
        data = Path(data)
        if not data.is_dir():
            raise DataError(f"{data}: demo.data is not a folder")
        return data
    data = out / "data"
    if not (data / "transforms.json").is_file():
        t = time.perf_counter()
        synth_generate.generate_scene("tower-small", data, seed=0, overwrite=True, progress=progress)
        timings["synth"] = time.perf_counter() - t
    return data


MASK_CHOICES = ("auto", "dpt", "robust", "dpt+robust", "none")


def mask_plan(choice: str, domain: dict | None, capture: bool = False) -> dict:
    """What trains, for `demo --masks choice` on a dataset whose masks got the verdict `domain`
    (transforms.json's `mask_domain`: `masking.domain_verdict`; None when not judged, e.g.
    ground-truth masks or masks made before the rule existed). capture: the dataset is real
    photos registered by `poses` (`is_capture`): "auto" trains on the DPT's masks there too,
    without the photometric evidence, which takes a tower's thin members for outliers (docs/MASKS.md
    "Which masks train"; measured in docs/RESULTS.md, "Real photos"), and the report says so.

    Returns {"mode": "dpt" | "robust" | "dpt+robust" | "none", "overrides": the train.* config
    changes ({"train": {"use_masks": bool[, "robust": {"mode": mode}]}}; `robust` only when not "off",
    its default), "why": a sentence for the report}.
    """
    if choice not in MASK_CHOICES:
        raise ConfigError(f"demo.masks = {choice!r}: must be one of {', '.join(MASK_CHOICES)}")
    if choice == "auto":
        if domain is not None and domain.get("out_of_domain"):
            mode = "robust"
            why = (f"chosen automatically: the DPT is out of its domain on these photos "
                   f"({domain['frames_mostly_masked']} of {domain['frames']} frames have more than "
                   f"{_share_text()} of their pixels masked, median {domain['median_share']:.0%}), so its "
                   "masks are not used")
        else:
            mode = "dpt"
            why = ("chosen automatically: the DPT is in its domain on these photos "
                   f"({domain['frames_mostly_masked']} of {domain['frames']} frames mostly masked, median "
                   f"{domain['median_share']:.0%})" if domain is not None else
                   "chosen automatically: the dataset's masks (not judged by the out-of-domain rule)")
            if capture:
                why += ("; the photometric evidence is not added on a real capture: it takes a tower's thin "
                        "members for outliers (demo.masks = dpt+robust adds it)")
    else:
        mode, why = choice, f"forced by the user (demo.masks = {choice})"
    train_over: dict[str, Any] = {"use_masks": mode in ("dpt", "dpt+robust")}
    robust = {"dpt": "off", "none": "off"}.get(mode, mode)
    if robust != "off":
        train_over["robust"] = {"mode": robust}
    return {"mode": mode, "overrides": {"train": train_over}, "why": why}


# train.depth.weight on a capture from `poses` (docs/RECIPES.md "The depth prior"; measured in
# docs/RESULTS.md, "Real photos")
DEPTH_WEIGHT = 0.1
# Cameras that surround the scene (an orbit of a tower) over this arc start the prior late: the
# colours settle every surface there, and the points seen past a thin member would thin it
# before the colours have laid it out (docs/RECIPES.md "The depth prior").
SURROUNDING_ARC_DEG = 240.0
SURROUNDING_DEPTH_START = 0.2


def capture_defaults(capture: bool, data: Path, meta: dict | None = None) -> dict:
    """The demo's defaults for a capture from `poses` (docs/RECIPES.md "The appearance embedding
    on a capture"): the per-photo appearance embedding (cameras change exposure and white balance
    between photos), held-out views rendered with the training photos' mean embedding
    (train.appearance_steps 0: no test-time fit, whole views scored) and, when its sparse model
    (DATA/sparse/0) is there, train.depth at DEPTH_WEIGHT, starting at SURROUNDING_DEPTH_START of
    the run where the cameras surround the scene (`surrounding`); nothing for other datasets. A
    default layer (`build.build`'s defaults), so a user's --set or config file changes it. meta:
    its transforms.json already read."""
    if not capture:
        return {}
    train: dict = {"appearance_steps": 0}
    if colmap_model.find_model_files(sparse_depth.model_folder(data)) is not None:
        train["depth"] = {"weight": DEPTH_WEIGHT}
        if surrounding(data, meta):
            train["depth"]["start"] = SURROUNDING_DEPTH_START
    return {"model": {"use_appearance": True}, "train": train}


def surrounding(data: Path, meta: dict | None = None) -> bool:
    """Whether the cameras of DATA's transforms.json (z up, as `poses` writes it) cover
    SURROUNDING_ARC_DEG or more about the point they look at; False when it cannot be read.
    meta: its transforms.json already read."""
    try:
        frames = (read_meta(data) if meta is None else meta).get("frames") or []
        c2w = np.asarray([f["transform_matrix"] for f in frames], np.float64).reshape(-1, 4, 4)
    except (DataError, OSError, ValueError, KeyError, TypeError):
        return False
    return len(c2w) >= 3 and camera_set.arc_around_deg(c2w) >= SURROUNDING_ARC_DEG


def is_capture(data: Path, meta: dict | None = None) -> bool:
    """Whether a transforms.json dataset is real photos registered by `poses` (its "poses"
    record); False for generated scenes and other layouts. meta: its transforms.json already read."""
    try:
        return isinstance((read_meta(data) if meta is None else meta).get("poses"), dict)
    except (DataError, OSError, ValueError):
        return False


def _share_text() -> str:
    return f"{masking.OOD_FRAME_SHARE:.0%}"


def dataset_domain(data: Path, meta: dict | None = None) -> dict | None:
    """The out-of-domain verdict of a dataset's DPT masks: transforms.json's `mask_domain`; for
    DPT masks written before `mask` recorded it, `masking.domain_verdict` of the masks' shares,
    read from masks/; None for other masks (ground truth, the user's own) or none. meta: its
    transforms.json already read."""
    meta = read_meta(data) if meta is None else meta
    if meta.get("mask_domain") is not None:
        return meta["mask_domain"]
    frames = [f for f in meta.get("frames", []) if isinstance(f, dict)]
    if meta.get("mask_source") != "dpt" or not frames or not all(f.get("mask_path") for f in frames):
        return None
    return masking.domain_verdict([float(np.mean(io.read_mask(data / f["mask_path"]) > 0.5)) for f in frames])


def _with_plan(recipe: dict, plan: dict) -> dict:
    """recipe with the plan's train.* overrides laid on top (the recipe is not changed)."""
    return {**recipe, "train": {**recipe.get("train", {}), **plan["overrides"]["train"]}}


def _ensure_masks(data: Path, progress: bool, timings: dict) -> str:
    """Masks the dataset unless it has masks or weights (the built-in DPT; ground-truth stand-ins
    when no built-in model is shipped and the data are synthetic; seconds into timings["mask"]).
    Returns the dataset's mask source ("unknown" when it does not say)."""
    meta = read_meta(data)
    has_masks = "mask_source" in meta or any(isinstance(f, dict) and (f.get("weight_path") or f.get("mask_path"))
                                             for f in meta.get("frames", []))
    if not has_masks:
        t = time.perf_counter()
        gt = not masking.BUILTIN.exists() and "distractor_mask_path" in json.dumps(meta.get("frames", []))
        masking.write_masks(data, source="gt" if gt else "dpt", progress=progress)
        timings["mask"] = time.perf_counter() - t
        meta = read_meta(data)
    return meta.get("mask_source", "unknown")


def _mask_note(mask_source: str | None, plan: dict | None = None) -> str:
    """The report's line on which masks trained and why (plan: `mask_plan`'s; None = the DPT's
    masks, as before the rule)."""
    mode = plan["mode"] if plan else "dpt"
    why = f" Why: {plan['why']}." if plan else ""
    if mode == "robust":
        return ("Masks: **none used**; training down-weights pixels by photometric evidence "
                f"(`train.robust = robust`, docs/MASKS.md).{why}")
    if mode == "none":
        return f"Masks: **none used** (every pixel weight 1).{why}"
    if mask_source == "dpt":
        note = "Masks: built-in DPT (`jaxnerf-grid mask`), weights 1 - M_w."
    elif mask_source in ("gt", "ground-truth"):
        note = ("Masks: **ground-truth stand-ins** (mask source `ground-truth`): `jaxnerf-grid mask "
                "--source gt` built M from the synthetic distractor masks and D from the true depth.")
    else:
        note = f"Masks: from the dataset (mask source `{mask_source}`)."
    if mode == "dpt+robust":
        note += " They are the prior of `train.robust = dpt+robust` (docs/MASKS.md)."
    return note + why


def check_camera_set(data: Path, accept_few_cameras: bool = False) -> str | None:
    """For a dataset `jaxnerf-grid poses` wrote: DataError (one line, naming the counts) when its
    camera set is too thin to train on (`capture.camera_set.camera_set_verdict` on transforms.json's
    poses.camera_set), unless `accept_few_cameras`. Returns the line the report gets ("trained
    on N of the M photos ..."), None for a dataset poses did not write."""
    meta = read_meta(data)
    record = (meta.get("poses") or {}).get("camera_set") if isinstance(meta.get("poses"), dict) else None
    if not isinstance(record, dict):
        return None
    verdict = camera_set.camera_set_verdict(record)
    if verdict is not None and not accept_few_cameras:
        raise DataError(f"{data}: {verdict}; not trained (a NeRF trained on them renders the rest as a ghost); "
                        "accept_few_cameras=True trains anyway (docs/POSES.md)")
    frames = len(meta.get("frames") or [])
    split = _json_split_counts(meta, frames)
    return (f"Cameras: {split['train']} photos trained ({split['test']} held out for testing) of the "
            f"{record['photos']} photos given to `poses` ({record['kept']} kept, covering "
            f"{record['arc_kept_deg']:.0f} of {record['arc_flight_deg']:.0f} degrees around the scene)"
            + (f"; {verdict}, trained anyway" if verdict else "") + ".")


def _json_split_counts(meta: dict, frames: int) -> dict:
    """{"train", "test"}: how many frames of a transforms.json train and test (their `split`
    when every frame names one, else every 8th tests, `formats.frames.default_split`)."""
    named = [f.get("split") for f in meta.get("frames") or [] if isinstance(f, dict)]
    if named and all(n in ("train", "test") for n in named):
        return {"train": named.count("train"), "test": named.count("test")}
    split = default_split(frames)
    return {"train": len(split["train"]), "test": len(split["test"])}


def _say(line: str) -> None:
    print(line, flush=True)


def run_demo(data: str | Path | None, out: str | Path, steps: int | None = None, overwrite: bool = False,
             progress: bool = True, sets: list[str] | None = None, max_side: int | None = None,
             masks: str = "auto", video_frames: int = DEMO_VIDEO_FRAMES, minutes: float | None = None,
             accept_few_cameras: bool = False) -> dict:
    """The demo recipe as a library call: (synth when data is None) -> mask (when the dataset
    has no masks and they are needed) -> train the demo's recipe (DEMO_RECIPE) -> evaluate -> the
    fly-around video (`write_demo_video`, unless video_frames is 0). Returns {"run_dir", "metrics",
    "timings" (s per stage, STAGES), "total_seconds", "mask_source", "mask_plan", "video"
    (render_video's dict, None without a video)}. sets: --set KEY=VALUE changes to DEMO_CONFIG;
    max_side: train.max_side (the working resolution; None: the default, 640 px); masks: one of
    MASK_CHOICES (`mask_plan`); minutes: the training time budget the steps are chosen within when
    `steps` is None (config/budget.py; None: budget.DEFAULT_MINUTES). The config is checked
    (run_config.make_config) before anything is written; so is the camera set of a dataset `poses`
    wrote (`check_camera_set`: refused when too thin to train on, unless accept_few_cameras), and
    the report says how many photos trained."""
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise ConfigError(f"demo.steps = {steps}: must be an integer >= 1")
    check_video_frames(video_frames)
    if minutes is not None:
        config_lib.check_value("demo.minutes", minutes, float, config_lib.POSITIVE)
    request = build.Request(recipe=DEMO_RECIPE, sets=tuple(sets or ()), max_side=max_side, steps=steps,
                            minutes=minutes)
    recipe = build.build(request).overrides  # a bad --set fails before synth / mask
    method = recipes.get(DEMO_RECIPE).method
    forced = mask_plan(masks, None)  # a bad --masks fails here; auto is settled after masking
    # a bad --set fails before synth / mask
    make_config(method, _with_plan(recipe, forced) if masks != "auto" else recipe)
    start = time.perf_counter()
    out = Path(out)
    folders.check_folder(out, "demo.out")
    folders.check_outside(out, data, "demo.out")  # the dataset is never written into (links resolved)
    # a dataset in another layout train reads (COLMAP, LLFF, Blender): `mask` writes only into the
    # transforms.json layout, so such a dataset trains without masks (auto: robust)
    layout = data is None or (Path(data) / "transforms.json").is_file()
    if not layout and masks in ("dpt", "dpt+robust"):
        raise ConfigError(f"demo.masks = {masks}: {data} is not in the transforms.json layout (docs/DATASET.md), so "
                          "no masks can be written into it; use demo.masks robust or none (or auto)")
    if (out / "run").exists() and not (out / "run").is_dir():
        raise DataError(f"{out / 'run'}: exists and is not a folder")
    cameras_line = check_camera_set(Path(data), accept_few_cameras) if data is not None and layout else None
    timings: dict[str, float] = {}
    # multi-process (docs/DISTRIBUTED.md): process 0 makes the data, every process trains, process 0 evaluates
    if distributed.is_main():
        data = _dataset_folder(data, out, progress, timings)
        seconds = poses_seconds(data)
        if seconds is not None:
            timings["poses"] = seconds
        mask_source = (_ensure_masks(data, progress, timings) if masks not in ("robust", "none") and layout
                       else None)
    distributed.barrier("jaxnerf_grid.demo.data")
    if not distributed.is_main():
        data = Path(data) if data is not None else out / "data"
        mask_source = None
    # every process reads the same verdict from the dataset, so all train the same config
    data_dir = Path(data or out / "data")  # set above on every process
    meta = read_meta(data_dir)  # {} for another layout
    capture = is_capture(data_dir, meta)
    plan = mask_plan(masks, dataset_domain(data_dir, meta), capture)
    if not layout and masks == "auto":
        plan = dict(mask_plan("robust", None), why="chosen automatically: the dataset is not in the transforms.json "
                    "layout, so it has no masks and `mask` cannot write any")
    # the dataset's bounds, --set and --max-side on top, the mask plan, then the training budget
    built = build.build(request, data=data, extra=_with_plan({}, plan), devices_of=train.step_devices,
                        platform=distributed.jax.default_backend(), defaults=capture_defaults(capture, data_dir, meta),
                        measure=speed.planner(out / "run", overwrite,
                                              _say if progress and distributed.is_main() else None))
    bounds = built.bounds
    if bounds_warning(bounds) and distributed.is_main():
        print(bounds_warning(bounds), flush=True)
    if built.budget is not None and progress and distributed.is_main():
        print(budget_lib.report_line(built.budget), flush=True)
    if built.budget is not None and budget_lib.warning(built.budget) and distributed.is_main():
        print(budget_lib.warning(built.budget), flush=True)
    t = time.perf_counter()
    run_dir, _, _ = runs.train_run(str(data), method, out / "run", built.overrides, None, overwrite, progress,
                                   budget=built.budget)
    timings["train"] = time.perf_counter() - t
    if not distributed.is_main():
        return {"run_dir": run_dir, "metrics": None, "timings": timings, "total_seconds": time.perf_counter() - start,
                "mask_source": mask_source, "mask_plan": plan, "video": None}
    t = time.perf_counter()
    notes = [_mask_note(mask_source, plan), bounds_line(bounds)] + ([cameras_line] if cameras_line else [])
    metrics_out = evaluate.evaluate_run(run_dir, progress=progress, extra_notes=notes, distractor_views=2,
                                        cloud_views=DEMO_CLOUD_VIEWS, cloud_pixels=DEMO_CLOUD_PIXELS)
    timings["eval"] = time.perf_counter() - t
    video, lines = demo_video_step(Path(run_dir), video_frames, progress, timings)
    record_timings(Path(run_dir), timings, lines)
    return {"run_dir": run_dir, "metrics": metrics_out, "timings": timings,
            "total_seconds": time.perf_counter() - start, "mask_source": mask_source, "mask_plan": plan,
            "video": video}


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
