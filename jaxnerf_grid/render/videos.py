"""Fly-around videos of a trained run (`jaxnerf-grid render --orbit | --path FILE`, docs/VIDEOS.md).

A smooth orbit around the point the training cameras look at (`orbit_poses`: its height and
radius the training cameras' mean, about their mean up axis) or a camera path in nerfstudio's
camera-path JSON (`read_camera_path`, the subset documented in docs/VIDEOS.md), rendered frame by
frame (`views.frame_renderer`: one compiled call a frame) into two MP4 files written with OpenCV's VideoWriter (mp4v):
the colour and the depth (inverse depth through the TURBO map, one range for every frame).
"""

from __future__ import annotations

import math
import os
import re
import shutil
import socket
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.run_config import resolve_devices
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data.normalize import optical_axis_focus
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.render import views
from jaxnerf_grid.report import markdown as report
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train.runs import load_run_and_dataset
from jaxnerf_grid.util import folders, io
from jaxnerf_grid.util import progress as progress_lib
from jaxnerf_grid.util.io import DataError

DEFAULT_FRAMES = 120
DEFAULT_FPS = 24.0
DEFAULT_WIDTH = 160
MAX_SIDE = 8192  # MPEG-4 part 2 (mp4v): OpenCV refuses a wider or taller frame ("dimensions too large")


def orbit_poses(c2w: np.ndarray, frames: int) -> np.ndarray:
    """A closed orbit of `frames` camera-to-world matrices [frames, 4, 4] (OpenGL axes) around the
    training cameras c2w [N, 3|4, 4]: the up axis u = their mean +y axis (normalised); the
    target t = the point nearest every optical axis (`optical_axis_focus`; the centres' mean when
    the axes are nearly parallel); height = mean over cameras of u . (c - t); radius = mean
    distance of the centres from the vertical line through t; starting at the first camera's
    azimuth, turning by 2 pi / frames per frame, each camera looking at t."""
    c2w = np.asarray(c2w, np.float64)
    centres = c2w[:, :3, 3]
    up = c2w[:, :3, 1].mean(0)
    up /= max(np.linalg.norm(up), 1e-12)
    target, cond = optical_axis_focus(c2w)
    if cond < 1e-6:
        target = centres.mean(0)
    rel = centres - target
    height = float(np.mean(rel @ up))
    flat = rel - np.outer(rel @ up, up)
    radius = float(np.mean(np.linalg.norm(flat, axis=1)))
    e1 = flat[0] / max(np.linalg.norm(flat[0]), 1e-12) if np.linalg.norm(flat[0]) > 1e-9 else _any_perpendicular(up)
    e2 = np.cross(up, e1)
    out = []
    for k in range(int(frames)):
        a = 2 * math.pi * k / frames
        eye = target + height * up + radius * (math.cos(a) * e1 + math.sin(a) * e2)
        out.append(np.asarray(rays_lib.look_at(eye, target, up), np.float64))
    return np.stack(out)


def _any_perpendicular(v: np.ndarray) -> np.ndarray:
    helper = np.array([1.0, 0, 0]) if abs(v[0]) < 0.9 else np.array([0, 1.0, 0])
    w = np.cross(v, helper)
    return w / np.linalg.norm(w)


