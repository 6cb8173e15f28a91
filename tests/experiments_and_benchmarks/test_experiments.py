"""Smoke test of the experiments' machinery (settings, scenes, runner, tables, figures).

Toy scene -> mask variants -> train + eval -> resume/skip -> tables.

No numeric claims about the NeRF (3 steps of a tiny model); the checks are on the machinery:
variants share the scene's images, the mask IoU of ground-truth masks is 1, a finished run
is not re-run, mean/std come out of the recorded values, the results files and the plot exist.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from experiments import figures, runner, scenes, settings, tables
from jaxnerf_grid.config import recipes
from jaxnerf_grid.config import schema as config
from jaxnerf_grid.config.schema import merge

TINY = {"model": {"field": {"depth": 1, "width": 16, "skip": 0, "pos_max_deg": 2, "dir_max_deg": 1, "view_width": 8},
                  "num_coarse": 4, "num_fine": 4},
        "train": {"batch_rays": 64, "warmup": 1, "checkpoint_every": 2, "log_every": 1, "chunk": 512}}


def test_machinery_end_to_end(tmp_path, monkeypatch):
    monkeypatch.setitem(settings.TRAIN_SETTINGS, "quick", {"recipe": "ours-paper-mlp", "steps": 3, "seeds": 1,
                                                        "distractor_views": 1,
                                                        "overrides": TINY})
    monkeypatch.setitem(settings.SCENE_SIZES, "quick", {"tower-small": (24, 16, 2, 1, 1)})
    ctx = runner.Context("quick", 1, 3, tmp_path / "cache", tmp_path / "results", None, None, False, "test")
    ctx.machine = runner.machine_info()

    scene = scenes.scene(ctx, "tower-small", 0, distractors="high")
    variant = scenes.mask_variant(ctx, scene, "gt_binary", "gt", floor=1.0)
    clean = scenes.clean_variant(ctx, scene)
    for v in (variant, clean):  # no image copied: every frame points back at the scene folder
        meta = json.loads((v / "transforms.json").read_text())
        assert all(f["file_path"].startswith("../../scenes/") for f in meta["frames"])
        assert not (v / "images").exists()
    clean_meta = json.loads((clean / "transforms.json").read_text())
    assert all("/clean/" in f["file_path"] for f in clean_meta["frames"] if "clean_file_path" in f)

    iou = scenes.mask_iou(variant)  # ground-truth masks against the ground truth they came from
    if iou["gt_pixels"] > 0:
        assert iou["iou"] == 1.0

    rec = runner.run_condition(ctx, variant, "ours", 0, "smoke", {"train": {"use_masks": True}})
    assert not rec["cached"] and (Path(rec["run_dir"]) / "metrics.json").is_file()
    assert np.isfinite(rec["metrics"]["mean"]["psnr"]) and rec["samples_per_ray"] == 8
    mtime = os.path.getmtime(Path(rec["run_dir"]) / "metrics.json")
    again = runner.run_condition(ctx, variant, "ours", 0, "other-label", {"train": {"use_masks": True}})
    assert again["cached"] and again["run_dir"] == rec["run_dir"]
    assert os.path.getmtime(Path(rec["run_dir"]) / "metrics.json") == mtime

    fake = dict(rec, seed=1, metrics=dict(rec["metrics"], mean=dict(rec["metrics"]["mean"], psnr=10.0)))
    agg = tables.aggregate([rec, fake, None], {"mask_iou": [0.2, 0.4, None]})
    vals = [rec["metrics"]["mean"]["psnr"], 10.0]
    assert agg["n"] == 2 and agg["psnr"]["values"] == vals
    assert abs(agg["psnr"]["std"] - np.std(vals)) < 1e-12 and abs(agg["mask_iou"]["mean"] - 0.3) < 1e-12

    base = {"seeds": [1, 0], "psnr": {"values": [9.0, vals[0] - 0.5]}}  # paired by seed, not by position
    tables.add_paired_delta(agg, base)
    assert np.allclose(agg["delta_psnr"]["values"], [0.5, 1.0])

    lines = tables.markdown_table([("a", agg), ("b", None)], [("psnr", "PSNR", 2)])
    assert lines[2].startswith("| a | 2 |") and "±" in lines[2] and "not run" in lines[3]
    tables.write_results(ctx, "smoke", "Smoke", {"rows": []}, lines, ["note"])
    assert json.loads((ctx.results / "smoke.json").read_text())["command"] == "test"
    assert "LPIPS unavailable" in (ctx.results / "smoke.md").read_text()

    img = figures.line_plot([{"label": "a", "x": [16, 32], "y": [20.0, 21.0]},
                            {"label": "b", "x": [16, 32], "y": [19.0, 22.0], "dashed": True}], "x", "y", "t")
    assert img.shape == (480, 760, 3) and img.min() < 0.5  # something was drawn
    assert has_colour(img, C0) and has_colour(img, C1)  # both series, in matplotlib's first two colours
    figures.write_figure(ctx, "plot", img)
    assert (ctx.results / "plot.png").stat().st_size > 0

    ctx.budget_s = 0.0  # out of budget: an unfinished condition is not started, and says so
    assert runner.run_condition(ctx, variant, "ours", 5, "late") is None
    assert ctx.not_run == ["late seed 5"]


C0, C1 = (0x1F, 0x77, 0xB4), (0xFF, 0x7F, 0x0E)  # matplotlib's default first two line colours


def has_colour(img: np.ndarray, rgb: tuple, pixels: int = 20) -> bool:
    """At least `pixels` pixels of img [H, W, 3] in [0, 1] within 2/255 of the 8-bit colour rgb."""
    return int(np.sum(np.all(np.abs(img * 255 - np.asarray(rgb)) <= 2, axis=-1))) >= pixels


def test_sampling_figure_is_redrawn_from_its_results_file(tmp_path):
    """`benchmarks.sampling_schemes --replot`: the PNG from the JSON alone, one line per scheme
    that has cells (linear in C0, disparity in C1), nothing for a scheme without any."""
    from benchmarks import sampling_schemes as bench
    from jaxnerf_grid.util import io

    cell = lambda v: {"n": 1, "seeds": [0], "psnr": {"mean": v, "std": 0.1, "values": [v]}}  # noqa: E731
    rows = [{"scheme": "linear + proposal", "samples_per_ray": n, "aggregate": cell(20.0 + n / 16)} for n in (8, 16)]
    body = {"samples": [8, 16], "settings": {"setting": "standard", "steps": 10}, "rows": rows}
    io.write_json(tmp_path / "sampling_schemes.json", body)
    img = io.read_image(bench.replot(tmp_path))
    assert img.shape == (480, 760, 3) and has_colour(img, C0) and not has_colour(img, C1)
    rows += [{"scheme": "disparity + proposal", "samples_per_ray": 8, "aggregate": cell(21.0)}]
    io.write_json(tmp_path / "sampling_schemes.json", body)
    assert has_colour(io.read_image(bench.replot(tmp_path)), C1)


def test_builtin_dpt_variants_follow_the_weights(tmp_path, monkeypatch):
    """A retrained built-in DPT must not reuse masks cached from the old weights: the variant
    folder name carries a digest of the weights folder's bytes."""
    weights = tmp_path / "weights"
    weights.mkdir()
    (weights / "config.json").write_text("{}")
    (weights / "params.safetensors").write_bytes(b"old")
    before = scenes.weights_digest(weights)
    assert scenes.weights_digest(weights) == before  # stable
    (weights / "params.safetensors").write_bytes(b"new")
    assert scenes.weights_digest(weights) != before

    calls = []
    from jaxnerf_grid.masks import write as masking

    monkeypatch.setattr(masking, "BUILTIN", weights)
    monkeypatch.setattr(masking, "write_masks", lambda data, **kw: calls.append(kw) or {})
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "transforms.json").write_text(json.dumps({"frames": []}))
    ctx = runner.Context("quick", 1, 3, tmp_path / "cache", tmp_path / "results", None, None, False, "test")
    out = scenes.mask_variant(ctx, scene, "dpt_builtin_eq7", "dpt")
    assert out.name == f"scene__dpt_builtin_eq7_{scenes.weights_digest(weights)}" and len(calls) == 1
    assert calls[0]["dilate"] == 0 and "threshold" not in calls[0]
    low = scenes.mask_variant(ctx, scene, "dpt_builtin_eq7", "dpt", threshold=0.2)  # another T: its own folder
    assert low.name == f"{out.name}_t0.2" and calls[-1]["threshold"] == 0.2 and len(calls) == 2
    calls.pop()
    gt = scenes.mask_variant(ctx, scene, "gt_eq7", "gt")  # other sources keep their plain names
    assert gt.name == "scene__gt_eq7"
    other = tmp_path / "crossover"  # a DPT given by folder (Table 4's) is keyed on its bytes too
    other.mkdir()
    (other / "params.safetensors").write_bytes(b"crossover")
    out = scenes.mask_variant(ctx, scene, "dpt_from_x", "dpt", weights=str(other))
    assert out.name == f"scene__dpt_from_x_{scenes.weights_digest(other)}" and len(calls) == 3
    from experiments import table1_foreground as t1  # Table 1's dilated row asks write_masks for --dilate 2

    monkeypatch.setattr(t1, "builtin_available", lambda: True)
    monkeypatch.setattr(scenes, "mask_iou", lambda v, split="train": {"iou": 0.5, "recall": 0.8})
    data, ov, stats = t1.condition_data(ctx, scene, t1.DILATED)
    assert stats["recall"] == 0.8
    assert calls[-1]["dilate"] == 2 and "dilate2" in data.name and ov == {"train": {"use_masks": True}}
    # --dpt-weights: the DPT rows mask with that model, under a name keyed on its bytes
    data, _, _ = t1.condition_data(ctx, scene, "built-in DPT masks + Eq. 7", str(other))
    assert calls[-1]["weights"] == str(other) and calls[-1]["dilate"] == 0
    assert data.name == f"scene__dpt_builtin_eq7_{scenes.weights_digest(other)}"


