"""The demo: the CPU recipe (`DEMO_CONFIG`) end to end, as library calls.

`run_demo(data, out)`: synthetic tower-small (when no data is given) -> masks (when the dataset
has none; `masking.write_masks`) -> train the `ours` recipe (DEMO_CONFIG; `runs.train_run`, at the
working resolution of `train.max_side`, data/working.py; near, far and contract_radius from the
dataset's `scene_bounds` when it records them, `data.bounds`) -> evaluate (`evaluate.evaluate_run`).
`demo_summary(result)` is its one-line summary. The seconds of each stage (STAGES: poses when the
dataset was made by `jaxnerf-grid poses`, from its record; synth, mask, train, eval) go into
RUN/timings.json and a "Time per stage" table at the end of RUN/report.md (`timings_lines`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from jaxnerf_grid import config as config_lib, distributed, evaluate, io, masking, recipes, runs
from jaxnerf_grid.config import ConfigError
from jaxnerf_grid.data.bounds import bounds_line, read_bounds, recipe_with_bounds
from jaxnerf_grid.data.synthetic import generate as synth_generate
from jaxnerf_grid.io import DataError
from jaxnerf_grid.run_config import make_config

# The demo's recipe: `recipes.overrides("ours")`, the recipe that resolves the tower (docs/GRID.md,
# docs/RECIPES.md): a hash grid on the contracted coordinates, one proposal round of 64 samples
# stratified in s feeding 32 samples of the main field, an opaque far bin at 1000 units.
DEMO_RECIPE = "ours"
DEMO_CONFIG = recipes.overrides(DEMO_RECIPE)


# Training views whose depth also goes into the demo's tower cloud (evaluate_run's cloud_views).
DEMO_CLOUD_VIEWS = 16

# The stages of a demo, in order, as timings.json and the report name them.
STAGES = {"poses": "poses (`jaxnerf-grid poses`, before the demo; from the dataset's record)",
          "synth": "synthetic scene", "mask": "masks", "train": "training", "eval": "evaluation"}


def poses_seconds(data: Path) -> float | None:
    """The seconds `jaxnerf-grid poses` took to make the dataset (transforms.json's
    poses.seconds); None for a dataset it did not make."""
    poses = _read_meta(data).get("poses")
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


def record_timings(run_dir: Path, timings: dict) -> None:
    """Writes RUN/timings.json ({stage: seconds}) and appends the "Time per stage" table to
    RUN/report.md (written just before by evaluate_run)."""
    io.write_json(run_dir / "timings.json", {k: round(float(v), 2) for k, v in timings.items()})
    report = run_dir / "report.md"
    if report.is_file():
        text = report.read_text(encoding="utf-8").rstrip("\n") + "\n\n" + "\n".join(timings_lines(timings))
        io.atomic_write_bytes(report, text.encode("utf-8"))


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


def _read_meta(data: Path) -> dict:
    return io.read_json(data / "transforms.json") if (data / "transforms.json").is_file() else {}


def _ensure_masks(data: Path, progress: bool, timings: dict) -> str:
    """Masks the dataset unless it has masks or weights (the built-in DPT; ground-truth stand-ins
    when no built-in model is shipped and the data are synthetic; seconds into timings["mask"]).
    Returns the dataset's mask source ("unknown" when it does not say)."""
    meta = _read_meta(data)
    has_masks = "mask_source" in meta or any(isinstance(f, dict) and (f.get("weight_path") or f.get("mask_path"))
                                             for f in meta.get("frames", []))
    if not has_masks:
        t = time.perf_counter()
        gt = not masking.BUILTIN.exists() and "distractor_mask_path" in json.dumps(meta.get("frames", []))
        masking.write_masks(data, source="gt" if gt else "dpt", progress=progress)
        timings["mask"] = time.perf_counter() - t
        meta = _read_meta(data)
    return meta.get("mask_source", "unknown")


def _mask_note(mask_source: str) -> str:
    """The report's line on where the masks came from."""
    if mask_source == "dpt":
        return "Masks: built-in DPT (`jaxnerf-grid mask`), weights 1 - M_w."
    if mask_source in ("gt", "ground-truth"):
        return ("Masks: **ground-truth stand-ins** (mask source `ground-truth`): `jaxnerf-grid mask "
                "--source gt` built M from the synthetic distractor masks and D from the true depth.")
    return f"Masks: from the dataset (mask source `{mask_source}`)."


def run_demo(data: str | Path | None, out: str | Path, steps: int | None = None, overwrite: bool = False,
             progress: bool = True, sets: list[str] | None = None, max_side: int | None = None) -> dict:
    """The demo recipe as a library call: (synth when data is None) -> mask (when the dataset
    has no masks) -> train the `ours` recipe (DEMO_RECIPE) -> evaluate. Returns {"run_dir", "metrics",
    "timings" (s per stage, STAGES), "total_seconds", "mask_source"}. sets: --set KEY=VALUE
    changes to DEMO_CONFIG; max_side: train.max_side (the working resolution; None: the
    default, 640 px). The config is checked (run_config.make_config) before anything is written."""
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise ConfigError(f"demo.steps = {steps}: must be an integer >= 1")
    method = recipes.get(DEMO_RECIPE).method
    recipe = runs.overrides_with_sets(recipes.overrides(DEMO_RECIPE), sets)
    if max_side is not None:
        recipe = config_lib.merge(recipe, {"train": {"max_side": max_side}})
    make_config(method, runs._with_steps(recipe, steps))  # a bad --set fails before synth / mask
    start = time.perf_counter()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: demo.out exists and is not a folder")
    if (out / "run").exists() and not (out / "run").is_dir():
        raise DataError(f"{out / 'run'}: exists and is not a folder")
    timings = {}
    # multi-process (docs/DISTRIBUTED.md): process 0 makes the data, every process trains, process 0 evaluates
    if distributed.is_main():
        data = _dataset_folder(data, out, progress, timings)
        if poses_seconds(data) is not None:
            timings["poses"] = poses_seconds(data)
        mask_source = _ensure_masks(data, progress, timings)
    distributed.barrier("jaxnerf_grid.demo.data")
    if not distributed.is_main():
        data = Path(data) if data is not None else out / "data"
        mask_source = None
    bounds = read_bounds(_read_meta(data), data / "transforms.json")
    recipe = runs.overrides_with_sets(recipe_with_bounds(DEMO_CONFIG, bounds), sets)
    t = time.perf_counter()
    run_dir, _, _ = runs.train_run(str(data), method, out / "run", recipe, steps, overwrite, progress)
    timings["train"] = time.perf_counter() - t
    if not distributed.is_main():
        return {"run_dir": run_dir, "metrics": None, "timings": timings,
                "total_seconds": time.perf_counter() - start, "mask_source": mask_source}
    t = time.perf_counter()
    notes = [_mask_note(mask_source), bounds_line(bounds)]
    metrics_out = evaluate.evaluate_run(run_dir, progress=progress, extra_notes=notes, distractor_views=2,
                                        cloud_views=DEMO_CLOUD_VIEWS)
    timings["eval"] = time.perf_counter() - t
    record_timings(Path(run_dir), timings)
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
