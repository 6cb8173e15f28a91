"""The bad-input corpus (docs/RELIABILITY.md): every broken dataset, config and flag,
built from one tiny `synth` scene and one tiny finished run, goes through the real CLI entry
point (`jaxnerf_grid.cli.main`). Each case asserts a non-zero exit, one line of error naming the
file or key, no traceback, and that no file that was there before is lost or changed.

A fault-injection test kills `mask --overwrite` (SIGKILL) while it writes and while it swaps the
new set in, and checks that the dataset then holds the old mask set or the new one, never a mix.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.masks import write as masking
from jaxnerf_grid.train import runs
from jaxnerf_grid.util import io, staging
from tests.support.killing import kill_when

ROOT = Path(__file__).resolve().parents[2]

# a 2x32 MLP, 8 + 8 samples, 64 rays, 10 steps: the whole run takes seconds
# the paper's MLP setting, which TINY shrinks (`train` alone trains the grid recipe `ours`)
PAPER_MLP = ["--recipe", "ours-paper-mlp"]
TINY = {"model": {"field": {"depth": 2, "width": 32, "skip": 0, "view_width": 16},
                  "sampler": {"kind": "hierarchical", "samples": [8, 8]}},
        "train": {"batch_rays": 64, "max_steps": 10, "checkpoint_every": 5, "log_every": 5, "warmup": 2,
                  "chunk": 512}}
SYNTH = ["--width", "32", "--height", "24", "--num-train", "6", "--num-test", "2", "--supersample", "1",
         "--workers", "1", "--quiet"]


def snapshot(*roots: Path) -> dict:
    """{path: sha256 of the file} of every file under the roots (directories as "dir")."""
    out = {}
    for root in roots:
        if root.is_file():
            out[str(root)] = hashlib.sha256(root.read_bytes()).hexdigest()
            continue
        for p in sorted(root.rglob("*")):
            out[str(p)] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def run_cli(argv: list[str], capsys) -> tuple[int, str]:
    """(exit code, stderr) of cli.main(argv); argparse's SystemExit counts as its code."""
    capsys.readouterr()
    try:
        rc = cli.main([str(a) for a in argv])
    except SystemExit as exit_:
        rc = exit_.code if isinstance(exit_.code, int) else 1
    return rc, capsys.readouterr().err


def assert_one_line_error(rc: int, err: str, *names: str) -> str:
    """A non-zero exit, no traceback, one line of error naming each of `names`."""
    assert rc != 0, err
    assert "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1, err
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """{"data": a tiny synth scene, "run": a finished 10-step run on it, "cfg": TINY's file,
    "tmp": a scratch folder}; shared by every case, which must leave them unchanged."""
    tmp = tmp_path_factory.mktemp("bad_input")
    data, run, cfg = tmp / "data", tmp / "run", tmp / "tiny.json"
    assert cli.main(["synth", "--out", str(data), *SYNTH]) == 0
    cfg.write_text(json.dumps(TINY))
    assert cli.main(["train", *PAPER_MLP,
                     "--data", str(data), "--method", "nerf", "--config", str(cfg), "--out", str(run),
                     "--quiet"]) == 0
    return {"data": data, "run": run, "cfg": cfg, "tmp": tmp}


def config_file(scene, name: str, change: dict) -> Path:
    """TINY with `change` merged in, written as <name>.json (NaN / Infinity as JSON allows)."""
    from jaxnerf_grid.config.schema import merge

    path = scene["tmp"] / f"{name}.json"
    path.write_text(json.dumps(merge(TINY, change)))
    return path


# (case id, config change, words the error must name)
BAD_CONFIGS = [
    ("batch_rays_0", {"train": {"batch_rays": 0}}, ["train.batch_rays", "0", ">= 1"]),
    ("batch_rays_negative", {"train": {"batch_rays": -64}}, ["train.batch_rays", "-64"]),
    ("batch_rays_huge", {"train": {"batch_rays": 4_000_000}}, ["train.batch_rays", "GiB", "try batch_rays"]),
    ("batch_rays_float", {"train": {"batch_rays": 64.5}}, ["train.batch_rays", "integer"]),
    ("checkpoint_every_0", {"train": {"checkpoint_every": 0}}, ["train.checkpoint_every"]),
    ("log_every_0", {"train": {"log_every": 0}}, ["train.log_every"]),
    ("keep_checkpoints_0", {"train": {"keep_checkpoints": 0}}, ["train.keep_checkpoints"]),
    ("lr_nan", {"train": {"lr_init": float("nan")}}, ["train.lr_init", "NaN", "finite"]),
    ("lr_inf", {"train": {"lr_final": float("inf")}}, ["train.lr_final", "finite"]),
    ("lr_string", {"train": {"lr_init": "fast"}}, ["train.lr_init", "fast", "number"]),
    ("lr_negative", {"train": {"lr_init": -1e-3}}, ["train.lr_init", "> 0"]),
    ("seed_float", {"train": {"seed": 1.5}}, ["train.seed", "1.5", "integer"]),
    ("max_steps_string", {"train": {"max_steps": "10"}}, ["train.max_steps", "integer"]),
    ("use_masks_int", {"train": {"use_masks": 1}}, ["train.use_masks", "true or false"]),
    ("mask_weight_floor_2", {"train": {"mask_weight_floor": 2}}, ["train.mask_weight_floor", "[0, 1]"]),
    ("field_depth_0", {"model": {"field": {"depth": 0}}}, ["model.field", "depth"]),
    ("field_width_0", {"model": {"field": {"width": 0}}}, ["model.field.width", ">= 1"]),
    ("near_ge_far", {"model": {"near": 5.0, "far": 1.0}}, ["near", "far"]),
    ("near_negative", {"model": {"near": -1.0}}, ["model.near", "> 0"]),
    ("samples_negative", {"model": {"sampler": {"samples": [8, -8]}}}, ["model.sampler.samples", ">= 1"]),
    ("sampler_key_of_another_kind", {"model": {"sampler": {"main_samples": 8}}}, ["model.sampler", "main_samples"]),
    ("unknown_key", {"train": {"batch_size": 64}}, ["batch_size"]),
]