def test_verdict_follows_the_stated_rule():
    """The verdict on a paired effect, case by case against VERDICT_RULE's wording."""
    cell = lambda *v: {"mean": float(np.mean(v)), "std": float(np.std(v)), "values": list(v)}  # noqa: E731
    assert tables.verdict(cell(2.0, 1.5, 1.2), 2.22) == "reproduced"      # all > 0, mean 1.57 >= 1.11
    assert tables.verdict(cell(1.0, 1.2, 1.1), 2.22) == "partly"          # all > 0, mean 1.1 < 1.11
    assert tables.verdict(cell(3.0, 2.0, -0.1), 2.22) == "partly"         # a seed not positive
    assert tables.verdict(cell(3.0, -0.5, -0.1), 2.22) == "not reproduced"  # 1 of 3 positive
    assert tables.verdict(cell(-0.2, 0.1, 0.05), 2.22) == "not reproduced"  # mean <= 0
    assert tables.verdict(None, 2.22) == "not run"
    line = tables.claim_line("x", cell(2.0, 1.5, 1.2), 2.22)
    assert "+2.22" in line and "+1.57" in line and "reproduced" in line


def test_standard_setting_is_one_recipe_for_every_method():
    """At --standard every method trains the same field, sampler, samples, rays and steps; the
    methods differ only in contraction / warp / masks / embeddings, and a run without contraction
    gets a grid that covers every point it samples (the synthetic orbits' farthest camera plus
    the far plane, computed here from the generator's orbits)."""
    from jaxnerf_grid.data import synthetic
    from jaxnerf_grid.train import loop as train

    ov = settings.TRAIN_SETTINGS["standard"]["overrides"]
    cfgs = {m: train.make_config(m, merge(ov, settings.space_overrides("standard", m)))
            for m in ("ours", "nerf", "nerfw")}
    for cfg in cfgs.values():
        assert cfg.model.field.kind == "grid" and cfg.model.sampler.kind == "proposal"
        assert (cfg.model.sampler.main_samples, cfg.model.sampler.samples) == (32, (64,))
        assert cfg.model.sampler.field.density_bias == -4.0  # the demo's proposal field, kept
        assert cfg.train.batch_rays == 1024
    assert cfgs["ours"].model.use_contraction and cfgs["ours"].model.warp == "disparity"
    assert cfgs["ours"].train.use_masks
    scale = synthetic.NORMALIZATION["scale"]
    shift = np.asarray(synthetic.NORMALIZATION["translation"])
    farthest = max(np.linalg.norm((np.array([r * 1.05, 0.0, h + 1.5]) + shift) * scale)
                   for r, h, _ in synthetic._ORBITS + (synthetic._LOW_PASS,))
    for m in ("nerf", "nerfw"):
        model = cfgs[m].model
        assert not model.use_contraction and model.warp == "linear" and not cfgs[m].train.use_masks
        assert model.encoding_scale >= model.far + farthest
    # Table 2's rows without contraction get the bounded space too; rows with it do not
    assert settings.space_overrides("standard", "ours", {"model": {"use_contraction": False}})["model"]["far"] == 40.0
    assert settings.space_overrides("standard", "ours", {"model": {"use_contraction": True}}) == {}
    assert settings.space_overrides("quick", "nerf") == {}
    # every method at --standard is the recipe of its name (docs/RECIPES.md) at the setting's steps
    for m, cfg in cfgs.items():
        assert config.to_dict(cfg) == config.to_dict(recipes.make_config(m, {"train": {"max_steps": 2000}}))
    assert cfgs["ours"].train.max_steps == 2000  # RunConfig's; run_condition sets the setting's own


