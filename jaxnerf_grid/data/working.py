"""The working resolution: which size a run trains at, and the cache of frames at that size.

The rule (docs/DATASET.md, "Working resolution"): a budget `max_side` in pixels (the
`train.max_side` config key, 640 by default, 0 = full size) picks the smallest integer factor
k >= 1 with long side / k <= max_side, and every image is resized to
(round(W / k), round(H / k)) with area averaging (`downscaled_size`, cv2.INTER_AREA). An
integer factor makes each working pixel the mean of a k x k block when k divides the size.
The intrinsics are scaled per axis by (W'/W, H'/H) (`frames.scale_intrinsics`): with pixel
centres at +0.5, continuous pixel coordinates scale exactly, so a working pixel's ray passes
through the same 3-D points as the full-size rays of its block's centre.

The cache: decoding and resizing full-size photos is the slow part of loading a capture, so
each resized frame (image, the undistortion's valid mask, masks, weights and the other extras)
is stored once in `<dataset>/.jaxnerf-grid-cache/working/` as an .npz named by the image and
the rule, keyed by the path, byte size and modification time of the image and of every extra
file, and by the reading options. A frame whose files or options change misses and is read
again; its stale entries are removed when the new one is written. Entries are written to a
temporary file and renamed (a killed process leaves no half-written entry), and nothing else
in the dataset is touched; a read-only dataset folder just goes without a cache.
"""

from __future__ import annotations

import hashlib
import math
import os
import zipfile
from pathlib import Path

import numpy as np

from jaxnerf_grid.util import io

DEFAULT_MAX_SIDE = 640   # px; a 2-core CPU trains and renders this in minutes
CACHE_FOLDER = Path(".jaxnerf-grid-cache") / "working"
CACHE_VERSION = 1


def working_factor(width: int, height: int, max_side: int) -> int:
    """The integer downscale factor k of the working resolution: the smallest k >= 1 with
    max(width, height) / k <= max_side; 1 when max_side is 0 (full size)."""
    if isinstance(max_side, bool) or not isinstance(max_side, (int, np.integer)) or max_side < 0:
        raise ValueError(f"max_side must be an integer >= 0, got {max_side!r}")
    if max_side == 0:
        return 1
    return max(1, math.ceil(max(int(width), int(height)) / int(max_side)))


def working_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    """(W', H') = (round(W / k), round(H / k)) with k = working_factor (at least 1 px each)."""
    k = working_factor(width, height, max_side)
    return max(1, int(round(width / k))), max(1, int(round(height / k)))


# ----------------------------------------------------------------------------------------- the cache


def cache_folder(root) -> Path:
    """Where a dataset's working frames are cached: <root>/.jaxnerf-grid-cache/working."""
    return Path(root) / CACHE_FOLDER


def _stat(path: Path) -> list:
    st = os.stat(path)
    return [str(Path(path).resolve()), int(st.st_size), int(st.st_mtime_ns)]


def frame_key(image_path, extra_paths: dict, rule: str, options: dict) -> str:
    """sha256 hex of what a cached frame depends on: the image's and each extra file's path,
    size and mtime, the resizing rule (e.g. "max_side=640") and the reading options (a dict of
    JSON-able values: distortion, background, ...)."""
    h = hashlib.sha256()
    parts = [CACHE_VERSION, rule, _stat(Path(image_path)),
             sorted((k, _stat(Path(p))) for k, p in extra_paths.items()), sorted(options.items())]
    h.update(repr(parts).encode("utf-8"))
    return h.hexdigest()


def entry_path(root, image_path, rule: str, key: str) -> Path:
    """The cache file of one frame: <cache>/<image id>-<rule>-<key>.npz."""
    image_id = hashlib.sha256(str(Path(image_path).resolve()).encode("utf-8")).hexdigest()[:16]
    return cache_folder(root) / f"{image_id}-{rule}-{key[:24]}.npz"