@pytest.mark.parametrize("change, names", [c[1:] for c in BAD_CONFIGS], ids=[c[0] for c in BAD_CONFIGS])
def test_bad_config_is_refused_before_the_run_is_touched(scene, capsys, change, names):
    """Each bad value, even with --overwrite on a finished run, exits 1 with a line naming the
    key, and the run is left exactly as it was."""
    cfg = config_file(scene, "bad", change)
    before = snapshot(scene["run"], scene["data"])
    rc, err = run_cli(["train", *PAPER_MLP,
                       "--data", scene["data"], "--method", "nerf", "--config", cfg, "--out", scene["run"],
                       "--overwrite", "--quiet"], capsys)
    assert_one_line_error(rc, err, *names)
    assert snapshot(scene["run"], scene["data"]) == before


BAD_FLAGS = [
    ("steps_0", ["--steps", "0"], ["--steps", "0"]),
    ("steps_negative", ["--steps", "-5"], ["--steps", "-5"]),
    ("set_unknown", ["--set", "model.sampling.warp=log"], ["model.sampling.warp", "sampling"]),
    ("set_no_value", ["--set", "model.warp"], ["model.warp", "key=value"]),
    ("set_bad_value", ["--set", "train.batch_rays=many"], ["train.batch_rays", "many"]),
    ("set_bad_warp", ["--set", "model.warp=spiral"], ["model.warp", "spiral"]),
    ("steps_text", ["--steps", "ten"], ["--steps"]),
]


@pytest.mark.parametrize("flags, names", [c[1:] for c in BAD_FLAGS], ids=[c[0] for c in BAD_FLAGS])
def test_bad_train_flag_is_refused(scene, capsys, flags, names):
    before = snapshot(scene["run"], scene["data"])
    rc, err = run_cli(["train", *PAPER_MLP, "--data", scene["data"], "--method", "nerf", "--config", scene["cfg"],
                       "--out", scene["run"], "--overwrite", "--quiet", *flags], capsys)
    if flags[0] == "--steps" and flags[1] == "ten":  # argparse: usage line + error line, exit 2
        assert rc == 2 and "Traceback" not in err and "--steps" in err
    else:
        assert_one_line_error(rc, err, *names)
    assert snapshot(scene["run"], scene["data"]) == before


def test_set_changes_the_config(scene, capsys, tmp_path):
    """--set reaches the config (dotted keys, JSON values) and is applied after --config."""
    from jaxnerf_grid.config import schema as config
    from jaxnerf_grid.train import loop as train

    sets = config.parse_sets(["model.warp=log", "train.lr_init=1e-3", "model.sampler.samples=[32,16]",
                              "model.field.kind=\"grid\"", "model.near=null"], train.RunConfig)
    assert sets == {"model": {"warp": "log", "sampler": {"samples": [32, 16]}, "field": {"kind": "grid"}, "near": None},
                    "train": {"lr_init": 1e-3}}
    run = tmp_path / "run"
    # --config says 10 steps and log_every 5; --set wins for the keys it names
    rc, err = run_cli(["train", *PAPER_MLP,
                       "--data", scene["data"], "--method", "nerf", "--config", scene["cfg"], "--out", run,
                       "--set", "train.max_steps=4", "--set", "train.log_every=2", "--set", "model.warp=log",
                       "--quiet"], capsys)
    assert rc == 0, err
    saved = json.loads((run / "config.json").read_text())
    assert saved["train"]["max_steps"] == 4 and saved["train"]["log_every"] == 2
    assert saved["model"]["warp"] == "log" and saved["model"]["field"]["width"] == 32


def test_overwrite_never_clears_the_dataset(scene, capsys):
    """`train --data D --out D --overwrite` deleted D's depth/."""
    before = snapshot(scene["data"])
    for extra in ([], ["--overwrite"]):
        rc, err = run_cli(["train", *PAPER_MLP,
                           "--data", scene["data"], "--config", scene["cfg"], "--out", scene["data"],
                           "--quiet", *extra], capsys)
        assert_one_line_error(rc, err, str(scene["data"]))
    assert snapshot(scene["data"]) == before


def test_overwrite_never_clears_a_folder_that_is_not_a_run(scene, capsys, tmp_path):
    """A folder without the run marker is never cleared, with or without --overwrite; even a
    folder holding a depth/ and a config.json of the user's."""
    other = tmp_path / "mine"
    (other / "depth").mkdir(parents=True)
    (other / "depth" / "survey.exr").write_bytes(b"precious")
    (other / "config.json").write_text('{"camera": "mine"}')
    (other / "checkpoints").mkdir()
    before = snapshot(other)
    for extra in ([], ["--overwrite"]):
        rc, err = run_cli(["train", *PAPER_MLP,
                           "--data", scene["data"], "--config", scene["cfg"], "--out", other, "--quiet",
                           *extra], capsys)
        assert_one_line_error(rc, err, str(other), runs.RUN_MARKER)
    assert snapshot(other) == before


