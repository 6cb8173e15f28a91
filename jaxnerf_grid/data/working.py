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
