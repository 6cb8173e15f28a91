"""The experiments' datasets, cached: synthetic scenes and their mask variants.

  * `scene(...)`: a synthetic dataset generated once per (preset, seed, size, views,
    distractors) under the cache (default experiments/.cache/scenes/);
  * `mask_variant(...)`: a copy of a scene's transforms.json in its own folder whose image
    paths point back at the scene's files (no image is copied) and whose masks / weights are
    written by `masking.write_masks` (what `jaxnerf-grid mask` runs: ground truth with or
    without Eq. 7's depth weighting, or a DPT); `clean_variant(...)`: the same with the clean
    images as training targets; `mask_iou(...)`: a variant's masks against the ground truth.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from experiments import settings
from jaxnerf_grid.util import io


def scene(ctx, preset: str, seed: int, distractors: str | None = None, size: tuple | None = None) -> Path:
    """Dataset folder of a synthetic scene (generated on first use). size: (w, h, train, test, ss)."""
    from jaxnerf_grid.data.synthetic.generate import generate_scene

    w, h, n_train, n_test, ss = size or settings.SCENE_SIZES[ctx.setting][preset]
    name = f"{preset}_s{seed}_{w}x{h}_{n_train}+{n_test}_ss{ss}_{distractors or 'preset'}_g{generator_digest()}"
    out = ctx.cache / "scenes" / name
    if not (out / "transforms.json").is_file():
        print(f"[scene] generating {name}", flush=True)
        generate_scene(preset, out, seed=seed, distractors=distractors, overwrite=True, progress=ctx.progress,
                       width=w, height=h, num_train=n_train, num_test=n_test, supersample=ss,
                       workers=min(2, os.cpu_count() or 1) if w * h * (n_train + n_test) > 100_000 else 1)
    return out


# digests of generator sources that make the same scenes as an earlier one (only import paths moved,
# or an option added whose default renders as before: `conductors`), mapped to it so that cached
# scenes and the committed results' keys still match
SAME_GENERATOR = {"b1573a": "5aab61", "c7e725": "5aab61"}


def generator_digest() -> str:
    """Short SHA-1 of the synthetic generator's source: a cached scene made by other code is not reused."""
    from jaxnerf_grid.data import synthetic

    h = hashlib.sha1()
    for f in sorted(Path(synthetic.__file__).parent.glob("*.py")):
        h.update(f.read_bytes())
    digest = h.hexdigest()[:6]
    return SAME_GENERATOR.get(digest, digest)


RELINKED = ("file_path", "clean_file_path", "depth_file_path", "semantic_file_path", "distractor_mask_path",
            "shadow_mask_path")


def _relink(scene_dir: Path, variant_dir: Path, meta: dict, keys=RELINKED) -> dict:
    """transforms.json `meta` of scene_dir with every per-frame path rewritten relative to variant_dir."""
    meta = json.loads(json.dumps(meta))
    rel = os.path.relpath(scene_dir, variant_dir)
    for frame in meta["frames"]:
        for k in keys:
            if k in frame:
                frame[k] = f"{rel}/{frame[k]}"
        for k in ("mask_path", "weight_path", "dpt_depth_path", "overlay_path"):
            frame.pop(k, None)
    for k in ("mask_source", "mask_params"):
        meta.pop(k, None)
    if "tower_ply" in meta:
        meta["tower_ply"] = f"{rel}/{meta['tower_ply']}"
    return meta


def weights_digest(folder: Path) -> str:
    """Short SHA-1 of every file in a weights folder (names and bytes), for cache keys."""
    h = hashlib.sha1()
    for f in sorted(Path(folder).iterdir()):
        if f.is_file():
            h.update(f.name.encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:8]


def mask_variant(ctx, scene_dir: Path, name: str, source: str = "gt", floor: float = 0.0,
                 weights: str | None = None, max_side: int = 160, dilate: int = 0,
                 threshold: float = 0.5) -> Path:
    """A folder whose transforms.json points at scene_dir's images, with masks from `masking.write_masks`.

    source "gt": ground-truth distractor masks and depth (floor 0 = Eq. 7, floor 1 = binary
    masks, every masked pixel excluded); "dpt": a DPT (`weights` folder, default built-in).
    dilate: pixels of `mask --dilate` (M and M_w grown by a disc); 0 keeps the folder name of old.
    threshold: T of M = [C > T] (DPT only); 0.5 keeps the folder name of old.
    """
    from jaxnerf_grid.masks import write as masking

    if source == "dpt":  # any DPT can be retrained (the built-in; Table 4's crossover models): key the
        # cached masks, and so the run key of every run on them, on the weights' bytes
        name = f"{name}_{weights_digest(Path(weights) if weights else masking.BUILTIN)}"
    if threshold != 0.5:
        name = f"{name}_t{threshold:g}"
    out = ctx.cache / "variants" / f"{scene_dir.name}__{name}"
    meta_path = out / "transforms.json"
    if meta_path.is_file() and "mask_source" in io.read_json(meta_path):
        return out
    out.mkdir(parents=True, exist_ok=True)
    io.write_json(meta_path, _relink(scene_dir, out, io.read_json(scene_dir / "transforms.json")))
    settings = {"source": source, "floor": floor, "overwrite": True, "max_side": max_side,
                "weights": str(weights) if weights else None, "dilate": dilate}
    if threshold != 0.5:
        settings["threshold"] = threshold
    print(f"[mask] {out.name}: masking.write_masks {settings}", flush=True)
    masking.write_masks(out, progress=ctx.progress, **settings)
    return out


def clean_variant(ctx, scene_dir: Path) -> Path:
    """A folder whose training targets are the scene's clean (distractor-free) images: the upper bound."""
    out = ctx.cache / "variants" / f"{scene_dir.name}__clean"
    meta_path = out / "transforms.json"
    if not meta_path.is_file():
        out.mkdir(parents=True, exist_ok=True)
        meta = _relink(scene_dir, out, io.read_json(scene_dir / "transforms.json"))
        for frame in meta["frames"]:
            if "clean_file_path" in frame:
                frame["file_path"] = frame["clean_file_path"]
        io.write_json(meta_path, meta)
    return out


def mask_iou(variant_dir: Path, split: str = "train") -> dict:
    """IoU / precision / recall of a variant's masks M against the synthetic distractor masks (bit 0),
    pooled over the frames of `split`."""
    import cv2

    meta = io.read_json(variant_dir / "transforms.json")
    tp = fp = fn = 0.0
    for f in meta["frames"]:
        if f.get("split", "train") != split or "mask_path" not in f or "distractor_mask_path" not in f:
            continue
        pred = io.read_mask(variant_dir / f["mask_path"]) > 0.5
        raw = cv2.imread(str(variant_dir / f["distractor_mask_path"]), cv2.IMREAD_UNCHANGED)
        gt = (raw.astype(np.int64) & 1).astype(bool)
        tp += float(np.sum(pred & gt))
        fp += float(np.sum(pred & ~gt))
        fn += float(np.sum(~pred & gt))
    return {"iou": tp / max(tp + fp + fn, 1.0), "precision": tp / max(tp + fp, 1.0),
            "recall": tp / max(tp + fn, 1.0), "gt_pixels": tp + fn}