def read_camera_path(path) -> dict:
    """A camera path in nerfstudio's camera-path JSON: {"render_width", "render_height", "fps"
    (optional), "camera_path": [{"camera_to_world": 16 numbers (row-major 4x4) or 4 rows of 4,
    "fov": vertical field of view in degrees}]} with the poses in the run's normalised scene (OpenGL
    axes, as nerfstudio's). Returns {"c2w" [F, 4, 4], "fov" [F] (degrees), "width", "height", "fps"
    (None when absent)}. DataError naming the file and the key for anything else."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: camera path file not found (render.path)")
    try:
        spec = io.read_json(path)
    except DataError:
        raise
    except ValueError as err:
        raise DataError(f"{path}: not a JSON camera path ({err})") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("camera_path"), list) or not spec["camera_path"]:
        raise DataError(f"{path}: expected a JSON object with a non-empty list 'camera_path' (render.path)")
    poses, fovs = [], []
    for k, cam in enumerate(spec["camera_path"]):
        try:
            m = np.asarray(cam["camera_to_world"], np.float64).reshape(-1)
            fov = float(cam["fov"])
        except (KeyError, TypeError, ValueError):
            raise DataError(f"{path}: camera_path[{k}] needs 'camera_to_world' (16 numbers) and 'fov' "
                            "(degrees)") from None
        if m.size not in (12, 16) or not np.all(np.isfinite(m)) or not 0 < fov < 180:
            raise DataError(f"{path}: camera_path[{k}]: 'camera_to_world' must be 16 finite numbers and 'fov' "
                            f"in (0, 180) degrees")
        poses.append(np.vstack([m.reshape(-1, 4)[:3], [0, 0, 0, 1]]))
        fovs.append(fov)
    size = {}
    for key in ("render_width", "render_height"):
        value = spec.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise DataError(f"{path}: '{key}' must be a positive integer, got {value!r}")
        size[key] = value
    fps = spec.get("fps")
    if fps is not None and not (isinstance(fps, (int, float)) and not isinstance(fps, bool) and 0 < fps < math.inf):
        raise DataError(f"{path}: 'fps' must be a positive number, got {fps!r}")
    return {"c2w": np.stack(poses), "fov": np.asarray(fovs), "width": size["render_width"],
            "height": size["render_height"], "fps": None if fps is None else float(fps)}


def orbit_size(ds, width: int) -> tuple[int, int, float]:
    """(width, height, vertical fov in degrees) of an orbit's frames: `width` wide with the
    dataset's aspect ratio and its first training camera's vertical field of view."""
    height = max(1, round(width * ds.height / ds.width))
    fy = float(ds.intrinsics[int(np.asarray(ds.split["train"])[0]) if len(ds.split["train"]) else 0][1])
    return width, height, math.degrees(2 * math.atan(0.5 * ds.height / fy))


def open_writer(path: Path, fps: float, width: int, height: int, name: Path | None = None):
    """An OpenCV VideoWriter (mp4v) for `path`; DataError naming `name` (the video the user asked
    for, default `path`) when OpenCV cannot open it (`write_failure`)."""
    cv2 = io.opencv()
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (int(width), int(height)))
    if not writer.isOpened():
        raise write_failure(name or path, path, "OpenCV cannot open an mp4v video there")
    return writer


FULL_DISK_BYTES = 1 << 20  # less free space than this where a video failed: reported as a full disk


def write_failure(final: Path, partial: Path, what: str) -> DataError:
    """The one-line error of a video OpenCV could not write, naming `final` (not its hidden staging
    file `partial`): OpenCV reports no OS error, so the disk's free space says whether it is full."""
    try:
        free = shutil.disk_usage(partial.parent).free
    except OSError:
        free = None
    reason = ("No space left on device" if free is not None and free < FULL_DISK_BYTES else "a write error")
    room = "" if free is None else f", {free // 1024} KiB free there"
    return DataError(f"{final}: cannot write ({what}: {reason}{room})")


def check_written(final: Path, partial: Path, frames: int) -> None:
    """DataError (`write_failure`) unless the video written to `partial` reads back with
    `frames` frames: OpenCV's VideoWriter drops what it cannot write (a full disk) without a
    word, and a video whose end is missing has no index to read."""
    cv2 = io.opencv()
    cap = cv2.VideoCapture(str(partial))
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
    cap.release()
    if count != frames:
        raise write_failure(final, partial, f"{max(count, 0)} of {frames} frames could be read back")


def _frame_bytes(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] in [0, 1] RGB -> uint8 BGR (OpenCV's order)."""
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)[..., ::-1].copy()