def test_synth_overwrite_never_clears_a_folder_it_did_not_write(scene, capsys, tmp_path):
    """synth --overwrite clears only a dataset synth wrote (its marker): a user's dataset with
    images/, depth/ and a transforms.json of its own is left as it was."""
    theirs = tmp_path / "survey"
    shutil.copytree(scene["data"], theirs)
    (theirs / ".jaxnerf-grid-synth").unlink()
    meta = json.loads((theirs / "transforms.json").read_text())
    meta.pop("generator")
    (theirs / "transforms.json").write_text(json.dumps(meta))
    before = snapshot(theirs)
    rc, err = run_cli(["synth", "--out", theirs, *SYNTH, "--overwrite"], capsys)
    assert_one_line_error(rc, err, str(theirs), ".jaxnerf-grid-synth")
    assert snapshot(theirs) == before
    again = tmp_path / "again"
    shutil.copytree(scene["data"], again)
    (again / "masks").mkdir(exist_ok=True)
    (again / "masks" / "stale.png").write_bytes(b"old mask of the old photos")
    rc, err = run_cli(["synth", "--out", again, *SYNTH, "--overwrite"], capsys)   # its own: replaced
    assert rc == 0, err
    assert not (again / "masks").exists()   # mask outputs of the old photos go with them


def test_overwrite_clears_only_the_runs_own_outputs(scene, capsys, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    (run / "notes.txt").write_text("the user's own file")
    rc, err = run_cli(["train", *PAPER_MLP,
                       "--data", scene["data"], "--method", "nerf", "--config", scene["cfg"], "--out", run,
                       "--steps", "5", "--overwrite", "--quiet"], capsys)
    assert rc == 0, err
    assert (run / "notes.txt").read_text() == "the user's own file"
    assert (run / runs.RUN_MARKER).is_file()
    assert json.loads((run / "config.json").read_text())["train"]["max_steps"] == 5


def test_rerun_of_a_finished_run_says_so(scene, capsys):
    rc = cli.main(["train", *PAPER_MLP, "--data", str(scene["data"]), "--method", "nerf", "--config", str(scene["cfg"]),
                   "--out", str(scene["run"]), "--quiet"])
    out = capsys.readouterr().out
    assert rc == 0 and "already trained to step 10" in out and "nan" not in out.lower(), out


def test_out_is_a_file(scene, capsys, tmp_path):
    f = tmp_path / "a_file"
    f.write_text("keep me")
    for argv in (["train", *PAPER_MLP, "--data", scene["data"], "--config", scene["cfg"], "--out", f, "--quiet"],
                 ["demo", "--out", f, "--quiet"]):
        rc, err = run_cli(argv, capsys)
        assert_one_line_error(rc, err, str(f))
    assert f.read_text() == "keep me"


def test_demo_checks_its_recipe_before_writing(capsys, tmp_path):
    """A bad --set or --steps of the demo fails before it synthesises or masks anything."""
    for flags, names in ((["--set", "train.batch_rays=0"], ["train.batch_rays"]),
                         (["--set", "model.sampling.warp=log"], ["model.sampling.warp"]),
                         (["--steps", "0"], ["--steps"])):
        rc, err = run_cli(["demo", "--out", tmp_path / "demo", "--quiet", *flags], capsys)
        assert_one_line_error(rc, err, *names)
        assert not (tmp_path / "demo").exists()


def test_camera_far_outside_the_others(scene, capsys, tmp_path):
    """A camera translated 1e30 away trained on a garbage frame."""
    data = tmp_path / "data"
    shutil.copytree(scene["data"], data)
    meta = io.read_json(data / "transforms.json")
    meta["frames"][2]["transform_matrix"][0][3] = 1e30
    io.write_json(data / "transforms.json", meta)
    rc, err = run_cli(["train", *PAPER_MLP,
                       "--data", data, "--config", scene["cfg"], "--out", tmp_path / "run", "--quiet"],
                      capsys)
    assert_one_line_error(rc, err, Path(meta["frames"][2]["file_path"]).name)
    assert not (tmp_path / "run").exists()


def test_os_errors_are_one_line(scene, capsys, tmp_path, monkeypatch):
    """A read-only folder and a full disk (simulated: the tests run as root, which ignores
    permissions) give one line naming the path; the run left behind resumes."""
    run = tmp_path / "run"
    real = io.write_json

    def full_disk(path, obj):
        if Path(path).name == "config.json":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, obj)

    monkeypatch.setattr(io, "write_json", full_disk)
    rc, err = run_cli(["train", *PAPER_MLP,
                       "--data", scene["data"], "--method", "nerf", "--config", scene["cfg"], "--out", run,
                       "--quiet"], capsys)
    assert_one_line_error(rc, err, str(run / "config.json"), "No space left on device")
    monkeypatch.setattr(io, "write_json", real)

    def read_only(self, *args, **kwargs):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))

    monkeypatch.setattr(Path, "mkdir", read_only)
    rc, err = run_cli(["train", *PAPER_MLP,
                       "--data", scene["data"], "--config", scene["cfg"], "--out", tmp_path / "ro" / "run",
                       "--quiet"], capsys)
    assert_one_line_error(rc, err, "Permission denied", "ro")
    monkeypatch.undo()
    # the run stopped by the full disk (marker and fingerprint written, no config.json) starts again
    rc, err = run_cli(["train", *PAPER_MLP,
                       "--data", scene["data"], "--method", "nerf", "--config", scene["cfg"], "--out", run,
                       "--steps", "5", "--quiet"], capsys)
    assert rc == 0, err


def test_eval_writes_over_a_folder(scene, capsys, tmp_path):
    """An OSError from deep inside (metrics.json is a folder) is one line naming the path."""
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    (run / "metrics.json").mkdir()
    rc, err = run_cli(["eval", "--run", run, "--quiet", "--distractor-views", "0"], capsys)
    assert_one_line_error(rc, err, "metrics.json")


