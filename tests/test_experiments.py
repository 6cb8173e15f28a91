"""Smoke test of experiments/common.py (imported as the package `experiments`): toy scene -> mask variants -> train + eval -> resume/skip -> tables.

No numeric claims about the NeRF (3 steps of a tiny model); the checks are on the machinery:
variants share the scene's images, the mask IoU of ground-truth masks is 1, a finished run
is not re-run, mean/std come out of the recorded values, the results files and the plot exist.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from experiments import common

TINY = {"model": {"field": {"depth": 1, "width": 16, "skip": 0, "pos_max_deg": 2, "dir_max_deg": 1, "view_width": 8},
                  "num_coarse": 4, "num_fine": 4},
        "train": {"batch_rays": 64, "warmup": 1, "checkpoint_every": 2, "log_every": 1, "chunk": 512}}


def test_machinery_end_to_end(tmp_path, monkeypatch):
    monkeypatch.setitem(common.TRAIN_SETTINGS, "quick", {"steps": 3, "seeds": 1, "distractor_views": 1,
                                                        "overrides": TINY})
    monkeypatch.setitem(common.SCENE_SIZES, "quick", {"tower-small": (24, 16, 2, 1, 1)})
    ctx = common.Context("quick", 1, 3, tmp_path / "cache", tmp_path / "results", None, None, False, "test")
    ctx.machine = common.machine_info()

    scene = common.scene(ctx, "tower-small", 0, distractors="high")
    variant = common.mask_variant(ctx, scene, "gt_binary", "gt", floor=1.0)
    clean = common.clean_variant(ctx, scene)
    for v in (variant, clean):  # no image copied: every frame points back at the scene folder
        meta = json.loads((v / "transforms.json").read_text())
        assert all(f["file_path"].startswith("../../scenes/") for f in meta["frames"])
        assert not (v / "images").exists()
    clean_meta = json.loads((clean / "transforms.json").read_text())
    assert all("/clean/" in f["file_path"] for f in clean_meta["frames"] if "clean_file_path" in f)

    iou = common.mask_iou(variant)  # ground-truth masks against the ground truth they came from
    if iou["gt_pixels"] > 0:
        assert iou["iou"] == 1.0

    rec = common.run_condition(ctx, variant, "ours", 0, "smoke", {"train": {"use_masks": True}})
    assert not rec["cached"] and (Path(rec["run_dir"]) / "metrics.json").is_file()
    assert np.isfinite(rec["metrics"]["mean"]["psnr"]) and rec["samples_per_ray"] == 8
    mtime = os.path.getmtime(Path(rec["run_dir"]) / "metrics.json")
    again = common.run_condition(ctx, variant, "ours", 0, "other-label", {"train": {"use_masks": True}})
    assert again["cached"] and again["run_dir"] == rec["run_dir"]
    assert os.path.getmtime(Path(rec["run_dir"]) / "metrics.json") == mtime

    fake = dict(rec, seed=1, metrics=dict(rec["metrics"], mean=dict(rec["metrics"]["mean"], psnr=10.0)))
    agg = common.aggregate([rec, fake, None], {"mask_iou": [0.2, 0.4, None]})
    vals = [rec["metrics"]["mean"]["psnr"], 10.0]
    assert agg["n"] == 2 and agg["psnr"]["values"] == vals
    assert abs(agg["psnr"]["std"] - np.std(vals)) < 1e-12 and abs(agg["mask_iou"]["mean"] - 0.3) < 1e-12

    base = {"seeds": [1, 0], "psnr": {"values": [9.0, vals[0] - 0.5]}}  # paired by seed, not by position
    common.add_paired_delta(agg, base)
    assert np.allclose(agg["delta_psnr"]["values"], [0.5, 1.0])

    lines = common.markdown_table([("a", agg), ("b", None)], [("psnr", "PSNR", 2)])
    assert lines[2].startswith("| a | 2 |") and "±" in lines[2] and "not run" in lines[3]
    common.write_results(ctx, "smoke", "Smoke", {"rows": []}, lines, ["note"])
    assert json.loads((ctx.results / "smoke.json").read_text())["command"] == "test"
    assert "LPIPS unavailable" in (ctx.results / "smoke.md").read_text()

    img = common.line_plot([{"label": "a", "x": [16, 32], "y": [20.0, 21.0]},
                            {"label": "b", "x": [16, 32], "y": [19.0, 22.0], "dashed": True}], "x", "y", "t")
    assert img.shape == (480, 760, 3) and img.min() < 0.5  # something was drawn
    common.write_figure(ctx, "plot", img)
    assert (ctx.results / "plot.png").stat().st_size > 0

    ctx.budget_s = 0.0  # out of budget: an unfinished condition is not started, and says so
    assert common.run_condition(ctx, variant, "ours", 5, "late") is None
    assert ctx.skipped_for_budget == ["late seed 5"]


def test_builtin_dpt_variants_follow_the_weights(tmp_path, monkeypatch):
    """A retrained built-in DPT must not reuse masks cached from the old weights: the variant
    folder name carries a digest of the weights folder's bytes."""
    weights = tmp_path / "weights"
    weights.mkdir()
    (weights / "config.json").write_text("{}")
    (weights / "params.safetensors").write_bytes(b"old")
    before = common.weights_digest(weights)
    assert common.weights_digest(weights) == before  # stable
    (weights / "params.safetensors").write_bytes(b"new")
    assert common.weights_digest(weights) != before

    calls = []
    from jaxnerf_grid import masking

    monkeypatch.setattr(masking, "BUILTIN", weights)
    monkeypatch.setattr(masking, "write_masks", lambda data, **kw: calls.append(kw) or {})
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "transforms.json").write_text(json.dumps({"frames": []}))
    ctx = common.Context("quick", 1, 3, tmp_path / "cache", tmp_path / "results", None, None, False, "test")
    out = common.mask_variant(ctx, scene, "dpt_builtin_eq7", "dpt")
    assert out.name == f"scene__dpt_builtin_eq7_{common.weights_digest(weights)}" and len(calls) == 1
    gt = common.mask_variant(ctx, scene, "gt_eq7", "gt")  # other sources keep their plain names
    assert gt.name == "scene__gt_eq7"
