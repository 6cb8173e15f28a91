"""Dataset loaders: transforms.json (nerfstudio / instant-ngp), Blender synthetic, COLMAP, LLFF.

Every loader returns a `Dataset` (dataset.py): c2w camera-to-world with OpenGL camera axes
(x right, y up, looking down -z), intrinsics (fx, fy, cx, cy) in pixels with pixel centres at
+0.5, images float32 RGB in [0, 1], the scene normalised so the region of interest lies in the
unit sphere (`normalization` maps metric points to it: x_norm = scale * (x + translation)).

Formats, and how each gets its normalisation and near/far (distances along unit rays in the
normalised scene):
- transforms.json (docs/DATASET.md): a file with `scene_normalization` is already normalised
  and used as is. Without it the poses are normalised with `normalize_poses` (cameras method)
  unless `normalize=False`. near/far: the file's `near`/`far` (times the scale when this loader
  normalised), else DEFAULT_NEAR / DEFAULT_FAR.
- Blender synthetic (transforms_{train,val,test}.json, `camera_angle_x`, file paths without
  extension, RGBA PNG composited on `background`, white by default): as transforms.json, with
  near/far 2 / 6 (the NeRF convention, metric) when the files name none.
- COLMAP sparse model (text or binary): OpenCV-axis world-to-camera (qvec, tvec) converted to
  OpenGL c2w; distorted models (SIMPLE_RADIAL, RADIAL, OPENCV) are undistorted with OpenCV on
  load (pixels that fall outside the source image get loss weight 0) or refused with
  `undistort=False`. Normalised with the points3D (robust extent). near/far: from the z-depths
  of the points each image observes: near = 0.9 x the 0.5th percentile, far = 1.1 x the 99.5th
  percentile divided by the smallest cosine between a pixel ray and the optical axis (z-depth
  -> ray distance); DEFAULT_NEAR / DEFAULT_FAR without points.
- LLFF poses_bounds.npy: [N, 17], a [3, 5] matrix per image (columns down, right, backwards,
  centre, (H, W, focal)) and (near, far) z-depth bounds. near/far from the bounds, as for
  COLMAP (0.9 x min, 1.1 x max / cos).

Splits: a frame's `split` key, or the Blender file a frame came from, or `train_filenames` /
`test_filenames` lists; otherwise every `test_every`-th frame (0, 8, 16, ...) is a test frame.
An empty train or test split is a DataError.

All bad input raises `DataError` naming the file: missing / unreadable image, size mismatch,
non-finite or degenerate pose, unknown camera model, empty split.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxnerf_grid import io
from jaxnerf_grid.data import colmap as colmap_io
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.data.normalize import (apply_normalization_to_points, compose_normalization,
                                         normalize_poses)
from jaxnerf_grid.io import DataError

DEFAULT_NEAR = 0.05   # normalised units; cameras usually sit 1.5-3 units from the centre
DEFAULT_FAR = 100.0   # generous: the contraction compresses everything past the unit sphere
BLENDER_NEAR, BLENDER_FAR = 2.0, 6.0
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
SEMANTIC_UNKNOWN = 255  # class id of pixels of frames without a semantic map
# GL camera axes from CV ones (and back): flip y and z.
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def _cv2():
    import cv2

    return cv2


# ----------------------------------------------------------------------------------------
# Checks and small helpers


def validate_c2w(matrix, source: str, tol: float = 1e-3) -> np.ndarray:
    """Checks a camera-to-world pose and returns it as [4, 4] float64.

    matrix: [3, 4] or [4, 4]. DataError (naming `source`) when entries are non-finite, the
    rotation is not orthonormal (max |R^T R - I| > tol) or its determinant is not +1.
    """
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{source}: pose is not a numeric matrix") from None
    if m.shape not in ((3, 4), (4, 4)):
        raise DataError(f"{source}: pose must be 3x4 or 4x4, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise DataError(f"{source}: degenerate pose (non-finite entries)")
    r = m[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > tol:
        raise DataError(f"{source}: degenerate pose (rotation not orthonormal, max |R^T R - I| = {err:.3g})")
    det = float(np.linalg.det(r))
    if abs(det - 1.0) > tol:
        raise DataError(f"{source}: degenerate pose (rotation determinant {det:.3g}, expected +1)")
    if m.shape == (4, 4) and not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
        raise DataError(f"{source}: degenerate pose (last row {m[3].tolist()} is not [0, 0, 0, 1])")
    out = np.eye(4)
    out[:3] = m[:3]
    return out


def read_rgb(path, background=None, honour_exif: bool = True) -> np.ndarray:
    """Reads an image as float32 RGB [H, W, 3] in [0, 1].

    An alpha channel is composited over `background` ([3] RGB in [0, 1]) when one is given
    (straight alpha, as PNG stores it), else dropped.
    """
    path = Path(path)
    if background is None or path.suffix.lower() != ".png":
        return io.read_image(path, honour_exif=honour_exif)
    img, _ = io.decode_raw(path, "image")
    if img.ndim != 3 or img.shape[-1] != 4:
        return io.read_image(path, honour_exif=honour_exif)
    img = img.astype(np.float32) / (65535.0 if img.dtype == np.uint16 else 255.0)
    rgb, alpha = img[..., 2::-1], img[..., 3:]
    bg = np.asarray(background, np.float32).reshape(1, 1, 3)
    return np.ascontiguousarray(rgb * alpha + bg * (1.0 - alpha))


def downscaled_size(width: int, height: int, downscale: float) -> tuple[int, int]:
    """Image size after dividing the resolution by `downscale` (rounded, at least 1)."""
    if downscale <= 0:
        raise ValueError(f"downscale must be positive, got {downscale}")
    return max(1, int(round(width / downscale))), max(1, int(round(height / downscale)))


def scale_intrinsics(intrinsics: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics after resizing an image by (sx, sy) = (W'/W, H'/H).

    intrinsics: [..., 4] (fx, fy, cx, cy), pixel centres at +0.5, so continuous pixel
    coordinates scale exactly: u' = sx u, hence fx' = sx fx, cx' = sx cx. Returns [..., 4].
    """
    k = np.asarray(intrinsics, dtype=np.float64)
    return k * np.array([sx, sy, sx, sy])


