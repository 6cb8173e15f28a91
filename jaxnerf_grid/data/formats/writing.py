"""Writing datasets in the transforms.json layout (docs/DATASET.md): frames, the top-level
keys, a whole `Dataset`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.data.formats.frames import EXTRAS
from jaxnerf_grid.data.normalize import normalization_record
from jaxnerf_grid.util import folders, io

# The folders `jaxnerf-grid mask` writes into a dataset (`masking.write_masks`): part of the
# dataset's layout, named here so that the data layer (data/poses.py clears them when it
# replaces the photos) does not import `masking`.
MASK_OUTPUT_DIRS = ("masks", "weights", "dpt_depth", "overlays")

# What `save_transforms_json` writes into its folder, so what its overwrite=True clears in a folder
# holding its marker (folders.MARKERS["dataset"]): transforms.json, images/, the extras' folders
# and the mask outputs made from the photos it replaces. A tower PLY (`transforms_top`) is
# replaced by name.
DATASET_OUTPUTS = ("transforms.json", "images", *dict.fromkeys(extra.folder for extra in EXTRAS.values()),
                   *MASK_OUTPUT_DIRS)


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
        key, _, _, folder, ext = EXTRAS[name]
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
    """Top-level keys of a written transforms.json (copies `tower_ply` next to it). A `poses`
    dataset's `poses` and `georeference` records pass through (the export reads its units,
    CRS and residuals from them, docs/EXPORT.md), less the georeference's two keys derived from
    the old normalisation (`scene_to_crs`, `metres_per_scene_unit`)."""
    top = {"w": int(width), "h": int(height), "camera_model": "PINHOLE",
           "near": float(near), "far": float(far),
           "scene_normalization": normalization_record(normalization)}
    if "generator" in meta:
        top["generator"] = meta["generator"]
    if "poses" in meta:
        top["poses"] = meta["poses"]
    if isinstance(meta.get("georeference"), dict):
        top["georeference"] = {key: value for key, value in meta["georeference"].items()
                               if key not in ("scene_to_crs", "metres_per_scene_unit")}
    tower = meta.get("tower_ply")
    if tower and (Path(root) / tower).is_file():
        io.atomic_write_bytes(Path(out_dir) / tower, (Path(root) / tower).read_bytes())
        top["tower_ply"] = tower
    return top


def split_names(split: dict, num_frames: int) -> list:
    """Per frame its split name ("train" / "test", first match; None when in neither)."""
    names: list[str | None] = [None] * num_frames
    for name in ("train", "test"):
        for i in np.asarray(split.get(name, []), np.int64):
            if names[int(i)] is None:
                names[int(i)] = name
    return names


def save_transforms_json(ds: Dataset, out_dir, *, overwrite: bool = False) -> Path:
    """Writes `ds` as a transforms.json dataset (docs/DATASET.md) under `out_dir`.

    Images and masks as 8-bit PNG, weights / depth as EXR, per-frame intrinsics. The marker rule
    (`folders.prepare_output`, docs/RELIABILITY.md): a non-empty `out_dir` is refused unless
    `overwrite`, which clears only a folder holding this writer's marker, and in it only
    DATASET_OUTPUTS (a user's other files stay). Returns the path of transforms.json.
    """
    out = folders.prepare_output(out_dir, "dataset", DATASET_OUTPUTS, "dataset.out_dir", overwrite)
    return write_transforms_json(ds, out)


def write_transforms_json(ds: Dataset, out_dir) -> Path:
    """Writes `ds`'s files and transforms.json into `out_dir` (made if missing), with no check:
    the caller owns the folder (`save_transforms_json`, `data.preprocess`). Returns the path of
    transforms.json."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = split_names(ds.split, ds.num_frames)
    frames = []
    for i in range(ds.num_frames):
        stem = f"{i:05d}_{Path(ds.frame_paths[i]).stem}" if ds.frame_paths else f"{i:05d}"
        extras = {name: None if getattr(ds, name) is None else getattr(ds, name)[i] for name in EXTRAS}
        frames.append(write_frame(out, stem, ds.images[i], ds.intrinsics[i], ds.c2w[i], names[i], extras))
    top = transforms_top(ds.width, ds.height, ds.near, ds.far, ds.normalization, ds.meta, ds.root, out)
    top["frames"] = frames
    io.write_json(out / "transforms.json", top)
    return out / "transforms.json"
