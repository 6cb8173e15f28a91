"""A hostile-user corpus run against the real command line.

    python scripts/hostile_corpus.py WORK_DIR [--only ID[,ID...]] [--summary FILE]

Builds one tiny `synth` scene (32x24, 6 + 2 frames, with GPS photos) and one finished 10-step run
(a 2x32 MLP) in WORK_DIR, then runs each case below as a subprocess of
`python -m jaxnerf_grid ...` in a folder of its own. For each case it records the exit code,
whether stderr is one line of error naming the expected file or key (argparse's usage block
before its one error line is allowed), whether a traceback appeared, and which files of the
protected trees (the dataset, the run and the case's own inputs; sha256 of every file before
and after) were lost, changed or added. A case holds when the outcome is the expected one (an
error: non-zero exit, one line naming what is wrong, nothing written into the protected trees;
a success: exit 0; "any": either, an error's last line naming it, notices before it allowed)
with no traceback and nothing lost. One-line warnings (`jaxnerf-grid NAME: warning: ...`) may
come before the error line. Writes WORK_DIR/summary.json (or
--summary) and prints one line per case. Not run in CI (minutes on two CPU cores);
tests/cli/test_hostile_corpus.py holds the cases that failed, and a sample of those that held.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the suite's helpers are the package `tests`
from tests.cli.test_bad_input import SYNTH, TINY  # noqa: E402  (the suite's tiny run and scene, shared)
from tests.support import unprivileged  # noqa: E402  (setpriv, the tmpfs of a full disk)

TRAIN = ["train", "--recipe", "ours-paper-mlp", "--method", "nerf", "--quiet"]


def snapshot(*roots: Path) -> dict:
    """{path: sha256 of the file, "dir" for a folder, "link -> target" for a link} under the roots."""
    out = {}
    for root in roots:
        if root.is_symlink():
            out[str(root)] = f"link -> {os.readlink(root)}"
        elif root.is_file():
            out[str(root)] = hashlib.sha256(root.read_bytes()).hexdigest()
        elif root.is_dir():
            for p in sorted(root.rglob("*")):
                if p.is_symlink():
                    out[str(p)] = f"link -> {os.readlink(p)}"
                elif p.is_dir():
                    out[str(p)] = "dir"
                elif p.is_file():
                    out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def cli(argv, cwd: Path, env: dict | None = None, timeout: float = 300, nobody: dict | None = None
        ) -> subprocess.CompletedProcess:
    """`python -m jaxnerf_grid argv` in cwd (this checkout's package first on the path). With
    `nobody` ({"home": a folder it may write, "disk": a folder, "disk_kib": KiB}, the last two
    optional), as the unprivileged user 65534, on a tmpfs of disk_kib at disk when given
    (tests/support/unprivileged.py)."""
    full_env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": os.environ.get("JAX_PLATFORMS", "cpu"),
                **(env or {})}
    command = [sys.executable, "-m", "jaxnerf_grid", *[str(a) for a in argv]]
    if nobody is not None:
        full_env = {**unprivileged.environment(nobody["home"]), **(env or {})}
        command = unprivileged.as_nobody(command[1:], nobody.get("disk"), nobody.get("disk_kib", 0))
    return subprocess.run(command, cwd=cwd, env=full_env, capture_output=True, text=True, timeout=timeout)


def error_lines(stderr: str) -> list[str]:
    """The lines of stderr that are not argparse's usage block (usage: ... up to its error line)
    nor a progress bar's carriage-return updates."""
    lines, in_usage = [], False
    for line in stderr.splitlines():
        if line.startswith("usage:"):
            in_usage = True
            continue
        if in_usage and line.startswith(" "):
            continue
        in_usage = False
        if line.strip() and "\r" not in line and "it/s]" not in line and "s/it]" not in line:
            lines.append(line)
    return lines


def build_fixtures(work: Path) -> dict:
    """The shared dataset (with photos_gps/) and finished run, built once per WORK_DIR and kept
    pristine in WORK/pristine/ (`fresh_fixtures` copies them back before each case)."""
    data, run, cfg, pristine = work / "data", work / "run", work / "tiny.json", work / "pristine"
    cfg.write_text(json.dumps(TINY))
    if not (pristine / "run" / "config.json").exists():
        shutil.rmtree(data, ignore_errors=True)
        shutil.rmtree(run, ignore_errors=True)
        done = cli(["synth", "--out", data, *SYNTH, "--gps-origin", "47.0,8.0,500"], work)
        assert done.returncode == 0, done.stderr
        done = cli([*TRAIN, "--data", data, "--config", cfg, "--out", run], work)
        assert done.returncode == 0, done.stderr
        shutil.rmtree(pristine, ignore_errors=True)
        pristine.mkdir()
        shutil.copytree(data, pristine / "data", symlinks=True)
        shutil.copytree(run, pristine / "run", symlinks=True)
    return {"data": data, "run": run, "cfg": cfg, "work": work}


def fresh_fixtures(f: dict) -> None:
    """The dataset and the run as built (one case's fault never leaks into the next)."""
    for name in ("data", "run"):
        shutil.rmtree(f[name], ignore_errors=True)
        shutil.copytree(f["work"] / "pristine" / name, f[name], symlinks=True)


# --- helpers that prepare a case's inputs in its folder `d` (fixtures in `f`) ---

def copy_data(f, d, name="data"):
    shutil.copytree(f["data"], d / name, symlinks=True)
    return d / name


def copy_run(f, d, data=None, name="run"):
    """A copy of the run; with `data`, its config names that copy of the dataset."""
    shutil.copytree(f["run"], d / name, symlinks=True)
    if data is not None:
        cfg_path = d / name / "config.json"
        cfg = json.loads(cfg_path.read_text())
        text = json.dumps(cfg).replace(json.dumps(str(f["data"]))[1:-1], str(data))
        cfg_path.write_text(text)
    return d / name


def first_image(data: Path, split="train") -> Path:
    frames = json.loads((data / "transforms.json").read_text())["frames"]
    return data / frames[0]["file_path"]


def write_path_json(d, body, name="path.json"):
    p = d / name
    p.write_bytes(body if isinstance(body, bytes) else (body if isinstance(body, str) else json.dumps(body)).encode())
    return p


def photos(f, d, count=6):
    """A folder of the synthetic scene's GPS photos (JPEG with EXIF)."""
    out = d / "photos"
    out.mkdir()
    for p in sorted((f["data"] / "photos_gps").glob("*.jpg"))[:count]:
        shutil.copy(p, out / p.name)
    return out


def image_mode(f, d, convert):
    """A dataset copy whose first training photo is rewritten by `convert(PIL image) -> image`."""
    from PIL import Image

    data = copy_data(f, d)
    img = first_image(data)
    convert(Image.open(img)).save(img)
    return data


def truncate(path: Path, keep: float = 0.5):
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * keep)])


