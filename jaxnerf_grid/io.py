"""File I/O: PNG / JPEG images, EXR float maps, PLY point clouds, atomic writes.

Images are float32 HWC in [0, 1], RGB order (OpenCV's BGR is converted here and nowhere
else). Float maps (depth, weights) are written as single- or multi-channel EXR.
Every reader raises `DataError` naming the file and what is wrong with it.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np


class DataError(ValueError):
    """Bad input data: the message names the file and what is wrong."""


def _cv2():
    import cv2  # imported lazily: OpenCV is slow to import

    return cv2


def decode_raw(path: str | os.PathLike, what: str = "image", flags: int | None = None):
    """Decodes a PNG / JPEG as OpenCV stores it (BGR(A), uint8 or uint16, no conversion).

    Raises DataError naming the file when it is missing or not decodable. `what` names the
    file's role in the message ("image", "mask", ...). Returns (array, raw bytes).
    """
    cv2 = _cv2()
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {what} file not found")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED if flags is None else flags) if data.size else None
    if img is None:
        raise DataError(f"{path}: not a readable {what} (corrupt or unsupported format)")
    return img, data


def read_image(path: str | os.PathLike, honour_exif: bool = True) -> np.ndarray:
    """Reads an 8/16-bit PNG or JPEG as float32 RGB in [0, 1].

    Returns: [H, W, 3] (alpha dropped, grey expanded). EXIF orientation is applied when
    `honour_exif` (OpenCV's default for JPEG).
    """
    cv2 = _cv2()
    path = Path(path)
    flags = cv2.IMREAD_UNCHANGED
    if not honour_exif:
        flags |= cv2.IMREAD_IGNORE_ORIENTATION
    img, data = decode_raw(path, "image", flags)
    if honour_exif and img.ndim == 3 and path.suffix.lower() in (".jpg", ".jpeg"):
        # IMREAD_UNCHANGED skips EXIF rotation; decode again with colour to honour it.
        img = cv2.imdecode(data, cv2.IMREAD_COLOR)
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float32) / scale
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    elif img.shape[-1] == 4:
        img = img[..., :3]
    elif img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    return np.ascontiguousarray(img[..., ::-1])


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Reads a single-channel PNG (8 or 16 bit) as float32 in [0, 1]. Returns: [H, W]."""
    img, _ = decode_raw(path, "mask")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    if img.ndim == 3:
        img = img[..., 0]
    return img.astype(np.float32) / scale


def write_png(path: str | os.PathLike, image: np.ndarray, bits: int = 8) -> None:
    """Writes an image in [0, 1] as PNG (atomic). image: [H, W], [H, W, 1], [H, W, 3] or [H, W, 4]."""
    cv2 = _cv2()
    img = np.asarray(image, dtype=np.float32)
    if not np.all(np.isfinite(img)):
        raise DataError(f"{path}: refusing to write an image with non-finite values")
    img = np.clip(img, 0.0, 1.0)
    if img.ndim == 3 and img.shape[-1] == 1:
        img = img[..., 0]
    if img.ndim == 3 and img.shape[-1] == 3:
        img = img[..., ::-1]
    elif img.ndim == 3 and img.shape[-1] == 4:
        img = img[..., [2, 1, 0, 3]]
    if bits == 16:
        arr = np.round(img * 65535.0).astype(np.uint16)
    else:
        arr = np.round(img * 255.0).astype(np.uint8)
    ok, buf = cv2.imencode(".png", arr)
    if not ok:
        raise DataError(f"{path}: OpenCV could not encode the PNG")
    atomic_write_bytes(path, buf.tobytes())


def write_exr(path: str | os.PathLike, data: np.ndarray, channel_names: tuple[str, ...] | None = None) -> None:
    """Writes a float32 map as EXR (atomic). data: [H, W] or [H, W, C].

    Single-channel maps use the channel name "Z" (depth convention) unless named otherwise;
    3-channel maps use R, G, B.
    """
    import OpenEXR

    arr = np.asarray(data, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise DataError(f"{path}: EXR data must be [H, W] or [H, W, C], got {arr.shape}")
    num_channels = arr.shape[-1]
    if channel_names is None:
        channel_names = {1: ("Z",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}.get(
            num_channels, tuple(f"C{i}" for i in range(num_channels))
        )
    if len(channel_names) != num_channels:
        raise DataError(f"{path}: {num_channels} channels but {len(channel_names)} names")
    channels = {name: np.ascontiguousarray(arr[..., i]) for i, name in enumerate(channel_names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, suffix=".exr") as tmp:
        with OpenEXR.File(header, channels) as exr_file:
            exr_file.write(str(tmp))


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Reads an EXR written by `write_exr`. Returns float32 [H, W] (one channel) or [H, W, C]."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: EXR file not found")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr_file:
            channels = exr_file.channels()
            names = list(channels.keys())
            planes = {name: np.asarray(channels[name].pixels, dtype=np.float32) for name in names}
    except Exception as err:  # OpenEXR raises plain RuntimeError on corrupt files
        raise DataError(f"{path}: not a readable EXR file ({err})") from None
    if len(names) == 1:
        return planes[names[0]]
    order = [n for n in ("R", "G", "B", "A") if n in planes]
    if len(order) != len(names):
        order = sorted(names)
    return np.stack([planes[n] for n in order], axis=-1)


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None,
              faces: np.ndarray | None = None) -> None:
    """Writes a binary little-endian PLY (atomic).

    points: [N, 3] float; colors: optional [N, 3] in [0, 1]; faces: optional [F, 3] int.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DataError(f"{path}: points must be [N, 3], got {points.shape}")
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}",
              "property float x", "property float y", "property float z"]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    vertex = np.empty(len(points), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = points.T
    if colors is not None:
        rgb = np.round(np.clip(np.asarray(colors, np.float32), 0, 1) * 255).astype(np.uint8)
        vertex["red"], vertex["green"], vertex["blue"] = rgb.T
    body = vertex.tobytes()
    if faces is not None:
        faces = np.asarray(faces, dtype=np.int32)
        face_rec = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
        face_rec["n"] = 3
        face_rec["v"] = faces
        body += face_rec.tobytes()
    atomic_write_bytes(path, ("\n".join(header) + "\n").encode("ascii") + body)


def read_ply_points(path: str | os.PathLike) -> np.ndarray:
    """Reads the vertex positions of a PLY written by `write_ply`. Returns: [N, 3] float32."""
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise DataError(f"{path}: not a PLY file")
    header = raw[:end].decode("ascii").splitlines()
    count = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    props = [line.split() for line in header if line.startswith("property")]
    vertex_props = []
    for p in props:
        if p[1] == "list":
            break
        vertex_props.append((p[2], "<f4" if p[1] == "float" else "u1"))
    vertex = np.frombuffer(raw, dtype=vertex_props, count=count, offset=end + len(b"end_header\n"))
    return np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=-1).astype(np.float32)


def atomic_write_bytes(path: str | os.PathLike, payload: bytes) -> None:
    """Writes bytes to `path` through a temporary file and a rename (never half-written)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(payload)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp"):
    """Yields a temporary path beside `path`; on success renames it over `path`, on any error
    removes it, so `path` is either the old file or the complete new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Writes JSON atomically with indentation."""
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=False) + "\n").encode("utf-8"))


def read_json(path: str | os.PathLike) -> Any:
    """Reads JSON, raising DataError naming the file on a missing file or a syntax error."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise DataError(f"{path}: invalid JSON at line {err.lineno}, column {err.colno}: {err.msg}") from None


def ensure_writable(path: str | os.PathLike, overwrite: bool) -> Path:
    """Refuses to touch an existing non-empty output unless `overwrite`. Returns the Path."""
    path = Path(path)
    if path.exists() and not overwrite:
        if path.is_file() or any(path.iterdir()):
            raise DataError(f"{path}: already exists and is not empty; pass --overwrite to replace it")
    return path
