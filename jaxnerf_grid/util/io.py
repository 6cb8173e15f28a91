"""File I/O: PNG / JPEG images, EXR float maps, PLY point clouds, atomic writes.

Images are float32 HWC in [0, 1], RGB order (OpenCV's BGR is converted here and nowhere
else). Float maps (depth, weights) are written as single- or multi-channel EXR.
Every reader raises `DataError` naming the file and what is wrong with it.
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np


class DataError(ValueError):
    """Bad input data: the message names the file and what is wrong."""


_OPENCV_QUIET = {"active": False, "level": None}  # `quiet_opencv`'s state: on, and the level it replaced


def opencv():
    """The cv2 module, imported on first use (OpenCV is slow to import). Inside `quiet_opencv`
    (the command line) its own log is lowered to errors only; outside, it is left as it is."""
    import cv2

    if _OPENCV_QUIET["active"] and _OPENCV_QUIET["level"] is None:
        _OPENCV_QUIET["level"] = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    return cv2


@contextlib.contextmanager
def quiet_opencv():
    """Inside the block, OpenCV's own log shows errors only, so a corrupt image is reported
    once, as a DataError naming the file, not also as OpenCV's "[ WARN:0@0.013] global
    grfmt_png.cpp ..." line; after it (also on an error) the level is what it was. Does not
    import cv2 itself (`opencv` lowers the level on first use inside the block), so a command
    that never reads an image pays nothing. Used by the dispatcher (`cli.main`) only: a
    program that uses the library keeps OpenCV's log as it set it."""
    if _OPENCV_QUIET["active"]:  # nested: the outer block restores
        yield
        return
    _OPENCV_QUIET.update(active=True, level=None)
    try:
        if "cv2" in sys.modules:
            opencv()
        yield
    finally:
        level = _OPENCV_QUIET["level"]
        _OPENCV_QUIET.update(active=False, level=None)
        if level is not None:
            sys.modules["cv2"].utils.logging.setLogLevel(level)


def resize(array: np.ndarray, size: tuple[int, int], interpolation: str = "area") -> np.ndarray:
    """Resizes [H, W] or [H, W, C] to size = (W', H') (OpenCV's order, width first).

    interpolation: "area" (INTER_AREA when shrinking, bilinear when either side grows: OpenCV's
    INTER_AREA only averages when shrinking), "linear" or "nearest". Returns the input itself
    when the size is unchanged; a [H, W, 1] input keeps its channel axis.
    """
    cv2 = opencv()
    width, height = size
    if array.shape[1] == width and array.shape[0] == height:
        return array
    flag = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST}[interpolation]
    if interpolation == "area" and (width > array.shape[1] or height > array.shape[0]):
        flag = cv2.INTER_LINEAR
    out = cv2.resize(array, (width, height), interpolation=flag)
    if array.ndim == 3 and out.ndim == 2:
        out = out[..., None]
    return out


def decode_raw(path: str | os.PathLike, what: str = "image", flags: int | None = None):
    """Decodes a PNG / JPEG as OpenCV stores it (BGR(A), uint8 or uint16, no conversion).

    Raises DataError naming the file when it is missing or not decodable. `what` names the
    file's role in the message ("image", "mask", ...). Returns (array, raw bytes).
    """
    cv2 = opencv()
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
    cv2 = opencv()
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


def distractor_bit(raw: np.ndarray) -> np.ndarray:
    """The synthetic scenes' distractor mask from its stored pixels: the low bit of channel 0.

    The generator (jaxnerf_grid/data/synthetic/generate.py) writes 0 / 255, so the low bit is the
    mask whether the PNG was decoded raw or resized with nearest-neighbour. raw: integers of
    any shape (one channel: [H, W], or a stack [N, H, W]). Returns: bool, raw's shape.
    """
    return (np.asarray(raw).astype(np.int64) & 1).astype(bool)


def read_distractor_mask(path: str | os.PathLike) -> np.ndarray:
    """Reads a synthetic scene's distractor mask PNG (see `distractor_bit`); of a colour PNG,
    channel 0. Returns: bool [H, W]."""
    raw, _ = decode_raw(path, "distractor mask")
    return distractor_bit(raw[..., 0] if raw.ndim == 3 else raw)