GOOD_POSE = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 3, 0, 0, 0, 1]


def case_list():
    """(id, kind, prepare(f, d) -> {"argv", "protect", "env"}, expect "error"|"ok", names)."""
    C = []

    def add(cid, kind, prepare, expect="error", names=()):
        C.append({"id": cid, "kind": kind, "prepare": prepare, "expect": expect, "names": list(names)})

    R = lambda f, d, *a, **kw: {"argv": ["render", "--run", f["run"], "--quiet", *a], "protect": [], **kw}  # noqa: E731
    # render: camera paths and video flags
    add("render_path_missing", "missing file", lambda f, d: R(f, d, "--path", d / "nope.json"), names=["nope.json"])
    add("render_path_not_json", "bad JSON", lambda f, d: R(f, d, "--path", write_path_json(d, "{camera_path: [")),
        names=["path.json"])
    add("render_path_a_list", "bad JSON", lambda f, d: R(f, d, "--path", write_path_json(d, [1, 2])),
        names=["path.json"])
    add("render_path_nan_matrix", "bad JSON", lambda f, d: R(f, d, "--path", write_path_json(
        d, '{"camera_path": [{"camera_to_world": [NaN,0,0,0,0,1,0,0,0,0,1,3,0,0,0,1], "fov": 50}]}')),
        names=["path.json", "camera_path[0]"])
    add("render_path_fov_zero", "bad JSON", lambda f, d: R(f, d, "--path", write_path_json(
        d, {"camera_path": [{"camera_to_world": GOOD_POSE, "fov": 0}]})), names=["path.json", "fov"])
    add("render_path_fov_180", "bad JSON", lambda f, d: R(f, d, "--path", write_path_json(
        d, {"camera_path": [{"camera_to_world": GOOD_POSE, "fov": 180}]})), names=["path.json", "fov"])
    add("render_path_size_zero", "bad JSON", lambda f, d: R(f, d, "--path", write_path_json(
        d, {"camera_path": [{"camera_to_world": GOOD_POSE, "fov": 50}], "render_width": 0})),
        names=["path.json", "render_width"])
    add("render_path_latin1", "bad JSON", lambda f, d: R(f, d, "--path", write_path_json(
        d, b'{"camera_path": [], "note": "M\xe4st"}')), names=["path.json"])
    add("render_path_is_a_folder", "bad file", lambda f, d: R(f, d, "--path", d), names=["--path"])
    add("render_orbit_frames_0", "bad flag", lambda f, d: R(f, d, "--orbit", "--frames", "0"), names=["--frames"])
    add("render_orbit_width_negative", "bad flag", lambda f, d: R(f, d, "--orbit", "--width", "-5"),
        names=["--width"])
    add("render_orbit_fps_nan", "bad flag", lambda f, d: R(f, d, "--orbit", "--fps", "nan"), names=["--fps"])
    add("render_orbit_width_huge", "bad flag", lambda f, d: R(f, d, "--orbit", "--width", "10000000"),
        names=["--width"])
    add("render_orbit_out_in_dataset", "data stranded",
        lambda f, d: R(f, d, "--orbit", "--frames", "2", "--width", "16", "--out", f["data"] / "orbit"),
        names=["--out"])
    add("render_orbit_out_parent_a_file", "full disk / permission",
        lambda f, d: (d / "afile").write_text("x") and R(f, d, "--orbit", "--frames", "2", "--width", "16",
                                                         "--out", d / "afile" / "orbit"), names=["afile"])
    add("render_orbit_non_ascii_out", "non-ASCII path",
        lambda f, d: R(f, d, "--orbit", "--frames", "2", "--width", "16", "--out", d / "Mast ü 1" / "orbit"),
        expect="ok")

    # render / eval / export on a run missing pieces
    def run_without(piece):
        def prep(f, d, cmd):
            run = copy_run(f, d)
            target = run / piece
            shutil.rmtree(target) if target.is_dir() else target.unlink()
            return {"argv": [cmd, "--run", run, "--quiet"], "protect": [run]}
        return prep

    for cmd in ("render", "eval", "export"):
        add(f"{cmd}_run_without_checkpoints", "run missing pieces",
            lambda f, d, cmd=cmd: run_without("checkpoints")(f, d, cmd), names=["checkpoints"])
    add("render_run_without_config", "run missing pieces",
        lambda f, d: run_without("config.json")(f, d, "render"), names=["config.json"])
    add("eval_run_without_dataset_json", "run missing pieces",
        lambda f, d: {**run_without("dataset.json")(f, d, "eval"), "may_change": True}, expect="ok")

    def run_with_empty_checkpoint(f, d, cmd="render"):
        run = copy_run(f, d)
        ckpts = sorted(p for p in (run / "checkpoints").iterdir())
        for p in ckpts:
            if p.is_file():
                p.write_bytes(b"")
            else:
                for q in p.rglob("*"):
                    if q.is_file():
                        q.write_bytes(b"")
        return {"argv": [cmd, "--run", run, "--quiet"], "protect": [run]}

    add("render_all_checkpoints_empty", "bad file", run_with_empty_checkpoint, names=["checkpoints"])

    def images_deleted(cmd):
        def prep(f, d):
            data = copy_data(f, d)
            run = copy_run(f, d, data)
            frames = json.loads((data / "transforms.json").read_text())["frames"]
            for fr in frames:
                (data / fr["file_path"]).unlink()
            return {"argv": [cmd, "--run", run, "--quiet"] if cmd != "train" else
                    [*TRAIN, "--data", data, "--config", f["cfg"], "--out", d / "newrun"],
                    "protect": [data, run], "absent": [d / "newrun"]}
        return prep

    for cmd in ("render", "eval", "export", "train"):
        add(f"{cmd}_images_deleted_after_poses", "missing file", images_deleted(cmd), names=["images"])

    # eval inputs
    E = lambda f, d, *a: {"argv": ["eval", "--run", f["run"], "--quiet", *a], "protect": []}  # noqa: E731
    add("eval_lpips_weights_corrupt", "bad file",
        lambda f, d: (d / "lpips.npz").write_bytes(b"PK\x03\x04garbage") and E(f, d, "--lpips-weights",
                                                                            d / "lpips.npz"), names=["lpips.npz"])
    add("eval_reference_ply_is_a_folder", "bad file", lambda f, d: E(f, d, "--reference-ply", d), names=[])
    add("eval_reference_ply_no_vertices", "bad PLY",
        lambda f, d: (d / "ref.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                                "property float y\nproperty float z\nend_header\n")
        and E(f, d, "--reference-ply", d / "ref.ply"), names=["ref.ply"])
    add("eval_reference_ply_short_binary", "bad PLY",
        lambda f, d: (d / "ref.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\n"
                                                 b"property float x\nproperty float y\nproperty float z\n"
                                                 b"end_header\n" + b"\0" * 40)
        and E(f, d, "--reference-ply", d / "ref.ply"), names=["ref.ply"])

    def eval_metrics_is_a_folder(f, d):
        run = copy_run(f, d)
        (run / "metrics.json").unlink(missing_ok=True)
        (run / "metrics.json").mkdir()
        (run / "metrics.json" / "keep.txt").write_text("user file")
        return {"argv": ["eval", "--run", run, "--quiet"], "protect": [run / "metrics.json"]}

    def eval_report_latin1(f, d, cmd, *extra):
        run = copy_run(f, d)
        (run / "report.md").write_bytes("# Mast 7 \u2013 notes\n\nGepr\u00fcft von J. M\u00fcller\n".encode("latin-1",
                                                                                                  "replace"))
        return {"argv": [cmd, "--run", run, "--quiet", *extra], "protect": []}

    # report.md is eval's own output (replaced whole); export adds its section to it
    add("eval_report_not_utf8", "bad file", lambda f, d: eval_report_latin1(f, d, "eval"), expect="ok")
    add("export_report_not_utf8", "bad file", lambda f, d: eval_report_latin1(
        f, d, "export", "--resolution", "8", "--views", "1", "--box=-30,-30,-1,30,30,40"), expect="any")
    add("eval_metrics_json_is_a_folder", "permission / OS error", eval_metrics_is_a_folder, names=["metrics.json"])

    # export flags
    X = lambda f, d, *a: {"argv": ["export", "--run", f["run"], "--out", d / "exp", "--quiet", *a],  # noqa: E731
                          "protect": [], "absent": [d / "exp"]}
    add("export_box_three_numbers", "bad flag", lambda f, d: X(f, d, "--box", "1,2,3"), names=["--box"])
    add("export_box_min_above_max", "bad flag", lambda f, d: X(f, d, "--box", "1,1,1,0,0,0"), names=["--box"])
    add("export_box_negative_first", "unclear error", lambda f, d: X(f, d, "--box", "-30,-30,-1,30,30,40",
                                                                      "--resolution", "8", "--views", "1"),
        expect="ok")
    add("export_box_nan", "bad flag", lambda f, d: X(f, d, "--box", "nan,0,0,1,1,1"), names=["--box"])
    add("export_threshold_1_5", "bad flag", lambda f, d: X(f, d, "--threshold", "1.5"), names=["--threshold"])
    add("export_threshold_nan", "bad flag", lambda f, d: X(f, d, "--threshold", "nan"), names=["--threshold"])
    add("export_views_0", "bad flag", lambda f, d: X(f, d, "--views", "0"), names=["--views"])
    add("export_out_dangling_link", "symlink",
        lambda f, d: (d / "exp").symlink_to(d / "gone") or
        {"argv": ["export", "--run", f["run"], "--out", d / "exp", "--quiet", "--resolution", "8", "--views", "1"],
         "protect": [d / "exp"]}, expect="any")

    # poses
    def P(*a, photos_count=6):
        def prep(f, d):
            imgs = photos(f, d, photos_count)
            return {"argv": ["poses", "--images", imgs, "--out", d / "ds", "--quiet", *a], "protect": [imgs],
                    "absent": [d / "ds"]}
        return prep

    add("poses_images_missing", "missing file",
        lambda f, d: {"argv": ["poses", "--images", d / "nope", "--out", d / "ds", "--quiet"], "protect": [],
                      "absent": [d / "ds"]}, names=["nope"])
    add("poses_images_empty", "missing file",
        lambda f, d: (d / "empty").mkdir() or {"argv": ["poses", "--images", d / "empty", "--out", d / "ds",
                                                        "--quiet"], "protect": [d / "empty"],
                                               "absent": [d / "ds"]}, names=["empty"])
    add("poses_crs_unknown_code", "bad flag", P("--crs", "EPSG:99999999"), names=["--crs"])
    add("poses_crs_not_a_crs", "bad flag", P("--crs", "metres please"), names=["--crs"])
    add("poses_crs_geographic", "bad flag", P("--crs", "EPSG:4326"), names=["--crs"])
    add("poses_gcp_missing", "missing file", P("--gcp", "/nonexistent/gcp.csv"), names=["gcp.csv"])

    def gcp_file(body):
        def prep(f, d):
            out = P("--gcp", d / "gcp.csv")(f, d)
            (d / "gcp.csv").write_bytes(body if isinstance(body, bytes) else body.encode())
            out["protect"].append(d / "gcp.csv")
            return out
        return prep

    add("poses_gcp_not_numbers", "bad CSV", gcp_file("image,x,y,X,Y,Z\nr_000.jpg,ten,5,1,2,3\n"), names=["gcp.csv"])
    add("poses_gcp_short_row", "bad CSV", gcp_file("image,x,y,X,Y,Z\nr_000.jpg,10,5\n"), names=["gcp.csv"])
    add("poses_gcp_binary", "bad CSV", gcp_file(b"\xff\xfe\x00\x81"), names=["gcp.csv"])
    add("poses_scale_bar_three_numbers", "bad flag", P("--scale-bar", "1,2,3"), names=["--scale-bar"])
    add("poses_scale_bar_zero_metres", "bad flag", P("--scale-bar", "0,0,0,1,1,1,0"), names=["--scale-bar"])
    add("poses_scale_bar_same_points", "bad flag", P("--scale-bar", "1,1,1,1,1,1,5"), names=["--scale-bar"])
    add("poses_overlap_0", "bad flag", P("--matcher", "sequential", "--overlap", "0"), names=["--overlap"])
    add("poses_max_side_0", "bad flag", P("--max-side", "0"), names=["--max-side"])
    add("poses_vocab_without_tree", "bad flag", P("--matcher", "vocab"), names=["--vocab-tree"])

    def truncated_jpeg(f, d):
        out = P()(f, d)
        truncate(sorted((d / "photos").glob("*.jpg"))[0], 0.3)
        return out

    add("poses_truncated_jpeg", "bad image", truncated_jpeg, expect="any")

    # mask on odd images (built-in DPT at a small working size)
    M = ["--max-side", "32"]

    def mask_on(convert):
        def prep(f, d):
            data = image_mode(f, d, convert)
            return {"argv": ["mask", "--data", data, "--quiet", *M], "protect": [data], "may_change": True}
        return prep

    add("mask_grey_photo", "odd image", mask_on(lambda im: im.convert("L")), expect="ok")
    add("mask_rgba_photo", "odd image", mask_on(lambda im: im.convert("RGBA")), expect="ok")
    add("mask_16bit_photo", "odd image", mask_on(lambda im: im.convert("I;16")), expect="ok")

    def mask_truncated(f, d):
        data = copy_data(f, d)
        truncate(first_image(data), 0.4)
        return {"argv": ["mask", "--data", data, "--quiet", *M], "protect": [data]}

    add("mask_truncated_png", "bad image", mask_truncated, names=[".png"])

    def mask_image_deleted(f, d):
        data = copy_data(f, d)
        img = first_image(data)
        img.unlink()
        return {"argv": ["mask", "--data", data, "--quiet", *M], "protect": [data]}

    add("mask_image_deleted", "missing file", mask_image_deleted, names=["train_000.png"])
    add("mask_tile_overlap_0_9", "bad flag",
        lambda f, d: {"argv": ["mask", "--data", copy_data(f, d), "--tile-overlap", "0.9", "--quiet"],
                      "protect": [d / "data"]}, names=["--tile-overlap"])
    add("mask_batch_size_0", "bad flag",
        lambda f, d: {"argv": ["mask", "--data", copy_data(f, d), "--batch-size", "0", "--quiet"],
                      "protect": [d / "data"]}, names=["--batch-size"])
    add("mask_weights_missing", "missing file",
        lambda f, d: {"argv": ["mask", "--data", copy_data(f, d), "--weights", d / "nodpt", "--quiet"],
                      "protect": [d / "data"]}, names=["nodpt"])

    # synth
    S = lambda *a: lambda f, d: {"argv": ["synth", "--out", d / "s", *SYNTH, *a], "protect": [],  # noqa: E731
                                 "absent": [d / "s"]}
    add("synth_gps_origin_lat_91", "bad flag", S("--gps-origin", "91,0,0"), names=["--gps-origin"])
    add("synth_gps_origin_two_values", "bad flag", S("--gps-origin", "47,8"), names=["--gps-origin"])
    add("synth_gps_origin_alt_inf", "bad flag", S("--gps-origin", "47,8,inf"), names=["--gps-origin"])
    add("synth_gps_origin_text", "bad flag", S("--gps-origin", "Zürich"), names=["--gps-origin"])
    add("synth_non_ascii_space_out", "non-ASCII path",
        lambda f, d: {"argv": ["synth", "--out", d / "Mast Nr ß 3", *SYNTH], "protect": []}, expect="ok")

    # demo
    D = lambda *a, **kw: lambda f, d: {"argv": ["demo", "--data", f["data"], "--out", d / "demo", "--quiet",  # noqa
                                                 *a], "protect": [], "absent": [d / "demo"], **kw}
    add("demo_steps_0", "bad flag", D("--steps", "0"), names=["--steps"])
    add("demo_max_side_negative", "bad flag", D("--max-side", "-2"), names=["--max-side"])
    add("demo_set_unknown_key", "bad flag", D("--set", "model.colour=red"), names=["model.colour"])
    add("demo_set_bad_json", "bad flag", D("--set", "train.batch_rays=[1,"), names=["train.batch_rays"])
    add("demo_data_missing", "missing file",
        lambda f, d: {"argv": ["demo", "--data", d / "nodata", "--out", d / "demo", "--quiet"], "protect": [],
                      "absent": [d / "demo"]}, names=["nodata"])

    # train
    T = lambda *a, **kw: lambda f, d: {"argv": [*TRAIN, "--data", f["data"], "--config", f["cfg"],  # noqa: E731
                                                "--out", d / "newrun", *a], "protect": [], "absent": [d / "newrun"],
                                       **kw}
    add("train_max_side_negative", "bad flag", T("--max-side", "-3"), names=["--max-side"])
    add("train_progress_page_negative", "bad flag", T("--progress-page", "-1"), names=["--progress-page"])
    add("train_recipe_unknown", "bad flag", T("--recipe", "fastest"), names=["fastest"])
    add("train_set_float_for_int", "bad flag", T("--set", "train.batch_rays=1e3"), names=["train.batch_rays"])
    add("train_set_samples_one_pass", "bad flag", T("--set", "model.sampler.samples=[8]"), expect="ok")  # one pass
    add("train_set_samples_three", "bad flag", T("--set", "model.sampler.samples=[8,8,8]"),
        names=["model.sampler.samples"])
    add("train_connect_timeout_text", "bad environment", T(env={"JAXNERF_CONNECT_TIMEOUT": "soon"}),
        names=["JAXNERF_CONNECT_TIMEOUT"])
    add("demo_heartbeat_timeout_0", "bad environment", D(env={"JAXNERF_HEARTBEAT_TIMEOUT": "0"}),
        names=["JAXNERF_HEARTBEAT_TIMEOUT"])

    def train_config(body):
        def prep(f, d):
            (d / "c.json").write_text(body)
            return {"argv": [*TRAIN, "--data", f["data"], "--config", d / "c.json", "--out", d / "newrun"],
                    "protect": [d / "c.json"], "absent": [d / "newrun"]}
        return prep

    add("train_config_a_list", "bad JSON", train_config("[1, 2]"), names=["c.json"])
    add("train_config_empty_file", "bad JSON", train_config(""), names=["c.json"])
    add("train_config_latin1", "bad JSON", train_config("{\"train\": {\"seed\": 1}} \xe9"), names=["c.json"])
    add("train_config_missing", "missing file",
        lambda f, d: {"argv": [*TRAIN, "--data", f["data"], "--config", d / "none.json", "--out", d / "newrun"],
                      "protect": [], "absent": [d / "newrun"]}, names=["none.json"])

    def transforms_edit(edit, *, train_args=()):
        def prep(f, d):
            data = copy_data(f, d)
            meta = json.loads((data / "transforms.json").read_text())
            text = edit(meta)
            (data / "transforms.json").write_text(text if isinstance(text, str) else json.dumps(meta))
            return {"argv": [*TRAIN, "--data", data, "--config", f["cfg"], "--out", d / "newrun", *train_args],
                    "protect": [data], "absent": [d / "newrun"]}
        return prep

    add("train_transforms_no_frames", "bad JSON", transforms_edit(lambda m: m.update(frames=[])),
        names=["transforms.json"])
    add("train_transforms_nan_pose", "bad JSON", transforms_edit(
        lambda m: m["frames"][0].update(transform_matrix=[[float("nan")] * 4] * 4)), names=["transforms.json"])
    add("train_transforms_pose_3x3", "bad JSON", transforms_edit(
        lambda m: m["frames"][0].update(transform_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1]])),
        names=["transforms.json"])
    add("train_transforms_truncated", "bad JSON",
        lambda f, d: (lambda data: (truncate(data / "transforms.json", 0.5),
                                    {"argv": [*TRAIN, "--data", data, "--config", f["cfg"], "--out", d / "newrun"],
                                     "protect": [data], "absent": [d / "newrun"]})[1])(copy_data(f, d)),
        names=["transforms.json"])

    def train_truncated_image(f, d):
        data = copy_data(f, d)
        truncate(first_image(data), 0.4)
        return {"argv": [*TRAIN, "--data", data, "--config", f["cfg"], "--out", d / "newrun"], "protect": [data],
                "absent": [d / "newrun"]}

    add("train_truncated_png", "bad image", train_truncated_image, names=[".png"])

    def train_image_other_size(f, d):
        from PIL import Image

        data = copy_data(f, d)
        img = first_image(data)
        Image.open(img).resize((48, 20)).save(img)
        return {"argv": [*TRAIN, "--data", data, "--config", f["cfg"], "--out", d / "newrun"], "protect": [data],
                "absent": [d / "newrun"]}

    add("train_image_of_another_size", "bad image", train_image_other_size, names=[".png"])
    add("train_out_dangling_link", "symlink",
        lambda f, d: (d / "newrun").symlink_to(d / "elsewhere") or
        {"argv": [*TRAIN, "--data", f["data"], "--config", f["cfg"], "--out", d / "newrun"],
         "protect": [d / "newrun"]}, expect="any")
    add("train_non_ascii_space_out", "non-ASCII path",
        lambda f, d: {"argv": [*TRAIN, "--data", f["data"], "--config", f["cfg"], "--out", d / "Läuf 1",
                               "--steps", "2"], "protect": []}, expect="ok")

    def resume_with_other_config_file(f, d):
        run = copy_run(f, d)
        (run / "config.json").write_text("{\"model\": ")
        return {"argv": [*TRAIN, "--data", f["data"], "--config", f["cfg"], "--out", run], "protect": [run]}

    add("train_resume_torn_config", "interrupted run", resume_with_other_config_file, names=["config.json"])

    def resume_after_checkpoint_temp(f, d):
        run = copy_run(f, d)
        (run / "checkpoints" / ".tmp-leftover").write_bytes(b"\0" * 100)
        return {"argv": [*TRAIN, "--data", f["data"], "--config", f["cfg"], "--out", run], "protect": []}

    add("train_resume_with_temp_leftover", "interrupted run", resume_after_checkpoint_temp, expect="ok")

    def metrics_jsonl_binary(f, d):
        run = copy_run(f, d)
        with open(run / "metrics.jsonl", "ab") as fh:
            fh.write(b"\xff\xfe\x00garbage")
        newest = sorted((run / "checkpoints").iterdir())[-1]
        shutil.rmtree(newest) if newest.is_dir() else newest.unlink()  # resumes from step 5, trims the log
        return {"argv": [*TRAIN, "--data", f["data"], "--config", f["cfg"], "--out", run], "protect": []}

    add("train_resume_metrics_binary_tail", "interrupted run", metrics_jsonl_binary, expect="ok")
    permission_cases(add)
    return C