def test_importing_the_experiments_changes_no_environment_variable():
    """Only the scripts' entry points (`runner.cpu_defaults`) choose JAX's platform and devices."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("JAX_PLATFORMS", "XLA_FLAGS")}
    code = ("import os, sys; before = dict(os.environ)\n"
            "import experiments.table1_foreground, experiments.table2_farview, experiments.table3_methods, "
            "experiments.table4_crossover, experiments.mask_tiling, experiments.paired_rows, "
            "benchmarks.sampling_schemes\n"
            "assert dict(os.environ) == before, set(os.environ) ^ set(before)\n"
            "import jax\n"
            "from experiments import runner\n"
            "runner.cpu_defaults()\n"
            "print(os.environ['JAX_PLATFORMS'], os.environ['XLA_FLAGS'], jax.config.jax_platforms)\n")
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=settings.ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["cpu", "--xla_force_host_platform_device_count=2", "cpu"]


def test_not_run_text_names_each_label_once_by_the_seeds_it_misses():
    entries = ["a seed 0", "b seed 0", "a seed 1", "c-d seed 2", "b seed 1", "e seed 0", "a seed 2"]
    assert tables.not_run_text(entries) == "seeds 0, 1, 2: a; seeds 0, 1: b; seed 0: e; seed 2: c-d"


def test_samples_to_reach_its_own_best():
    from benchmarks import sampling_schemes as bench

    cell = lambda v: {"n": 1, "psnr": {"mean": v, "std": 0.0, "values": [v]}}  # noqa: E731
    table = {("a", 8): cell(20.0), ("a", 16): cell(22.6), ("a", 32): cell(23.0), ("a", 128): cell(23.0)}
    assert bench.samples_to_reach(table, "a", (8, 16, 32, 64, 128)) == 16  # 22.6 >= 23.0 - 0.5
    assert bench.samples_to_reach(table, "b", (8, 128)) is None
    # cells that list their seeds are compared on the seeds both ran: at 32 the mean over three
    # seeds (27.93) is within 0.5 dB of the 128-sample run's 27.5 but seed 0 alone is 0.7 short;
    # the 16-sample cell shares no seed with it and is not compared
    seeded = lambda seeds, vals: {"n": len(vals), "seeds": seeds,  # noqa: E731
                                  "psnr": {"mean": float(np.mean(vals)), "std": 0.0, "values": vals}}
    table = {("c", 16): seeded([1], [27.4]), ("c", 32): seeded([0, 1, 2], [26.8, 28.5, 28.5]),
             ("c", 64): seeded([0], [27.2]), ("c", 128): seeded([0], [27.5])}
    assert bench.samples_to_reach(table, "c", (16, 32, 64, 128)) == 64
    assert bench.gaps_text(table, "c", (16, 32, 64, 128)) == "32: -0.70 dB over 1 seed, 64: -0.30 dB over 1 seed"
    assert bench.model_overrides("log", False, 16, "standard") == {"warp": "log", "sampler": "proposal", "num_fine": 16}
    # the quarter-samples line pairs the two cells by seed, on the seeds both ran
    cells = lambda seeds, vals: {"n": len(vals), "seeds": seeds,  # noqa: E731
                                 "psnr": {"mean": float(np.mean(vals)), "std": float(np.std(vals)), "values": vals}}
    dis, lin = cells([0, 1, 2], [27.0, 26.0, 25.0]), cells([0, 2], [24.0, 24.5])
    assert bench.paired_text(dis, lin) == ", paired over seeds [0, 2]: +1.75 +- 1.25 dB (each seed +3.00, +0.50)"
    assert bench.paired_text(dis, cells([1], [20.0])) == ""
    assert bench.seeds_text(dis, cells([1], [20.0])) == " (means over 3 and 1 seeds)"
    assert bench.seeds_text(dis, dis) == ""
    table = {("disparity + proposal", 8): dis, ("linear + proposal", 32): lin}
    lines = bench.summary(table, (8, 32), "standard")
    assert lines[:2] == ["8 samples/ray: only disparity + proposal ran, 26.00 dB.",
                         "32 samples/ray: only linear + proposal ran, 24.25 dB."]
    line = [x for x in lines if x.startswith("Quarter")]
    assert line == ["Quarter-samples test: disparity + proposal at 8 samples/ray (26.00 dB) matches (within 0.1 dB) "
                    "or beats linear + proposal at 32 (24.25 dB), +1.75 dB, paired over seeds [0, 2]: +1.75 +- 1.25 dB "
                    "(each seed +3.00, +0.50)."]
    assert bench.model_overrides("log", True, 16, "standard")["num_coarse"] == 8
    # coarse/fine against proposal sampling at equal samples: paired on the seeds both ran. Seed 1
    # scores high on both (28.5 against 29.0): the difference of the means (+1.50) would credit
    # coarse/fine with the seed's scene
    hier, prop = cells([1], [28.5]), cells([0, 1, 2], [27.0, 29.0, 25.0])
    lines = bench.summary({("disparity + hierarchical", 8): hier, ("disparity + proposal", 8): prop}, (8,), "standard")
    assert ("Hierarchical resampling vs proposal sampling at equal samples per ray: -0.50 dB on average "
            "(range -0.50 to -0.50) over 1 (warp, N) pairs (each pair on the seeds both ran).") in lines
    # and the best scheme at a count is picked on the seeds every scheme there ran (seed 1: 29.0
    # against 28.5), not by means over different seeds (27.0 against 28.5)
    assert lines[0] == ("8 samples/ray: best disparity + proposal at 29.00 dB on seed [1] (the seeds every scheme "
                        "at 8 ran; +0.50 dB over the runner-up).")
    same = bench.summary({("a", 8): cells([0, 1], [20.0, 22.0]), ("b", 8): cells([0, 1], [20.5, 20.5])}, (8,))
    assert same[0] == "8 samples/ray: best a at 21.00 dB (+0.50 dB over the runner-up)."


def _fake_tables(monkeypatch, tmp_path, psnr_of):
    """Replaces training with records whose metrics come from psnr_of(label, method, overrides, seed),
    so a table's assembly (rows, paired deltas, claims, verdicts, files) is checked on known numbers."""
    def run_condition(ctx, data, method, seed, label, overrides=None, steps=None):
        v = float(psnr_of(label, method, overrides or {}, seed))
        metrics = {"mean": {"psnr": v, "ssim": 0.5}, "mean_right_half": {"psnr": v},
                   "regions_mean": {"tower": v - 3, "near_ground": v + 1, "far_background": v + 2},
                   "geometry": {"thresholds": {"0.02": {"fscore": 0.7}}}, "distractor_psnr": v, "per_view": []}
        return {"seed": seed, "run_dir": str(tmp_path / f"{label}-{seed}"), "metrics": metrics,
                "seconds_per_step": 0.1}

    monkeypatch.setattr(runner, "run_condition", run_condition)
    monkeypatch.setattr(scenes, "scene", lambda ctx, preset, seed, distractors=None, size=None: tmp_path / preset)
    monkeypatch.setattr(scenes, "mask_variant",
                        lambda ctx, scene_dir, name, *a, **k: tmp_path / f"{scene_dir.name}-{name}")
    monkeypatch.setattr(scenes, "clean_variant", lambda ctx, scene_dir: tmp_path / f"{scene_dir.name}-clean")
    monkeypatch.setattr(scenes, "mask_iou", lambda v, split="train": {"iou": 1.0, "precision": 1.0, "recall": 0.75})
    monkeypatch.setattr(runner, "enable_compile_cache", lambda path=None: None)


