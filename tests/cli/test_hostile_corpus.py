"""The fresh hostile-user corpus (scripts/hostile_corpus.py,
docs/RELIABILITY.md). Each case that once failed there, and a sample of
those that held, through the real CLI entry point (`jaxnerf_grid.cli.main`): the exit code, one
line of error naming the file or key, no traceback, and the trees hash-identical before and after.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.cli import flags as cli_flags
from jaxnerf_grid.cli import train as cli_train
from jaxnerf_grid.masks import write as masking
from jaxnerf_grid.util import io
from tests.cli.test_bad_input import PAPER_MLP, SYNTH, TINY, assert_one_line_error, run_cli, snapshot
from tests.support.killing import kill_when

ROOT = Path(__file__).resolve().parents[2]
GOOD_POSE = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 3, 0, 0, 0, 1]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """{"data": a tiny synth scene, "run": a finished 10-step run on it, "cfg": TINY's file}."""
    tmp = tmp_path_factory.mktemp("hostile3")
    data, run, cfg = tmp / "data", tmp / "run", tmp / "tiny.json"
    assert cli.main(["synth", "--out", str(data), *SYNTH]) == 0
    cfg.write_text(json.dumps(TINY))
    assert cli.main(["train", *PAPER_MLP, "--data", str(data), "--method", "nerf", "--config", str(cfg),
                     "--out", str(run), "--quiet"]) == 0
    return {"data": data, "run": run, "cfg": cfg}


def first_image(data: Path) -> Path:
    return data / json.loads((data / "transforms.json").read_text())["frames"][0]["file_path"]


def test_video_out_inside_the_dataset_is_refused(scene, capsys, tmp_path):
    """Failed: `render --orbit --out DATA/orbit` wrote two videos into the dataset."""
    before = snapshot(scene["data"], scene["run"])
    for out in (scene["data"] / "orbit", scene["data"] / "images" / "orbit"):
        rc, err = run_cli(["render", "--run", scene["run"], "--orbit", "--frames", "2", "--width", "16",
                           "--out", out, "--quiet"], capsys)
        assert_one_line_error(rc, err, "--out", str(scene["data"]))
    (tmp_path / "link").symlink_to(scene["data"])
    rc, err = run_cli(["render", "--run", scene["run"], "--orbit", "--frames", "2", "--width", "16",
                       "--out", tmp_path / "link" / "orbit", "--quiet"], capsys)
    assert_one_line_error(rc, err, "--out")
    assert snapshot(scene["data"], scene["run"]) == before


def test_video_frames_too_large_are_refused_before_anything_is_written(scene, capsys, tmp_path):
    """Failed: `--width 10000000` said "OpenCV cannot write an mp4v video here" and left RUN/videos/."""
    from jaxnerf_grid.render import videos

    before = snapshot(scene["data"], scene["run"])
    rc, err = run_cli(["render", "--run", scene["run"], "--orbit", "--width", "10000000", "--quiet"], capsys)
    assert_one_line_error(rc, err, "--width", "10000000", str(videos.MAX_SIDE))
    path = tmp_path / "wide.json"
    path.write_text(json.dumps({"camera_path": [{"camera_to_world": GOOD_POSE, "fov": 50}],
                                "render_width": videos.MAX_SIDE + 1, "render_height": 8}))
    rc, err = run_cli(["render", "--run", scene["run"], "--path", path, "--quiet"], capsys)
    assert_one_line_error(rc, err, str(path), str(videos.MAX_SIDE + 1))
    path.write_text(json.dumps({"camera_path": [{"camera_to_world": GOOD_POSE, "fov": 50}], "fps": 1e400,
                                "render_width": 8, "render_height": 8}))
    rc, err = run_cli(["render", "--run", scene["run"], "--path", path, "--quiet"], capsys)
    assert_one_line_error(rc, err, str(path), "'fps'")
    assert snapshot(scene["data"], scene["run"]) == before
    assert not (scene["run"] / "videos").exists()


def test_video_of_a_run_without_weights_adds_nothing(scene, capsys, tmp_path):
    """Failed: the videos/ folder was made before the weights were read."""
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    shutil.rmtree(run / "checkpoints")
    before = snapshot(run)
    rc, err = run_cli(["render", "--run", run, "--orbit", "--frames", "2", "--width", "16", "--quiet"], capsys)
    assert_one_line_error(rc, err, "checkpoints")
    assert snapshot(run) == before


def _photos(folder: Path, count: int = 4) -> Path:
    rng = np.random.default_rng(0)
    for i in range(count):
        io.write_png(folder / f"p{i}.png", rng.random((24, 32, 3)))
    return folder


@pytest.mark.parametrize("spec, names", [
    ("1,1,1,1,1,1,5", ["--scale-bar", "same point"]),
    ("0,0,0,1,nan,1,5", ["--scale-bar", "finite"]),
    ("0,0,0,1,1,1,inf", ["--scale-bar", "positive"]),
    ("p0.png:3,4;p1.png:5,6;p0.png:3,4;p1.png:5,6;2", ["--scale-bar", "same pixels"]),
], ids=["same_points", "nan_coordinate", "infinite_metres", "same_pixels"])
def test_degenerate_scale_bar_is_refused_before_colmap(capsys, tmp_path, spec, names):
    """Failed: a bar whose two ends are one point was accepted; COLMAP then ran to a useless end."""
    pytest.importorskip("pycolmap")
    photos = _photos(tmp_path / "photos")
    before = snapshot(photos)
    rc, err = run_cli(["poses", "--images", photos, "--out", tmp_path / "d", "--scale-bar", spec, "--quiet"], capsys)
    assert_one_line_error(rc, err, *names)
    assert snapshot(photos) == before and sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


def test_text_inputs_that_are_not_utf8_are_named(scene, capsys, tmp_path):
    """Failed: a --gcp file in another encoding ended in a UnicodeDecodeError traceback. Every
    text the user gives goes through `io.read_text` (JSON, CSV)."""
    pytest.importorskip("pycolmap")
    photos = _photos(tmp_path / "photos")
    gcp = tmp_path / "gcp.csv"
    gcp.write_bytes("image,x,y,X,Y,Z\np0.png,1,2,3,4,5 # M\u00fcller\n".encode("utf-16"))
    before = snapshot(photos, gcp)
    rc, err = run_cli(["poses", "--images", photos, "--out", tmp_path / "d", "--gcp", gcp, "--quiet"], capsys)
    assert_one_line_error(rc, err, str(gcp), "UTF-8")
    assert snapshot(photos, gcp) == before and not (tmp_path / "d").exists()
    transforms = tmp_path / "t.json"
    transforms.write_bytes(b'{"frames": [], "note": "Gepr\xfcft"}')
    with pytest.raises(io.DataError, match="t.json.*UTF-8"):
        io.read_json(transforms)


def test_mask_error_leaves_no_staging_folder_and_one_line(scene, capfd, tmp_path):
    """Failed: a truncated photo left `.jaxnerf-grid-mask-new/` in the dataset, and OpenCV's own
    "[ WARN:0@...] global grfmt_png.cpp" line came before the error."""
    data = tmp_path / "data"
    shutil.copytree(scene["data"], data)
    raw = first_image(data).read_bytes()
    first_image(data).write_bytes(raw[: len(raw) * 2 // 5])
    before = snapshot(data)
    capfd.readouterr()
    rc = cli.main(["mask", "--data", str(data), "--max-side", "32", "--quiet"])
    err = capfd.readouterr().err
    assert_one_line_error(rc, err, str(first_image(data)), "not a readable image")
    assert snapshot(data) == before
    assert not (data / masking.STAGING).exists()


def test_eval_refuses_an_empty_reference_before_rendering(scene, capsys, tmp_path):
    """Failed: an empty or non-finite --reference-ply was found only after the test views were
    rendered into the run (depth/, renders/ written, then the error)."""
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    header = ("ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n"
              "end_header\n")
    for name, body in (("empty.ply", header.format(0)), ("nan.ply", header.format(1) + "nan 0 0\n")):
        ref = tmp_path / name
        ref.write_text(body)
        before = snapshot(run)
        rc, err = run_cli(["eval", "--run", run, "--reference-ply", ref, "--quiet"], capsys)
        assert_one_line_error(rc, err, str(ref))
        assert snapshot(run) == before


def test_export_keeps_a_report_that_is_not_utf8_and_takes_a_negative_box(scene, capsys, tmp_path):
    """Failed twice: `--box -30,...` was read as an unknown flag ("expected one argument"), and a
    run report.md saved in Latin-1 ended export in a UnicodeDecodeError traceback after its files
    were written. Now the box is taken and the report keeps its bytes, the Tower model added."""
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    notes = "# Mast 7\n\nGepr\u00fcft von J. M\u00fcller\n".encode("latin-1")
    (run / "report.md").write_bytes(notes)
    rc, err = run_cli(["export", "--run", run, "--box", "-30,-30,-1,30,30,40", "--resolution", "8", "--views", "1",
                       "--quiet"], capsys)
    assert rc == 0 and "Traceback" not in err, err
    report = (run / "report.md").read_bytes()
    assert report.startswith(notes) and b"Tower model" in report[len(notes):]
    assert json.loads((run / "export" / "box.json").read_text())["min"][0] == pytest.approx(-30)


def test_negative_values_join_their_flag_as_argparse_reads_them():
    """`join_negative_values` against argparse's own `--flag=value` spelling."""
    parser = cli_train.build_parser()
    argv = ["--data", "d", "--set", "-1", "--max-side", "-3", "--steps", "-5", "--overwrite", "--out", "-x"]
    joined = cli_flags.join_negative_values(argv)
    assert joined == ["--data", "d", "--set=-1", "--max-side=-3", "--steps=-5", "--overwrite", "--out", "-x"]
    spelled = parser.parse_args(["--data", "d", "--set=-1", "--max-side=-3", "--steps=-5", "--overwrite"])
    assert vars(parser.parse_args(joined[:-2])) == vars(spelled)
    assert cli_flags.join_negative_values(["--box=-1,2", "--", "--box", "-3,4"]) == ["--box=-1,2", "--", "--box",
                                                                                      "-3,4"]


def _one_value_or_none(action) -> bool:
    """True for an option that takes exactly one value (store, append) or none (a switch, help)."""
    return action.nargs is None or action.nargs == 0


def test_every_option_takes_one_value_or_none():
    """What `join_negative_values` relies on, reading argv only: no subcommand has an option of
    several values (`nargs`) or a positional argument, so `--flag -3,4` always means
    `--flag=-3,4`, and a switch given such a value stays an error."""
    import importlib

    for name, (module, _) in cli.SUBCOMMANDS.items():
        parser = importlib.import_module(module).build_parser()
        actions = parser._actions  # the test may read argparse's internals; the library does not
        assert all(a.option_strings for a in actions), (name, "a positional argument")
        assert all(_one_value_or_none(a) for a in actions), (name, [a.option_strings for a in actions
                                                                    if not _one_value_or_none(a)])
    parser = importlib.import_module("jaxnerf_grid.cli.render").build_parser()
    with pytest.raises(SystemExit):  # a switch given a value: argparse's error, as before the join
        parser.parse_args(cli_flags.join_negative_values(["--run", "r", "--quiet", "-3,4"]))


def test_warnings_are_one_line_each(scene, tmp_path):
    """Failed: a checkpoint that could not be read printed Python's warning with its source line
    (three lines before the error). A child process: pytest records warnings itself."""
    run = tmp_path / "run"
    shutil.copytree(scene["run"], run)
    for p in (run / "checkpoints").rglob("*"):
        if p.is_file():
            p.write_bytes(b"")
    done = subprocess.run([sys.executable, "-m", "jaxnerf_grid", "render", "--run", str(run), "--quiet"],
                          capture_output=True, text=True, timeout=600, cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"})
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and "Traceback" not in done.stderr and len(lines) >= 2, done.stderr
    assert all(line.startswith("jaxnerf-grid render: warning: ") for line in lines[:-1]), done.stderr
    assert lines[-1].startswith("jaxnerf-grid render: error: ") and "checkpoints" in lines[-1]


@pytest.mark.parametrize("command", ["train", "demo"])
def test_max_side_names_the_flag(scene, capsys, tmp_path, command):
    """Failed: `--max-side -3` was refused naming the key train.max_side, not the flag."""
    argv = ([command, "--data", scene["data"], "--out", tmp_path / "r", "--max-side", "-3", "--quiet"]
            + ([*PAPER_MLP, "--config", scene["cfg"]] if command == "train" else []))
    rc, err = run_cli(argv, capsys)
    assert_one_line_error(rc, err, "--max-side", "-3")
    assert not (tmp_path / "r").exists()


# --- a sample of the cases that held ---

@pytest.mark.parametrize("body, names", [
    (None, ["nope.json", "not found"]),
    ("[1, 2]", ["camera_path"]),
    ('{"camera_path": [{"camera_to_world": [NaN,0,0,0,0,1,0,0,0,0,1,3,0,0,0,1], "fov": 50}]}', ["camera_path[0]"]),
    (json.dumps({"camera_path": [{"camera_to_world": GOOD_POSE, "fov": 180}]}), ["fov"]),
    (json.dumps({"camera_path": [{"camera_to_world": GOOD_POSE, "fov": 50}], "render_width": 0}), ["render_width"]),
], ids=["missing", "a_list", "nan_matrix", "fov_180", "width_0"])
def test_bad_camera_path_is_one_line(scene, capsys, tmp_path, body, names):
    path = tmp_path / "nope.json"
    if body is not None:
        path.write_text(body)
    before = snapshot(scene["data"], scene["run"])
    rc, err = run_cli(["render", "--run", scene["run"], "--path", path, "--quiet"], capsys)
    assert_one_line_error(rc, err, str(path), *names)
    assert snapshot(scene["data"], scene["run"]) == before


@pytest.mark.parametrize("origin", ["91,0,0", "47,8", "47,8,inf", "Z\u00fcrich", "-91,8,400"])
def test_bad_gps_origin_is_refused_before_writing(capsys, tmp_path, origin):
    rc, err = run_cli(["synth", "--out", tmp_path / "s", *SYNTH, "--gps-origin", origin], capsys)
    assert_one_line_error(rc, err, "--gps-origin")
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("edit", ["no_frames", "nan_pose", "truncated"])
def test_broken_transforms_json_is_named(scene, capsys, tmp_path, edit):
    data = tmp_path / "data"
    shutil.copytree(scene["data"], data)
    meta = json.loads((data / "transforms.json").read_text())
    if edit == "no_frames":
        meta["frames"] = []
    elif edit == "nan_pose":
        meta["frames"][0]["transform_matrix"] = [[float("nan")] * 4] * 4
    text = json.dumps(meta)
    (data / "transforms.json").write_text(text[: len(text) // 2] if edit == "truncated" else text)
    before = snapshot(data)
    rc, err = run_cli(["train", *PAPER_MLP, "--data", data, "--method", "nerf", "--config", scene["cfg"],
                       "--out", tmp_path / "r", "--quiet"], capsys)
    assert_one_line_error(rc, err, "transforms.json")
    assert snapshot(data) == before and not (tmp_path / "r").exists()


@pytest.mark.parametrize("command", ["train", "demo"])
def test_bad_timeout_variables_are_named_in_a_single_process_run(scene, capsys, tmp_path, monkeypatch, command):
    """Failed: JAXNERF_*_TIMEOUT values were checked only in a multi-process run; a single
    process trained with `JAXNERF_CONNECT_TIMEOUT=soon` in its environment without a word."""
    monkeypatch.setenv("JAXNERF_CONNECT_TIMEOUT", "soon")
    argv = ([command, "--data", scene["data"], "--out", tmp_path / "r", "--quiet"]
            + (["--config", scene["cfg"]] if command == "train" else []))
    rc, err = run_cli(argv, capsys)
    assert_one_line_error(rc, err, "JAXNERF_CONNECT_TIMEOUT", "soon")
    assert not (tmp_path / "r").exists()


# --- process-wide side effects, scoped to the command line ---

def _opencv_level() -> int:
    import cv2

    return cv2.utils.logging.getLogLevel()


def test_the_command_line_restores_the_warning_format_and_opencv_log(scene, capfd, tmp_path):
    """`cli.main` prints one-line warnings and quiets OpenCV's log only while it runs: after it
    returns (an error, a success, argparse's SystemExit) both are what they were before."""
    import warnings

    import cv2

    data = tmp_path / "data"
    shutil.copytree(scene["data"], data)
    raw = first_image(data).read_bytes()
    first_image(data).write_bytes(raw[: len(raw) * 2 // 5])
    mine = lambda message, *_: f"mine: {message}\n"  # noqa: E731
    before_level, before_format = _opencv_level(), warnings.formatwarning
    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_INFO)  # not OpenCV's default: seen restored
        warnings.formatwarning = mine
        capfd.readouterr()
        rc = cli.main(["train", *PAPER_MLP, "--data", str(data), "--method", "nerf", "--config", str(scene["cfg"]),
                       "--out", str(tmp_path / "r"), "--quiet"])
        err = capfd.readouterr().err
        assert_one_line_error(rc, err, str(first_image(data)))  # quiet inside: no "[ WARN" line from OpenCV
        assert warnings.formatwarning is mine and _opencv_level() == cv2.utils.logging.LOG_LEVEL_INFO
        assert cli.main(["recipes"]) == 0
        assert warnings.formatwarning is mine and _opencv_level() == cv2.utils.logging.LOG_LEVEL_INFO
        with pytest.raises(SystemExit):
            cli.main(["render", "--frames"])
        assert warnings.formatwarning is mine and _opencv_level() == cv2.utils.logging.LOG_LEVEL_INFO
    finally:
        warnings.formatwarning = before_format
        cv2.utils.logging.setLogLevel(before_level)


IMPORT_EVERYTHING = """
import importlib, pkgutil, sys, warnings
import cv2
import numpy as np
level, fmt = cv2.utils.logging.getLogLevel(), warnings.formatwarning
import jaxnerf_grid
for m in pkgutil.walk_packages(jaxnerf_grid.__path__, "jaxnerf_grid."):
    if not m.name.endswith("__main__"):
        importlib.import_module(m.name)
from jaxnerf_grid.util import io
try:
    io.read_image(sys.argv[1])
except io.DataError:
    pass
io.resize(np.zeros((4, 4), np.float32), (2, 2))
assert cv2.utils.logging.getLogLevel() == level, (level, cv2.utils.logging.getLogLevel())
assert warnings.formatwarning is fmt
print("unchanged", level)
"""


def test_the_library_leaves_the_warning_format_and_opencv_log_alone(scene, tmp_path):
    """Importing every module of the package, and reading a corrupt image through `io`, changes
    neither `warnings.formatwarning` nor OpenCV's log level (a program using the library keeps
    its own); OpenCV's warning about the corrupt image then reaches stderr, as OpenCV prints it."""
    bad = tmp_path / "bad.png"
    raw = first_image(scene["data"]).read_bytes()
    bad.write_bytes(raw[: len(raw) * 2 // 5])
    done = subprocess.run([sys.executable, "-c", IMPORT_EVERYTHING, str(bad)], capture_output=True, text=True,
                          timeout=300, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"})
    assert done.returncode == 0 and "unchanged" in done.stdout, done.stderr[-2000:]
    assert "WARN" in done.stderr and "grfmt_png" in done.stderr, done.stderr[-2000:]


# --- render --orbit killed mid-video ---

VIDEO = ["--orbit", "--frames", "4", "--width", "16", "--quiet"]


def _slow_video_child(run: str, out: str, pause: str) -> None:
    """`render --orbit` with a pause after each frame written, so the parent can kill it while
    its staging files exist."""
    from jaxnerf_grid.render import videos

    real = videos.open_writer

    class Slow:
        def __init__(self, writer):
            self.writer = writer

        def write(self, frame):
            self.writer.write(frame)
            time.sleep(float(pause))

        def release(self):
            self.writer.release()

    videos.open_writer = lambda *args, **kwargs: Slow(real(*args, **kwargs))
    sys.exit(cli.main(["render", "--run", run, "--out", out, *VIDEO]))


def _frames(path: Path) -> np.ndarray:
    import cv2

    cap, frames = cv2.VideoCapture(str(path)), []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    return np.asarray(frames)


def test_killed_video_leaves_a_partial_the_next_render_removes(scene, tmp_path):
    """kill -9 of `render --orbit` while it writes left `.orbit.partial.mp4` that nothing removed.
    The next render to the same --out removes its own leftovers (a dead process's staging files)
    and nothing else: the user's files, a file of a similar name, a live render's staging file
    and another host's stay byte for byte; the videos are those of an uninterrupted render."""
    from jaxnerf_grid.render import videos

    ref = tmp_path / "ref"
    assert cli.main(["render", "--run", str(scene["run"]), "--out", str(ref / "orbit"), *VIDEO]) == 0
    folder = tmp_path / "videos"
    folder.mkdir()
    (folder / "notes.txt").write_text("the client's notes")
    (folder / ".orbit.partial.keep.txt").write_text("not a video")
    (folder / "orbit.mp4.bak").write_bytes(b"an older video the user kept")
    (folder / f".orbit.partial.elsewhere.{os.getpid()}.mp4").write_bytes(b"another host's render")
    live = folder / f".orbit_depth.partial.{socket.gethostname()}.{os.getppid()}.mp4"
    live.write_bytes(b"a render still running here")
    users = snapshot(folder)
    run_before = snapshot(scene["run"])

    def partials() -> list:
        """The child's colour staging files that hold frames (none while it starts up)."""
        found = []
        for p in folder.iterdir():
            try:
                if (p.name.startswith(".orbit.partial.") and p.name.endswith(".mp4") and "elsewhere" not in p.name
                        and p.stat().st_size > 0):
                    found.append(p)
            except FileNotFoundError:  # renamed between the listing and the stat
                pass
        return found

    kill_when([__file__, "video", str(scene["run"]), str(folder / "orbit"), "0.5"], timeout=600,
              ready=lambda: bool(partials()))
    assert partials() and not (folder / "orbit.mp4").exists()  # it really died mid-video
    assert cli.main(["render", "--run", str(scene["run"]), "--out", str(folder / "orbit"), *VIDEO]) == 0
    assert snapshot(folder / "notes.txt", folder / ".orbit.partial.keep.txt", folder / "orbit.mp4.bak",
                    folder / f".orbit.partial.elsewhere.{os.getpid()}.mp4", live) == users
    assert sorted(p.name for p in folder.iterdir()) == sorted([*(Path(k).name for k in users), "orbit.mp4",
                                                               "orbit_depth.mp4"])
    for name in ("orbit.mp4", "orbit_depth.mp4"):
        np.testing.assert_array_equal(_frames(folder / name), _frames(ref / name))
        assert len(_frames(folder / name)) == 4
    assert snapshot(scene["run"]) == run_before
    assert videos.stale_partials(folder / "orbit.mp4") == []


def test_stale_partials_are_only_a_dead_renders_own(tmp_path):
    """`videos.stale_partials` against the processes it names: a finished child's id is stale, the
    test's parent (running) and another host's are not, nor any other name."""
    from jaxnerf_grid.render import videos

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = socket.gethostname()
    names = {f".orbit.partial.{host}.{dead.pid}.mp4": True, ".orbit.partial.mp4": True,
             f".orbit.partial.{host}.{os.getppid()}.mp4": False, f".orbit.partial.other-host.{dead.pid}.mp4": False,
             f".orbit_depth.partial.{host}.{dead.pid}.mp4": False, f"orbit.partial.{host}.{dead.pid}.mp4": False,
             f".orbit.partial.{host}.{dead.pid}.mp4.txt": False, "orbit.mp4": False}
    for name in names:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / f".orbit.partial.{host}.{dead.pid + 1000000}").mkdir()
    stale = {p.name for p in videos.stale_partials(tmp_path / "orbit.mp4")}
    assert stale == {name for name, is_stale in names.items() if is_stale}
    assert videos.stale_partials(tmp_path / "missing" / "orbit.mp4") == []


if __name__ == "__main__":
    if sys.argv[1] == "video":
        _slow_video_child(*sys.argv[2:])


def test_a_video_opencv_could_not_finish_is_refused_not_renamed(tmp_path, monkeypatch):
    """OpenCV's VideoWriter drops frames it cannot write (a full disk) without a word: the video
    is read back before it is renamed (`videos.check_written`); the error names the video, an
    earlier one stays, no staging file is left. The writer here stops writing after 2 frames."""
    from jaxnerf_grid.render import videos
    from jaxnerf_grid.util import progress

    video, depth = tmp_path / "orbit.mp4", tmp_path / "orbit_depth.mp4"
    video.write_bytes(b"the earlier video")
    real = videos.open_writer

    class Dropping:
        def __init__(self, writer):
            self.writer, self.count = writer, 0

        def write(self, frame):
            self.count += 1
            if self.count <= 2:
                self.writer.write(frame)

        def release(self):
            self.writer.release()

    monkeypatch.setattr(videos, "open_writer", lambda *a, **kw: Dropping(real(*a, **kw)))
    render = lambda k: {"rgb": np.full((6, 8, 3), 0.1 * k), "depth": np.full((6, 8), 2.0 + k)}  # noqa: E731
    with pytest.raises(io.DataError, match=r"orbit.mp4: cannot write \(2 of 4 frames could be read back"):
        videos.write_videos(video, depth, [(k,) for k in range(4)], render, 5.0, 8, 6, progress.bar(enabled=False))
    assert video.read_bytes() == b"the earlier video"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["orbit.mp4"]
    monkeypatch.setattr(videos, "open_writer", real)
    assert videos.write_videos(video, depth, [(k,) for k in range(4)], render, 5.0, 8, 6,
                               progress.bar(enabled=False)) == 4
    assert len(_frames(video)) == 4 and len(_frames(depth)) == 4
