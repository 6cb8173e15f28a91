"""LLFF datasets: poses_bounds.npy ([N, 17]: a 3x5 pose-and-size matrix and z-depth bounds)."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np

from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.data.formats.frames import (
    IMAGE_EXTENSIONS,
    Frame,
    Scene,
    check_split,
    default_split,
    min_ray_cosine,
    scale_intrinsics,
    scene_to_dataset,
    validate_c2w,
)
from jaxnerf_grid.data.normalize import z_up_normalization
from jaxnerf_grid.util.io import DataError, load_error_reason


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
    (e.g. images_4/). cx, cy = W/2, H/2. When normalising, the scene is also turned so the up
    axis found from the cameras is +z (`normalize.z_up_normalization`, recorded as the "rotation").
    """
    del load_extras  # LLFF has no extra per-frame files
    root = Path(path)
    npy = root / "poses_bounds.npy"
    if not npy.is_file():
        raise DataError(f"{npy}: file not found")
    try:
        arr = np.load(npy, allow_pickle=False)
    except Exception as err:  # numpy raises several types on corrupt files
        raise DataError(f"{npy}: not a readable .npy file ({load_error_reason(err)})") from None
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
        if not (h >= 1 and w >= 1):
            raise DataError(f"{source}: image size H, W = {h:g}, {w:g}: both must be >= 1")
        if not focal > 0:
            raise DataError(f"{source}: focal length {focal:g}: must be > 0")
        if not 0 < row[15] < row[16]:
            raise DataError(f"{source}: depth bounds near, far = {row[15]:g}, {row[16]:g}: need 0 < near < far")
        c2w = validate_c2w(c2w, source)
        pose_intr = np.array([focal, focal, 0.5 * w, 0.5 * h])
        min_cos = min(min_cos, min_ray_cosine(pose_intr, w, h))
        # images may be a downsampled copy (images_4/): intrinsics follow the actual image size
        intr_fn = functools.partial(_llff_intrinsics, pose_intr, (w, h), img_path, npy)
        frames.append(Frame(img_path, c2w, intr_fn, None, None, None, source))
    c2w = np.stack([f.c2w for f in frames])
    if normalize is False:
        norm: dict[str, Any] = {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}
    else:
        focus = float(np.median(bounds.mean(axis=1)))
        method = "cameras" if normalize is True else normalize
        c2w, norm = z_up_normalization(c2w, None, method=method, focus_depth=focus)
    near = max(0.9 * float(bounds.min()) * norm["scale"], 1e-3)
    far = 1.1 * float(bounds.max()) * norm["scale"] / min_cos
    split = check_split(default_split(len(frames), test_every), npy)
    meta = {"format": "llff", "source": str(npy)}
    return Scene(root, frames, c2w, split, near, far, norm, meta, None, True, honour_exif)