def test_tables_turn_known_runs_into_the_right_claims(tmp_path, monkeypatch):
    """Table 1 / 2 / 3 at --standard on fake runs with known PSNRs: the claim's effect is the paired
    difference of the right rows, and its verdict follows."""
    from experiments import table1_foreground as t1
    from experiments import table2_farview as t2
    from experiments import table3_methods as t3

    def psnr_of(label, method, overrides, seed):
        if label.startswith("t3-"):
            return {"nerf": 15.0, "nerfw": 21.0}[method] + seed  # ours: Table 1's GT + Eq. 7 run, 25 + seed
        if "DPT" in label:
            return 22.0 + seed
        if "no_masks" in label:
            return 20.5 + seed + (0.5 if seed == 1 else 0.0)  # DPT - none: 1.5, 1.0, 1.5
        if label.startswith("t2-off") or label.startswith("t2-disparity"):
            return 24.0 + seed - 0.2 * seed  # on - off: 1.0, 1.2, 1.4
        return 25.0 + seed

    _fake_tables(monkeypatch, tmp_path, psnr_of)
    monkeypatch.setattr(t1, "builtin_available", lambda: True)
    monkeypatch.setattr(t2, "far_background_share", lambda ctx, seed: 0.25)
    monkeypatch.setattr(t3, "crops_figure", lambda records, data_dir: None)
    out = tmp_path / "results"
    common_args = ["--standard", "--seeds", "3", "--cache", str(tmp_path / "cache"), "--results", str(out), "--quiet"]
    assert t1.main(common_args) == 0 and t2.main(common_args) == 0 and t3.main(common_args) == 0

    table1 = json.loads((out / "table1_foreground.json").read_text())
    assert table1["settings"]["setting"] == "standard"
    claim_a = table1["claims"][0]
    np.testing.assert_allclose(claim_a["effect"]["values"], [1.5, 1.0, 1.5])
    assert claim_a["paper_db"] == 2.22 and claim_a["verdict"] == "reproduced"
    assert {c["scene_set"].split(":")[0] for c in table1["claims"]} == {"A", "B", "A-low", "A-high"}
    gt_row = next(r for r in table1["rows"] if r["condition"] == "GT masks + Eq. 7")
    assert gt_row["aggregate"]["mask_recall"]["values"] == [0.75] * 3
    assert next(r for r in table1["rows"] if r["condition"] == "no masks")["aggregate"]["mask_recall"] is None
    dilated = [r["scene_set"].split(":")[0] for r in table1["rows"] if r["condition"] == t1.DILATED]
    assert dilated == ["B", "A-high"]  # the sets where the DPT's masks leave the tower under target
    quick = ["--quick", "--seeds", "1", "--cache", str(tmp_path / "cache"), "--results", str(tmp_path / "q"), "--quiet"]
    assert t1.main(quick) == 0  # CI's smoke setting: sets A and B, no dilated row
    rows = json.loads((tmp_path / "q" / "table1_foreground.json").read_text())["rows"]
    assert {r["scene_set"].split(":")[0] for r in rows} == {"A", "B"}
    assert t1.DILATED not in {r["condition"] for r in rows}
    row = next(r for r in table1["rows"] if r["condition"] == "no masks")
    np.testing.assert_allclose([row["aggregate"]["geometry_f"]["mean"], row["aggregate"]["psnr_tower"]["mean"]],
                               [0.7, 20.5 + 1 - 3 + 0.5 / 3])

    table2 = json.loads((out / "table2_farview.json").read_text())
    np.testing.assert_allclose(table2["claim"]["effect"]["values"], [1.0, 1.2, 1.4])
    assert table2["claim"]["verdict"] == "partly"  # all positive, mean 1.2 < 3.43 / 2
    assert table2["far_background_share_of_test_pixels"] == [0.25, 0.25, 0.25]

    table3 = json.loads((out / "table3_methods.json").read_text())
    vs_nerf, vs_nerfw, vs_check = table3["claims"]  # the check row (NeRF without the far bin) at --standard
    np.testing.assert_allclose(vs_check["effect"]["values"], [10.0, 10.0, 10.0])
    np.testing.assert_allclose(vs_nerf["effect"]["values"], [10.0, 10.0, 10.0])
    np.testing.assert_allclose(vs_nerfw["effect"]["values"], [4.0, 4.0, 4.0])
    assert vs_nerf["verdict"] == "reproduced" and vs_nerfw["verdict"] == "reproduced"
    assert "paper +10.68 dB" in (out / "table3_methods.md").read_text()


