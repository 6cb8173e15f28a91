"""What every format shares: constants, pose and image checks, resizing of intrinsics, the
frame-wise reading of a collected `Scene` into a `Dataset` (docs/DATASET.md)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from jaxnerf_grid.data import working
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.data.normalize import normalization_record
from jaxnerf_grid.util import io
from jaxnerf_grid.util import progress as progress_lib
from jaxnerf_grid.util.io import DataError

DEFAULT_NEAR = 0.05   # normalised units; cameras usually sit 1.5-3 units from the centre
DEFAULT_FAR = 100.0   # generous: the contraction compresses everything past the unit sphere
BLENDER_NEAR, BLENDER_FAR = 2.0, 6.0
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
SEMANTIC_UNKNOWN = 255  # class id of pixels of frames without a semantic map
# GL camera axes from CV ones (and back): flip y and z.
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


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


def min_ray_cosine(intrinsics: np.ndarray, width: float, height: float) -> float:
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


def check_split(split: dict, source) -> dict:
    for name in ("train", "test"):
        if len(split.get(name, [])) == 0:
            raise DataError(f"{source}: empty split {name!r} (no {name} frames)")
    return {k: np.asarray(v, dtype=np.int64) for k, v in split.items()}


def undistort_maps(fx, fy, cx, cy, dist, width: int, height: int):
    """OpenCV remap tables that undistort an image into the pinhole camera (fx, fy, cx, cy).

    dist: [4|5] (k1, k2, p1, p2[, k3]). OpenCV puts pixel centres at integers, so its principal
    point is (cx - 0.5, cy - 0.5). Returns (map_x [H, W], map_y [H, W]) float32.
    """
    cv2 = io.opencv()
    k = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return cv2.initUndistortRectifyMap(k, np.asarray(dist, np.float64), None, k, (width, height),
                                       cv2.CV_32FC1)


def _remap(array, maps, interpolation: str):
    cv2 = io.opencv()
    flag = cv2.INTER_NEAREST if interpolation == "nearest" else cv2.INTER_LINEAR
    out = cv2.remap(array, maps[0], maps[1], flag, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if array.ndim == 3 and out.ndim == 2:
        out = out[..., None]
    return out


# ----------------------------------------------------------------------------------------
# Frame-wise loading shared by every format


class Frame:
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
        # set by the transforms.json loader: the frame's own (fl_x, fl_y, cx, cy) and camera angles
        self.json_intrinsics: Any = None
        self.json_angles: Any = None


class Extra(NamedTuple):
    """How one optional per-frame field is stored: its transforms.json key, how it is read and
    resampled (interpolation for downscaling / undistortion), and where the writer puts it."""
    key: str
    kind: str
    interp: str
    folder: str
    ext: str


EXTRAS = {  # Dataset field -> storage; one table for reading and writing
    "clean_images": Extra("clean_file_path", "rgb", "area", "clean", ".png"),
    "depth": Extra("depth_file_path", "exr", "nearest", "depth", ".exr"),
    "semantics": Extra("semantic_file_path", "u8", "nearest", "semantic", ".png"),
    "distractor_masks": Extra("distractor_mask_path", "u8", "nearest", "distractor", ".png"),
    "masks": Extra("mask_path", "mask", "area", "masks", ".png"),
    "weights": Extra("weight_path", "exr", "area", "weights", ".exr"),
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
        fx, fy, cx, cy = intr
        maps_key = (tuple(intr), tuple(frame.dist), w, h)
        if maps_key not in cache:
            cache[maps_key] = undistort_maps(fx, fy, cx, cy, frame.dist, w, h)
        maps = cache[maps_key]
        img = _remap(img, maps, "linear")
        valid = _remap(np.ones((h, w), np.float32), maps, "nearest") > 0.5
    extras = {}
    if load_extras:
        for name, (key, kind, interp, _, _) in EXTRAS.items():
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
    extras = {name: io.resize(arr, size, EXTRAS[name].interp) for name, arr in frame["extras"].items()}
    valid = frame["valid"]
    if valid is not None:
        valid = io.resize(valid.astype(np.float32), size, "area") > 0.999
    return {"image": io.resize(frame["image"], size, "area"),
            "intrinsics": scale_intrinsics(frame["intrinsics"], size[0] / w, size[1] / h),
            "valid": valid, "extras": extras}


def working_dataset(ds: Dataset, max_side: int) -> Dataset:
    """An in-memory dataset at the working resolution of `max_side` (working.working_size; the
    dataset itself when it is already that size): images, clean images, masks and weights by
    area averaging (masks then re-binarised at 0.5, as on load), depth, semantics and
    distractor masks by nearest neighbour (EXTRAS), intrinsics scaled (scale_intrinsics)."""
    w, h = ds.width, ds.height
    size = working.working_size(w, h, int(max_side))
    if size == (w, h):
        return ds

    def each(arr, interp):
        if arr is None:
            return None
        dtype = arr.dtype
        src = arr.astype(np.uint8) if dtype.kind == "b" else arr
        out = np.stack([io.resize(np.asarray(a), size, interp) for a in src])
        return out.astype(dtype)

    masks = each(ds.masks, EXTRAS["masks"].interp)
    meta = dict(ds.meta, native_size=list(ds.meta.get("native_size", (w, h))))
    return dataclasses.replace(
        ds, images=each(ds.images, "area"), clean_images=each(ds.clean_images, EXTRAS["clean_images"].interp),
        weights=each(ds.weights, EXTRAS["weights"].interp),
        masks=None if masks is None else (masks > 0.5).astype(np.float32),
        depth=each(ds.depth, EXTRAS["depth"].interp), semantics=each(ds.semantics, EXTRAS["semantics"].interp),
        distractor_masks=each(ds.distractor_masks, EXTRAS["distractor_masks"].interp),
        intrinsics=scale_intrinsics(ds.intrinsics, size[0] / w, size[1] / h).astype(np.float32), meta=meta)


def _cache_options(scene: Scene, frame: Frame, load_extras: bool) -> dict:
    """The reading options a cached frame depends on besides its files (working.frame_key)."""
    return {"dist": None if frame.dist is None else frame.dist.tolist(), "undistort": scene.undistort,
            "background": None if scene.background is None else np.asarray(scene.background).tolist(),
            "honour_exif": scene.honour_exif, "load_extras": load_extras,
            "mask_convention": scene.meta.get("mask_convention")}


def _native_intrinsics(frame: Frame, size) -> np.ndarray:
    return np.asarray(frame.intrinsics(*size) if callable(frame.intrinsics) else frame.intrinsics, np.float64)


def read_resized_frame(scene: Scene, index: int, load_extras: bool, *, downscale: float = 1,
                       max_side: int = 0, cache: bool = True) -> tuple[dict, tuple[int, int]]:
    """Frame `index` at its working size: divided by `downscale`, or to the long side `max_side`
    (working.working_size; 0 = full size). Returns (a `resize_frame` dict, the native (W, H)).

    With `cache`, a frame that is resized is read from / written to the dataset's cache of
    working frames (working.py) instead of being decoded again."""
    frame = scene.frames[index]
    rule = f"max_side={int(max_side)}" if max_side else f"downscale={float(downscale):g}"
    extras = {k: p for k, p in frame.extras.items()} if load_extras else {}
    path = None
    if cache and (max_side or downscale != 1):
        try:
            key = working.frame_key(frame.image_path, extras, rule, _cache_options(scene, frame, load_extras))
            path = working.entry_path(scene.root, frame.image_path, rule, key)
        except OSError:  # a file vanished: read_frame says which
            path = None
        hit = working.load_entry(path) if path is not None else None
        if hit is not None and (frame.size is None or tuple(frame.size) == hit["native_size"]) \
                and np.array_equal(_native_intrinsics(frame, hit["native_size"]), hit["native_intrinsics"]):
            w, h = hit["native_size"]
            size = hit["image"].shape[1], hit["image"].shape[0]
            return {"image": hit["image"], "valid": hit["valid"], "extras": hit["extras"],
                    "intrinsics": scale_intrinsics(hit["native_intrinsics"], size[0] / w, size[1] / h)}, (w, h)
    fr = read_frame(scene, index, load_extras)
    h, w = fr["image"].shape[:2]
    size = working.working_size(w, h, int(max_side)) if max_side else downscaled_size(w, h, downscale)
    resized = resize_frame(fr, size)
    if path is not None and size != (w, h):
        working.store_entry(path, (w, h), fr["intrinsics"], resized)
    return resized, (w, h)


def _load_frames(scene: Scene, *, downscale: float, load_extras: bool, progress: bool = True,
                 max_side: int = 0, cache: bool = True, uint8_images: bool = False) -> dict:
    """Reads every frame, checks they share one size, downscales (by `downscale`, or to the
    working resolution of `max_side`, read_resized_frame). Returns stacked arrays.

    Each frame's image goes into one preallocated array as it is read (float32, or uint8 in a
    `working.frame_buffer` with `uint8_images`), so at most one full-size photo is in memory."""
    if max_side and downscale != 1:
        raise ValueError(f"give downscale ({downscale}) or max_side ({max_side}), not both")
    frames = scene.frames
    read = []
    images: Any = None  # [N, H, W, 3], allocated once the first frame's working size is known
    ref: Any = None  # (W, H, path) of the first frame
    for i in progress_lib.bar(range(len(frames)), desc=f"loading {scene.meta.get('format', 'images')}",
                              unit="frame", enabled=progress and len(frames) >= 32, leave=False):
        fr, (w, h) = read_resized_frame(scene, i, load_extras, downscale=downscale, max_side=max_side,
                                        cache=cache)
        if ref is None:
            ref = (w, h, frames[i].image_path)
        elif (w, h) != ref[:2]:
            raise DataError(f"{frames[i].image_path}: image is {w}x{h} but {ref[2].name} is "
                            f"{ref[0]}x{ref[1]}; every image of a dataset must have one size "
                            f"(resize them with jaxnerf_grid.data.preprocess first)")
        if images is None:
            hh, ww = fr["image"].shape[:2]
            images = working.frame_buffer(len(frames), hh, ww) if uint8_images else \
                np.empty((len(frames), hh, ww, 3), np.float32)
        images[i] = working.to_uint8(fr["image"]) if uint8_images else fr["image"]
        read.append(dict(fr, image=None))  # the image lives in `images` only
    scene.meta.pop("_undistort_maps", None)
    out: dict[str, Any] = {"images": images,
           "intrinsics": np.stack([f["intrinsics"] for f in read]).astype(np.float32),
           "undistorted": any(f["valid"] is not None for f in read), "native_size": ref[:2]}
    n, hh, ww = out["images"].shape[:3]
    for name in EXTRAS:
        values = [f["extras"].get(name) for f in read]
        if all(v is None for v in values):
            out[name] = None
            continue
        fill = {"clean_images": None, "depth": np.nan, "semantics": SEMANTIC_UNKNOWN,
                "distractor_masks": 0, "masks": 0.0, "weights": 1.0}[name]
        out[name] = np.stack([(working.as_float(out["images"][j]) if name == "clean_images"
                               else np.full((hh, ww), fill)) if v is None else v for j, v in enumerate(values)])
    if out["masks"] is not None:
        out["masks"] = (out["masks"] > 0.5).astype(np.float32)
    if out["distractor_masks"] is not None:
        out["distractor_masks"] = io.distractor_bit(out["distractor_masks"])
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
                     progress: bool = True, max_side: int = 0, cache: bool = True,
                     uint8_images: bool = False) -> Dataset:
    """Reads the pixels of a collected scene into a `Dataset` (`progress`: a bar for 32+ frames),
    at the working resolution of `max_side` (0: full size; working.py) or divided by `downscale`;
    `cache`: keep the resized frames in the dataset's cache (working.py); `uint8_images`: images
    as uint8 (value / 255) in a `working.frame_buffer`, for training. meta["native_size"] is the
    photos' (W, H)."""
    arrays = _load_frames(scene, downscale=downscale, load_extras=load_extras, progress=progress,
                          max_side=max_side, cache=cache, uint8_images=uint8_images)
    paths = []
    for frame in scene.frames:
        try:
            paths.append(os.path.relpath(frame.image_path, scene.root))
        except ValueError:
            paths.append(str(frame.image_path))
    meta = dict(scene.meta)
    meta["undistorted"] = arrays["undistorted"]
    meta["native_size"] = [int(v) for v in arrays["native_size"]]
    return Dataset(
        root=scene.root, images=arrays["images"], c2w=np.asarray(scene.c2w, np.float32),
        intrinsics=arrays["intrinsics"], split=scene.split, near=float(scene.near), far=float(scene.far),
        weights=arrays["weights"], masks=arrays["masks"], clean_images=arrays["clean_images"],
        depth=arrays["depth"], semantics=arrays["semantics"],
        distractor_masks=arrays["distractor_masks"],
        normalization=normalization_record(scene.normalization),
        frame_paths=paths, meta=meta,
    )