def load_entry(path: Path) -> dict | None:
    """A cached frame {"native_size": (W, H), "native_intrinsics": [4], "image", "valid" or None,
    "extras": {name: array}}; None when absent or unreadable (a miss, never an error)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        return {"native_size": tuple(int(v) for v in arrays.pop("native_size")),
                "native_intrinsics": arrays.pop("native_intrinsics").astype(np.float64),
                "image": arrays.pop("image"), "valid": arrays.pop("valid", None),
                "extras": {k[len("extra_"):]: v for k, v in arrays.items() if k.startswith("extra_")}}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


def store_entry(path: Path, native_size, native_intrinsics, frame: dict) -> bool:
    """Writes a resized frame (a `frames.resize_frame` result) to `path` atomically and removes
    the stale entries of the same image and rule. Returns False when the folder is not writable."""
    arrays = {"native_size": np.asarray(native_size, np.int64),
              "native_intrinsics": np.asarray(native_intrinsics, np.float64), "image": frame["image"]}
    if frame["valid"] is not None:
        arrays["valid"] = frame["valid"]
    arrays.update({f"extra_{k}": v for k, v in frame["extras"].items()})
    try:
        with io.atomic_path(path, suffix=".part") as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
        prefix = path.name.rsplit("-", 1)[0] + "-"
        for old in path.parent.glob(prefix + "*.npz"):
            if old != path:
                old.unlink(missing_ok=True)
    except (OSError, io.DataError):  # a full disk or read-only cache (io.atomic_path names it): no cache
        return False
    return True


# ------------------------------------------------------------------------------------ 8-bit frames
# A capture's working frames are held as uint8 (1 byte a channel: a 20 MP capture's frames at
# --max-side 1600 are 1.5 GB instead of 6 GB as float32) in one buffer laid out so that the
# training pool can hand whole groups of frames to the devices without copying them
# (`frame_rows`): every frame starts on a FRAME_ALIGN-byte boundary (XLA's CPU client then
# aliases the host memory instead of copying it) and FRAME_SPARE frames of zeros follow the last,
# so n * ceil(N / n) frames exist for any device count n dividing FRAME_SPARE + 1.

FRAME_ALIGN = 64
FRAME_SPARE = 7


def frame_stride(height: int, width: int) -> int:
    """Bytes from one frame's start to the next in a frame buffer: H * W * 3 rounded up to FRAME_ALIGN."""
    return -(-int(height) * int(width) * 3 // FRAME_ALIGN) * FRAME_ALIGN


def _aligned_zeros(nbytes: int) -> np.ndarray:
    """[nbytes] uint8 zeros starting on a FRAME_ALIGN boundary (a view of a slightly larger owner)."""
    owner = np.zeros(nbytes + FRAME_ALIGN, np.uint8)
    start = (-owner.ctypes.data) % FRAME_ALIGN
    return owner[start:start + nbytes]


def frame_buffer(frames: int, height: int, width: int) -> np.ndarray:
    """Zeroed uint8 images [frames, H, W, 3], each frame FRAME_ALIGN-aligned, with FRAME_SPARE spare
    zero frames after the last in the same buffer (`frame_rows` finds them)."""
    stride = frame_stride(height, width)
    rows = _aligned_zeros((int(frames) + FRAME_SPARE) * stride).reshape(-1, stride)
    return rows[:int(frames), :height * width * 3].reshape(int(frames), height, width, 3)


def frame_rows(images: np.ndarray) -> np.ndarray | None:
    """The buffer of a `frame_buffer` array as [F, stride] uint8 rows, one per frame (F >= N: the
    spare frames included), sharing its memory; None for any other array (then a copy is needed).
    images: [N, H, W, 3] uint8."""
    if not isinstance(images, np.ndarray) or images.dtype != np.uint8 or images.ndim != 4:
        return None
    n, h, w, _ = images.shape
    stride = frame_stride(h, w)
    base = images.base
    while isinstance(base, np.ndarray) and base.base is not None and base.ndim != 1:
        base = base.base
    if (not isinstance(base, np.ndarray) or base.ndim != 1 or base.dtype != np.uint8
            or images.strides != (stride, w * 3, 3, 1) or images.ctypes.data % FRAME_ALIGN):
        return None
    offset = images.ctypes.data - base.ctypes.data
    if offset < 0 or (base.size - offset) < n * stride:
        return None
    rows = (base.size - offset) // stride
    return base[offset:offset + rows * stride].reshape(rows, stride)


def to_uint8(images: np.ndarray) -> np.ndarray:
    """Float images in [0, 1] as uint8 (round(255 x), clipped); exact for values k / 255 (8-bit
    photos at their native size), within 0.5 / 255 for resized ones. [...] -> [...] uint8."""
    images = np.asarray(images)
    if images.dtype == np.uint8:
        return images
    return np.clip(np.rint(np.asarray(images, np.float32) * 255.0), 0, 255).astype(np.uint8)


def as_float(images: np.ndarray) -> np.ndarray:
    """Images as float32 in [0, 1]: uint8 ones divided by 255 (the same float32 operation as
    io.read_image, so an 8-bit photo's values are bit-identical), others as float32."""
    images = np.asarray(images)
    if images.dtype == np.uint8:
        return images.astype(np.float32) / 255.0
    return images.astype(np.float32, copy=False)