def permission_cases(add) -> None:
    """Read-only folders, unreadable files and a full disk, run as the unprivileged user 65534
    (skipped with the reason where that cannot run: tests/support/unprivileged.py). The fixtures and the
    case's folder belong to root: the user may read them, not change them; it may write only
    the case's home/ (and a full disk's tmpfs)."""
    def N(argv, protect=(), absent=(), disk_kib=0, **kw):
        def prep(f, d):
            home = unprivileged.give_to_nobody(d / "home")
            nobody = {"home": home}
            if disk_kib:
                nobody.update(disk=unprivileged.give_to_nobody(d / "disk"), disk_kib=disk_kib)
            (d / "ro").mkdir()
            return {"argv": argv(f, d), "protect": [*protect(f, d)] if callable(protect) else list(protect),
                    "absent": [*absent(f, d)] if callable(absent) else list(absent), "nobody": nobody, **kw}
        return prep

    P = "permission (unprivileged)"
    train = lambda f, d, out, data=None: [*TRAIN, "--data", data or f["data"], "--config", f["cfg"],  # noqa: E731
                                          "--out", out]
    add("perm_train_out_read_only", P, N(lambda f, d: train(f, d, d / "ro" / "run"), absent=lambda f, d: [
        d / "ro" / "run"]), names=["ro/run", "permission denied"])
    add("perm_export_out_read_only", P, N(lambda f, d: ["export", "--run", f["run"], "--out", d / "ro" / "exp",
                                                         "--quiet"], absent=lambda f, d: [d / "ro" / "exp"]),
        names=["ro/exp", "permission denied"])
    add("perm_render_orbit_out_read_only", P, N(lambda f, d: ["render", "--run", f["run"], "--orbit", "--frames", "2",
                                                               "--width", "16", "--out", d / "ro" / "v" / "orbit",
                                                               "--quiet"]), names=["ro/v", "Permission denied"])
    add("perm_synth_out_read_only", P, N(lambda f, d: ["synth", "--out", d / "ro" / "s", *SYNTH]),
        names=["ro/s", "Permission denied"])
    add("perm_poses_out_read_only", P, N(lambda f, d: ["poses", "--images", photos(f, d), "--out", d / "ro" / "ds",
                                                        "--quiet"], absent=lambda f, d: [d / "ro" / "ds"]),
        names=["ro/ds", "permission denied"])  # before COLMAP; not the staging folder beside it
    add("perm_mask_dataset_read_only", P, N(lambda f, d: ["mask", "--data", f["data"], "--source", "gt",
                                                           "--quiet"]), names=["data: --data is not writable"])
    add("perm_eval_run_read_only", P, N(lambda f, d: ["eval", "--run", f["run"], "--quiet"]),
        names=["run", "Permission denied"])
    add("perm_render_run_read_only", P, N(lambda f, d: ["render", "--run", f["run"], "--quiet"]),
        names=["run", "Permission denied"])
    add("perm_export_into_read_only_run", P, N(lambda f, d: ["export", "--run", f["run"], "--quiet"]),
        names=["run/export", "permission denied"])

    def interrupted_run(f, d):
        run = copy_run(f, d)
        newest = sorted((run / "checkpoints").iterdir())[-1]
        shutil.rmtree(newest) if newest.is_dir() else newest.unlink()  # as a kill after step 5 left it
        return train(f, d, run)

    add("perm_train_resume_read_only_run", P, N(interrupted_run, protect=lambda f, d: [d / "run"]),
        names=["run: --out is not writable"])

    def unreadable_photo(f, d):
        data = copy_data(f, d)
        first_image(data).chmod(0)
        return train(f, d, d / "home" / "run", data)

    add("perm_photo_unreadable", P, N(unreadable_photo, protect=lambda f, d: [d / "data"],
                                      absent=lambda f, d: [d / "home" / "run"]), names=["train_000.png"])

    def unreadable(name, body, argv):
        def make(f, d):
            (d / name).write_text(body)
            (d / name).chmod(0o600)
            return argv(f, d)
        return make

    add("perm_config_unreadable", P, N(unreadable("c.json", json.dumps(TINY), lambda f, d: [
        *TRAIN, "--data", f["data"], "--config", d / "c.json", "--out", d / "home" / "run"]),
        absent=lambda f, d: [d / "home" / "run"]), names=["c.json", "Permission denied"])
    add("perm_camera_path_unreadable", P, N(unreadable("path.json", json.dumps(
        {"camera_path": [{"camera_to_world": GOOD_POSE, "fov": 50}], "render_width": 8, "render_height": 8}),
        lambda f, d: ["render", "--run", f["run"], "--path", d / "path.json", "--out", d / "home" / "v", "--quiet"])),
        names=["path.json", "Permission denied"])
    add("perm_read_only_dataset_trains", P, N(lambda f, d: train(f, d, d / "home" / "run") + ["--max-side", "16"],
                                              protect=lambda f, d: [f["data"]]), expect="ok")

    D = "full disk (unprivileged)"
    add("disk_train_full", D, N(lambda f, d: train(f, d, d / "disk" / "run"), disk_kib=24),
        names=["disk/run/", "No space left on device"])
    add("disk_synth_full", D, N(lambda f, d: ["synth", "--out", d / "disk" / "s", *SYNTH], disk_kib=16),
        names=["disk/s/", "No space left on device"])
    add("disk_export_full", D, N(lambda f, d: ["export", "--run", f["run"], "--out", d / "disk" / "exp", "--quiet",
                                               "--resolution", "16", "--views", "2", "--box=-10,-10,0,10,10,20",
                                               "--threshold", "0.0001"], disk_kib=8),
        names=["disk/exp/", "No space left on device"])
    add("disk_render_orbit_full", D, N(lambda f, d: ["render", "--run", f["run"], "--orbit", "--frames", "40",
                                                     "--width", "64", "--out", d / "disk" / "orbit", "--quiet"],
                                       disk_kib=8), names=["disk/orbit", "No space left on device"])