def test_eval_render_and_export_refuse_another_dataset(scene, capsys, tmp_path):
    """A run trained on 8 frames of 32x24 scored (or exported) on another dataset."""
    other = tmp_path / "other"
    assert cli.main(["synth", "--out", str(other), "--width", "40", "--height", "30", "--num-train", "8",
                     "--num-test", "2", "--supersample", "1", "--workers", "1", "--quiet"]) == 0
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    saved = io.read_json(run / "config.json")
    io.write_json(run / "config.json", {**saved, "data": str(other)})
    before = snapshot(run)
    for argv in (["eval", "--run", run, "--quiet"], ["render", "--run", run, "--quiet"],
                 ["export", "--run", run, "--quiet", "--out", tmp_path / "export"],
                 ["train", *PAPER_MLP,
                  "--data", other, "--method", "nerf", "--config", scene["cfg"], "--out", run, "--quiet"]):
        rc, err = run_cli(argv, capsys)
        assert_one_line_error(rc, err, runs.FINGERPRINT_FILE, "--allow-other-data", "10 frames of 40x30")
    assert snapshot(run) == before
    rc, err = run_cli(["render", "--run", run, "--quiet", "--allow-other-data"], capsys)
    assert rc == 0, err


def test_missing_files_and_unknown_commands(scene, capsys, tmp_path):
    cases = [
        (["render", "--run", tmp_path / "nope"], ["nope"]),
        (["eval", "--run", tmp_path / "nope"], ["nope"]),
        (["eval", "--run", scene["run"], "--lpips-weights", tmp_path / "alex.npz"], ["alex.npz"]),
        (["eval", "--run", scene["run"], "--reference-ply", tmp_path / "tower.ply"], ["tower.ply"]),
        (["demo", "--data", tmp_path / "nope", "--out", tmp_path / "demo"], ["nope"]),
        (["train", *PAPER_MLP, "--data", tmp_path / "nope", "--out", tmp_path / "r"], ["nope"]),
        (["mask", "--data", tmp_path / "nope", "--source", "gt"], ["nope"]),
        (["train", *PAPER_MLP,
          "--data", scene["data"], "--config", tmp_path / "cfg.json", "--out", tmp_path / "r"], ["cfg.json"]),
    ]
    before = snapshot(scene["run"], scene["data"])
    for argv, names in cases:
        rc, err = run_cli(argv + ["--quiet"], capsys)
        assert_one_line_error(rc, err, *names)
    assert snapshot(scene["run"], scene["data"]) == before
    rc, err = run_cli(["bogus"], capsys)
    assert rc == 2 and "unknown command 'bogus'" in err and "Traceback" not in err