def test_poses_chain_true_pose_dataset_matches_the_registered_frames(tmp_path):
    """Chain B holds exactly chain A's frames in A's order, with the generator's poses and its
    intrinsics scaled to A's image size, and the photos scaled to that size."""
    from experiments import poses_chain
    from jaxnerf_grid.util import io

    scene, chain_a = tmp_path / "scene", tmp_path / "A"
    (scene / "images").mkdir(parents=True)
    chain_a.mkdir()
    frames = []
    for k in range(4):
        io.write_png(scene / "images" / f"v{k}.png", np.full((40, 60, 3), k / 4.0, np.float32))
        pose = np.eye(4)
        pose[0, 3] = k
        frames.append({"file_path": f"images/v{k}.png", "transform_matrix": pose.tolist()})
    io.write_json(scene / "transforms.json", {"fl_x": 50.0, "fl_y": 52.0, "cx": 30.0, "cy": 20.0, "w": 60, "h": 40,
                                              "near": 0.5, "far": 40.0, "frames": frames,
                                              "scene_normalization": {"scale": 0.05, "translation": [0, 0, -15]}})
    io.write_json(chain_a / "transforms.json",
                  {"frames": [{"file_path": "images/v3.png"}, {"file_path": "images/v1.png"}]})
    out = poses_chain.true_pose_dataset(scene, chain_a, tmp_path / "B", (30, 20))
    meta = io.read_json(out / "transforms.json")
    assert [f["file_path"] for f in meta["frames"]] == ["images/v3.png", "images/v1.png"]
    assert [f["transform_matrix"][0][3] for f in meta["frames"]] == [3.0, 1.0]
    intrinsics = (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], meta["w"], meta["h"])
    assert intrinsics == (25.0, 26.0, 15.0, 10.0, 30, 20)
    img = io.read_image(out / "images" / "v3.png")
    assert img.shape == (20, 30, 3) and abs(float(img.mean()) - 0.75) < 0.01


def test_train_only_trains_the_chosen_runs_and_reads_the_others_from_the_cache(tmp_path, monkeypatch):
    """--train-only REGEX: a run whose 'LABEL seed N' does not match is not trained (listed as not
    run), a matching one is, and a cached run is read back whether or not it matches."""
    from jaxnerf_grid.eval import evaluate
    from jaxnerf_grid.train import loop as train
    from jaxnerf_grid.train import runs

    trained = []

    def fake_train_run(data, method, run_dir, ov, steps, progress=False, dataset=None):
        trained.append(Path(run_dir).name)
        Path(run_dir).mkdir(parents=True)
        return run_dir, train.make_config(method, ov), None

    monkeypatch.setattr(runs, "train_run", fake_train_run)
    def fake_evaluate_run(run_dir, *a, **k):  # like evaluate_run, leaves metrics.json in the run
        (Path(run_dir) / "metrics.json").write_text(json.dumps({"mean": {"psnr": 20.0}}))
        return {"mean": {"psnr": 20.0}}

    monkeypatch.setattr(evaluate, "evaluate_run", fake_evaluate_run)
    monkeypatch.setattr("jaxnerf_grid.data.formats.load_dataset", lambda data, progress=False: None)
    monkeypatch.setattr(runner, "enable_compile_cache", lambda path=None: None)
    monkeypatch.setattr(runner, "seconds_per_step", lambda run_dir, batch: 0.1)
    args = runner.base_parser("t").parse_args(["--standard", "--cache", str(tmp_path / "cache"), "--results",
                                              str(tmp_path / "out"), "--quiet", "--train-only", "seed 1$"])
    ctx = runner.make_context(args, "table_x.py")
    data = tmp_path / "scene"
    assert runner.run_condition(ctx, data, "ours", 0, "t9-a") is None
    assert ctx.not_run == ["t9-a seed 0"] and trained == []
    got = runner.run_condition(ctx, data, "ours", 1, "t9-a")
    assert got["metrics"]["mean"]["psnr"] == 20.0 and not got["cached"] and len(trained) == 1
    ctx.train_only = "nothing matches this"
    again = runner.run_condition(ctx, data, "ours", 1, "t9-a")
    assert again["cached"] and len(trained) == 1 and ctx.not_run == ["t9-a seed 0"]