def check_settings(frames, fps, width) -> None:
    """ConfigError naming render.frames / render.fps / render.width unless they are positive
    (frames and width integers, width >= 8)."""
    config_lib.check_value("render.frames", frames, int, config_lib.AT_LEAST_ONE)
    config_lib.check_value("render.width", width, int, config_lib.Range(8))
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not fps > 0:
        raise ConfigError(f"render.fps must be a positive number, got {fps!r}")


def check_frames(width: int, height: int, frames: int, source: str) -> None:
    """Refuses (ConfigError naming `source`: render.width or the camera path file) frames wider
    or taller than MAX_SIDE, which mp4v cannot hold, or a video whose depth frames (kept for one
    colour range, 4 bytes a pixel) would not fit in half the host's memory."""
    if max(width, height) > MAX_SIDE:
        raise ConfigError(f"{source}: frames of {width} x {height} pixels; an mp4v video holds at most "
                          f"{MAX_SIDE} pixels a side")
    need = 4 * width * height * frames
    host = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if need > host // 2:
        raise ConfigError(f"{source}: {frames} frames of {width} x {height} pixels need {need / 2**30:.1f} GiB of "
                          f"depth maps, more than half of this host's {host / 2**30:.1f} GiB; fewer or smaller frames")


def render_video(run_dir, path_file=None, frames: int = DEFAULT_FRAMES, fps: float | None = None,
                 width: int = DEFAULT_WIDTH, out=None, progress: bool = True, dataset=None,
                 allow_other_data: bool = False) -> dict:
    """Renders an orbit (no `path_file`) or the camera path of `path_file` and writes OUT.mp4 and
    OUT_depth.mp4 (default RUN/videos/orbit or RUN/videos/<path file's stem>). An orbit has
    `frames` frames `width` wide (the dataset's aspect); a path its own size and frames. fps:
    the flag, else the path's "fps", else DEFAULT_FPS. Everything is checked before a frame is
    rendered. Returns {"video", "depth_video", "frames", "width", "height", "fps"}."""
    run_dir = Path(run_dir)
    check_settings(frames, DEFAULT_FPS if fps is None else fps, width)
    spec = read_camera_path(path_file) if path_file is not None else None
    cfg, data, ds = load_run_and_dataset(run_dir, dataset, progress, allow_other_data)
    if spec is None:
        w, h, fov = orbit_size(ds, width)
        check_frames(w, h, frames, "render.width")
        train_ids = np.asarray(ds.split["train"]) if len(ds.split["train"]) else np.arange(ds.num_frames)
        poses, fovs = orbit_poses(np.asarray(ds.c2w)[train_ids], frames), np.full(frames, fov)
        name = "orbit"
    else:
        w, h, poses, fovs, name = spec["width"], spec["height"], spec["c2w"], spec["fov"], Path(path_file).stem
        check_frames(w, h, len(poses), str(path_file))
    fps = float(fps if fps is not None else (spec or {}).get("fps") or DEFAULT_FPS)
    out = Path(out) if out is not None else run_dir / "videos" / name
    video, depth_video = out.parent / f"{out.name}.mp4", out.parent / f"{out.name}_depth.mp4"
    folders.check_outside(out.parent, data, "render.out")
    params, _ = train.load_params(run_dir, cfg, ds)  # before the first write: a run without weights adds nothing
    with io.naming_path(out.parent, "cannot create the folder"):
        out.parent.mkdir(parents=True, exist_ok=True)
    near, far = config_lib.near_far(cfg.model, ds)
    renderer = views.frame_renderer(params, cfg.model, resolve_devices(cfg.train))
    render = lambda pose, fov: _render_frame(renderer, pose, fov, w, h, near, far)  # noqa: E731
    frames_done = write_videos(video, depth_video, zip(poses, fovs), render, fps, w, h,
                               progress_lib.bar(total=len(poses), desc="render video", unit="frame",
                                                enabled=progress))
    return {"video": video, "depth_video": depth_video, "frames": frames_done, "width": w, "height": h, "fps": fps}


