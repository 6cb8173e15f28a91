"""Dataset loaders: transforms.json (nerfstudio / instant-ngp), Blender synthetic, COLMAP, LLFF.

Every loader returns a `Dataset` (dataset.py): c2w camera-to-world with OpenGL camera axes
(x right, y up, looking down -z), intrinsics (fx, fy, cx, cy) in pixels with pixel centres at
+0.5, images float32 RGB in [0, 1], the scene normalised so the region of interest lies in the
unit sphere (`normalization` maps metric points to it: x_norm = scale * R (x + translation), R
the optional "rotation", the identity when absent; docs/DATASET.md).

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
  `undistort=False`. Turned so the cameras' up axis is +z (`normalize.up_from_cameras`; the turn is
  the record's "rotation") and normalised with the points3D (robust extent). near/far: from the z-depths
  of the points each image observes: near = 0.9 x the 0.5th percentile, far = 1.1 x the 99.5th
  percentile divided by the smallest cosine between a pixel ray and the optical axis (z-depth
  -> ray distance); DEFAULT_NEAR / DEFAULT_FAR without points.
- LLFF poses_bounds.npy: [N, 17], a [3, 5] matrix per image (columns down, right, backwards,
  centre, (H, W, focal)) and (near, far) z-depth bounds. near/far from the bounds, as for
  COLMAP (0.9 x min, 1.1 x max / cos). Turned z-up as COLMAP.

Splits: a frame's `split` key, or the Blender file a frame came from, or `train_filenames` /
`test_filenames` lists; otherwise every `test_every`-th frame (0, 8, 16, ...) is a test frame.
An empty train or test split is a DataError.

All bad input raises `DataError` naming the file: missing / unreadable image, size mismatch,
non-finite or degenerate pose, unknown camera model, empty split.

The package has one module per format (`transforms_json`, `blender`, `colmap`, `llff`), the
frame reading they share (`frames`) and the writer (`writing`); this module detects the
format and re-exports the public names, so `formats.load_dataset(path)` is the entry point.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.data.formats import colmap_model as colmap_io
from jaxnerf_grid.data.formats.blender import collect_blender, load_blender
from jaxnerf_grid.data.formats.colmap import collect_colmap, colmap_w2c_to_c2w_gl, load_colmap
from jaxnerf_grid.data.formats.frames import (
    BLENDER_FAR,
    BLENDER_NEAR,
    CV_TO_GL,
    DEFAULT_FAR,
    DEFAULT_NEAR,
    IMAGE_EXTENSIONS,
    SEMANTIC_UNKNOWN,
    Scene,
    default_split,
    downscaled_size,
    min_ray_cosine,
    read_frame,
    read_rgb,
    resize_frame,
    scale_intrinsics,
    scene_to_dataset,
    undistort_maps,
    validate_c2w,
    working_dataset,
)
from jaxnerf_grid.data.formats.llff import collect_llff, llff_to_c2w_gl, load_llff
from jaxnerf_grid.data.formats.transforms_json import collect_transforms_json, load_transforms_json
from jaxnerf_grid.data.formats.writing import (
    save_transforms_json,
    split_names,
    transforms_top,
    write_frame,
    write_transforms_json,
)
from jaxnerf_grid.util.io import DataError

__all__ = ["BLENDER_FAR", "BLENDER_NEAR", "collect_blender", "collect_colmap", "collect_llff",
           "collect_scene", "collect_transforms_json", "colmap_w2c_to_c2w_gl", "CV_TO_GL", "DataError",
           "Dataset", "DEFAULT_FAR", "DEFAULT_NEAR", "default_split", "detect_format", "downscaled_size",
           "IMAGE_EXTENSIONS", "llff_to_c2w_gl", "load_blender", "load_colmap", "load_dataset", "load_llff",
           "load_transforms_json", "min_ray_cosine", "read_frame", "read_rgb", "resize_frame",
           "save_transforms_json", "scale_intrinsics", "Scene", "scene_to_dataset", "SEMANTIC_UNKNOWN",
           "split_names", "transforms_top", "undistort_maps", "validate_c2w", "working_dataset", "write_frame",
           "write_transforms_json"]


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
    collectors: dict[str, Callable[..., Scene]] = {
        "transforms.json": collect_transforms_json, "blender": collect_blender, "colmap": collect_colmap,
        "llff": collect_llff}
    collect = collectors[fmt]
    return collect(path, load_extras=load_extras, **kwargs)


def load_dataset(path, split: str | None = None, *, downscale: float = 1, load_extras: bool = True,
                 progress: bool = True, max_side: int = 0, cache: bool = True, uint8_images: bool = False,
                 **kwargs) -> Dataset:
    """Loads any supported dataset (autodetected, see `detect_format`).

    max_side: the working resolution's budget (data/working.py: the long side at most max_side
    px, an integer downscale factor; 0 = full size), or `downscale` to divide the size; cache:
    keep the resized frames in the dataset's cache (working.py); uint8_images: images as uint8
    (value / 255; working.frame_buffer), what training holds.
    split: None (all frames, `Dataset.split` says which are which) or a split name, which
    returns only those frames (`Dataset.subset`). Other keyword arguments go to the loader.
    """
    scene = collect_scene(path, load_extras=load_extras, **kwargs)
    ds = scene_to_dataset(scene, downscale=downscale, load_extras=load_extras, progress=progress,
                          max_side=max_side, cache=cache, uint8_images=uint8_images)
    if split is None:
        return ds
    if split not in ds.split or len(ds.split[split]) == 0:
        raise DataError(f"{path}: empty split {split!r} (available: {', '.join(ds.split)})")
    return ds.subset(ds.split[split])