def test_recorded_runs_stand_in_for_a_lost_cache(tmp_path, monkeypatch):
    """A fresh clone has no experiments/.cache: the runs a committed results file lists are read
    back from it (same seed and run key = the identical run), give the same aggregate as the
    runs themselves did, and are not trained again; a run the file does not list is still
    missing, a metric whose values do not line up with the runs is not guessed, and
    --ignore-recorded trains instead."""
    from jaxnerf_grid.eval import evaluate
    from jaxnerf_grid.train import loop as train
    from jaxnerf_grid.train import runs

    trained = []

    def fake_train_run(data, method, run_dir, ov, steps, progress=False, dataset=None):
        trained.append(Path(run_dir).name)
        Path(run_dir).mkdir(parents=True)
        return run_dir, train.make_config(method, ov), None

    def fake_evaluate_run(run_dir, *a, **k):  # numbers that differ by seed, at the places eval writes them
        seed = int(Path(run_dir).name.split("-s")[-1].split("-")[0])
        m = {"mean": {"psnr": 20.0 + 1.5 * seed, "ssim": 0.5 + 0.1 * seed},
             "regions_mean": {"tower": 18.0 + seed, "far_background": 25.0 - seed},
             "geometry": {"thresholds": {"0.02": {"fscore": 0.7 + 0.05 * seed}}}}
        (Path(run_dir) / "metrics.json").write_text(json.dumps(m))
        return m

    monkeypatch.setattr(runs, "train_run", fake_train_run)
    monkeypatch.setattr(evaluate, "evaluate_run", fake_evaluate_run)
    monkeypatch.setattr("jaxnerf_grid.data.formats.load_dataset", lambda data, progress=False: None)
    monkeypatch.setattr(runner, "enable_compile_cache", lambda path=None: None)
    monkeypatch.setattr(runner, "seconds_per_step", lambda run_dir, batch: 0.1)
    monkeypatch.setattr(settings, "RESULTS", tmp_path / "results")  # not the repository's committed results
    monkeypatch.setattr(settings, "BENCH_RESULTS", tmp_path / "bench-results")

    def context(cache, *extra):
        args = runner.base_parser("t").parse_args(["--standard", "--cache", str(tmp_path / cache), "--results",
                                                  str(tmp_path / "out"), "--quiet", *extra])
        return runner.make_context(args, "table_x.py")

    data, other = tmp_path / "scene", tmp_path / "other-scene"
    ctx = context("cache-a")
    first = tables.aggregate([runner.run_condition(ctx, data, "ours", s, "t9-a") for s in (0, 1)])
    tables.write_results(ctx, "table_x", "T", {"rows": [{"condition": "a", "aggregate": first}]}, [], [])
    assert len(trained) == 2

    ctx = context("cache-b", "--train-only", "nothing matches this")  # the clone: an empty cache
    recs = [runner.run_condition(ctx, data, "ours", s, "t9-a") for s in (0, 1)]
    again = tables.aggregate(recs)
    assert len(trained) == 2 and ctx.not_run == [] and len(ctx.restored) == 2
    for k in ("psnr", "ssim", "psnr_tower", "psnr_far_background", "geometry_f", "seconds_per_step", "wall_s"):
        assert again[k]["values"] == first[k]["values"], k
    assert again["psnr"]["values"] == [20.0, 21.5] and again["seeds"] == [0, 1]
    assert again["runs"] == [str(Path(r).relative_to(settings.ROOT)) if Path(r).is_relative_to(settings.ROOT) else r
                             for r in first["runs"]]
    # not recorded: another seed, or the same seed on another dataset (another run key)
    assert runner.run_condition(ctx, data, "ours", 2, "t9-a") is None
    assert runner.run_condition(ctx, other, "ours", 0, "t9-a") is None
    assert ctx.not_run == ["t9-a seed 2", "t9-a seed 0"]
    # the written table says how many of its runs came from a results file
    tables.write_results(ctx, "table_y", "T", {"rows": []}, [], [])
    written = json.loads((tmp_path / "out" / "table_y.json").read_text())
    assert written["runs_from_results_files"] == sorted(again["runs"])

    # a metric with a value missing cannot be assigned to runs: it is left out, the others stay
    path = tmp_path / "out" / "table_x.json"
    table = json.loads(path.read_text())
    table["rows"][0]["aggregate"]["ssim"]["values"] = [0.5]
    path.write_text(json.dumps(table))
    rec = context("cache-c", "--train-only", "nothing matches this").recorded
    assert {k[0] for k in rec} == {0, 1}
    assert all("ssim" not in r["metrics"]["mean"] and "psnr" in r["metrics"]["mean"] for r in rec.values())

    ctx = context("cache-d", "--ignore-recorded")
    assert runner.run_condition(ctx, data, "ours", 0, "t9-a")["cached"] is False and len(trained) == 3


def test_recorded_runs_prefer_the_newest_file_and_read_nested_aggregates(tmp_path):
    """Two results files record one run with different numbers (a table assembled before an
    evaluation was redone): the newer file's number is kept. Aggregates are found at any depth."""
    def results(date, psnr, nested=False):
        agg = {"n": 1, "seeds": [3], "runs": ["experiments/.cache/runs/t9-b-s3-0123456789"],
               "psnr": {"mean": psnr, "std": 0.0, "values": [psnr]}}
        return {"machine": {"date_utc": date}, "rows": [{"deep": {"aggregate": agg}} if nested else {"aggregate": agg}]}

    (tmp_path / "old.json").write_text(json.dumps(results("2026-11-20T00:00:00Z", 21.0)))
    (tmp_path / "new.json").write_text(json.dumps(results("2026-11-22T00:00:00Z", 22.0, nested=True)))
    (tmp_path / "notes.json").write_text("not json")  # a stray file is skipped, not fatal
    # another benchmark's file: `machine` a sentence, a list at the top (sorted as undated, not fatal)
    (tmp_path / "other.json").write_text(json.dumps({"machine": "2-core CPU, shared", "rows": []}))
    (tmp_path / "list.json").write_text(json.dumps([1, 2]))
    got = runner.recorded_runs([tmp_path])
    assert list(got) == [(3, "0123456789")]
    assert got[(3, "0123456789")]["metrics"]["mean"]["psnr"] == 22.0
    assert got[(3, "0123456789")]["label"] == "t9-b"


def test_throughput_times_a_case_with_and_without_computed_once(tmp_path):
    # benchmarks/throughput.py's "-fused" cases trace fields.hashgrid.computed_once as a no-op:
    # the no-op must reach the traced encode (fewer dots in the HLO) and must not leak out.
    import jax

    from benchmarks import throughput
    from jaxnerf_grid.nerf.fields import hashgrid

    original = hashgrid.computed_once
    out = tmp_path / "t.json"
    throughput.main(["--configs", "demo-piecewise,demo-piecewise-fused", "--steps", "1", "--repeats", "1",
                     "--render-rays", "64", "--batch-rays", "256", "--out", str(out)])
    assert hashgrid.computed_once is original
    rows = json.loads(out.read_text())["results"]
    assert [r["config"] for r in rows] == ["demo-piecewise", "demo-piecewise-fused"]
    assert [r["batch_rays"] for r in rows] == [256, 256]  # --batch-rays over the recipe's 1024
    assert all(r["train_rays_per_s"] > 0 and r["render_rays_per_s"] > 0 for r in rows)
    x = jax.numpy.zeros((4, 3))
    cfg = hashgrid.HashConfig(num_levels=2, log2_table_size=6, min_resolution=2, max_resolution=4)
    params = hashgrid.init(jax.random.PRNGKey(0), cfg)
    dots = [jax.jit(lambda p: hashgrid.encode(p, cfg, x)).lower(params).as_text().count("dot_general")]
    with throughput._tracing_as_before(throughput.FUSED):
        dots.append(jax.jit(lambda p: hashgrid.encode(p, cfg, x)).lower(params).as_text().count("dot_general"))
    assert dots[0] == dots[1] + 1