def resize(array: np.ndarray, size: tuple[int, int], interpolation: str = "area") -> np.ndarray:
    """Resizes [H, W] or [H, W, C] to size = (W', H'). interpolation: area | linear | nearest."""
    cv2 = _cv2()
    width, height = size
    if array.shape[1] == width and array.shape[0] == height:
        return array
    flag = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST}[interpolation]
    if interpolation == "area" and (width > array.shape[1] or height > array.shape[0]):
        flag = cv2.INTER_LINEAR  # INTER_AREA only averages when shrinking
    out = cv2.resize(array, (width, height), interpolation=flag)
    if array.ndim == 3 and out.ndim == 2:
        out = out[..., None]
    return out


def min_ray_cosine(intrinsics: np.ndarray, width: int, height: int) -> float:
    """Smallest cosine between a pixel ray and the optical axis (at the image corners).

    intrinsics: [N, 4]. Used to turn z-depth bounds into ray-distance bounds (t = z / cos).
    """
    k = np.asarray(intrinsics, np.float64).reshape(-1, 4)
    u = np.array([0.0, width, 0.0, width])
    v = np.array([0.0, 0.0, height, height])
    x = (u[None] - k[:, 2:3]) / k[:, 0:1]
    y = (v[None] - k[:, 3:4]) / k[:, 1:2]
    return float((1.0 / np.sqrt(1.0 + x * x + y * y)).min())


def default_split(num_frames: int, test_every: int = 8) -> dict:
    """Every `test_every`-th frame (0, 8, ...) is a test frame; the rest train."""
    idx = np.arange(num_frames)
    test = idx[idx % test_every == 0]
    train = idx[idx % test_every != 0]
    return {"train": train, "test": test}


def _check_split(split: dict, source) -> dict:
    for name in ("train", "test"):
        if len(split.get(name, [])) == 0:
            raise DataError(f"{source}: empty split {name!r} (no {name} frames)")
    return {k: np.asarray(v, dtype=np.int64) for k, v in split.items()}


def undistort_maps(fx, fy, cx, cy, dist, width: int, height: int):
    """OpenCV remap tables that undistort an image into the pinhole camera (fx, fy, cx, cy).

    dist: [4|5] (k1, k2, p1, p2[, k3]). OpenCV puts pixel centres at integers, so its principal
    point is (cx - 0.5, cy - 0.5). Returns (map_x [H, W], map_y [H, W]) float32.
    """
    cv2 = _cv2()
    k = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return cv2.initUndistortRectifyMap(k, np.asarray(dist, np.float64), None, k, (width, height),
                                       cv2.CV_32FC1)


