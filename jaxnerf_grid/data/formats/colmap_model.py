"""COLMAP sparse models: readers and writers for the text and binary forms.

A model is three files in one folder: `cameras`, `images`, `points3D`, each `.txt` or `.bin`
(the layouts of COLMAP's `src/colmap/scene/reconstruction_io`). Conventions kept as COLMAP has
them: `qvec` (w, x, y, z) and `tvec` map world to camera, `x_cam = R(qvec) @ x_world + tvec`,
camera axes OpenCV (x right, y down, z forward); pixel centres at +0.5 (so `cx`, `cy` use the
same convention as `rays.py`). Conversion to c2w OpenGL lives in `formats/colmap.py`.

Every reader raises `DataError` naming the file and what is wrong with it.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from pathlib import Path

import numpy as np

from jaxnerf_grid.util.io import DataError, atomic_write_bytes

# model id -> (name, number of parameters); COLMAP's own numbering.
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}
MODEL_IDS = {name: (model_id, n) for model_id, (name, n) in CAMERA_MODELS.items()}
# The models the loaders accept (pinhole + polynomial radial/tangential distortion).
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclasses.dataclass
class Camera:
    """One COLMAP camera. params: [P] float64 in COLMAP's order for `model`."""

    id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclasses.dataclass
class Image:
    """One registered image. qvec: [4] (w, x, y, z) and tvec: [3], world-to-camera.

    xys: [K, 2] keypoint pixel positions; point3D_ids: [K] int64 (-1 = no 3-D point).
    """

    id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str
    xys: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))
    point3D_ids: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0,), np.int64))


@dataclasses.dataclass
class Point3D:
    """One triangulated point. xyz: [3]; rgb: [3] uint8; track: [T, 2] (image_id, point2D_idx)."""

    id: int
    xyz: np.ndarray
    rgb: np.ndarray
    error: float
    track: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2), np.int64))


# ----------------------------------------------------------------------------------------
# Rotations