def write_png(path: str | os.PathLike, image: np.ndarray, bits: int = 8) -> None:
    """Writes an image in [0, 1] as PNG (atomic). image: [H, W], [H, W, 1], [H, W, 3] or [H, W, 4]."""
    cv2 = opencv()
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
              faces: np.ndarray | None = None, comments: tuple[str, ...] = ()) -> None:
    """Writes a binary little-endian PLY (atomic).

    points: [N, 3] float; colors: optional [N, 3] in [0, 1]; faces: optional [F, 3] int;
    comments: header comment lines (one line each, e.g. the units; a PLY header is ASCII, so
    other characters, such as those of a path, are written as backslash escapes: `ascii_text`).
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DataError(f"{path}: points must be [N, 3], got {points.shape}")
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {ascii_text(' '.join(str(c).split()))}" for c in comments]
    header += [f"element vertex {len(points)}",
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


def ascii_text(text: str) -> str:
    """`text` with every non-ASCII character as a backslash escape ("Tür" -> "T\\xfcr")."""
    return text.encode("ascii", "backslashreplace").decode("ascii")


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _ply_header(path: Path, raw: bytes) -> tuple[str, list, int]:
    """(format, elements [(name, count, [(prop, type) | (prop, "list", count_type, item_type)])],
    offset of the body) of a PLY file's bytes."""
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise DataError(f"{path}: not a PLY file")
    body = raw.find(b"\n", end) + 1
    if body <= 0:
        raise DataError(f"{path}: PLY header does not end with a newline")
    fmt = None
    elements: list = []
    for line in raw[:end].decode("ascii", errors="replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and words[1] == "list":
                elements[-1][2].append((words[4], "list", _PLY_TYPES[words[2]], _PLY_TYPES[words[3]]))
            elif words[0] == "property":
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise DataError(f"{path}: unexpected PLY header line {line!r}")
        except (IndexError, KeyError, ValueError):
            raise DataError(f"{path}: bad PLY header line {line!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DataError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements, body


def read_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Reads the vertex element of a PLY file (ascii, binary little- or big-endian).

    Returns {property name: [N] array} for every scalar vertex property (x, y, z, and e.g.
    red, green, blue, nx, ...), in the file's types. Elements listed before the vertex
    element are skipped (in binary files only when they have no list properties).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise DataError(f"{path}: cannot read ({e.strerror or e})") from None
    fmt, elements, offset = _ply_header(path, raw)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise DataError(f"{path}: PLY file has no vertex element")
    if fmt == "ascii":
        lines = raw[offset:].decode("ascii", errors="replace").splitlines()
        start = sum(e[1] for e in elements[:names.index("vertex")])
        _, count, props = elements[names.index("vertex")]
        if any(p[1] == "list" for p in props):
            raise DataError(f"{path}: list properties in the vertex element are not supported")
        rows = [line.split() for line in lines[start:start + count]]
        if len(rows) != count or any(len(r) < len(props) for r in rows):
            raise DataError(f"{path}: PLY file is truncated (expected {count} vertex lines)")
        table = np.asarray([r[:len(props)] for r in rows], dtype=np.float64).reshape(count, len(props))
        return {name: table[:, k].astype(kind) for k, (name, kind) in enumerate(props)}
    order = "<" if fmt == "binary_little_endian" else ">"
    for name, count, props in elements:
        if any(p[1] == "list" for p in props):
            raise DataError(f"{path}: binary PLY with list properties in element {name!r} before or in "
                            "the vertex element is not supported")
        dtype = np.dtype([(p[0], order + p[1]) for p in props])
        if offset + count * dtype.itemsize > len(raw):
            raise DataError(f"{path}: PLY file is truncated ({name} element)")
        if name == "vertex":
            table = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
            return {p[0]: table[p[0]].astype(p[1]) for p in props}
        offset += count * dtype.itemsize
    raise AssertionError("unreachable")


def read_ply_points(path: str | os.PathLike) -> np.ndarray:
    """Vertex positions of a PLY file (see `read_ply`). Returns: [N, 3] float32."""
    vertex = read_ply(path)
    missing = [k for k in "xyz" if k not in vertex]
    if missing:
        raise DataError(f"{path}: PLY vertices have no {', '.join(missing)} property")
    return np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=-1).astype(np.float32)


@contextlib.contextmanager
def naming_path(path: str | os.PathLike, doing: str = "cannot write"):
    """Turns an OSError raised inside the block (a full disk, a read-only folder, a permission)
    into a one-line DataError naming `path`: "PATH: cannot write (No space left on device)".
    The OSError a write raises often names no file (ENOSPC from write()), and a temporary
    file's name would not tell the user which output failed."""
    try:
        yield
    except OSError as err:
        reason = err.strerror or str(err) or type(err).__name__
        raise DataError(f"{path}: {doing} ({reason})") from None


def load_error_reason(err: BaseException) -> str:
    """Why NumPy could not load a .npy / .npz, for a one-line error: NumPy's own message, except
    that its advice to load with allow_pickle (which runs code stored in the file) is not passed
    on: such a file holds Python objects, not plain arrays."""
    text = str(err) or type(err).__name__
    if "allow_pickle" in text or "pickle" in text.lower():
        return "it holds Python objects, not plain arrays; not loaded, as unpickling can run code"
    return text


def atomic_write_bytes(path: str | os.PathLike, payload: bytes) -> None:
    """Writes bytes to `path` through a temporary file and a rename (never half-written)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(payload)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp", durable: bool = False):
    """Yields a temporary path beside `path`; on success renames it over `path`, on any error
    removes it, so `path` is either the old file or the complete new one.

    The temporary file is named `.{name}.XXXX{suffix}` in the same folder. durable=True also
    fsyncs the file before the rename and the folder after it, so the new file survives a
    power cut as well as a killed process (checkpoints use it).
    """
    path = Path(path)
    with naming_path(path):  # an OSError (full disk, read-only folder) names `path`, not the temporary file
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
        os.close(fd)
        try:
            try:  # mkstemp makes it 0600; the file gets the mode open() would give
                os.chmod(tmp, _mode_for(path))
            except OSError:  # a filesystem without permissions (FAT, some network shares): keep going
                pass
            yield Path(tmp)
            if durable:
                _fsync(tmp, os.O_RDONLY)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        if durable:
            _fsync(path.parent, os.O_RDONLY)


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _read_umask()  # read once, at import: os.umask can only be read by setting it


def _mode_for(path: Path) -> int:
    """The permission bits a written file gets: those of the file it replaces, else 0666 less
    the process's umask (what open() gives a new file)."""
    try:
        return stat.S_IMODE(path.stat().st_mode)
    except OSError:
        return 0o666 & ~_UMASK


def _fsync(path: str | os.PathLike, flags: int) -> None:
    """fsync of a file or folder; a filesystem that cannot fsync a folder is not an error."""
    try:
        fd = os.open(path, flags)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Writes JSON atomically with indentation."""
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=False) + "\n").encode("utf-8"))


def read_text(path: str | os.PathLike, what: str = "file", encoding: str = "utf-8") -> str:
    """The text of a UTF-8 file the user gave. DataError naming the file (and `what` it is)
    when it is missing, not a file, unreadable (OSError) or not UTF-8 text."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {what} not found" + (" (it is a folder)" if path.is_dir() else ""))
    try:
        return path.read_text(encoding=encoding)
    except UnicodeDecodeError as err:
        raise DataError(f"{path}: {what} is not UTF-8 text (byte {err.object[err.start]:#x} at offset "
                        f"{err.start}); save it as UTF-8") from None
    except OSError as err:
        raise DataError(f"{path}: cannot read the {what}: {err.strerror or err}") from None


def read_json(path: str | os.PathLike) -> Any:
    """Reads JSON, raising DataError naming the file on a missing file, a syntax error or
    text that is not UTF-8 (`read_text`)."""
    path = Path(path)
    text = read_text(path)
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise DataError(f"{path}: invalid JSON at line {err.lineno}, column {err.colno}: {err.msg}") from None


def ensure_writable(path: str | os.PathLike, overwrite: bool) -> Path:
    """Refuses to touch an existing non-empty output unless `overwrite`. Returns the Path."""
    path = Path(path)
    if path.exists() and not overwrite:
        if path.is_file() or any(path.iterdir()):
            raise DataError(f"{path}: already exists and is not empty; pass overwrite=True to replace it")
    return path