def judge(case, proc, before, after, absent) -> dict:
    """The record of one case (module docstring)."""
    lines = error_lines(proc.stderr)
    traceback = "Traceback" in proc.stderr or "Fatal Python error" in proc.stderr
    lost = sorted(k for k in before if k not in after)
    changed = sorted(k for k in before if k in after and after[k] != before[k])
    added = sorted(k for k in after if k not in before)
    leftovers = [str(p) for p in absent if os.path.lexists(p)]
    errors = [line for line in lines if ": warning: " not in line]  # a warning is one line of its own
    names_ok = all(n.lower() in (errors[-1] if errors else "").lower() for n in case["names"])
    one_line = len(errors) == 1 and errors[0].startswith("jaxnerf-grid")
    if case["expect"] == "ok":
        held = proc.returncode == 0 and not traceback and not lost and not (changed and not case.get("may_change"))
    elif case["expect"] == "any":  # either a clean success or a clean one-line error
        held = not traceback and not lost and not changed and (proc.returncode == 0 or (
            errors and ": error: " in errors[-1] and errors[-1].startswith("jaxnerf-grid") and not added
            and not leftovers))
    else:
        held = (proc.returncode != 0 and one_line and names_ok and not traceback and not lost and not changed
                and not (added and not case.get("may_add")) and not leftovers)
    return {"id": case["id"], "kind": case["kind"], "expect": case["expect"], "rc": proc.returncode,
            "one_line": one_line, "names_ok": names_ok, "traceback": traceback, "lost": lost, "changed": changed,
            "added": added[:5], "leftovers": leftovers, "held": held,
            "stderr_tail": "\n".join(proc.stderr.strip().splitlines()[-3:])[-600:]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("work", help="work folder (made if missing; fixtures reused when present)")
    p.add_argument("--only", default=None, help="comma-separated case ids")
    p.add_argument("--summary", default=None, help="JSON summary path (default WORK/summary.json)")
    p.add_argument("--timeout", type=float, default=300, help="seconds per case")
    args = p.parse_args(argv)
    work = Path(args.work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    f = build_fixtures(work)
    only = set(args.only.split(",")) if args.only else None
    results, skipped = [], []
    for case in case_list():
        if only and case["id"] not in only:
            continue
        fresh_fixtures(f)
        d = work / "cases" / case["id"]
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        if case["kind"].endswith("(unprivileged)"):
            why = unprivileged.disk_unavailable() if case["id"].startswith("disk_") else unprivileged.unavailable()
            why = why or unprivileged.cannot_read(work)
            if why is not None:
                skipped.append({"id": case["id"], "reason": why})
                print(f"skip {case['id']:40s} {why}", flush=True)
                continue
        spec = case["prepare"](f, d)
        case = {**case, **{k: v for k, v in spec.items() if k in ("may_add", "may_change")}}
        roots = [f["data"], f["run"], *[Path(x) for x in spec["protect"]]]
        before = snapshot(*roots)
        t0 = time.time()
        try:
            proc = cli(spec["argv"], d, spec.get("env"), args.timeout, spec.get("nobody"))
        except subprocess.TimeoutExpired as err:
            proc = subprocess.CompletedProcess(err.cmd, 124, "", f"timeout after {args.timeout} s")
        after = snapshot(*roots)
        rec = judge(case, proc, before, after, spec.get("absent", []))
        rec["seconds"] = round(time.time() - t0, 1)
        rec["argv"] = [str(a).replace(str(work), "WORK") for a in spec["argv"]]
        rec["stderr_tail"] = rec["stderr_tail"].replace(str(work), "WORK")
        results.append(rec)
        print(f"{'held' if rec['held'] else 'FAIL'} {case['id']:40s} rc={rec['rc']} {rec['seconds']}s "
              f"{'' if rec['held'] else rec['stderr_tail'].splitlines()[-1] if rec['stderr_tail'] else ''}",
              flush=True)
    held = sum(r["held"] for r in results)
    summary = {"held": held, "total": len(results), "cases": results, "skipped": skipped}
    out = Path(args.summary) if args.summary else work / "summary.json"
    out.write_text(json.dumps(summary, indent=1))
    print(f"{held} of {len(results)} held" + (f", {len(skipped)} skipped" if skipped else "") + f"; {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