def qvec_to_rotmat(qvec) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> rotation [3, 3]. qvec: [4] (normalised here)."""
    q = np.asarray(qvec, dtype=np.float64)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotmat_to_qvec(rotation) -> np.ndarray:
    """Rotation [3, 3] -> unit quaternion [4] (w, x, y, z) with w >= 0.

    Uses the eigenvector of the symmetric 4x4 matrix K built from R (Bar-Itzhack), which is
    stable for every rotation, including 180-degree turns.
    """
    r = np.asarray(rotation, dtype=np.float64)
    rxx, ryx, rzx, rxy, ryy, rzy, rxz, ryz, rzz = r.ravel()
    k = np.array([
        [rxx - ryy - rzz, 0, 0, 0],
        [ryx + rxy, ryy - rxx - rzz, 0, 0],
        [rzx + rxz, rzy + ryz, rzz - rxx - ryy, 0],
        [ryz - rzy, rzx - rxz, rxy - ryx, rxx + ryy + rzz],
    ]) / 3.0
    eigvals, eigvecs = np.linalg.eigh(k)
    x, y, z, w = eigvecs[:, np.argmax(eigvals)]
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


# ----------------------------------------------------------------------------------------
# Text form


def _data_lines(path: Path) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f"{path}: not a readable COLMAP text file ({err})") from None
    return [line for line in text.splitlines() if not line.lstrip().startswith("#")]


def _token_rows(path: Path):
    """(line, tokens) of each non-empty, non-comment line of a COLMAP text file."""
    for line in _data_lines(path):
        tokens = line.split()
        if tokens:
            yield line, tokens


def _check_model(path: Path, model: str, num_params: int) -> None:
    if model not in MODEL_IDS:
        raise DataError(f"{path}: unknown camera model {model!r} (known: {', '.join(MODEL_IDS)})")
    expected = MODEL_IDS[model][1]
    if num_params != expected:
        raise DataError(f"{path}: camera model {model} needs {expected} parameters, got {num_params}")


def read_cameras_text(path) -> dict[int, Camera]:
    """Reads `cameras.txt`: lines `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`."""
    path = Path(path)
    cameras = {}
    for line, tokens in _token_rows(path):
        try:
            cam_id, model = int(tokens[0]), tokens[1]
            width, height = int(tokens[2]), int(tokens[3])
            params = np.array([float(v) for v in tokens[4:]], dtype=np.float64)
        except (ValueError, IndexError):
            raise DataError(f"{path}: malformed camera line {line!r}") from None
        _check_model(path, model, len(params))
        cameras[cam_id] = Camera(cam_id, model, width, height, params)
    return cameras


def read_images_text(path) -> dict[int, Image]:
    """Reads `images.txt`: per image a line `ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` and a
    line of `X Y POINT3D_ID` triples (possibly empty)."""
    path = Path(path)
    lines = _data_lines(path)
    images = {}
    i = 0
    while i < len(lines):
        tokens = lines[i].split()
        i += 1
        if not tokens:
            continue
        if len(tokens) < 10:
            raise DataError(f"{path}: malformed image line {lines[i - 1]!r}")
        try:
            image_id = int(tokens[0])
            qvec = np.array([float(v) for v in tokens[1:5]])
            tvec = np.array([float(v) for v in tokens[5:8]])
            camera_id = int(tokens[8])
        except ValueError:
            raise DataError(f"{path}: malformed image line {lines[i - 1]!r}") from None
        name = " ".join(tokens[9:])
        point_tokens = lines[i].split() if i < len(lines) else []
        i += 1
        if len(point_tokens) % 3:
            raise DataError(f"{path}: points line of image {name!r} is not X Y POINT3D_ID triples")
        try:
            triples = np.array([float(v) for v in point_tokens], dtype=np.float64).reshape(-1, 3)
        except ValueError:
            raise DataError(f"{path}: malformed points line of image {name!r}") from None
        images[image_id] = Image(image_id, qvec, tvec, camera_id, name,
                                 triples[:, :2], triples[:, 2].astype(np.int64))
    return images


def read_points3D_text(path) -> dict[int, Point3D]:
    """Reads `points3D.txt`: `ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)`."""
    path = Path(path)
    points = {}
    for line, tokens in _token_rows(path):
        try:
            pid = int(tokens[0])
            xyz = np.array([float(v) for v in tokens[1:4]])
            rgb = np.array([int(v) for v in tokens[4:7]], dtype=np.uint8)
            error = float(tokens[7])
            track = np.array([int(v) for v in tokens[8:]], dtype=np.int64).reshape(-1, 2)
        except (ValueError, IndexError):
            raise DataError(f"{path}: malformed point line {line[:80]!r}") from None
        points[pid] = Point3D(pid, xyz, rgb, error, track)
    return points


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def write_cameras_text(path, cameras: dict[int, Camera]) -> None:
    """Writes `cameras.txt` (atomic)."""
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cameras)}"]
    for cam in cameras.values():
        lines.append(f"{cam.id} {cam.model} {cam.width} {cam.height} {_fmt(cam.params)}")
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8"))


def write_images_text(path, images: dict[int, Image]) -> None:
    """Writes `images.txt` (atomic), two lines per image."""
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(images)}"]
    for im in images.values():
        lines.append(f"{im.id} {_fmt(im.qvec)} {_fmt(im.tvec)} {im.camera_id} {im.name}")
        lines.append(" ".join(f"{float(x)!r} {float(y)!r} {int(p)}"
                              for (x, y), p in zip(im.xys, im.point3D_ids)))
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8"))


def write_points3D_text(path, points: dict[int, Point3D]) -> None:
    """Writes `points3D.txt` (atomic)."""
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(points)}"]
    for p in points.values():
        track = " ".join(f"{int(a)} {int(b)}" for a, b in np.asarray(p.track).reshape(-1, 2))
        rgb = " ".join(str(int(v)) for v in p.rgb)
        lines.append(f"{p.id} {_fmt(p.xyz)} {rgb} {float(p.error)!r} {track}".rstrip())
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8"))


# ----------------------------------------------------------------------------------------
# Binary form (little endian)


class _Reader:
    """Sequential little-endian reader over a byte buffer; truncation -> DataError."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.buf = path.read_bytes()
        except FileNotFoundError:
            raise DataError(f"{path}: file not found") from None
        except OSError as err:
            raise DataError(f"{path}: not readable ({err})") from None
        self.pos = 0

    def take(self, fmt: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.buf):
            raise DataError(f"{self.path}: truncated binary COLMAP file (at byte {self.pos})")
        values = struct.unpack_from("<" + fmt, self.buf, self.pos)
        self.pos += size
        return values

    def array(self, dtype, count: int) -> np.ndarray:
        dtype = np.dtype(dtype).newbyteorder("<")
        size = dtype.itemsize * count
        if count < 0 or self.pos + size > len(self.buf):
            raise DataError(f"{self.path}: truncated binary COLMAP file (at byte {self.pos})")
        out = np.frombuffer(self.buf, dtype=dtype, count=count, offset=self.pos)
        self.pos += size
        return out

    def cstring(self) -> str:
        end = self.buf.find(b"\x00", self.pos)
        if end < 0:
            raise DataError(f"{self.path}: truncated binary COLMAP file (unterminated name)")
        name = self.buf[self.pos:end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return name


def read_cameras_binary(path) -> dict[int, Camera]:
    """Reads `cameras.bin`: uint64 count; per camera int32 id, int32 model, uint64 w, h, f64 params."""
    reader = _Reader(Path(path))
    (count,) = reader.take("Q")
    cameras = {}
    for _ in range(count):
        cam_id, model_id, width, height = reader.take("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise DataError(f"{path}: unknown camera model id {model_id} (camera {cam_id})")
        model, num_params = CAMERA_MODELS[model_id]
        params = reader.array("f8", num_params).astype(np.float64)
        cameras[cam_id] = Camera(cam_id, model, int(width), int(height), params)
    return cameras


def read_images_binary(path) -> dict[int, Image]:
    """Reads `images.bin`: uint64 count; per image int32 id, f64 qvec[4], tvec[3], int32
    camera id, NUL-terminated name, uint64 K, K x (f64 x, f64 y, int64 point3D_id)."""
    reader = _Reader(Path(path))
    (count,) = reader.take("Q")
    images = {}
    point_dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
    for _ in range(count):
        image_id, *rest = reader.take("i7di")
        qvec, tvec, camera_id = np.array(rest[:4]), np.array(rest[4:7]), rest[7]
        name = reader.cstring()
        (num_points,) = reader.take("Q")
        pts = reader.array(point_dtype, num_points)
        xys = np.stack([pts["x"], pts["y"]], axis=-1) if num_points else np.zeros((0, 2))
        images[image_id] = Image(image_id, qvec, tvec, camera_id, name, xys,
                                 pts["id"].astype(np.int64))
    return images


def read_points3D_binary(path) -> dict[int, Point3D]:
    """Reads `points3D.bin`: uint64 count; per point uint64 id, f64 xyz[3], uint8 rgb[3],
    f64 error, uint64 T, T x (int32 image_id, int32 point2D_idx)."""
    reader = _Reader(Path(path))
    (count,) = reader.take("Q")
    points = {}
    for _ in range(count):
        pid, x, y, z, r, g, b, error, track_len = reader.take("Q3d3BdQ")
        track = reader.array("i4", 2 * track_len).astype(np.int64).reshape(-1, 2)
        points[pid] = Point3D(pid, np.array([x, y, z]), np.array([r, g, b], np.uint8), error, track)
    return points


def write_cameras_binary(path, cameras: dict[int, Camera]) -> None:
    """Writes `cameras.bin` (atomic)."""
    out = [struct.pack("<Q", len(cameras))]
    for cam in cameras.values():
        model_id, num_params = MODEL_IDS[cam.model]
        if len(cam.params) != num_params:
            raise DataError(f"{path}: camera {cam.id} ({cam.model}) needs {num_params} parameters")
        out.append(struct.pack("<iiQQ", cam.id, model_id, cam.width, cam.height))
        out.append(np.asarray(cam.params, "<f8").tobytes())
    atomic_write_bytes(path, b"".join(out))


def write_images_binary(path, images: dict[int, Image]) -> None:
    """Writes `images.bin` (atomic)."""
    out = [struct.pack("<Q", len(images))]
    point_dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
    for im in images.values():
        out.append(struct.pack("<i7di", im.id, *np.asarray(im.qvec, float), *np.asarray(im.tvec, float),
                               im.camera_id))
        out.append(im.name.encode("utf-8") + b"\x00")
        pts = np.empty(len(im.point3D_ids), dtype=point_dtype)
        if len(pts):
            pts["x"], pts["y"] = np.asarray(im.xys, float).T
            pts["id"] = im.point3D_ids
        out.append(struct.pack("<Q", len(pts)) + pts.tobytes())
    atomic_write_bytes(path, b"".join(out))


def write_points3D_binary(path, points: dict[int, Point3D]) -> None:
    """Writes `points3D.bin` (atomic)."""
    out = [struct.pack("<Q", len(points))]
    for p in points.values():
        track = np.asarray(p.track, "<i4").reshape(-1, 2)
        out.append(struct.pack("<Q3d3BdQ", p.id, *np.asarray(p.xyz, float), *[int(v) for v in p.rgb],
                               float(p.error), len(track)))
        out.append(track.tobytes())
    atomic_write_bytes(path, b"".join(out))


# ----------------------------------------------------------------------------------------
# Whole models


def find_model_files(folder) -> tuple[Path, str] | None:
    """The folder and extension (".bin" or ".txt") of a sparse model, or None.

    Binary wins when both forms are present (COLMAP's own preference).
    """
    folder = Path(folder)
    for ext in (".bin", ".txt"):
        if (folder / f"cameras{ext}").is_file() and (folder / f"images{ext}").is_file():
            return folder, ext
    return None


def read_model(folder, ext: str | None = None):
    """Reads a sparse model. Returns (cameras, images, points3D) dicts keyed by id.

    `points3D` is optional on disk (an empty dict when absent).
    """
    folder = Path(folder)
    if ext is None:
        found = find_model_files(folder)
        if found is None:
            raise DataError(f"{folder}: no COLMAP model (cameras.bin/images.bin or cameras.txt/images.txt)")
        ext = found[1]
    if ext == ".bin":
        cameras = read_cameras_binary(folder / "cameras.bin")
        images = read_images_binary(folder / "images.bin")
        pts_path = folder / "points3D.bin"
        points = read_points3D_binary(pts_path) if pts_path.is_file() else {}
    elif ext == ".txt":
        cameras = read_cameras_text(folder / "cameras.txt")
        images = read_images_text(folder / "images.txt")
        pts_path = folder / "points3D.txt"
        points = read_points3D_text(pts_path) if pts_path.is_file() else {}
    else:
        raise ValueError(f"ext must be '.bin' or '.txt', got {ext!r}")
    return cameras, images, points


def write_model(folder, cameras, images, points=None, ext: str = ".txt") -> None:
    """Writes a sparse model (cameras, images, points3D) as text (".txt") or binary (".bin")."""
    folder = Path(folder)
    os.makedirs(folder, exist_ok=True)
    points = {} if points is None else points
    if ext == ".txt":
        write_cameras_text(folder / "cameras.txt", cameras)
        write_images_text(folder / "images.txt", images)
        write_points3D_text(folder / "points3D.txt", points)
    elif ext == ".bin":
        write_cameras_binary(folder / "cameras.bin", cameras)
        write_images_binary(folder / "images.bin", images)
        write_points3D_binary(folder / "points3D.bin", points)
    else:
        raise ValueError(f"ext must be '.bin' or '.txt', got {ext!r}")


# ----------------------------------------------------------------------------------------
# Intrinsics


def pinhole_and_distortion(camera: Camera, source: Path | str = "cameras") -> tuple[np.ndarray, np.ndarray]:
    """Splits a camera's params into pinhole intrinsics and OpenCV distortion coefficients.

    Returns (fx_fy_cx_cy [4], dist [4] = (k1, k2, p1, p2)). Models outside
    SUPPORTED_MODELS raise DataError naming `source` and the model.
    """
    p = np.asarray(camera.params, dtype=np.float64)
    zero = np.zeros(4)
    if camera.model == "SIMPLE_PINHOLE":
        return np.array([p[0], p[0], p[1], p[2]]), zero
    if camera.model == "PINHOLE":
        return p[:4].copy(), zero
    if camera.model == "SIMPLE_RADIAL":
        return np.array([p[0], p[0], p[1], p[2]]), np.array([p[3], 0.0, 0.0, 0.0])
    if camera.model == "RADIAL":
        return np.array([p[0], p[0], p[1], p[2]]), np.array([p[3], p[4], 0.0, 0.0])
    if camera.model == "OPENCV":
        return p[:4].copy(), p[4:8].copy()
    raise DataError(f"{source}: camera {camera.id} uses camera model {camera.model}, which is not "
                    f"supported (supported: {', '.join(SUPPORTED_MODELS)}); undistort the images "
                    f"with `colmap image_undistorter` first")
