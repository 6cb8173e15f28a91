"""The demo: the CPU recipe (`DEMO_CONFIG`) end to end, as library calls.

`run_demo(data, out)`: synthetic tower-small (when no data is given) -> masks (when the dataset
has none; `masking.write_masks`) -> train "ours" with DEMO_CONFIG (`runs.train_run`) ->
evaluate (`evaluate.evaluate_run`). `demo_summary(result)` is its one-line summary.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from jaxnerf_grid import evaluate, io, runs
from jaxnerf_grid.config import ConfigError
from jaxnerf_grid.io import DataError

# The CPU recipe of the demo (docs/GRID.md): a hash-grid field on the contracted coordinates
# (fields/grid.py), one density-only proposal round of 64 samples stratified in s (disparity
# warp) feeding 32 samples of the main field, the interlevel and distortion losses (in s), an
# opaque far bin at 1000 units so the sky sits at infinity, and Instant-NGP's Adam settings.
# Each choice was measured at 1000 steps on tower-small (docs/GRID.md, "How the recipe was chosen").
DEMO_CONFIG = {
    "model": {"sampler": {"kind": "proposal", "samples": [64], "main_samples": 32, "field": {"density_bias": -4.0}},
              "contract_radius": 2.0,
              "field": {"kind": "grid", "depth": 1, "width": 64, "view_depth": 2, "view_width": 64,
                        "dir_max_deg": 3, "density_activation": "exp", "density_bias": -4.0,
                        "grid": {"num_levels": 12, "features_per_level": 2, "log2_table_size": 17,
                                 "min_resolution": 16, "max_resolution": 1024}},
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


def _dataset_folder(data, out: Path, progress: bool, timings: dict) -> Path:
    """The demo's dataset: `data` (must be a folder), else tower-small synthesised into
    out/data once (its seconds into timings["synth"])."""
    if data is not None:
        data = Path(data)
        if not data.is_dir():
            raise DataError(f"{data}: --data is not a folder")
        return data
    data = out / "data"
    if not (data / "transforms.json").is_file():
        from jaxnerf_grid.data.synthetic.generate import generate_scene

        t = time.perf_counter()
        generate_scene("tower-small", data, seed=0, overwrite=True, progress=progress)
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
        from jaxnerf_grid import masking

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
             progress: bool = True, sets: list[str] | None = None) -> dict:
    """The demo recipe as a library call: (synth when data is None) -> mask (when the dataset
    has no masks) -> train "ours" with DEMO_CONFIG -> evaluate. Returns {"run_dir", "metrics",
    "timings" (s per stage), "total_seconds", "mask_source"}. sets: --set KEY=VALUE changes to
    DEMO_CONFIG. The config is checked (train.make_config) before anything is written."""
    from jaxnerf_grid import train

    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise ConfigError(f"--steps = {steps}: must be an integer >= 1")
    recipe = runs.overrides_with_sets(DEMO_CONFIG, sets)
    train.make_config("ours", runs._with_steps(recipe, steps))  # a bad --set fails before synth / mask
    start = time.perf_counter()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: --out exists and is not a folder")
    if (out / "run").exists() and not (out / "run").is_dir():
        raise DataError(f"{out / 'run'}: exists and is not a folder")
    timings = {}
    from jaxnerf_grid import distributed

    # multi-process (docs/DISTRIBUTED.md): process 0 makes the data, every process trains, process 0 evaluates
    if distributed.is_main():
        data = _dataset_folder(data, out, progress, timings)
        mask_source = _ensure_masks(data, progress, timings)
    distributed.barrier("jaxnerf_grid.demo.data")
    if not distributed.is_main():
        data = Path(data) if data is not None else out / "data"
        mask_source = None
    t = time.perf_counter()
    run_dir, _, _ = runs.train_run(str(data), "ours", out / "run", recipe, steps, overwrite, progress)
    timings["train"] = time.perf_counter() - t
    if not distributed.is_main():
        return {"run_dir": run_dir, "metrics": None, "timings": timings,
                "total_seconds": time.perf_counter() - start, "mask_source": mask_source}
    t = time.perf_counter()
    notes = [_mask_note(mask_source),
             "Timings so far (s): " + ", ".join(f"{k} {v:.0f}" for k, v in timings.items())]
    metrics_out = evaluate.evaluate_run(run_dir, progress=progress, extra_notes=notes, distractor_views=2,
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