def test_throughput_concat_case_traces_the_per_sample_colour_input_with_the_same_value():
    """The "-concat" suffix traces the colour branch as the per-sample-direction field did (the direction encoded at
    every sample): same rgb as fields.layers.first_colour_layer, one more sine per sample, and
    the module restored afterwards."""
    import jax

    from benchmarks import throughput
    from jaxnerf_grid.nerf import fields
    from jaxnerf_grid.nerf.fields import layers

    cfg = fields.grid.Config(view_depth=2, view_width=8, dir_max_deg=2, appearance_dim=3, geo_features=4)
    params = fields.init(jax.random.PRNGKey(0), cfg)
    rng = np.random.default_rng(0)
    feature = jax.numpy.asarray(rng.normal(size=(3, 5, 4)), jax.numpy.float32)
    d = jax.numpy.asarray(rng.normal(size=(3, 1, 3)), jax.numpy.float32)
    app = jax.numpy.asarray(rng.normal(size=(3,)), jax.numpy.float32)
    original = layers.first_colour_layer

    def rgb(p):
        return layers.radiance_outputs(p, cfg, jax.numpy.zeros((3, 5)), feature, d, app, None)["rgb"]

    def sine_shapes():
        jaxpr = jax.make_jaxpr(lambda p: rgb(p))(params).jaxpr  # a fresh function: no cached trace
        return [tuple(e.outvars[0].aval.shape) for e in jaxpr.eqns if e.primitive.name == "sin"]

    new, new_sines = rgb(params), sine_shapes()
    with throughput._tracing_as_before(throughput.CONCAT):
        old, old_sines = rgb(params), sine_shapes()
    assert layers.first_colour_layer is original
    np.testing.assert_allclose(np.asarray(old), np.asarray(new), atol=2e-6)
    assert old.shape == (3, 5, 3)
    # 2 octaves x 3 axes x (sin, cos): the direction encoded once per ray now, at every sample before
    assert new_sines == [(3, 1, 12)] and old_sines == [(3, 5, 12)]


def test_mask_tower_overlap_counts_a_hand_made_view():
    """Tower pixels covered, distractor recall and wholly missed regions, on a 6x8 view counted by hand."""
    from experiments import mask_tower_overlap as mto

    semantic = np.zeros((6, 8), np.int32)
    semantic[:, 0:2] = 1  # a 2-pixel-wide tower column: 12 pixels
    distractor = np.zeros((6, 8), bool)
    distractor[0:2, 1:3] = True  # a 2x2 person over the tower's edge: hides 2 tower pixels
    distractor[5, 6:8] = True  # a 2-pixel bird nobody masked
    mask = np.zeros((6, 8), bool)
    mask[0:3, 1:3] = True  # covers the person (4) and one visible tower pixel (row 2, col 1)
    got = mto.frame_counts(mask, distractor, semantic)
    np.testing.assert_array_equal(got, [10, 1, 6, 4, 2, 2])


def test_mask_tower_overlap_rules_spare_tower_pixels_by_hand():
    """rule_masks on four hand-made pixels: a clear person, a person-vs-tower tie the argmax gives
    the tower, a pixel over T with tower probability 0.15, and a clear tower."""
    from experiments import mask_tower_overlap as mto

    prob = np.zeros((1, 4, 9))
    prob[0, 0, 6] = 1.0                                    # person: masked by every rule
    prob[0, 1, [6, 8, 1]] = [0.3, 0.25, 0.45]              # C 0.55, argmax tower
    prob[0, 2, [7, 1, 3]] = [0.8, 0.15, 0.05]              # C 0.8, P(tower) 0.15
    prob[0, 3, 1] = 1.0                                    # tower: never masked
    got = {k: v[0].tolist() for k, v in mto.rule_masks(prob).items()}
    assert got == {"C > T": [True, True, True, False],
                   "C > T, argmax not tower": [True, False, True, False],
                   "C > T, P(tower) < 0.1": [True, False, False, False],
                   "C > T, P(tower) < 0.2": [True, False, True, False]}


def test_paired_rows_differences_by_seed():
    """experiments.paired_rows: OTHER - BASE per seed both ran, matched on the row's labels."""
    from experiments import paired_rows as pr

    def row(cond, seeds, psnr):
        return {"scene_set": "B", "condition": cond,
                "aggregate": {"seeds": seeds, "psnr": {"mean": float(np.mean(psnr)), "std": 0.0, "values": psnr}}}
    base = {"rows": [row("dpt", [0, 1, 2], [20.0, 21.0, 22.0]), row("gt", [0], [25.0])]}
    other = {"rows": [row("dpt", [1, 2, 0], [21.5, 22.1, 20.3]), row("gt", [3], [26.0]), row("new", [0], [1.0])]}
    got = {(c["row"], c["metric"]): c for c in pr.paired_rows(base, other, metrics=("psnr",))}
    assert set(got) == {("B / dpt", "psnr"), ("B / gt", "psnr")}  # "new" is not in the base
    d = got[("B / dpt", "psnr")]["delta"]
    assert d["values"] == pytest.approx([0.3, 0.5, 0.1])  # seeds 0, 1, 2, whatever the order in the file
    assert d["mean"] == pytest.approx(0.3) and d["std"] == pytest.approx(np.std([0.3, 0.5, 0.1]))
    assert got[("B / gt", "psnr")]["delta"] is None  # no seed in common
    assert [c["row"] for c in pr.paired_rows(base, other, ("psnr",), rows="gt")] == ["B / gt"]


def test_paired_rows_within_one_file_by_label_replacement(capsys, tmp_path):
    """experiments.paired_rows --replace: two rows of one results file (integer fields are part of
    the label), NEW row minus OLD row per shared seed, population std as the tables' Δ columns."""
    from experiments import paired_rows as pr

    def row(scheme, n, seeds, psnr):
        return {"scheme": scheme, "samples_per_ray": n,
                "aggregate": {"seeds": seeds, "psnr": {"mean": float(np.mean(psnr)), "std": 0.0, "values": psnr}}}
    results = {"rows": [row("log + hierarchical", 16, [0, 1, 2], [23.0, 24.0, 22.0]),
                        row("log + proposal", 16, [2, 0, 1], [25.0, 26.0, 26.5]),
                        row("log + hierarchical", 32, [0], [25.0]),
                        row("log + proposal", 32, [1], [27.0]),
                        row("log + proposal", 64, [0], [28.0])]}
    got = pr.paired_rows(results, results, ("psnr",), replace=("hierarchical", "proposal"))
    assert [(c["row"], c["other_row"]) for c in got] == [
        ("log + hierarchical / 16", "log + proposal / 16"), ("log + hierarchical / 32", "log + proposal / 32")]
    want = [26.0 - 23.0, 26.5 - 24.0, 25.0 - 22.0]           # seeds 0, 1, 2
    assert got[0]["delta"]["values"] == pytest.approx(want)
    assert got[0]["delta"]["std"] == pytest.approx(np.std(want))  # population std, ddof=0
    assert got[1]["delta"] is None                            # seeds 0 and 1: none shared
    assert pr.paired_rows(results, results, ("psnr",), rows="/ 32", replace=("hierarchical", "proposal"))[0]["row"] \
        == "log + hierarchical / 32"

    path = tmp_path / "r.json"
    path.write_text(json.dumps(results))
    assert pr.main([str(path), "--replace", "hierarchical", "proposal", "--metrics", "psnr"]) == 0
    out = capsys.readouterr().out
    assert "log + proposal / 16  against  log + hierarchical / 16" in out and "+2.833 ± 0.236" in out
    assert pr.main([str(path), "--replace", "nothing", "else", "--metrics", "psnr"]) == 1
    with pytest.raises(SystemExit):
        pr.main([str(path)])                                  # one file needs --replace