def _remap(array, maps, interpolation: str):
    cv2 = _cv2()
    flag = cv2.INTER_NEAREST if interpolation == "nearest" else cv2.INTER_LINEAR
    out = cv2.remap(array, maps[0], maps[1], flag, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if array.ndim == 3 and out.ndim == 2:
        out = out[..., None]
    return out


# ----------------------------------------------------------------------------------------
# Frame-wise loading shared by every format


class _Frame:
    """What a loader knows about one frame before pixels are read."""

    def __init__(self, image_path: Path, c2w: np.ndarray, intrinsics, size, dist=None, extras=None,
                 source=""):
        self.image_path = image_path
        self.c2w = c2w
        # [4] at the stated size, or a function (W, H) -> [4] evaluated once the image is read
        if not (callable(intrinsics) or intrinsics is None):
            intrinsics = np.asarray(intrinsics, np.float64)
        self.intrinsics = intrinsics
        self.size = size  # (W, H) the intrinsics refer to, or None (take the image's)
        self.dist = None if dist is None or not np.any(np.asarray(dist)) else np.asarray(dist, np.float64)
        self.extras = extras or {}  # field -> Path
        self.source = source


class _Extra(NamedTuple):
    """How one optional per-frame field is stored: its transforms.json key, how it is read and
    resampled (interpolation for downscaling / undistortion), and where the writer puts it."""
    key: str
    kind: str
    interp: str
    folder: str
    ext: str


_EXTRAS = {  # Dataset field -> storage; one table for reading and writing
    "clean_images": _Extra("clean_file_path", "rgb", "area", "clean", ".png"),
    "depth": _Extra("depth_file_path", "exr", "nearest", "depth", ".exr"),
    "semantics": _Extra("semantic_file_path", "u8", "nearest", "semantic", ".png"),
    "distractor_masks": _Extra("distractor_mask_path", "u8", "nearest", "distractor", ".png"),
    "masks": _Extra("mask_path", "mask", "area", "masks", ".png"),
    "weights": _Extra("weight_path", "exr", "area", "weights", ".exr"),
}


def _read_extra(kind: str, path: Path, background, honour_exif: bool) -> np.ndarray:
    if kind == "rgb":
        return read_rgb(path, background, honour_exif)
    if kind == "exr":
        arr = io.read_exr(path)
        return arr if arr.ndim == 2 else arr[..., 0]
    if kind == "mask":
        return io.read_mask(path)
    img, _ = io.decode_raw(path, "image")
    if img.ndim == 3:
        img = img[..., 0]
    if img.dtype != np.uint8:
        raise DataError(f"{path}: expected an 8-bit single-channel PNG, got {img.dtype}")
    return img


@dataclasses.dataclass
class Scene:
    """A dataset before its pixels are read: what every loader collects first.

    frames: per-frame image path, pose, intrinsics (or a function of the image size), lens
    distortion and extra-file paths; c2w: [N, 4, 4] normalised OpenGL poses; the rest as in
    `Dataset`. `read_frame` reads one frame at its native size, `scene_to_dataset` all of them.
    """

    root: Path
    frames: list
    c2w: np.ndarray
    split: dict
    near: float
    far: float
    normalization: dict
    meta: dict
    background: object = None
    undistort: bool = True
    honour_exif: bool = True


def read_frame(scene: Scene, index: int, load_extras: bool = True) -> dict:
    """Reads frame `index` at its native size, undistorted when its camera has distortion.

    Returns {"image": [H, W, 3], "intrinsics": [4] (fx, fy, cx, cy), "valid": [H, W] bool or
    None (False where undistortion sampled outside the source), "extras": {field: [H, W(, 3)]}}
    with fields named as in `Dataset` (masks, weights, depth, ...; raw, before binarising).
    """
    frame = scene.frames[index]
    img = read_rgb(frame.image_path, scene.background, scene.honour_exif)
    h, w = img.shape[:2]
    if frame.size is not None and tuple(frame.size) != (w, h):
        hint = " (EXIF orientation is applied; pass honour_exif=False if the cameras use the raw layout)" \
            if frame.image_path.suffix.lower() in (".jpg", ".jpeg") else ""
        raise DataError(f"{frame.image_path}: image is {w}x{h} but its camera ({frame.source}) "
                        f"says {frame.size[0]}x{frame.size[1]} (size mismatch){hint}")
    intr = frame.intrinsics(w, h) if callable(frame.intrinsics) else frame.intrinsics
    maps = valid = None
    if frame.dist is not None:
        if not scene.undistort:
            raise DataError(f"{frame.source}: camera of {frame.image_path.name} has lens distortion "
                            f"{frame.dist.tolist()}; undistortion was turned off (undistort=False)")
        cache = scene.meta.setdefault("_undistort_maps", {})
        key = (tuple(intr), tuple(frame.dist), w, h)
        if key not in cache:
            cache[key] = undistort_maps(*intr, frame.dist, w, h)
        maps = cache[key]
        img = _remap(img, maps, "linear")
        valid = _remap(np.ones((h, w), np.float32), maps, "nearest") > 0.5
    extras = {}
    if load_extras:
        for name, (key, kind, interp, _, _) in _EXTRAS.items():
            path = frame.extras.get(key)
            if path is None:
                continue
            arr = _read_extra(kind, path, scene.background, scene.honour_exif)
            if name == "masks" and scene.meta.get("mask_convention") == "keep":
                arr = 1.0 - arr  # nerfstudio: 1 = train on the pixel; M is the opposite
            if arr.shape[:2] != (h, w):
                raise DataError(f"{path}: is {arr.shape[1]}x{arr.shape[0]} but its image "
                                f"{frame.image_path.name} is {w}x{h} (size mismatch)")
            if maps is not None:
                arr = _remap(arr, maps, "linear" if kind == "rgb" else interp)
            extras[name] = arr
    return {"image": img, "intrinsics": np.asarray(intr, np.float64), "valid": valid, "extras": extras}


def resize_frame(frame: dict, size: tuple[int, int]) -> dict:
    """A `read_frame` result resized to size = (W', H'), intrinsics rescaled consistently."""
    h, w = frame["image"].shape[:2]
    extras = {name: resize(arr, size, _EXTRAS[name].interp) for name, arr in frame["extras"].items()}
    valid = frame["valid"]
    if valid is not None:
        valid = resize(valid.astype(np.float32), size, "area") > 0.999
    return {"image": resize(frame["image"], size, "area"),
            "intrinsics": scale_intrinsics(frame["intrinsics"], size[0] / w, size[1] / h),
            "valid": valid, "extras": extras}


def _load_frames(scene: Scene, *, downscale: float, load_extras: bool, progress: bool = True) -> dict:
    """Reads every frame, checks they share one size, downscales. Returns stacked arrays."""
    from jaxnerf_grid import progress as progress_lib

    frames = scene.frames
    read = []
    ref = None  # (W, H, path) of the first frame
    for i in progress_lib.bar(range(len(frames)), desc=f"loading {scene.meta.get('format', 'images')}",
                              unit="frame", enabled=progress and len(frames) >= 32, leave=False):
        fr = read_frame(scene, i, load_extras)
        h, w = fr["image"].shape[:2]
        if ref is None:
            ref = (w, h, frames[i].image_path)
        elif (w, h) != ref[:2]:
            raise DataError(f"{frames[i].image_path}: image is {w}x{h} but {ref[2].name} is "
                            f"{ref[0]}x{ref[1]}; every image of a dataset must have one size "
                            f"(resize them with jaxnerf_grid.data.preprocess first)")
        read.append(resize_frame(fr, downscaled_size(w, h, downscale)))
    scene.meta.pop("_undistort_maps", None)
    out = {"images": np.stack([f["image"] for f in read]).astype(np.float32),
           "intrinsics": np.stack([f["intrinsics"] for f in read]).astype(np.float32),
           "undistorted": any(f["valid"] is not None for f in read)}
    n, hh, ww = out["images"].shape[:3]
    for name in _EXTRAS:
        values = [f["extras"].get(name) for f in read]
        if all(v is None for v in values):
            out[name] = None
            continue
        fill = {"clean_images": None, "depth": np.nan, "semantics": SEMANTIC_UNKNOWN,
                "distractor_masks": 0, "masks": 0.0, "weights": 1.0}[name]
        out[name] = np.stack([(out["images"][j] if name == "clean_images" else np.full((hh, ww), fill))
                              if v is None else v for j, v in enumerate(values)])
    if out["masks"] is not None:
        out["masks"] = (out["masks"] > 0.5).astype(np.float32)
    if out["distractor_masks"] is not None:
        out["distractor_masks"] = (out["distractor_masks"].astype(np.uint8) & 1).astype(bool)
    if out["semantics"] is not None:
        out["semantics"] = out["semantics"].astype(np.uint8)
    for name in ("clean_images", "depth", "weights"):
        if out[name] is not None:
            out[name] = out[name].astype(np.float32)
    if out["weights"] is None and out["masks"] is not None:
        out["weights"] = 1.0 - out["masks"]  # only mask_path given: weights = 1 - M
    if out["undistorted"]:
        valid = np.stack([np.ones((hh, ww), bool) if f["valid"] is None else f["valid"] for f in read])
        base = out["weights"] if out["weights"] is not None else np.ones((n, hh, ww), np.float32)
        out["weights"] = (base * valid).astype(np.float32)
    return out


def scene_to_dataset(scene: Scene, *, downscale: float = 1, load_extras: bool = True,
                     progress: bool = True) -> Dataset:
    """Reads the pixels of a collected scene into a `Dataset` (`progress`: a bar for 32+ frames)."""
    arrays = _load_frames(scene, downscale=downscale, load_extras=load_extras, progress=progress)
    paths = []
    for frame in scene.frames:
        try:
            paths.append(os.path.relpath(frame.image_path, scene.root))
        except ValueError:
            paths.append(str(frame.image_path))
    meta = dict(scene.meta)
    meta["undistorted"] = arrays["undistorted"]
    norm = scene.normalization
    return Dataset(
        root=scene.root, images=arrays["images"], c2w=np.asarray(scene.c2w, np.float32),
        intrinsics=arrays["intrinsics"], split=scene.split, near=float(scene.near), far=float(scene.far),
        weights=arrays["weights"], masks=arrays["masks"], clean_images=arrays["clean_images"],
        depth=arrays["depth"], semantics=arrays["semantics"],
        distractor_masks=arrays["distractor_masks"],
        normalization={"scale": float(norm["scale"]), "translation": [float(v) for v in norm["translation"]]},
        frame_paths=paths, meta=meta,
    )


# ----------------------------------------------------------------------------------------
# transforms.json and Blender


_KNOWN_JSON_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def _resolve_image(base: Path, file_path: str, json_path: Path, index: int) -> Path:
    if not isinstance(file_path, str) or not file_path:
        raise DataError(f"{json_path}: frame {index} has no file_path")
    path = (base / file_path)
    if path.suffix == "" or not path.is_file():
        for ext in IMAGE_EXTENSIONS:
            candidate = path.with_name(path.name + ext)
            if candidate.is_file():
                return candidate
    if not path.is_file():
        raise DataError(f"{path}: image file not found (frame {index} of {json_path})")
    return path


def _json_frame(top: dict, frame: dict, json_path: Path, index: int, load_extras: bool) -> _Frame:
    base = json_path.parent
    if not isinstance(frame, dict):
        raise DataError(f"{json_path}: frame {index} is not an object")
    image_path = _resolve_image(base, frame.get("file_path"), json_path, index)

    def get(key, default=None):
        return frame.get(key, top.get(key, default))

    model = str(get("camera_model", "PINHOLE")).upper()
    if model not in _KNOWN_JSON_MODELS:
        raise DataError(f"{json_path}: unknown or unsupported camera model {model!r} "
                        f"(supported: {', '.join(_KNOWN_JSON_MODELS)})")
    if "transform_matrix" not in frame:
        raise DataError(f"{json_path}: frame {index} ({frame.get('file_path')}) has no transform_matrix")
    c2w = validate_c2w(frame["transform_matrix"], f"{json_path} (frame {index}, {frame.get('file_path')})")
    w, h = get("w"), get("h")
    size = (int(w), int(h)) if w is not None and h is not None else None
    intr = [get("fl_x"), get("fl_y"), get("cx"), get("cy")]
    dist = [float(get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")]
    if any(float(get(k, 0.0)) != 0.0 for k in ("k4",)):
        raise DataError(f"{json_path}: distortion coefficient k4 is not supported (camera model {model})")
    extras = {}
    if load_extras:
        for key in (e.key for e in _EXTRAS.values()):
            if frame.get(key):
                extras[key] = base / frame[key]
                if not extras[key].is_file():
                    raise DataError(f"{extras[key]}: {key} file not found (frame {index} of {json_path})")
    fr = _Frame(image_path, c2w, None, size, dist, extras, str(json_path))
    fr.json_intrinsics = intr
    fr.json_angles = (get("camera_angle_x"), get("camera_angle_y"))
    fr.intrinsics = lambda width, height: _json_intrinsics(fr, json_path, width, height)
    return fr


def _json_intrinsics(fr: _Frame, json_path: Path, width: int, height: int) -> np.ndarray:
    """(fx, fy, cx, cy) [4] of a JSON frame from fl_x/fl_y/cx/cy or camera_angle_x/y."""
    fx, fy, cx, cy = fr.json_intrinsics
    ax, ay = fr.json_angles
    if fx is None and fy is None:
        if ax is None:
            raise DataError(f"{json_path}: no focal length for {fr.image_path.name} "
                            f"(need fl_x/fl_y or camera_angle_x)")
        fx = 0.5 * width / math.tan(0.5 * float(ax))
        fy = 0.5 * height / math.tan(0.5 * float(ay)) if ay is not None else fx
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    cx = 0.5 * width if cx is None else cx
    cy = 0.5 * height if cy is None else cy
    try:
        intr = np.array([fx, fy, cx, cy], dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{json_path}: non-numeric intrinsics for {fr.image_path.name}") from None
    if not np.all(np.isfinite(intr)) or intr[0] <= 0 or intr[1] <= 0:
        raise DataError(f"{json_path}: invalid intrinsics {intr.tolist()} for {fr.image_path.name}")
    return intr


def _normalise_json(c2w: np.ndarray, top: dict, json_path: Path, normalize, near_far_default):
    """Applies the normalisation policy of transforms.json; returns (c2w, norm, near, far).

    A file with `scene_normalization` is taken as normalised (its near/far as they are) unless
    `normalize=True`, which normalises again and composes the two maps.
    """
    near, far = top.get("near"), top.get("far")
    base = None
    if "scene_normalization" in top:
        sn = top["scene_normalization"]
        try:
            base = {"scale": float(sn["scale"]), "translation": [float(v) for v in sn["translation"]]}
        except (KeyError, TypeError, ValueError):
            raise DataError(f"{json_path}: scene_normalization needs 'scale' and 'translation' [3]") from None
        if len(base["translation"]) != 3 or not base["scale"] > 0:
            raise DataError(f"{json_path}: scene_normalization needs a positive scale and a "
                            f"3-vector translation")
        if normalize is not True:
            near = DEFAULT_NEAR if near is None else float(near)
            far = DEFAULT_FAR if far is None else float(far)
            return c2w, base, near, far
    base = base or {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}
    extra = {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}
    if normalize is not False:
        c2w, extra = normalize_poses(c2w)
    if near is None and near_far_default is not None and "scene_normalization" not in top:
        near, far = near_far_default
    near = DEFAULT_NEAR if near is None else float(near) * extra["scale"]
    far = DEFAULT_FAR if far is None else float(far) * extra["scale"]
    return c2w, compose_normalization(base, extra), near, far


def _collect_json(entries, top: dict, json_path: Path, root: Path, *, load_extras, background,
                  normalize, undistort, honour_exif, split, near_far_default, fmt) -> Scene:
    frames = [_json_frame(top, fr, path, i, load_extras) for i, (path, fr) in enumerate(entries)]
    c2w = np.stack([f.c2w for f in frames])
    c2w, norm, near, far = _normalise_json(c2w, top, json_path, normalize, near_far_default)
    meta = {"format": fmt, "source": str(json_path)}
    for key in ("generator", "tower_ply", "scene_normalization"):
        if key in top:
            meta[key] = top[key]
    return Scene(root, frames, c2w, split, near, far, norm, meta, background, undistort, honour_exif)


def load_transforms_json(path, *, downscale: float = 1, load_extras: bool = True, **kwargs) -> Dataset:
    """Loads a nerfstudio / instant-ngp `transforms.json` (docs/DATASET.md); options as in
    `collect_transforms_json`; `downscale` divides the resolution (cv2.INTER_AREA)."""
    scene = collect_transforms_json(path, load_extras=load_extras, **kwargs)
    return scene_to_dataset(scene, downscale=downscale, load_extras=load_extras)


def collect_transforms_json(path, *, load_extras: bool = True, normalize=None, background=None,
                            undistort: bool = True, honour_exif: bool = True, test_every: int = 8,
                            mask_convention: str = "foreground") -> Scene:
    """Collects a nerfstudio / instant-ngp `transforms.json` (docs/DATASET.md).

    path: the JSON file or its folder. normalize: None (normalise unless the file carries
    `scene_normalization`), True (always), False (never). background: [3] RGB to composite
    RGBA images over (None: alpha dropped). mask_convention: "foreground" (docs/DATASET.md:
    `mask_path` is the foreground mask M, 1 = excluded) or "keep" (nerfstudio's own
    convention: 1 = train on the pixel), which is inverted on load.
    """
    if mask_convention not in ("foreground", "keep"):
        raise ValueError(f"mask_convention must be 'foreground' or 'keep', got {mask_convention!r}")
    path = Path(path)
    json_path = path / "transforms.json" if path.is_dir() else path
    top = io.read_json(json_path)
    if not isinstance(top, dict):
        raise DataError(f"{json_path}: top level must be an object")
    frames = top.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{json_path}: no frames (empty split)")
    split = _json_split(top, json_path, test_every)
    scene = _collect_json([(json_path, f) for f in frames], top, json_path, json_path.parent,
                          load_extras=load_extras, background=background, normalize=normalize,
                          undistort=undistort, honour_exif=honour_exif, split=split,
                          near_far_default=None, fmt="transforms.json")
    scene.meta["mask_convention"] = mask_convention
    return scene


def _json_split(top: dict, json_path: Path, test_every: int) -> dict:
    frames = top["frames"]
    names = [f.get("split") if isinstance(f, dict) else None for f in frames]
    if any(n is not None for n in names):
        split = {}
        for i, n in enumerate(names):
            split.setdefault(n if n is not None else "train", []).append(i)
        if "test" not in split and "val" in split:
            split["test"] = split["val"]
        split.setdefault("train", [])
        split.setdefault("test", [])
        return _check_split(split, json_path)
    if "train_filenames" in top or "test_filenames" in top:
        index = {}
        for i, f in enumerate(frames):
            fp = str(f.get("file_path", ""))
            index[fp] = i
            index[os.path.normpath(fp)] = i
        split = {}
        for name in ("train", "val", "test"):
            listed = top.get(f"{name}_filenames") or []
            missing = [fp for fp in listed if fp not in index and os.path.normpath(fp) not in index]
            if missing:
                raise DataError(f"{json_path}: {name}_filenames names {missing[0]!r}, which is not a frame")
            split[name] = sorted(index.get(fp, index.get(os.path.normpath(fp))) for fp in listed)
        if not split["test"]:
            split["test"] = split["val"]
        return _check_split(split, json_path)
    return _check_split(default_split(len(frames), test_every), json_path)


def load_blender(path, *, downscale: float = 1, load_extras: bool = True, **kwargs) -> Dataset:
    """Loads a Blender-synthetic folder; options as in `collect_blender`."""
    scene = collect_blender(path, load_extras=load_extras, **kwargs)
    return scene_to_dataset(scene, downscale=downscale, load_extras=load_extras)


def collect_blender(path, *, load_extras: bool = True, background=(1.0, 1.0, 1.0), normalize=None,
                    honour_exif: bool = True) -> Scene:
    """Collects a Blender-synthetic folder (transforms_train.json, transforms_val.json,
    transforms_test.json; `camera_angle_x`; file paths without extension; RGBA PNG composited
    over `background`). Split: the file each frame came from ("val" frames are kept as a
    "val" split and stand in for "test" when there is no test file)."""
    root = Path(path)
    entries, split, top = [], {}, None
    for name in ("train", "val", "test"):
        json_path = root / f"transforms_{name}.json"
        if not json_path.is_file():
            continue
        data = io.read_json(json_path)
        frames = data.get("frames") if isinstance(data, dict) else None
        if not isinstance(frames, list) or not frames:
            raise DataError(f"{json_path}: no frames (empty split {name!r})")
        if top is None:
            top = dict(data)
        elif "camera_angle_x" in data and "camera_angle_x" not in top:
            top["camera_angle_x"] = data["camera_angle_x"]
        # camera_angle_x is per file in Blender data: copy it into frames so each file keeps its own.
        for fr in frames:
            fr = dict(fr)
            for key in ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h"):
                if key in data and key not in fr:
                    fr[key] = data[key]
            split.setdefault(name, []).append(len(entries))
            entries.append((json_path, fr))
    if top is None:
        raise DataError(f"{root}: no transforms_train.json / transforms_test.json (not a Blender folder)")
    if "train" not in split:
        raise DataError(f"{root / 'transforms_train.json'}: file not found (empty split 'train')")
    if "test" not in split and "val" in split:
        split["test"] = list(split["val"])
    split = _check_split(split, root / "transforms_test.json")
    top.pop("frames", None)
    return _collect_json(entries, top, root / "transforms_train.json", root, load_extras=load_extras,
                         background=background, normalize=normalize, undistort=True,
                         honour_exif=honour_exif, split=split,
                         near_far_default=(BLENDER_NEAR, BLENDER_FAR), fmt="blender")


# ----------------------------------------------------------------------------------------
# COLMAP


def colmap_w2c_to_c2w_gl(qvec, tvec) -> np.ndarray:
    """COLMAP world-to-camera (qvec (w, x, y, z), tvec [3], OpenCV axes) -> c2w [4, 4] OpenGL."""
    r = colmap_io.qvec_to_rotmat(qvec)
    c2w = np.eye(4)
    c2w[:3, :3] = r.T
    c2w[:3, 3] = -r.T @ np.asarray(tvec, np.float64)
    return c2w @ CV_TO_GL


def c2w_gl_to_colmap_w2c(c2w) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `colmap_w2c_to_c2w_gl`. c2w: [4, 4] OpenGL. Returns (qvec [4], tvec [3])."""
    c2w_cv = np.asarray(c2w, np.float64) @ CV_TO_GL
    r = c2w_cv[:3, :3].T
    t = -r @ c2w_cv[:3, 3]
    return colmap_io.rotmat_to_qvec(r), t


def _find_colmap(path: Path, images_dir) -> tuple[Path, str, Path, Path]:
    """(model folder, ext, images folder, dataset root) for a scene folder or a model folder."""
    found = colmap_io.find_model_files(path)
    if found is not None:
        model_dir, ext = found
        candidates = [path.parent.parent / "images", path.parent / "images", path / "images"]
    else:
        model_dir = ext = None
        for sub in (path / "sparse" / "0", path / "sparse", path / "colmap" / "sparse" / "0"):
            found = colmap_io.find_model_files(sub)
            if found is not None:
                model_dir, ext = found
                break
        if model_dir is None:
            raise DataError(f"{path}: no COLMAP sparse model (looked for cameras.bin/.txt in "
                            f"{path}, {path / 'sparse' / '0'}, {path / 'sparse'})")
        candidates = [path / "images"]
    if images_dir is not None:
        image_root = Path(images_dir)
    else:
        image_root = next((c for c in candidates if c.is_dir()), None)
        if image_root is None:
            raise DataError(f"{model_dir}: no images folder next to the COLMAP model "
                            f"(looked in {', '.join(str(c) for c in candidates)}); pass images_dir")
    return model_dir, ext, image_root, image_root.parent


def _near_far_from_points(c2w: np.ndarray, points: np.ndarray, min_cos: float,
                          observed: list | None = None) -> tuple[float, float] | None:
    """Ray-distance bounds from point z-depths (see module docstring).

    c2w: [N, 4, 4] OpenGL, normalised; points: [P, 3] normalised; observed: per frame an index
    array into points (None: all points, keeping those in front of the camera).
    """
    depths = []
    for i, m in enumerate(c2w):
        pts = points if observed is None or observed[i] is None else points[observed[i]]
        if len(pts) == 0:
            continue
        z = -(pts - m[:3, 3]) @ m[:3, 2]  # depth along the viewing axis (-z)
        depths.append(z[z > 0])
    if not depths or sum(len(d) for d in depths) == 0:
        return None
    z = np.concatenate(depths)
    near = max(0.9 * float(np.percentile(z, 0.5)), 1e-3)
    far = 1.1 * float(np.percentile(z, 99.5)) / min_cos
    return near, max(far, 2 * near)


def load_colmap(path, *, downscale: float = 1, load_extras: bool = True, **kwargs) -> Dataset:
    """Loads a COLMAP sparse model and its images; options as in `collect_colmap`."""
    scene = collect_colmap(path, load_extras=load_extras, **kwargs)
    return scene_to_dataset(scene, downscale=downscale, load_extras=False)


def collect_colmap(path, *, images_dir=None, undistort: bool = True, normalize: str | bool = "cameras",
                   honour_exif: bool = True, test_every: int = 8, load_extras: bool = True) -> Scene:
    """Collects a COLMAP sparse model (text or binary) and its images.

    path: a scene folder with sparse/0 (or sparse/) and images/, or the model folder itself
    (images then in ../../images or ../images). Frames sorted by image name; every
    `test_every`-th is a test frame. normalize: "cameras" | "points" | False.
    `load_extras` is accepted for a uniform signature (COLMAP has no extras).
    """
    del load_extras  # COLMAP has no extra per-frame files
    model_dir, ext, image_root, root = _find_colmap(Path(path), images_dir)
    cameras_file = model_dir / f"cameras{ext}"
    cameras, images, points3d = colmap_io.read_model(model_dir, ext)
    if not images:
        raise DataError(f"{model_dir / f'images{ext}'}: no registered images (empty split)")
    id_to_index = {pid: i for i, pid in enumerate(points3d)}
    xyz = np.array([p.xyz for p in points3d.values()], np.float64).reshape(-1, 3)
    frames, observed = [], []
    for im in sorted(images.values(), key=lambda im: im.name):
        if im.camera_id not in cameras:
            raise DataError(f"{model_dir / f'images{ext}'}: image {im.name} refers to camera "
                            f"{im.camera_id}, which {cameras_file.name} does not define")
        cam = cameras[im.camera_id]
        intr, dist = colmap_io.pinhole_and_distortion(cam, cameras_file)
        if not np.all(np.isfinite(cam.params)) or min(intr[0], intr[1], cam.width, cam.height) <= 0:
            raise DataError(f"{cameras_file}: camera {cam.id} has invalid parameters "
                            f"{cam.model} {cam.width}x{cam.height} {cam.params.tolist()}")
        source = f"{model_dir / f'images{ext}'} (image {im.name})"
        q = np.asarray(im.qvec, np.float64)
        if not np.all(np.isfinite(q)) or not np.all(np.isfinite(im.tvec)) or np.linalg.norm(q) < 1e-8:
            raise DataError(f"{source}: degenerate pose (non-finite or zero quaternion/translation)")
        c2w = validate_c2w(colmap_w2c_to_c2w_gl(q, im.tvec), source)
        frames.append(_Frame(image_root / im.name, c2w, intr, (cam.width, cam.height), dist, None,
                             str(cameras_file)))
        ids = np.asarray(im.point3D_ids, np.int64)
        observed.append(np.array([id_to_index[p] for p in ids if p in id_to_index], np.int64)
                        if len(ids) else None)
    c2w = np.stack([f.c2w for f in frames])
    if normalize is False:
        norm = {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}
    else:
        method = "cameras" if normalize is True else normalize
        c2w, norm = normalize_poses(c2w, xyz if len(xyz) else None, method=method)
    xyz_norm = apply_normalization_to_points(xyz, norm)
    min_cos = min(min_ray_cosine(f.intrinsics, *f.size) for f in frames)
    bounds = _near_far_from_points(c2w, xyz_norm, min_cos,
                                   observed if any(o is not None and len(o) for o in observed) else None)
    near, far = bounds if bounds is not None else (DEFAULT_NEAR, DEFAULT_FAR)
    split = _check_split(default_split(len(frames), test_every), model_dir)
    meta = {"format": "colmap", "source": str(model_dir),
            "camera_models": sorted({cameras[im.camera_id].model for im in images.values()}),
            "points3d": xyz_norm.astype(np.float32),
            "points3d_rgb": np.array([p.rgb for p in points3d.values()], np.uint8).reshape(-1, 3)}
    return Scene(root, frames, c2w, split, near, far, norm, meta, None, undistort, honour_exif)


# ----------------------------------------------------------------------------------------
# LLFF


def llff_to_c2w_gl(pose_3x5) -> tuple[np.ndarray, tuple[float, float, float]]:
    """One LLFF pose [3, 5] (columns down, right, backwards, centre, (H, W, focal)) ->
    (c2w [4, 4] OpenGL: right, up = -down, backwards; (H, W, focal))."""
    p = np.asarray(pose_3x5, np.float64)
    c2w = np.eye(4)
    c2w[:3, 0] = p[:, 1]
    c2w[:3, 1] = -p[:, 0]
    c2w[:3, 2] = p[:, 2]
    c2w[:3, 3] = p[:, 3]
    return c2w, (float(p[0, 4]), float(p[1, 4]), float(p[2, 4]))


def load_llff(path, *, downscale: float = 1, load_extras: bool = True, **kwargs) -> Dataset:
    """Loads an LLFF scene; options as in `collect_llff`."""
    scene = collect_llff(path, load_extras=load_extras, **kwargs)
    return scene_to_dataset(scene, downscale=downscale, load_extras=False)


def _llff_intrinsics(pose_intr, pose_size, image_path: Path, npy: Path, width: int, height: int):
    """LLFF intrinsics rescaled from the poses' (W, H) to the image's actual size."""
    sx, sy = width / pose_size[0], height / pose_size[1]
    if abs(sx - sy) > 0.02 * max(sx, sy):
        raise DataError(f"{image_path}: image is {width}x{height} but {npy.name} says "
                        f"{pose_size[0]:g}x{pose_size[1]:g} (size mismatch: aspect ratios differ)")
    return scale_intrinsics(pose_intr, sx, sy)


def collect_llff(path, *, images_dir=None, normalize: str | bool = "cameras", honour_exif: bool = True,
                 test_every: int = 8, load_extras: bool = True) -> Scene:
    """Collects an LLFF scene: poses_bounds.npy [N, 17] and images/ (sorted names, one per row).

    Focal lengths are rescaled when the images are smaller than the (H, W) in the poses
    (e.g. images_4/). cx, cy = W/2, H/2.
    """
    del load_extras  # LLFF has no extra per-frame files
    root = Path(path)
    npy = root / "poses_bounds.npy"
    if not npy.is_file():
        raise DataError(f"{npy}: file not found")
    try:
        arr = np.load(npy)
    except Exception as err:  # numpy raises several types on corrupt files
        raise DataError(f"{npy}: not a readable .npy file ({err})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or len(arr) == 0:
        raise DataError(f"{npy}: expected an [N, 17] array, got {arr.shape}")
    image_root = Path(images_dir) if images_dir is not None else root / "images"
    if not image_root.is_dir():
        raise DataError(f"{image_root}: images folder not found")
    names = sorted(p for p in image_root.iterdir() if p.suffix in IMAGE_EXTENSIONS and p.is_file())
    if len(names) != len(arr):
        raise DataError(f"{npy}: {len(arr)} poses but {len(names)} images in {image_root}")
    frames, bounds, min_cos = [], arr[:, 15:17].astype(np.float64), 1.0
    for i, (row, img_path) in enumerate(zip(arr, names)):
        source = f"{npy} (row {i}, {img_path.name})"
        if not np.all(np.isfinite(row)):
            raise DataError(f"{source}: degenerate pose (non-finite entries)")
        c2w, (h, w, focal) = llff_to_c2w_gl(row[:15].reshape(3, 5))
        c2w = validate_c2w(c2w, source)
        pose_intr = np.array([focal, focal, 0.5 * w, 0.5 * h])
        min_cos = min(min_cos, min_ray_cosine(pose_intr, w, h))
        # images may be a downsampled copy (images_4/): intrinsics follow the actual image size
        intr_fn = functools.partial(_llff_intrinsics, pose_intr, (w, h), img_path, npy)
        frames.append(_Frame(img_path, c2w, intr_fn, None, None, None, source))
    c2w = np.stack([f.c2w for f in frames])
    if normalize is False:
        norm = {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}
    else:
        focus = float(np.median(bounds.mean(axis=1)))
        method = "cameras" if normalize is True else normalize
        c2w, norm = normalize_poses(c2w, None, method=method, focus_depth=focus)
    near = max(0.9 * float(bounds.min()) * norm["scale"], 1e-3)
    far = 1.1 * float(bounds.max()) * norm["scale"] / min_cos
    split = _check_split(default_split(len(frames), test_every), npy)
    meta = {"format": "llff", "source": str(npy)}
    return Scene(root, frames, c2w, split, near, far, norm, meta, None, True, honour_exif)


# ----------------------------------------------------------------------------------------
# Autodetection


def detect_format(path) -> str:
    """"transforms.json" | "blender" | "colmap" | "llff" for a dataset path; DataError if none."""
    path = Path(path)
    if path.is_file():
        if path.suffix == ".json":
            return "transforms.json"
        if path.name == "poses_bounds.npy":
            return "llff"
        raise DataError(f"{path}: not a dataset (expected a folder, a transforms.json or poses_bounds.npy)")
    if not path.is_dir():
        raise DataError(f"{path}: dataset folder not found")
    if (path / "transforms.json").is_file():
        return "transforms.json"
    if (path / "transforms_train.json").is_file():
        return "blender"
    if colmap_io.find_model_files(path) is not None or any(
            colmap_io.find_model_files(p) is not None for p in (path / "sparse" / "0", path / "sparse")):
        return "colmap"
    if (path / "poses_bounds.npy").is_file():
        return "llff"
    raise DataError(f"{path}: no transforms.json, transforms_train.json, sparse/0/cameras.(bin|txt) "
                    f"or poses_bounds.npy: unknown dataset layout")


def collect_scene(path, *, load_extras: bool = True, **kwargs) -> Scene:
    """Collects any supported dataset (autodetected) without reading its pixels."""
    path = Path(path)
    fmt = detect_format(path)
    if fmt == "llff" and path.is_file():
        path = path.parent
    collect = {"transforms.json": collect_transforms_json, "blender": collect_blender,
               "colmap": collect_colmap, "llff": collect_llff}[fmt]
    return collect(path, load_extras=load_extras, **kwargs)


def load_dataset(path, split: str | None = None, *, downscale: float = 1, load_extras: bool = True,
                 progress: bool = True, **kwargs) -> Dataset:
    """Loads any supported dataset (autodetected, see `detect_format`).

    split: None (all frames, `Dataset.split` says which are which) or a split name, which
    returns only those frames (`Dataset.subset`). Other keyword arguments go to the loader.
    """
    scene = collect_scene(path, load_extras=load_extras, **kwargs)
    ds = scene_to_dataset(scene, downscale=downscale, load_extras=load_extras, progress=progress)
    if split is None:
        return ds
    if split not in ds.split or len(ds.split[split]) == 0:
        raise DataError(f"{path}: empty split {split!r} (available: {', '.join(ds.split)})")
    return ds.subset(ds.split[split])


# ----------------------------------------------------------------------------------------
# Writing


def write_frame(out_dir, stem: str, image: np.ndarray, intrinsics, c2w, split: str | None = None,
                extras: dict | None = None) -> dict:
    """Writes one frame's files under `out_dir` and returns its transforms.json entry.

    image: [H, W, 3] in [0, 1]; intrinsics: [4]; c2w: [4, 4]; extras: {Dataset field: array}
    (clean_images [H, W, 3]; depth, weights [H, W] float; masks [H, W] in [0, 1]; semantics,
    distractor_masks [H, W] uint8 / bool, written losslessly).
    """
    out_dir = Path(out_dir)
    rel = f"images/{stem}.png"
    io.write_png(out_dir / rel, image)
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    frame = {"file_path": rel, "transform_matrix": np.asarray(c2w, float).tolist(),
             "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": int(image.shape[1]), "h": int(image.shape[0])}
    if split is not None:
        frame["split"] = split
    for name, arr in (extras or {}).items():
        if arr is None:
            continue
        key, _, _, folder, ext = _EXTRAS[name]
        frame[key] = f"{folder}/{stem}{ext}"
        if ext == ".exr":
            io.write_exr(out_dir / frame[key], np.asarray(arr, np.float32))
        elif name in ("semantics", "distractor_masks"):
            raw = np.asarray(arr)
            raw = raw.astype(np.uint8) * (255 if raw.dtype == bool else 1)
            io.write_png(out_dir / frame[key], raw.astype(np.float32) / 255.0)
        else:
            io.write_png(out_dir / frame[key], np.asarray(arr, np.float32))
    return frame


def transforms_top(width: int, height: int, near: float, far: float, normalization: dict, meta: dict,
                   root, out_dir) -> dict:
    """Top-level keys of a written transforms.json (copies `tower_ply` next to it)."""
    top = {"w": int(width), "h": int(height), "camera_model": "PINHOLE",
           "near": float(near), "far": float(far),
           "scene_normalization": {"scale": float(normalization["scale"]),
                                   "translation": [float(v) for v in normalization["translation"]]}}
    if "generator" in meta:
        top["generator"] = meta["generator"]
    tower = meta.get("tower_ply")
    if tower and (Path(root) / tower).is_file():
        io.atomic_write_bytes(Path(out_dir) / tower, (Path(root) / tower).read_bytes())
        top["tower_ply"] = tower
    return top


def split_names(split: dict, num_frames: int) -> list:
    """Per frame its split name ("train" / "test", first match; None when in neither)."""
    names = [None] * num_frames
    for name in ("train", "test"):
        for i in np.asarray(split.get(name, []), np.int64):
            if names[int(i)] is None:
                names[int(i)] = name
    return names


def save_transforms_json(ds: Dataset, out_dir, *, overwrite: bool = False) -> Path:
    """Writes `ds` as a transforms.json dataset (docs/DATASET.md) under `out_dir`.

    Images and masks as 8-bit PNG, weights / depth as EXR, per-frame intrinsics. Refuses a
    non-empty `out_dir` unless `overwrite`. Returns the path of transforms.json.
    """
    out = io.ensure_writable(out_dir, overwrite)
    out.mkdir(parents=True, exist_ok=True)
    names = split_names(ds.split, ds.num_frames)
    frames = []
    for i in range(ds.num_frames):
        stem = f"{i:05d}_{Path(ds.frame_paths[i]).stem}" if ds.frame_paths else f"{i:05d}"
        extras = {name: None if getattr(ds, name) is None else getattr(ds, name)[i] for name in _EXTRAS}
        frames.append(write_frame(out, stem, ds.images[i], ds.intrinsics[i], ds.c2w[i], names[i], extras))
    top = transforms_top(ds.width, ds.height, ds.near, ds.far, ds.normalization, ds.meta, ds.root, out)
    top["frames"] = frames
    io.write_json(out / "transforms.json", top)
    return out / "transforms.json"
