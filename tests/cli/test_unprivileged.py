"""Read-only folders, permission-denied files and a full disk, as they really happen:
each command runs as the unprivileged user 65534 (`tests/support/unprivileged.py`: `setpriv`; the full
disk a tmpfs of a few KiB mounted for that command only), where the suite itself runs as root,
which ignores permissions. Each case asserts exit code 1, one line of error naming the path, no
traceback, and the dataset and the run hash-identical before and after. Skipped, with the
reason, where the tests do not run as root or `setpriv` / `unshare` is missing.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from jaxnerf_grid import cli
from tests.cli.test_bad_input import PAPER_MLP, SYNTH, TINY, assert_one_line_error, snapshot
from tests.support import unprivileged

ROOT = Path(__file__).resolve().parents[2]
CACHE = ".jaxnerf-grid-cache"


def _skip_unless(reason: str | None) -> None:
    if reason is not None:
        pytest.skip(reason)


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    """{"base": a folder the unprivileged user may read, holding "data" (a tiny synth scene
    without its working cache), "run" (a finished 10-step run on it), "cfg"; "home": a folder it
    may write}. Everything but home belongs to root, so the user may read it, not change it."""
    _skip_unless(unprivileged.unavailable())
    base = unprivileged.shared_folder()
    data, run, cfg = base / "data", base / "run", base / "tiny.json"
    assert cli.main(["synth", "--out", str(data), *SYNTH]) == 0
    cfg.write_text(json.dumps(TINY))
    assert cli.main(["train", *PAPER_MLP, "--data", str(data), "--method", "nerf", "--config", str(cfg),
                     "--out", str(run), "--quiet"]) == 0
    shutil.rmtree(data / CACHE, ignore_errors=True)
    (base / "ro").mkdir()  # a folder of root's: read-only to the user
    home = unprivileged.give_to_nobody(base / "home")
    yield {"base": base, "data": data, "run": run, "cfg": cfg, "home": home}
    shutil.rmtree(base, ignore_errors=True)


def run_as_nobody(argv: list, shared: dict, disk: Path | None = None, disk_kib: int = 0) -> tuple[int, str]:
    """(exit code, stderr) of `python -m jaxnerf_grid argv...` as the unprivileged user."""
    done = subprocess.run(unprivileged.as_nobody(["-m", "jaxnerf_grid", *[str(a) for a in argv]], disk, disk_kib),
                          cwd=ROOT, env=unprivileged.environment(shared["home"]), capture_output=True, text=True,
                          timeout=300)
    return done.returncode, done.stderr


def train_argv(shared, out, data=None) -> list:
    return ["train", *PAPER_MLP, "--data", data or shared["data"], "--method", "nerf", "--config", shared["cfg"],
            "--out", out, "--quiet"]


@pytest.mark.parametrize("command", ["train", "export", "render_orbit", "synth", "poses"])
def test_an_output_folder_the_user_cannot_write(shared, command):
    """Each command's output in a folder of root's: one line naming the folder, nothing made;
    `train`, `export` and `poses` say so before they train, render or run COLMAP
    (`folders.check_folder`: export without --box would otherwise render its views first and fail
    on the box; poses named its hidden staging folder beside the output)."""
    out = shared["base"] / "ro" / "out"
    argv = {"train": train_argv(shared, out),
            "export": ["export", "--run", shared["run"], "--out", out, "--resolution", "8", "--views", "1", "--quiet"],
            "render_orbit": ["render", "--run", shared["run"], "--orbit", "--frames", "2", "--width", "16",
                             "--out", out / "orbit", "--quiet"],
            "synth": ["synth", "--out", out, *SYNTH],
            "poses": ["poses", "--images", shared["data"] / "images", "--out", out, "--quiet"]}[command]
    if command == "poses":
        pytest.importorskip("pycolmap")
    before = snapshot(shared["data"], shared["run"], shared["base"] / "ro")
    rc, err = run_as_nobody(argv, shared)
    assert rc == 1
    assert "permission denied" in assert_one_line_error(rc, err, str(out)).lower()
    assert snapshot(shared["data"], shared["run"], shared["base"] / "ro") == before


def test_mask_into_a_dataset_the_user_cannot_write(shared):
    before = snapshot(shared["data"])
    rc, err = run_as_nobody(["mask", "--data", shared["data"], "--source", "gt", "--quiet"], shared)
    assert rc == 1
    line = assert_one_line_error(rc, err, f"{shared['data']}: --data is not writable", "permission denied")
    assert "/." not in line  # the dataset, not the hidden staging folder the masks go to first
    assert snapshot(shared["data"]) == before


def test_eval_into_a_run_the_user_cannot_write(shared):
    before = snapshot(shared["data"], shared["run"])
    rc, err = run_as_nobody(["eval", "--run", shared["run"], "--quiet"], shared)
    assert rc == 1
    assert_one_line_error(rc, err, str(shared["run"]), "Permission denied")
    assert snapshot(shared["data"], shared["run"]) == before


def test_a_photo_the_user_cannot_read(shared):
    """A photo of mode 000: one line naming it; no run folder made."""
    data = shared["base"] / "data_000"
    shutil.copytree(shared["data"], data)
    photo = data / json.loads((data / "transforms.json").read_text())["frames"][0]["file_path"]
    photo.chmod(0)
    out = unprivileged.give_to_nobody(shared["base"] / "home" / "w1") / "run"
    before = snapshot(data)
    rc, err = run_as_nobody(train_argv(shared, out, data), shared)
    assert rc == 1
    assert_one_line_error(rc, err, str(photo))
    assert snapshot(data) == before and not out.exists()


def test_a_read_only_dataset_trains_without_its_cache(shared):
    """The working-frame cache is skipped, not an error, in a dataset the user cannot write
    (docs/DATASET.md): training succeeds and the dataset is unchanged."""
    out = unprivileged.give_to_nobody(shared["base"] / "home" / "w2") / "run"
    before = snapshot(shared["data"])
    rc, err = run_as_nobody(train_argv(shared, out) + ["--max-side", "16"], shared)  # half size: cached frames
    assert rc == 0, err
    assert snapshot(shared["data"]) == before and not (shared["data"] / CACHE).exists()
    assert (out / "config.json").is_file()


@pytest.mark.parametrize("command, kib", [("train", 24), ("synth", 16), ("render_orbit", 8)])
def test_a_full_disk(shared, command, kib):
    """A real ENOSPC (a tmpfs of a few KiB): one line naming the file being written; the
    dataset and the run unchanged."""
    _skip_unless(unprivileged.disk_unavailable())
    disk = shared["base"] / "home" / f"disk_{command}"
    disk.mkdir()
    out = disk / "out"
    argv = {"train": train_argv(shared, out), "synth": ["synth", "--out", out, *SYNTH],
            "render_orbit": ["render", "--run", shared["run"], "--orbit", "--frames", "40", "--width", "64",
                             "--out", out / "orbit", "--quiet"]}[command]
    before = snapshot(shared["data"], shared["run"])
    rc, err = run_as_nobody(argv, shared, disk=disk, disk_kib=kib)
    assert rc == 1
    line = assert_one_line_error(rc, err, str(out), "No space left on device")
    assert line.split(": cannot write")[0].startswith(f"jaxnerf-grid {command.split('_')[0]}: error: {out}/"), line
    assert "/." not in line.split(": cannot write")[0], line  # the file the user asked for, not a hidden staging file
    assert snapshot(shared["data"], shared["run"]) == before