def test_throughput_variant_is_its_base_with_the_set_changes():
    """--variant NAME=BASE:KEY=VALUE;KEY=VALUE: the base's settings with those keys changed, the
    keys checked as --set checks them."""
    from benchmarks import throughput
    from jaxnerf_grid.config.schema import ConfigError

    name, base, changes = throughput.parse_variant(
        "m24=ours-fast:model.sampler.main_samples=24;model.field.grid.num_levels=8")
    assert (name, base) == ("m24", "ours-fast")
    assert changes == {"model": {"sampler": {"main_samples": 24}, "field": {"grid": {"num_levels": 8}}}}
    merged = throughput.merge(throughput.CONFIGS[base], changes)
    assert merged["model"]["sampler"]["samples"] == throughput.CONFIGS["ours-fast"]["model"]["sampler"]["samples"]
    assert merged["model"]["field"]["grid"]["log2_table_size"] == 17
    for bad in ("m24=nope:model.sampler.main_samples=24", "m24=ours-fast:model.sampler.mian_samples=24", "m24"):
        with pytest.raises(ConfigError):
            throughput.parse_variant(bad)


def _recorded_strict_run(seed_dir: str):
    """A run of the twenty-eighth session as its experiment.json records it: (dataset folder
    name, method, overrides, steps, the key in its folder's name)."""
    root = Path(__file__).resolve().parents[2] / "benchmarks/results/table1_strict_readmit" / seed_dir
    info = json.loads((root / "experiment.json").read_text())
    return Path(info["data"]).name, info["method"], info["overrides"], info["steps"], seed_dir.rsplit("-", 1)[1]


@pytest.mark.parametrize("seed_dir", ["t1-tower-small-built-in_DPT_masks__Eq_7__robust-strict-s0-a916966803",
                                      "t1-plad-like-built-in_DPT_masks__Eq_7__robust-strict-s1-48dd7ed14d"])
def test_run_keys_find_a_strict_run_under_its_older_key_and_the_default_now_means_it(tmp_path, seed_dir):
    """The keys of the committed runs made with robust_strict_readmit=true are the keys the code
    of that session gave (the folders' names); the default (None) on a dataset whose masks
    `mask` judged in their domain finds them, and so does the explicit setting, while off, out of
    the domain, or the automatic value on out-of-domain masks does not. In `robust` mode
    (nothing flagged) the setting leaves the key alone."""
    name, method, overrides, steps, recorded = _recorded_strict_run(seed_dir)
    data = tmp_path / name
    data.mkdir()

    def keys(strict, out_of_domain, robust="dpt+robust"):
        (data / "transforms.json").write_text(json.dumps({"mask_domain": {"out_of_domain": out_of_domain}}))
        ov = merge(overrides, {"train": {"robust_strict_readmit": strict, "robust": robust}})
        return runner.run_keys(data, method, ov, steps)

    assert recorded in keys(True, False) and recorded in keys(None, False) and recorded in keys(True, True)
    assert keys(None, False) == keys(True, False) == keys(True, True)
    for strict, out in ((False, False), (None, True), (False, True)):
        assert recorded not in keys(strict, out)
        assert keys(strict, out) == keys(False, False)
    assert keys(None, False, "robust") == keys(True, True, "robust") == keys(False, False, "robust")
    assert keys(None, False)[0] != keys(False, False)[0]  # a new strict run is made under its own key


def _condition(setting: str, method: str, robust: str | None = None, mlp: bool = False) -> dict:
    """A table's overrides as run_condition assembles them: the setting's, its space, the
    condition's own (the older flat robust keys, as the tables give them)."""
    from experiments import table3_methods

    own = table3_methods.mlp_field(settings.TRAIN_SETTINGS[setting]["overrides"]) if mlp else {}
    if robust:
        own = merge(own, {"train": {"robust": robust, "robust_patch": 8}})
    base = json.loads(json.dumps(settings.TRAIN_SETTINGS[setting]["overrides"]))
    return merge(merge(base, settings.space_overrides(setting, method, own)), own)


# Keys computed by the code before the field kinds and train.robust were nested (the configs
# hashed in their older layout): a run keeps its key, so the results files keep finding it.
PINNED_KEYS = [("standard", "ours", None, False, 100, "7d3d6ed2df"),
               ("standard", "nerfw", "dpt+robust", False, 100, "97a1d29bd5"),
               ("quick", "nerf", "robust", False, 100, "6c13e446ca"), ("full", "ours", None, False, 100, "3291fc7714"),
               ("standard", "nerf", None, True, 1200, "ab963bc97d"), ("quick", "ours", None, True, 1200, "2573dbb0cd")]


@pytest.mark.parametrize("setting, method, robust, mlp, steps, key", PINNED_KEYS)
def test_run_keys_hash_the_older_layout_and_the_builder_gives_the_hashed_config(tmp_path, setting, method, robust,
                                                                                mlp, steps, key):
    """run_key hashes the resolved config in the layout of the committed runs (flat robust keys,
    every field kind's keys), and run_condition's config through config.build is that config."""
    from jaxnerf_grid.config import run_config

    data = tmp_path / "tower-small"
    data.mkdir()
    ov = _condition(setting, method, robust, mlp)
    assert runner.run_keys(data, method, ov, steps)[0] == key
    built = runner.condition_config(setting, method, ov, steps)
    assert built.config() == run_config.make_config(method, merge(ov, {"train": {"max_steps": steps}}))