def _render_frame(renderer, pose: np.ndarray, fov: float, w: int, h: int, near: float, far: float) -> dict:
    """One frame of camera `pose` [4, 4] with vertical field of view `fov` (degrees), w x h pixels:
    {"rgb" [h, w, 3], "depth" [h, w]} (`renderer`: a `views.frame_renderer`)."""
    focal = 0.5 * h / math.tan(math.radians(fov) / 2)
    r = rays_lib.generate_rays(jnp.asarray(pose, jnp.float32), focal, focal, w / 2, h / 2, w, h, near, far)
    return renderer(r)


def partial_path(final: Path) -> Path:
    """Where the video `final` (DIR/STEM.mp4) is written until it is complete:
    DIR/.STEM.partial.HOST.PID.mp4, naming this process, so that a kill's leftover can be told
    from the file of a render still running (`stale_partials`)."""
    return final.with_name(f".{final.stem}.partial.{socket.gethostname()}.{os.getpid()}.mp4")


def _partial_owner(name: str, stem: str) -> tuple[str, int] | None:
    """(host, pid) of a file name of `partial_path`'s form for STEM.mp4; ("", 0) for the
    `.STEM.partial.mp4` of versions before the owner was named; None for any other name."""
    match = re.fullmatch(rf"\.{re.escape(stem)}\.partial(?:\.(?P<host>.+)\.(?P<pid>\d+))?\.mp4", name)
    if match is None:
        return None
    return (match["host"], int(match["pid"])) if match["pid"] else ("", 0)


def _runs(pid: int) -> bool:
    """Whether process `pid` of this host runs (this process's own id counts as not: its
    staging file is made after the stale ones are removed)."""
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def stale_partials(final: Path) -> list[Path]:
    """The staging files of the video `final` that no running render owns: those of
    `partial_path`'s form whose process, on this host, no longer runs (a kill -9), and the
    `.STEM.partial.mp4` of older versions. Never another name (a user's file), a link, or the
    file of a render running here or on another host."""
    if not final.parent.is_dir():
        return []
    out = []
    for path in sorted(final.parent.iterdir()):
        owner = _partial_owner(path.name, final.stem)
        if owner is None or path.is_symlink() or not path.is_file():
            continue
        host, pid = owner
        if pid == 0 or (host == socket.gethostname() and not _runs(pid)):
            out.append(path)
    return out


def write_videos(video: Path, depth_video: Path, cameras, render, fps: float, w: int, h: int, pbar) -> int:
    """Renders each camera of `cameras` with `render(*camera)` -> {"rgb", "depth"} and writes the
    colour to `video`, the depth (inverse depth, TURBO, one range for all frames) to `depth_video`.
    Both are written under temporary names (`partial_path`) and renamed when complete: a failure
    or a kill leaves an earlier video of the same name as it was, and the next call for the same
    videos removes what a killed one left (`stale_partials`). Returns the number of frames."""
    staged = {video: partial_path(video), depth_video: partial_path(depth_video)}
    for final in staged:
        for leftover in stale_partials(final):
            leftover.unlink(missing_ok=True)
    try:
        writer = open_writer(staged[video], fps, w, h, video)
        depths = []
        try:
            with pbar:
                for camera in cameras:
                    view = render(*camera)
                    writer.write(_frame_bytes(view["rgb"]))
                    depths.append(np.asarray(view["depth"], np.float32))
                    pbar.update(1)
        finally:
            writer.release()
        inv = 1.0 / np.maximum(np.stack(depths), 1e-6)
        lo, hi = np.percentile(inv[np.isfinite(inv)], [2, 98])
        writer = open_writer(staged[depth_video], fps, w, h, depth_video)
        try:
            for d in depths:
                writer.write(_frame_bytes(report.colourise_depth(d, lo, hi)))
        finally:
            writer.release()
        for final, partial in staged.items():
            check_written(final, partial, len(depths))
        for final, partial in staged.items():
            with io.naming_path(final):
                os.replace(partial, final)
    finally:
        for partial in staged.values():
            partial.unlink(missing_ok=True)
    return len(depths)