def test_broken_run_config(scene, capsys, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    (run / "config.json").write_text('{"data": "x", "model": {')
    rc, err = run_cli(["render", "--run", run, "--quiet"], capsys)
    assert_one_line_error(rc, err, "config.json", "invalid JSON")
    io.write_json(run / "config.json", {**io.read_json(scene["run"] / "config.json"), "train": {"batch_rays": 0}})
    rc, err = run_cli(["eval", "--run", run, "--quiet"], capsys)
    assert_one_line_error(rc, err, "config.json", "train.batch_rays")


BAD_MASK_FLAGS = [
    ("threshold_2", ["--threshold", "2"], ["--threshold", "[0, 1]"]),
    ("floor_negative", ["--floor", "-3"], ["--floor"]),
    ("classes_letters", ["--classes", "a,b", "--source", "dpt"], ["--classes", "'a'"]),
    ("classes_out_of_range", ["--classes", "999", "--source", "dpt"], ["--classes", "999", "labels"]),
    ("max_side_negative", ["--max-side", "-16"], ["--max-side"]),
    ("dilate_negative", ["--dilate", "-2"], ["--dilate"]),
    ("tiles_0", ["--tiles", "0"], ["--tiles"]),
]


@pytest.mark.parametrize("flags, names", [c[1:] for c in BAD_MASK_FLAGS], ids=[c[0] for c in BAD_MASK_FLAGS])
def test_bad_mask_flag(scene, capsys, flags, names):
    if "--classes" in flags and "999" in flags and not (masking.BUILTIN / "config.json").is_file():
        pytest.skip("no built-in DPT model in this build")
    before = snapshot(scene["data"])
    argv = ["mask", "--data", scene["data"], "--overwrite", "--quiet", *flags]
    if "--source" not in flags:
        argv += ["--source", "gt"]
    rc, err = run_cli(argv, capsys)
    assert_one_line_error(rc, err, *names)
    assert snapshot(scene["data"]) == before


def test_synth_refuses_a_dataset_train_cannot_use(capsys, tmp_path):
    for flags, name in ((["--num-test", "0"], "--num-test"), (["--num-train", "0"], "--num-train"),
                        (["--width", "0"], "--width")):
        rc, err = run_cli(["synth", "--out", tmp_path / "d", "--quiet", *flags], capsys)
        assert_one_line_error(rc, err, name)
        assert not (tmp_path / "d").exists()


def _llff(tmp_path: Path, scene, change) -> Path:
    """An LLFF copy of the tiny scene (poses_bounds.npy + images/) with `change(arr)` applied."""
    from jaxnerf_grid.data.formats import load_dataset

    ds = load_dataset(scene["data"], progress=False)
    root = tmp_path / "llff"
    (root / "images").mkdir(parents=True)
    rows = []
    for i in range(ds.num_frames):
        io.write_png(root / "images" / f"{i:03d}.png", ds.images[i])
        c2w = np.asarray(ds.c2w[i], np.float64)
        pose = np.stack([-c2w[:3, 1], c2w[:3, 0], c2w[:3, 2], c2w[:3, 3],
                         [ds.height, ds.width, float(ds.intrinsics[i, 0])]], axis=1)
        rows.append(np.concatenate([pose.reshape(-1), [0.5, 6.0]]))
    arr = np.asarray(rows)
    change(arr)
    np.save(root / "poses_bounds.npy", arr)
    return root


LLFF_CASES = [
    ("focal_negative", lambda a: a.__setitem__((0, 14), -a[0, 14]), "focal"),
    ("focal_zero", lambda a: a.__setitem__((1, 14), 0.0), "focal"),
    ("size_zero", lambda a: a.__setitem__((0, 4), 0.0), "H, W"),
    ("bounds_negative", lambda a: a.__setitem__((0, 15), -1.0), "near, far"),
]


@pytest.mark.parametrize("change, name", [c[1:] for c in LLFF_CASES], ids=[c[0] for c in LLFF_CASES])
def test_bad_llff(scene, capsys, tmp_path, change, name):
    root = _llff(tmp_path, scene, change)
    before = snapshot(root)
    rc, err = run_cli(["train", *PAPER_MLP,
                       "--data", root, "--config", scene["cfg"], "--out", tmp_path / "run", "--quiet"], capsys)
    assert_one_line_error(rc, err, "poses_bounds.npy", name)
    assert snapshot(root) == before


def test_good_llff_copy_loads(scene, tmp_path):
    """The corpus's LLFF writer makes a loadable dataset, so the cases above fail for their one change."""
    from jaxnerf_grid.data.formats import load_dataset

    ds = load_dataset(_llff(tmp_path, scene, lambda a: None), progress=False)
    assert ds.num_frames == 8


# --------------------------------------------------------------------------- kill -9 of mask --overwrite


MASK_SETS = ("masks", "weights", "dpt_depth", "overlays", "transforms.json")


def mask_state(data: Path) -> dict:
    return snapshot(*[data / name for name in MASK_SETS if (data / name).exists()])


def _relative(state: dict, root: Path) -> dict:
    return {str(Path(k).relative_to(root)): v for k, v in state.items()}


def _slow_mask_child(data: str, pause: str) -> None:
    """`mask --source gt --overwrite --dilate 2` with a pause after each frame written and after
    each folder renamed in the swap, so the parent can kill it at either stage."""
    pause_s = float(pause)
    write, rename = masking._write_frame, staging.move

    progress = Path(data + ".frames")  # frames written so far, outside the dataset

    def slow_write(*args, **kwargs):
        out = write(*args, **kwargs)
        progress.write_text(str(int(progress.read_text() or 0) + 1) if progress.exists() else "1")
        time.sleep(pause_s)
        return out

    def slow_rename(src, dst):
        rename(src, dst)
        time.sleep(pause_s)

    masking._write_frame, staging.move = slow_write, slow_rename
    sys.exit(cli.main(["mask", "--data", data, "--source", "gt", "--overwrite", "--dilate", "2", "--quiet"]))


@pytest.mark.parametrize("stage", ["writing", "swapping"])
def test_killed_mask_overwrite_leaves_old_or_new(scene, capsys, tmp_path, stage):
    """A killed `mask --overwrite` left 4 masks of one set and 6 of another."""
    old_data, new_data = tmp_path / "old", tmp_path / "new"
    shutil.copytree(scene["data"], old_data)
    assert cli.main(["mask", "--data", str(old_data), "--source", "gt", "--quiet"]) == 0
    shutil.copytree(old_data, new_data)
    assert cli.main(["mask", "--data", str(new_data), "--source", "gt", "--overwrite", "--dilate", "2",
                     "--quiet"]) == 0
    old, new = _relative(mask_state(old_data), old_data), _relative(mask_state(new_data), new_data)
    assert old != new
    outcomes = []
    for attempt in range(2):
        data = tmp_path / f"killed{attempt}"
        shutil.copytree(old_data, data)
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        proc = subprocess.Popen([sys.executable, __file__, str(data), "0.4"], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        stage_dir = data / masking.STAGING
        try:
            deadline = time.time() + 600  # a net against a hang, not a speed target
            # "writing": once a frame or two is written; "swapping": once the commit point is written
            frames = Path(str(data) + ".frames")
            ready = ((lambda: frames.exists() and int(frames.read_text() or 0) >= 1 + attempt)  # noqa: B023
                     if stage == "writing" else (lambda: (stage_dir / masking.COMPLETE).is_file()))  # noqa: B023
            while not ready():
                assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
                assert time.time() < deadline, "the child never reached the stage"
                time.sleep(0.02)
            time.sleep(0.2 + 0.4 * attempt)  # inside a frame's pause / between two renames
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == -signal.SIGKILL  # it really died mid-way
        runs.load_dataset(data, progress=False)  # what train does: finishes the swap, then loads
        state = _relative(mask_state(data), data)
        assert state in (old, new), "a mix of two mask sets"
        assert not (data / masking.STAGING).exists() and not (data / masking.RETIRED).exists()
        outcomes.append("new" if state == new else "old")
    assert outcomes == (["old", "old"] if stage == "writing" else ["new", "new"]), outcomes


# --------------------------------------------------------------------------- folders that are not the command's own

EXPORT_FAST = ["--resolution", "16", "--views", "2", "--box=-10,-10,0,10,10,20", "--threshold", "0.0001", "--quiet"]


def test_export_never_writes_into_a_folder_it_did_not_make(scene, capsys, tmp_path):
    """`export --overwrite --out DIR` replaced a user's box.json and appended to their
    report.md. A folder without export's marker is refused, --overwrite or not."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "box.json").write_text('{"mine": true}')
    (mine / "report.md").write_text("# my notes\n")
    before = snapshot(mine, scene["run"])
    for extra in ([], ["--overwrite"]):
        rc, err = run_cli(["export", "--run", scene["run"], "--out", mine, *extra, *EXPORT_FAST], capsys)
        assert_one_line_error(rc, err, str(mine))
    assert ".jaxnerf-grid-export" in err and "--out" in err
    # the run folder itself holds the run's marker, not export's
    rc, err = run_cli(["export", "--run", scene["run"], "--out", scene["run"], "--overwrite", *EXPORT_FAST], capsys)
    assert_one_line_error(rc, err, str(scene["run"]), ".jaxnerf-grid-export")
    assert snapshot(mine, scene["run"]) == before


def test_out_inside_the_dataset_is_refused_for_every_command(scene, capsys, tmp_path):
    """Export through a symlink into a dataset added files to it; train's --out inside
    the dataset was taken. Links are resolved."""
    alias = tmp_path / "alias"
    alias.symlink_to(scene["data"], target_is_directory=True)
    before = snapshot(scene["data"], scene["run"])
    cases = [["export", "--run", scene["run"], "--out", alias / "export", *EXPORT_FAST],
             ["export", "--run", scene["run"], "--out", scene["data"] / "export", *EXPORT_FAST],
             ["train", *PAPER_MLP, "--data", scene["data"], "--config", scene["cfg"], "--out", alias / "run",
              "--quiet"],
             ["train", *PAPER_MLP, "--data", alias, "--config", scene["cfg"], "--out", scene["data"] / "runs" / "a",
              "--quiet"],
             ["demo", "--data", scene["data"], "--out", alias / "demo", "--steps", "2", "--quiet"]]
    for argv in cases:
        rc, err = run_cli(argv, capsys)
        assert_one_line_error(rc, err, "--out", "inside")
    assert snapshot(scene["data"], scene["run"]) == before


def test_overwrite_refuses_a_symlinked_checkpoints_folder(scene, capsys, tmp_path):
    """With checkpoints/ a link (weights on a bigger disk) `train --overwrite` skipped
    it and reported "already trained": old weights under a new config.json."""
    run, disk = tmp_path / "run", tmp_path / "big_disk"
    shutil.copytree(scene["run"], run)
    shutil.move(run / "checkpoints", disk)
    (run / "checkpoints").symlink_to(disk, target_is_directory=True)
    before = snapshot(run, disk)
    rc, err = run_cli(["train", *PAPER_MLP, "--data", scene["data"], "--config", scene["cfg"], "--out", run,
                       "--set", "train.lr_init=1e-3", "--overwrite", "--quiet"], capsys)
    line = assert_one_line_error(rc, err, str(run / "checkpoints"), "symbolic link")
    assert "yourself" in line
    assert snapshot(run, disk) == before


BAD_VALUES_39 = [  # (case id, argv after the run / data flags, words the one line must name)
    ("export_views_negative", ["export", "--views", "-3"], ["--views", "-3"]),
    ("export_resolution_huge", ["export", "--resolution", "100000"], ["--resolution", "GiB", "at most"]),
    ("export_resolution_small", ["export", "--resolution", "4"], ["--resolution", "4"]),
    ("eval_distractor_views_negative", ["eval", "--distractor-views", "-5"], ["--distractor-views", "-5"]),
    ("train_set_data", ["train", "--set", "data=\"elsewhere\""], ["data", "--data"]),
    ("coordinator_without_port", ["train", "--coordinator", "localhost", "--num-processes", "2",
                                  "--process-id", "1"], ["--coordinator", "HOST:PORT"]),
    ("coordinator_not_an_address", ["train", "--coordinator", "a b:c"], ["--coordinator", "HOST:PORT"]),
    ("coordinator_port_range", ["train", "--coordinator", "localhost:70000"], ["--coordinator", "1..65535"]),
    ("process_id_range", ["train", "--coordinator", "localhost:1234", "--num-processes", "2",
                          "--process-id", "2"], ["--process-id", "[0, 2)"]),
    ("process_id_negative", ["train", "--num-processes", "2", "--process-id", "-1"], ["--process-id", "-1"]),
    ("num_processes_zero", ["train", "--num-processes", "0"], ["--num-processes", ">= 1"]),
]


@pytest.mark.parametrize("case, argv, names", BAD_VALUES_39, ids=[c[0] for c in BAD_VALUES_39])
def test_bad_values_of_round_two(scene, capsys, tmp_path, case, argv, names):
    command, rest = argv[0], argv[1:]
    where = (["--run", scene["run"]] if command in ("export", "eval")
             else [*PAPER_MLP, "--data", scene["data"], "--config", scene["cfg"], "--out", tmp_path / "run"])
    before = snapshot(scene["data"], scene["run"])
    rc, err = run_cli([command, *where, *rest, "--quiet"], capsys)
    assert_one_line_error(rc, err, *names)
    assert snapshot(scene["data"], scene["run"]) == before
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("name, value", [("JAX_NUM_PROCESSES", "abc"), ("JAX_PROCESS_ID", "one"),
                                         ("JAX_COORDINATOR_ADDRESS", "nohost"),
                                         ("JAXNERF_CONNECT_TIMEOUT", "soon"), ("JAXNERF_INIT_TIMEOUT", "0")])
def test_bad_environment_values_are_named(scene, capsys, tmp_path, monkeypatch, name, value):
    monkeypatch.setenv("JAX_NUM_PROCESSES", "2")
    monkeypatch.setenv(name, value)
    rc, err = run_cli(["train", *PAPER_MLP, "--data", scene["data"], "--config", scene["cfg"],
                       "--out", tmp_path / "run", "--quiet"], capsys)
    assert_one_line_error(rc, err, name, value)
    assert not (tmp_path / "run").exists()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_coordinator_port_in_use_and_unreachable(scene, capsys, tmp_path, monkeypatch):
    """Process 0 on a port another program listens on; process 1 with no coordinator there: one
    line naming the address, within the documented connect timeout (here 2 s), no stack dump."""
    import socket

    base = ["train", *PAPER_MLP, "--data", scene["data"], "--config", scene["cfg"], "--out", tmp_path / "run",
            "--quiet", "--num-processes", "2"]
    with socket.socket() as busy:
        busy.bind(("", 0))
        busy.listen()
        port = busy.getsockname()[1]
        rc, err = run_cli([*base, "--coordinator", f"127.0.0.1:{port}", "--process-id", "0"], capsys)
        assert_one_line_error(rc, err, f"127.0.0.1:{port}", "already in use")
    monkeypatch.setenv("JAXNERF_CONNECT_TIMEOUT", "2")
    port = _free_port()
    rc, err = run_cli([*base, "--coordinator", f"127.0.0.1:{port}", "--process-id", "1"], capsys)
    assert_one_line_error(rc, err, f"127.0.0.1:{port}", "within 2 s", "refused")   # the variable's wait, not 20 s
    rc, err = run_cli([*base, "--coordinator", "no-such-host.invalid:1234", "--process-id", "1"], capsys)
    assert_one_line_error(rc, err, "no-such-host.invalid:1234", "does not resolve")
    assert not (tmp_path / "run").exists()


def test_eval_reads_a_broken_reference_ply_before_rendering(scene, capsys, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    bad = tmp_path / "ref.ply"
    bad.write_text("not a ply\n")
    before = snapshot(run)
    rc, err = run_cli(["eval", "--run", run, "--reference-ply", bad, "--quiet"], capsys)
    assert_one_line_error(rc, err, str(bad), "PLY")
    assert snapshot(run) == before


def test_export_with_non_ascii_and_space_paths_and_a_full_disk(scene, capsys, tmp_path, monkeypatch):
    """The run path went into the PLY header (ASCII) and export died with a traceback.
    Then a full disk while writing the mesh names the file (write() raises ENOSPC without one)."""
    run, out = tmp_path / "Lauf ü" / "run 1", tmp_path / "Ausgabe é"
    shutil.copytree(scene["run"], run)
    rc, err = run_cli(["export", "--run", run, "--out", out, *EXPORT_FAST], capsys)
    assert rc == 0, err
    assert (out / ".jaxnerf-grid-export").is_file()
    assert len(io.read_ply_points(out / "tower_mesh.ply")) > 0
    header = (out / "tower_mesh.ply").read_bytes().split(b"end_header")[0].decode("ascii")
    assert "Lauf \\xfc" in header
    # an export folder export made is overwritten in place; a user's file in it stays
    (out / "notes.txt").write_text("mine")
    rc, err = run_cli(["export", "--run", run, "--out", out, "--overwrite", *EXPORT_FAST], capsys)
    assert rc == 0, err
    assert (out / "notes.txt").read_text() == "mine"
    real = Path.write_bytes

    def full_disk(self, data):
        if self.name.startswith(".tower_mesh.ply."):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as write() raises it: no file name
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", full_disk)
    rc, err = run_cli(["export", "--run", run, "--out", tmp_path / "full", *EXPORT_FAST], capsys)
    assert_one_line_error(rc, err, str(tmp_path / "full" / "tower_mesh.ply"), "No space left on device")
    assert not [p for p in (tmp_path / "full").iterdir() if p.name.startswith(".tower_mesh")]


def test_a_fingerprint_that_is_not_an_object_is_named(scene, capsys, tmp_path):
    """A dataset.json that was not an object turned the check off without a word."""
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    (run / runs.FINGERPRINT_FILE).write_text("[1, 2, 3]\n")
    before = snapshot(run)
    rc, err = run_cli(["eval", "--run", run, "--quiet"], capsys)
    assert_one_line_error(rc, err, str(run / runs.FINGERPRINT_FILE), "--allow-other-data")
    assert snapshot(run) == before


def test_numpys_advice_to_unpickle_is_not_passed_on(scene, capsys, tmp_path):
    root = _llff(tmp_path, scene, lambda a: None)
    np.save(root / "poses_bounds.npy", np.array([{"rows": 1}], dtype=object), allow_pickle=True)
    rc, err = run_cli(["train", *PAPER_MLP, "--data", root, "--config", scene["cfg"], "--out", tmp_path / "run",
                       "--quiet"], capsys)
    line = assert_one_line_error(rc, err, "poses_bounds.npy", "Python objects")
    assert "allow_pickle" not in line
    assert not (tmp_path / "run").exists()


def test_all_zero_weights_are_refused_before_the_run_folder_is_made(scene, capsys, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(scene["data"], data)
    assert cli.main(["mask", "--data", str(data), "--source", "gt", "--quiet"]) == 0
    for exr in (data / "weights").glob("*.exr"):
        io.write_exr(exr, np.zeros_like(io.read_exr(exr)))
    before = snapshot(data)
    rc, err = run_cli(["train", *PAPER_MLP, "--data", data, "--config", scene["cfg"], "--out", tmp_path / "run",
                       "--set", "train.use_masks=true", "--quiet"], capsys)
    assert_one_line_error(rc, err, str(data), "loss weight 0")
    assert not (tmp_path / "run").exists()
    assert snapshot(data) == before


@pytest.mark.parametrize("command", ["synth", "mask"])
def test_a_full_disk_names_the_file_in_synth_and_mask(scene, capsys, tmp_path, monkeypatch, command):
    """write() raises ENOSPC without a file name; the one line names the file being written, and
    `mask` leaves the dataset as it was."""
    data = tmp_path / "data"
    if command == "mask":
        shutil.copytree(scene["data"], data)
    before = snapshot(data) if data.exists() else {}
    real = Path.write_bytes

    def full_disk(self, payload):
        if self.name.startswith(".") and ".png." in self.name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(self, payload)

    monkeypatch.setattr(Path, "write_bytes", full_disk)
    argv = (["synth", "--out", data, *SYNTH] if command == "synth"
            else ["mask", "--data", data, "--source", "gt", "--quiet"])
    rc, err = run_cli(argv, capsys)
    line = assert_one_line_error(rc, err, str(data), ".png", "No space left on device")
    assert line.split(": cannot write")[0].endswith(".png")
    monkeypatch.undo()
    if command == "mask":
        runs.load_dataset(data, progress=False)  # what the next command does first
        assert snapshot(data) == before


def _slow_export_child(run: str, out: str, pause: str) -> None:
    """`export` with a pause after each file it writes (io.atomic_write_bytes), so the parent can
    kill it between two files."""
    real = io.atomic_write_bytes

    def slow(path, payload):
        real(path, payload)
        time.sleep(float(pause))

    io.atomic_write_bytes = slow
    sys.exit(cli.main(["export", "--run", run, "--out", out, *EXPORT_FAST]))


@pytest.mark.parametrize("files_before_kill", [1, 3])
def test_killed_export_leaves_whole_files_and_can_be_overwritten(scene, capsys, tmp_path, files_before_kill):
    """kill -9 of export between two of its files: the run is untouched, each file in the
    folder is whole (written through a temporary file and a rename), and `export --overwrite`
    then replaces the folder (it holds export's marker, written before the first file)."""
    run, out = tmp_path / "run", tmp_path / "exp"
    shutil.copytree(scene["run"], run)
    before = snapshot(run)
    kill_when([__file__, "export", str(run), str(out), "1.0"], timeout=600, ready=lambda: out.is_dir() and sum(
        p.name in export_files() for p in out.iterdir()) >= files_before_kill)
    written = sorted(p.name for p in out.iterdir() if p.name in export_files())
    assert 1 <= len(written) < len(export_files())  # it really stopped half-way
    for name in written:
        if name.endswith(".ply"):
            io.read_ply(out / name)
        elif name.endswith(".json"):
            assert isinstance(io.read_json(out / name), dict)
        elif name.endswith(".las"):
            import laspy
            laspy.read(out / name)      # a torn file fails to read (its header counts the points)
        else:
            io.read_image(out / name)
    assert snapshot(run) == before
    rc, err = run_cli(["export", "--run", run, "--out", out, *EXPORT_FAST], capsys)
    assert_one_line_error(rc, err, str(out), "--overwrite")
    rc, err = run_cli(["export", "--run", run, "--out", out, "--overwrite", *EXPORT_FAST], capsys)
    assert rc == 0, err
    assert set(export_files()) <= {p.name for p in out.iterdir()}


def export_files() -> tuple:
    from jaxnerf_grid.export import run as export_run

    return export_run.FILES


def test_poses_single_camera_on_two_photo_sizes_says_why(capsys, tmp_path):
    """The photos of the other size stayed unregistered without a word."""
    pytest.importorskip("pycolmap")
    photos = tmp_path / "photos"
    rng = np.random.default_rng(0)
    for i, (w, h) in enumerate([(40, 30)] * 3 + [(32, 24)] * 2):
        io.write_png(photos / f"p{i}.png", rng.random((h, w, 3)))
    before = snapshot(photos)
    rc, err = run_cli(["poses", "--images", photos, "--out", tmp_path / "d", "--single-camera", "--quiet"], capsys)
    assert_one_line_error(rc, err, str(photos), "--single-camera", "40x30: 3", "32x24: 2")
    assert snapshot(photos) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]  # no dataset, no staging copy left


def test_demo_takes_a_dataset_layout_train_takes(scene, capsys, tmp_path, monkeypatch):
    """`demo --data` refused a COLMAP folder `train` accepts (demo masked it first, and
    `mask` writes only into the transforms.json layout). Checked here on an LLFF folder (the same
    path: no transforms.json): auto trains robust, nothing is written into the dataset; a forced
    --masks dpt is refused in one line. Training itself is stubbed (the recipe is the demo's)."""
    from jaxnerf_grid import demo

    root = _llff(tmp_path, scene, lambda a: None)
    before = snapshot(root)
    seen = {}

    class Stop(Exception):
        pass

    def stub_train_run(data, method, out, overrides, *args, **kwargs):
        seen.update(data=data, overrides=overrides)
        raise Stop()

    monkeypatch.setattr(runs, "train_run", stub_train_run)
    with pytest.raises(Stop):
        demo.run_demo(root, tmp_path / "demo", steps=2, progress=False)
    assert seen["data"] == str(root) and seen["overrides"]["train"]["robust"] == {"mode": "robust"}
    assert seen["overrides"]["train"]["use_masks"] is False
    assert snapshot(root) == before
    rc, err = run_cli(["demo", "--data", root, "--out", tmp_path / "demo2", "--masks", "dpt", "--quiet"], capsys)
    assert_one_line_error(rc, err, "--masks", "transforms.json layout")
    assert snapshot(root) == before and not (tmp_path / "demo2").exists()


if __name__ == "__main__":
    if sys.argv[1] == "export":
        _slow_export_child(*sys.argv[2:])
    else:
        _slow_mask_child(sys.argv[1], sys.argv[2])
