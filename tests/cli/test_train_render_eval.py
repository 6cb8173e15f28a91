"""The train / render / eval subcommands end to end on a tiny dataset written to disk."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.data.formats import save_transforms_json
from jaxnerf_grid.util import io
from tests.train.test_loop import TINY_FIELD, tiny_dataset

# the paper's MLP setting, which TINY shrinks (`train` alone trains the grid recipe `ours`)
PAPER_MLP = ["--recipe", "ours-paper-mlp"]
TINY = {"model": {"field": TINY_FIELD, "num_coarse": 8, "num_fine": 8},
        "train": {"batch_rays": 64, "max_steps": 30, "checkpoint_every": 10, "log_every": 5, "warmup": 5,
                  "lr_init": 5e-3, "lr_final": 1e-3, "chunk": 256, "num_devices": 2}}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    ds = tiny_dataset()
    ds.frame_paths = [f"images/frame_{i:03d}.png" for i in range(ds.num_frames)]
    sem = np.zeros(ds.images.shape[:3], np.uint8)
    sem[:, 4:8, 6:10] = 1      # a "tower" patch
    sem[:, 9:, :] = 3          # "ground" rows
    ds.semantics = sem
    ds.clean_images = ds.images.copy()
    ds.distractor_masks = np.zeros(ds.images.shape[:3], bool)
    ds.distractor_masks[:, 2:4, 2:4] = True
    ds.depth = np.full(ds.images.shape[:3], 3.0, np.float32)
    out = tmp_path_factory.mktemp("tiny") / "data"
    save_transforms_json(ds, out)
    # a reference tower cloud named by transforms.json, as the synthetic datasets have
    io.write_ply(out / "tower.ply", np.random.default_rng(0).uniform(-0.3, 0.3, (500, 3)))
    meta = io.read_json(out / "transforms.json")
    io.write_json(out / "transforms.json", {**meta, "tower_ply": "tower.ply"})
    return out


def test_train_render_eval(data_dir, tmp_path, capsys):
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(json.dumps(TINY))
    run = tmp_path / "run"
    assert cli.main(["train", *PAPER_MLP, "--data", str(data_dir), "--method", "ours", "--config", str(cfg_file),
                     "--out", str(run), "--quiet"]) == 0
    saved = json.loads((run / "config.json").read_text())
    assert saved["model"]["method"] == "ours" and saved["model"]["warp"] == "disparity"
    assert saved["model"]["field"]["width"] == 32 and saved["train"]["use_masks"] is True
    assert len(list((run / "checkpoints").glob("ckpt_*.npz"))) == 3   # steps 10, 20, 30 (keep 3)
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 6
    assert cli.main(["render", "--run", str(run), "--quiet"]) == 0
    names = sorted(x.stem for x in (run / "renders").glob("*.png"))
    assert len(names) == 1 and (run / "depth" / f"{names[0]}.exr").is_file()
    assert (run / "opacity" / f"{names[0]}.png").is_file()
    assert cli.main(["eval", "--run", str(run), "--quiet"]) == 0
    m = json.loads((run / "metrics.json").read_text())
    assert m["num_views"] == 1 and m["lpips"] == "unavailable" and m["mean"]["lpips"] is None
    assert set(m["regions_mean"]) == {"tower", "near_ground", "far_background"}
    view = m["per_view"][0]
    # the stored PSNR is the PSNR of the written render against the target (8-bit rounding aside)
    from jaxnerf_grid.util.io import read_image
    pred = read_image(run / "renders" / f"{names[0]}.png")
    from jaxnerf_grid.train.runs import load_dataset
    target = load_dataset(data_dir, progress=False).clean_images[4]   # the target as stored (8-bit)
    ref = -10 * np.log10(np.mean((pred - target) ** 2))
    # rounding the render to 8 bits adds about 1 / (12 * 255^2) to an MSE of ~0.02: ~0.002 dB
    assert abs(ref - view["psnr"]) < 0.01
    assert m["distractor_psnr"] is not None and np.isfinite(m["distractor_psnr"])
    report = (run / "report.md").read_text()
    assert "| PSNR |" in report and "report_views.png" in report and (run / "report_views.png").is_file()
    assert (run / "report_crops.png").is_file()   # the "tower" patch gives a crop
    assert (run / "tower_points.ply").is_file()
    geo = m["geometry"]            # against the dataset's tower.ply
    assert set(geo) >= {"thresholds", "chamfer", "num_pred", "num_ref", "box", "reference"}
    assert set(geo["thresholds"]) == {"0.01", "0.02", "0.05"} and geo["reference"].endswith("tower.ply")
    assert 0 < geo["num_ref"] <= 500 and "## Tower geometry" in report
    # (the scoring itself, F = 1 for equal clouds: test_geometry.py::test_score_geometry_of_a_dataset)
    assert cli.main(["eval", "--run", str(run), "--quiet", "--reference-ply", str(tmp_path / "no.ply")]) == 1
    assert "no.ply" in capsys.readouterr().err    # refused before rendering
    # resuming the finished run is a no-op; a different config is refused
    assert cli.main(["train", *PAPER_MLP,
                     "--data", str(data_dir), "--config", str(cfg_file), "--out", str(run), "--quiet"]) == 0
    assert cli.main(["train", *PAPER_MLP, "--data", str(data_dir), "--method", "nerf", "--config", str(cfg_file),
                     "--out", str(run), "--quiet"]) == 1
    assert "different config" in capsys.readouterr().err


def test_bad_config_key_is_one_line_error(data_dir, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"model": {"num_corase": 4}}))
    assert cli.main(["train", *PAPER_MLP,
                     "--data", str(data_dir), "--config", str(bad), "--out", str(tmp_path / "r")]) == 1
    assert "num_corase" in capsys.readouterr().err


def test_lift_view_recovers_points_on_a_plane():
    """clouds.lift_view against a closed form: a camera at z = 0.8 looking down at the plane z = 0."""
    import jax.numpy as jnp

    from jaxnerf_grid import export
    from jaxnerf_grid.nerf import rays as rays_lib
    from jaxnerf_grid.render import clouds

    c2w = rays_lib.look_at([0.0, 0.0, 0.8], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    r = rays_lib.generate_rays(jnp.asarray(c2w), 10.0, 10.0, 8.0, 6.0, 16, 12)
    depth = np.full((12, 16), 0.8, np.float32)      # z-depth of the plane everywhere
    pts, cols = clouds.lift_view(r, np.ones((12, 16, 3)), depth, np.ones((12, 16)), radius=1.0)
    assert len(pts) == 16 * 12
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-5)
    metric = export.to_metric(pts, {"scale": 0.05, "translation": [0, 0, -15.0]})
    np.testing.assert_allclose(metric[:, 2], 15.0, atol=1e-3)


def test_demo_runs_the_recipe_on_a_given_dataset(data_dir, tmp_path, capsys):
    """`demo --data`: no synth, no mask (the dataset has weights), the demo recipe (grid field,
    proposal sampler) trained and evaluated; a bad --data is a one-line error."""
    import shutil

    from jaxnerf_grid import demo

    data = tmp_path / "data"
    shutil.copytree(data_dir, data)
    meta = io.read_json(data / "transforms.json")
    assert any("weight_path" in f for f in meta["frames"])  # so the demo must skip `mask`
    rc = cli.main(["demo", "--data", str(data), "--out", str(tmp_path / "demo"), "--steps", "2", "--quiet",
                   "--no-video"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "demo done" in out and "synth" not in out and "mask " not in out
    assert not (tmp_path / "demo" / "run" / "videos").exists() and "video" not in out   # --no-video
    cfg = io.read_json(tmp_path / "demo" / "run" / "config.json")
    assert cfg["model"]["field"]["kind"] == "grid" and cfg["model"]["sampler"]["kind"] == "proposal"
    assert cfg["train"]["max_steps"] == 2
    m = io.read_json(tmp_path / "demo" / "run" / "metrics.json")
    assert m["step"] == 2 and m["geometry"] is not None
    report = (tmp_path / "demo" / "run" / "report.md").read_text()
    # the budget's record: the steps the user gave, 2 x 1024 rays over 4 training frames of 16x12
    assert m["budget"]["rule"] == "given" and m["budget"]["train_pixels"] == 4 * 16 * 12
    assert "Training budget: 2 steps x 1024 rays, 2.67 epochs" in report
    assert "sampling in s: proposal 64 -> 24 main, 88 samples per ray, opaque far bin" in report
    assert "hash grid, 8 levels x 2 features" in report and "Tower geometry" in report
    assert m["cloud_views"]["test"] == [4] and m["cloud_views"]["train"] == [0, 1, 2, 3]  # 16 asked, 4 exist
    assert meta == io.read_json(data / "transforms.json")  # the dataset was not touched
    assert demo.DEMO_CONFIG["model"]["sampler"]["kind"] == "proposal"
    assert cli.main(["demo", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "x")]) == 1
    assert "--data is not a folder" in capsys.readouterr().err


def test_demo_takes_the_bounds_a_dataset_records(data_dir, tmp_path, capsys):
    """A dataset with `scene_bounds` (docs/BOUNDS.md): its near / far / contract_radius replace the
    recipe's, --set still wins, the report says where they came from; a bad record is a one-line
    error naming the file and key."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(data_dir, data)
    meta = io.read_json(data / "transforms.json")
    meta["scene_bounds"] = {"near": 0.6, "far": 300.0, "contract_radius": 1.5, "roi_radius": 1.0,
                            "roi_centre": [0.0, 0.0, 0.0], "nearest_camera_to_roi": 0.7}
    io.write_json(data / "transforms.json", meta)
    rc = cli.main(["demo", "--data", str(data), "--out", str(tmp_path / "demo"), "--steps", "1", "--quiet",
                   "--set", "model.far=400", "--no-video"])
    assert rc == 0, capsys.readouterr().err
    cfg = io.read_json(tmp_path / "demo" / "run" / "config.json")
    assert (cfg["model"]["near"], cfg["model"]["far"], cfg["model"]["contract_radius"]) == (0.6, 400.0, 1.5)
    assert "Scene bounds from the data" in (tmp_path / "demo" / "run" / "report.md").read_text()
    meta["scene_bounds"]["near"] = "close"
    io.write_json(data / "transforms.json", meta)
    assert cli.main(["demo", "--data", str(data), "--out", str(tmp_path / "demo2"), "--steps", "1", "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(data / "transforms.json") in err and "scene_bounds.near" in err


def test_train_takes_near_far_and_radius_from_the_datasets_scene_bounds(data_dir, tmp_path, capsys):
    """A dataset recording scene_bounds (as `poses` writes them) sets model.near / far /
    contract_radius of a contracted recipe; --set wins over them; the bounded `nerf` recipe,
    whose far plane is its own, keeps its constants."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(data_dir, data)
    meta = io.read_json(data / "transforms.json")
    recorded = {"near": 0.7, "far": 333.0, "contract_radius": 2.5, "roi_centre": [0.0, 0.0, 0.0], "roi_radius": 1.0}
    io.write_json(data / "transforms.json", {**meta, "scene_bounds": recorded})
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(json.dumps({"train": {**TINY["train"], "max_steps": 1, "checkpoint_every": 1}}))

    def trained(name, *extra):
        assert cli.main(["train", *PAPER_MLP, "--data", str(data), "--config", str(cfg_file), "--out",
                         str(tmp_path / name), "--quiet", *extra]) == 0
        return json.loads((tmp_path / name / "config.json").read_text())["model"]

    model = trained("a")
    assert (model["near"], model["far"], model["contract_radius"]) == (0.7, 333.0, 2.5)
    assert "Scene bounds from the data" in capsys.readouterr().out
    assert trained("b", "--set", "model.near=0.4")["near"] == 0.4
    nerf = trained("c", "--recipe", "nerf")
    assert (nerf["near"], nerf["far"]) != (0.7, 333.0) and nerf["use_contraction"] is False


def test_the_demo_cloud_keeps_its_16_views_on_tower_small_and_4_on_a_real_capture():
    """clouds.views_within with the demo's budget: 16 views at 160x120 (the synthetic demo is
    unchanged), 4 at 614x410 (fountain-P11's working size), never fewer than 2 nor more than asked."""
    from jaxnerf_grid import demo
    from jaxnerf_grid.render import clouds

    within = lambda w, h: clouds.views_within(demo.DEMO_CLOUD_VIEWS, demo.DEMO_CLOUD_PIXELS, w, h)  # noqa: E731
    assert within(160, 120) == 16
    assert within(614, 410) == 4                   # 2**20 // 251740
    assert within(3072, 2048) == 2
    assert clouds.views_within(3, 10 ** 9, 10, 10) == 3


def test_demo_trains_on_one_device_when_it_spreads_rendering_over_the_cores():
    """cli.demo adds train.num_devices=1 only where it forced one CPU device per core itself, on
    the CPU, and the user named no train.num_devices."""
    from jaxnerf_grid.cli.demo import sets_training_on_one_device as one

    assert one(None, True, "cpu") == ["train.num_devices=1"]
    assert one(["train.batch_rays=512"], True, "cpu") == ["train.batch_rays=512", "train.num_devices=1"]
    assert one(["train.num_devices=2"], True, "cpu") == ["train.num_devices=2"]  # the user's choice
    assert one([" train.num_devices =0"], True, "cpu") == [" train.num_devices =0"]
    assert one(['train={"num_devices": 2}'], True, "cpu") == ['train={"num_devices": 2}']  # the section set
    assert one(None, False, "cpu") == []            # XLA_FLAGS named a device count: as before
    assert one(None, True, "gpu") == []             # the CPU flag does not touch GPUs: all of them train


def test_demo_without_a_device_count_renders_on_every_core_and_trains_on_one(data_dir, tmp_path):
    """`jaxnerf-grid demo` in a fresh process with no device count in XLA_FLAGS (as README
    command 1 runs): training on one device (config.json), the run still completes."""
    import os
    import shutil
    import subprocess

    data = tmp_path / "data"
    shutil.copytree(data_dir, data)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    probe = subprocess.run([sys.executable, "-c", "import os; from jaxnerf_grid.cli.render import use_every_cpu_core; "
                            "use_every_cpu_core(cores=2); import jax; print(jax.local_device_count())"],
                           env=env, capture_output=True, text=True, timeout=600)
    assert probe.stdout.strip() == "2", probe.stderr  # the flag reaches a fresh process's CPU backend
    done = subprocess.run([sys.executable, "-m", "jaxnerf_grid", "demo", "--data", str(data), "--out",
                           str(tmp_path / "demo"), "--steps", "2", "--quiet", "--no-video"],
                          env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert io.read_json(tmp_path / "demo" / "run" / "config.json")["train"]["num_devices"] == 1


def test_train_without_steps_takes_the_budgets_steps_and_records_why(data_dir, tmp_path, capsys, monkeypatch):
    """No --steps: the budget chooses (here --minutes so short that one step fits: 0.0001 min x 60 x
    11000 rays/s / 64 rays = 1.03 steps, at the reference speed: the step is not timed here), the
    schedules follow, and budget.json says why."""
    from jaxnerf_grid.config import budget

    monkeypatch.setattr(budget, "MEASURE_SHARE", float("inf"))
    cfg_file = tmp_path / "cfg.json"
    train_keys = {k: v for k, v in TINY["train"].items() if k != "max_steps"}
    cfg_file.write_text(json.dumps({**TINY, "train": train_keys}))
    run = tmp_path / "run"
    assert cli.main(["train", *PAPER_MLP, "--data", str(data_dir), "--config", str(cfg_file), "--out", str(run),
                     "--quiet", "--minutes", "0.0001"]) == 0
    out = capsys.readouterr().out
    assert "Training budget: 1 steps x 64 rays" in out and "fewer than the recipe's 2000" in out
    saved = json.loads((run / "config.json").read_text())
    assert saved["train"]["max_steps"] == 1 and saved["train"]["warmup"] == 0    # 5 x 1 / 2000, rounded
    rec = json.loads((run / "budget.json").read_text())
    assert (rec["rule"], rec["limited_by"], rec["steps"], rec["train_pixels"]) == ("budget", "minutes", 1, 4 * 16 * 12)
    assert cli.main(["train", "--data", str(data_dir), "--out", str(tmp_path / "r2"), "--minutes", "0"]) == 1
    assert "--minutes = 0" in capsys.readouterr().err


def test_train_and_demo_plan_their_steps_at_the_measured_speed_and_a_resumed_run_at_its_recorded_one(
        data_dir, tmp_path, capsys, monkeypatch):
    """With the time cap able to bind (MEASURE_SHARE 0 here), `train` times its step and fits the
    steps to the minutes at that speed: 0.05 min x 60 x 640 rays/s / 64 rays = 30 steps (the
    reference 11k would give 500); run again on the same folder it plans at the recorded speed
    without timing, so it resumes the same run; `demo` hands its run folder's planner to the budget."""
    from jaxnerf_grid import demo
    from jaxnerf_grid.config import budget
    from jaxnerf_grid.train import speed

    monkeypatch.setattr(budget, "MEASURE_SHARE", 0.0)
    monkeypatch.setattr(speed, "measure", lambda cfg, seconds=speed.SECONDS: 640.0)
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(json.dumps({**TINY, "train": {k: v for k, v in TINY["train"].items() if k != "max_steps"}}))
    run = tmp_path / "run"
    args = ["train", *PAPER_MLP, "--data", str(data_dir), "--config", str(cfg_file), "--out", str(run),
            "--minutes", "0.05"]
    assert cli.main(args) == 0
    assert "timing the training step on this machine" in capsys.readouterr().out
    rec = json.loads((run / "budget.json").read_text())
    assert (rec["steps"], rec["rays_per_second"], rec["speed_source"]) == (30, 640.0, speed.MEASURED)

    def never(cfg, seconds=speed.SECONDS):
        raise AssertionError("the resumed run timed its step again")

    monkeypatch.setattr(speed, "measure", never)
    assert cli.main(args) == 0
    assert json.loads((run / "config.json").read_text())["train"]["max_steps"] == 30

    class Trained(Exception):
        pass

    def stop(data, method, run_dir, overrides, *rest, **kwargs):
        raise Trained(overrides, kwargs["budget"])

    monkeypatch.setattr(demo.runs, "train_run", stop)
    monkeypatch.setattr(speed, "measure", lambda cfg, seconds=speed.SECONDS: 640.0)
    with pytest.raises(Trained) as caught:
        demo.run_demo(data_dir, tmp_path / "demo", minutes=0.05, progress=False)
    overrides, rec = caught.value.args
    # the demo's recipe trains 1024 rays a step: 0.05 x 60 x 640 / 1024 = 1.9 -> 1 step
    assert overrides["train"]["max_steps"] == rec["steps"] == 1 and rec["speed_source"] == speed.MEASURED


def test_eval_of_an_appearance_model_scores_whole_views_with_the_mean_embedding_or_right_halves(data_dir, tmp_path,
                                                                                                 capsys):
    """With train.appearance_steps 0 the held-out view renders with the mean of the training
    photos' embeddings and the whole view is the headline; with steps it is NeRF-W's right half."""
    from jaxnerf_grid.train.runs import load_dataset
    from jaxnerf_grid.util.io import read_image

    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(json.dumps(TINY))
    run = tmp_path / "run"
    assert cli.main(["train", *PAPER_MLP, "--data", str(data_dir), "--config", str(cfg_file), "--out", str(run),
                     "--set", "model.use_appearance=true", "--set", "train.max_steps=10", "--quiet"]) == 0
    target = load_dataset(data_dir, progress=False).clean_images[4]
    assert cli.main(["eval", "--run", str(run), "--appearance-steps", "0", "--quiet"]) == 0
    m = json.loads((run / "metrics.json").read_text())
    pred = read_image(next((run / "renders").glob("*.png")))
    whole = -10 * np.log10(np.mean((pred - target) ** 2))
    assert abs(m["mean"]["psnr"] - whole) < 0.01 and "mean of the training photos'" in m["protocol"]
    half = target.shape[1] // 2
    right = -10 * np.log10(np.mean((pred[:, half:] - target[:, half:]) ** 2))
    assert abs(m["mean_right_half"]["psnr"] - right) < 0.01 and abs(whole - right) > 0.05
    assert cli.main(["eval", "--run", str(run), "--quiet"]) == 0   # the run's own 30 steps: NeRF-W
    m = json.loads((run / "metrics.json").read_text())
    assert m["mean"]["psnr"] == m["mean_right_half"]["psnr"] and "NeRF-W" in m["protocol"]
    capsys.readouterr()
    assert cli.main(["eval", "--run", str(run), "--appearance-steps", "-1", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "--appearance-steps" in err and len(err.strip().splitlines()) == 1


def test_demo_on_a_capture_from_poses_trains_its_masks_and_an_appearance_embedding(data_dir, tmp_path,
                                                                                 monkeypatch):
    """`demo --data` with masks "auto" on a dataset `poses` registered (its "poses" record) trains
    its DPT masks without the photometric evidence, and an appearance embedding; the same dataset
    without the record trains its masks alone, without one."""
    import shutil

    from jaxnerf_grid import demo

    class Trained(Exception):
        pass

    def stop(data, method, run_dir, overrides, *args, **kwargs):
        raise Trained(overrides)

    monkeypatch.setattr(demo.runs, "train_run", stop)
    trained = {}
    for name, record in (("capture", {"photos": 5, "registered": 5}), ("generated", None)):
        data = tmp_path / name
        shutil.copytree(data_dir, data)
        meta = io.read_json(data / "transforms.json")
        meta.pop("poses", None)
        if record is not None:
            meta["poses"] = record
        io.write_json(data / "transforms.json", meta)
        with pytest.raises(Trained) as caught:
            demo.run_demo(data, tmp_path / f"out_{name}", steps=1, progress=False)
        trained[name] = caught.value.args[0]
    assert (trained["capture"]["train"].get("robust", {}).get("mode", "off") == "off"
            and trained["capture"]["train"]["use_masks"])
    assert (trained["generated"]["train"].get("robust", {}).get("mode", "off") == "off"
            and trained["generated"]["train"]["use_masks"])
    # the capture trains a per-photo appearance embedding; the generated scene keeps the recipe's colour
    assert trained["capture"]["model"]["use_appearance"] is True
    assert trained["capture"]["train"]["appearance_steps"] == 0  # held-out views: the mean embedding, no fit
    assert not trained["generated"].get("model", {}).get("use_appearance", False)
