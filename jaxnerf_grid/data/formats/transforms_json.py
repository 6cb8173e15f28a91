"""transforms.json datasets (nerfstudio / instant-ngp layout, docs/DATASET.md)."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.data.formats.frames import (
    DEFAULT_FAR,
    DEFAULT_NEAR,
    EXTRAS,
    IMAGE_EXTENSIONS,
    Frame,
    Scene,
    check_split,
    default_split,
    scene_to_dataset,
    validate_c2w,
)
from jaxnerf_grid.data.normalize import check_rotation, compose_normalization, normalize_poses
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError

_KNOWN_JSON_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def read_meta(folder: str | os.PathLike) -> dict:
    """A dataset folder's transforms.json as it stands ({} when the folder has none): what `mask`
    and `poses` recorded there (mask_domain, poses, ...), read without loading the dataset."""
    path = Path(folder) / "transforms.json"
    return io.read_json(path) if path.is_file() else {}


def _resolve_image(base: Path, file_path: Any, json_path: Path, index: int) -> Path:
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


def _json_frame(top: dict, frame: dict, json_path: Path, index: int, load_extras: bool) -> Frame:
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
        for key in (e.key for e in EXTRAS.values()):
            if frame.get(key):
                extras[key] = base / frame[key]
                if not extras[key].is_file():
                    raise DataError(f"{extras[key]}: {key} file not found (frame {index} of {json_path})")
    fr = Frame(image_path, c2w, None, size, dist, extras, str(json_path))
    fr.json_intrinsics = intr
    fr.json_angles = (get("camera_angle_x"), get("camera_angle_y"))
    fr.intrinsics = lambda width, height: _json_intrinsics(fr, json_path, width, height)
    return fr


def _json_intrinsics(fr: Frame, json_path: Path, width: int, height: int) -> np.ndarray:
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
    base: dict[str, Any] | None = None
    if "scene_normalization" in top:
        sn = top["scene_normalization"]
        try:
            given: dict[str, Any] = {"scale": float(sn["scale"]), "translation": [float(v) for v in sn["translation"]]}
        except (KeyError, TypeError, ValueError):
            raise DataError(f"{json_path}: scene_normalization needs 'scale' and 'translation' [3]") from None
        if len(given["translation"]) != 3 or not given["scale"] > 0:
            raise DataError(f"{json_path}: scene_normalization needs a positive scale and a "
                            f"3-vector translation")
        if sn.get("rotation") is not None:  # absent: the identity (docs/DATASET.md)
            given["rotation"] = check_rotation(sn["rotation"], str(json_path)).tolist()
        base = given
        if normalize is not True:
            near = DEFAULT_NEAR if near is None else float(near)
            far = DEFAULT_FAR if far is None else float(far)
            return c2w, base, near, far
    base = base or {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}
    extra: dict[str, Any] = {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}
    if normalize is not False:
        c2w, extra = normalize_poses(c2w)
    if near is None and near_far_default is not None and "scene_normalization" not in top:
        near, far = near_far_default
    near = DEFAULT_NEAR if near is None else float(near) * extra["scale"]
    far = DEFAULT_FAR if far is None else float(far) * extra["scale"]
    return c2w, compose_normalization(base, extra), near, far


def collect_json_frames(entries, top: dict, json_path: Path, root: Path, *, load_extras, background,
                  normalize, undistort, honour_exif, split, near_far_default, fmt) -> Scene:
    frames = [_json_frame(top, fr, path, i, load_extras) for i, (path, fr) in enumerate(entries)]
    c2w = np.stack([f.c2w for f in frames])
    c2w, norm, near, far = _normalise_json(c2w, top, json_path, normalize, near_far_default)
    meta = {"format": fmt, "source": str(json_path)}
    for key in ("generator", "tower_ply", "scene_normalization", "georeference", "poses", "mask_source",
                "mask_domain"):
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
    scene = collect_json_frames([(json_path, f) for f in frames], top, json_path, json_path.parent,
                          load_extras=load_extras, background=background, normalize=normalize,
                          undistort=undistort, honour_exif=honour_exif, split=split,
                          near_far_default=None, fmt="transforms.json")
    scene.meta["mask_convention"] = mask_convention
    return scene


def _json_split(top: dict, json_path: Path, test_every: int) -> dict:
    frames = top["frames"]
    names = [f.get("split") if isinstance(f, dict) else None for f in frames]
    if any(n is not None for n in names):
        split: dict[str, list] = {}
        for i, n in enumerate(names):
            split.setdefault(n if n is not None else "train", []).append(i)
        if "test" not in split and "val" in split:
            split["test"] = split["val"]
        split.setdefault("train", [])
        split.setdefault("test", [])
        return check_split(split, json_path)
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
        return check_split(split, json_path)
    return check_split(default_split(len(frames), test_every), json_path)
