"""Foreground masks M, training weights 1 - M_w, depth and overlays for a dataset (the work of
`jaxnerf-grid mask`, as `write_masks(data, ...)`).

Per frame (stem = the image's file name without extension) it writes, inside the dataset:
  masks/<stem>.png      binary foreground mask M (after optional dilation)
  weights/<stem>.exr    per-pixel training weights 1 - M_w (0 = pixel ignored)
  dpt_depth/<stem>.exr  the depth D used by Eq. 7 (DPT: relative depth 1 / inverse depth, up to
                        scale; source "gt": the ground-truth z-depth)
  overlays/<stem>.png   the photo with M_w tinted red and M outlined | Eq. 8's filtered image
                        (longest side at most 1600 px per panel)
and rewrites transforms.json atomically, every other key preserved: each frame gains
`mask_path`, `weight_path`, `dpt_depth_path`, `overlay_path`, `masked_share` (the share of its
pixels in M) and, with DPT, `dpt_confidence` (the mean over the frame of the segmentation's
largest class probability, `foreground.max_class_probability`); the top level gains
`mask_source` ("dpt" or "ground-truth"), `mask_params` and, with DPT, `mask_domain`: the verdict
of the out-of-domain rule (`domain_verdict`, docs/MASKS.md), also printed in one line.

Crash safety (docs/RELIABILITY.md): every setting is checked (`check_settings`, the class ids
against the model) before anything is written. The new set is written into a staging folder
(STAGING: `.jaxnerf-grid-mask-new/`, beside a copy of the new transforms.json), marked complete
(`COMPLETE`), then swapped in: the old output folders move aside, the new ones move in, and
transforms.json is replaced last. `recover(root)` finishes an interrupted swap (a complete
staging folder is rolled forward) or discards an incomplete one (the old set stays), so a
kill at any moment leaves the old set or the new one; `runs.load_dataset` and `write_masks` call
it before reading a dataset.

source "dpt" (default) runs DPT: `weights` is a folder in the HF layout (e.g. a copy of
Intel/dpt-large-ade) or the native format; default: the built-in model shipped in
jaxnerf_grid/masks/assets/dpt_builtin (if present). An HF segmentation checkpoint has no depth head:
pass `depth_weights` (e.g. a copy of Intel/dpt-large) for Eq. 7, else M_w = M (floor 1).
source "gt" builds M from the synthetic ground truth `distractor_mask_path` and D from
`depth_file_path` (so training can run without any DPT model).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from jaxnerf_grid.capture import poses
from jaxnerf_grid.config import schema as config
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data.formats.writing import MASK_OUTPUT_DIRS
from jaxnerf_grid.masks import dpt
from jaxnerf_grid.masks import foreground as fg
from jaxnerf_grid.util import folders, io, staging
from jaxnerf_grid.util import progress as progress_lib
from jaxnerf_grid.util.io import DataError

OUTPUT_DIRS = MASK_OUTPUT_DIRS  # the dataset layout's names (data/formats/writing.py)
STAGING = ".jaxnerf-grid-mask-new"
RETIRED = ".jaxnerf-grid-mask-old"
COMPLETE = "COMPLETE"
BUILTIN = Path(__file__).parent / "assets" / "dpt_builtin"
OVERLAY_MAX_SIDE = 1600


# The out-of-domain rule (docs/MASKS.md): a frame is "mostly masked" when more than
# OOD_FRAME_SHARE of its pixels are in M; the model is out of its domain on a dataset when more
# than OOD_FRAMES of the frames are mostly masked (with an odd number of frames: when the median
# frame's share is above OOD_FRAME_SHARE). Measured with the built-in DPT (benchmarks/dpt_domain.py): the synthetic
# presets, high clutter included, mask at most a third of the frames that much; real photos
# (the Strecha scenes, scikit-image's sample photos) nearly all of them.
OOD_FRAME_SHARE = 0.4
OOD_FRAMES = 0.5


def domain_verdict(shares, confidences=None) -> dict:
    """The out-of-domain rule on a dataset's per-frame masked shares (list of floats in [0, 1]).

    Returns {"out_of_domain": bool, "frames": n, "frames_mostly_masked": k (share >
    OOD_FRAME_SHARE), "median_share", "mean_share", "mean_confidence" (None without
    confidences), "rule": the rule in words}. Out of domain when k > OOD_FRAMES * n.
    """
    shares = np.asarray(list(shares), np.float64)
    if shares.size == 0:
        raise ValueError("domain_verdict: no frames")
    k = int(np.sum(shares > OOD_FRAME_SHARE))
    conf = None if confidences is None or len(confidences) == 0 else round(float(np.mean(confidences)), 4)
    return {"out_of_domain": bool(k > OOD_FRAMES * shares.size), "frames": int(shares.size),
            "frames_mostly_masked": k, "median_share": round(float(np.median(shares)), 4),
            "mean_share": round(float(np.mean(shares)), 4), "mean_confidence": conf,
            "rule": f"out of domain when more than {OOD_FRAMES:.0%} of the frames have more than "
                    f"{OOD_FRAME_SHARE:.0%} of their pixels masked"}


def domain_line(verdict: dict) -> str:
    """`mask`'s one line on the verdict of `domain_verdict`."""
    k, n = verdict["frames_mostly_masked"], verdict["frames"]
    figures = (f"{k} of {n} frames have more than {OOD_FRAME_SHARE:.0%} of their pixels masked "
               f"(median {verdict['median_share']:.0%})")
    if verdict["out_of_domain"]:
        return (f"jaxnerf-grid mask: the DPT looks OUT OF ITS DOMAIN on these photos: {figures}; do not trust "
                "these masks (`demo` trains with train.robust = robust instead; docs/MASKS.md)")
    return f"jaxnerf-grid mask: the DPT looks in its domain: {figures}"


def _frame_stem(frame: dict, index: int) -> str:
    return Path(frame.get("file_path", f"frame_{index:04d}")).stem or f"frame_{index:04d}"


def _image_path(root: Path, frame: dict) -> Path:
    p = root / frame["file_path"]
    if not p.suffix:
        for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG"):
            if p.with_suffix(ext).is_file():
                return p.with_suffix(ext)
    return p


def load_models(weights: str | None, depth_weights: str | None):
    """(seg_model, depth_model or None or seg_model itself, source label)."""
    if weights is None:
        if not (BUILTIN / "config.json").is_file():
            raise DataError(f"{BUILTIN}: no built-in DPT model is shipped in this build; give mask.weights "
                            "(a folder: a copy of Intel/dpt-large-ade) or use mask.source gt on synthetic data")
        weights = str(BUILTIN)
    seg = dpt.load_pretrained(weights)
    if "segmentation" not in seg.config.heads:
        raise DataError(f"{weights}: this DPT has no segmentation head (heads: {seg.config.heads}); "
                        "mask.weights must be a segmentation model (e.g. Intel/dpt-large-ade)")
    if depth_weights is not None:
        depth = dpt.load_pretrained(depth_weights)
        if "depth" not in depth.config.heads:
            raise DataError(f"{depth_weights}: this DPT has no depth head")
    elif "depth" in seg.config.heads:
        depth = seg
    else:
        depth = None
    return seg, depth, weights


def default_classes(seg_model, weights_dir: str) -> list[int]:
    meta = io.read_json(Path(weights_dir) / "config.json")
    extra = meta.get("extra", {}) if isinstance(meta, dict) else {}
    if "dynamic_classes" in extra:
        return [int(c) for c in extra["dynamic_classes"]]
    if seg_model.config.num_labels == 150:
        return sorted(fg.ADE20K_DYNAMIC)
    raise DataError(f"{weights_dir}: {seg_model.config.num_labels}-label model with no known dynamic "
                    "classes; give mask.classes ID,ID,...")


def check_settings(threshold: float, floor: float, dilate: int, max_side: int | None, classes) -> None:
    """Raises ConfigError naming the key (mask.threshold, ...) when a mask setting is out of range: threshold and
    floor in [0, 1], dilate >= 0, max_side >= 1 (or None), classes integers >= 0."""
    config.check_value("mask.threshold", threshold, float, config.UNIT)
    config.check_value("mask.floor", floor, float, config.UNIT)
    config.check_value("mask.dilate", dilate, int, config.NONNEGATIVE)
    config.check_value("mask.max_side", max_side, int | None, config.AT_LEAST_ONE)
    for c in classes or []:
        config.check_value("mask.classes", c, int, config.NONNEGATIVE)


def parse_classes(text: str | None) -> list[int] | None:
    """mask.classes "12,20,127" as [12, 20, 127]; None for None / empty; ConfigError naming the bad entry."""
    if not text:
        return None
    out = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            out.append(int(part))
        except ValueError:
            raise ConfigError(f"mask.classes: {part!r} is not a class id (comma-separated integers, e.g. 12,20)"
                              ) from None
    return out


def check_classes(classes: list[int], num_labels: int, weights: str) -> None:
    """Refuses class ids outside the segmentation model's labels 0..num_labels-1."""
    bad = [c for c in classes if not 0 <= c < num_labels]
    if bad:
        raise ConfigError(f"mask.classes {bad}: outside the {num_labels} labels of {weights} (0..{num_labels - 1})")
    if not classes:
        raise ConfigError("mask.classes: no class id given")


def _swap_in(root: Path) -> None:
    """Rolls a complete staging folder forward (idempotent, so it may be re-run after a kill):
    each old output folder moves to RETIRED and its staged one (COMPLETE lists them) into place,
    then the staged transforms.json replaces the dataset's, then RETIRED and STAGING are removed
    (`staging.swap_in`, shared with `poses`)."""
    stage = root / STAGING
    staged = (stage / COMPLETE).read_text().split()  # the output folders of the new set
    staging.swap_in(root, stage, root / RETIRED, OUTPUT_DIRS, staged, last="transforms.json")


def recover(root) -> str | None:
    """Finishes what a killed `write_masks` left: a complete staging folder is swapped in
    ("rolled forward"), an incomplete one removed ("discarded"); None when there was nothing, or
    when the staging folder belongs to another process still running (`staging.other_owner`:
    a `mask` or `demo` writing this dataset's masks now), which is left alone."""
    import shutil

    root = Path(root)
    stage = root / STAGING
    if staging.other_owner(stage) is not None:
        return None  # another `mask` still writing this dataset: its work, not ours to finish
    if (stage / COMPLETE).is_file():
        _swap_in(root)
        return "rolled forward"
    if stage.exists():
        shutil.rmtree(stage, ignore_errors=True)
        shutil.rmtree(root / RETIRED, ignore_errors=True)
        return "discarded"
    if (root / RETIRED).exists():
        shutil.rmtree(root / RETIRED, ignore_errors=True)
        return "discarded"
    return None


def _refuse_if_busy(root: Path) -> None:
    """A one-line DataError when another process still running is writing masks into `root`
    (its staging folder's OWNER), before anything of this call is read or written."""
    owner = staging.other_owner(root / STAGING)
    if owner is not None:
        host, pid = owner
        raise DataError(f"{root}: another process (pid {pid} on {host}) is writing masks into this dataset "
                        f"now ({STAGING}); wait for it to finish, or mask a copy of the dataset")


def _check_outputs(root: Path, meta: dict, overwrite: bool) -> None:
    if overwrite:
        return
    for name in OUTPUT_DIRS:
        d = root / name
        if d.is_dir() and any(d.iterdir()):
            raise DataError(f"{d}: mask outputs already exist; pass overwrite=True to replace them")
    if any("mask_path" in f for f in meta.get("frames", [])):
        raise DataError(f"{root / 'transforms.json'}: frames already have mask_path; pass overwrite=True")


def _gt_frames(root: Path, frames: list):
    for frame in frames:
        for key in ("distractor_mask_path", "depth_file_path"):
            if key not in frame:
                raise DataError(f"{root / 'transforms.json'}: frame {frame.get('file_path')!r} has no {key!r}; "
                                "mask.source gt needs the synthetic ground truth")
        mask = io.read_distractor_mask(root / frame["distractor_mask_path"])
        yield mask.astype(np.float32), io.read_exr(root / frame["depth_file_path"])


def model_max_side(wdir) -> int:
    """The working size a DPT folder asks for (its config.json's extra.max_side), else 384."""
    return int(io.read_json(Path(wdir) / "config.json").get("extra", {}).get("max_side", 384))


def _dpt_maps(images: list[Path], weights, depth_weights, classes, max_side, batch_size, tiles,
              tile_overlap, params: dict):
    """Per image (C [H, W], depth [H, W] or None, C, confidence) from DPT; fills `params` (mask_params)."""
    seg, depth_model, wdir = load_models(weights, depth_weights)
    classes = list(classes) if classes is not None else default_classes(seg, wdir)
    check_classes(classes, seg.config.num_labels, str(wdir))
    if max_side is None:
        max_side = model_max_side(wdir)
    params.update(weights=str(wdir), depth_weights=depth_weights, classes=classes,
                  max_side=max_side, depth="relative (1 / DPT inverse depth)" if depth_model else None)
    if tiles > 1:
        params.update(tiles=tiles, tile_overlap=tile_overlap)
    if depth_model is None:
        print("jaxnerf-grid mask: no depth head available; using M_w = M (pass --depth-weights for Eq. 7)")
    preds = fg.predict_maps(seg, depth_model, (io.read_image(p) for p in images), classes, max_side=max_side,
                            batch_size=batch_size, tiles=tiles, tile_overlap=tile_overlap, with_confidence=True)
    return ((prob, None if inv is None else np.asarray(fg.inverse_depth_to_depth(inv)), prob, conf)
            for prob, inv, conf in preds)


def _write_frame(root: Path, frame: dict, index: int, ipath: Path, a, depth, prob, threshold: float,
                 floor: float, dilate: int) -> dict:
    """Writes one frame's mask, weights, depth and overlay under `root` (the staging folder). a:
    C [H, W] (prob given) or the binary mask itself; depth: [H, W] or None. Returns the frame's
    new relative paths and its `masked_share` (the mean of M, after dilation)."""
    image = io.read_image(ipath)
    h, w = image.shape[:2]
    mask = np.asarray(fg.binary_mask(a, threshold)) if prob is not None else a
    if mask.shape != (h, w):
        raise DataError(f"{ipath}: mask is {mask.shape}, image is {(h, w)}")
    mw = np.asarray(fg.depth_weighted_mask(mask, depth, floor=floor)) if depth is not None else mask.copy()
    mask, mw = fg.dilate(mask, dilate), fg.dilate(mw, dilate)
    stem = _frame_stem(frame, index)
    rel: dict[str, Any] = {"mask_path": f"masks/{stem}.png", "weight_path": f"weights/{stem}.exr",
           "dpt_depth_path": f"dpt_depth/{stem}.exr", "overlay_path": f"overlays/{stem}.png",
           "masked_share": round(float(np.mean(mask > 0.5)), 4)}
    io.write_png(root / rel["mask_path"], mask)
    io.write_exr(root / rel["weight_path"], np.asarray(fg.training_weights(mw)))
    if depth is not None:
        io.write_exr(root / rel["dpt_depth_path"], depth)
    else:
        rel.pop("dpt_depth_path")
    scale = min(1.0, OVERLAY_MAX_SIDE / max(h, w))  # overlays of 20 MP photos: a preview size
    oh, ow = max(1, round(h * scale)), max(1, round(w * scale))
    io.write_png(root / rel["overlay_path"], fg.overlay(fg.resize_map(image, oh, ow),
                                                        fg.resize_map(mask, oh, ow), fg.resize_map(mw, oh, ow)))
    return rel


def write_masks(data, source: str = "dpt", weights: str | None = None, depth_weights: str | None = None,
                classes: list[int] | None = None, threshold: float = 0.5, floor: float = 0.0, dilate: int = 0,
                max_side: int | None = None, tiles: int = 1, tile_overlap: float = 0.25,
                batch_size: int | None = None, overwrite: bool = False, progress: bool = True) -> dict:
    """Masks every frame of the dataset folder `data` (see the module docstring) and rewrites its
    transforms.json. Returns {"root", "source" ("dpt" | "ground-truth"), "frames", "params",
    "domain" (`domain_verdict` with DPT, None with the ground truth)}.

    source: "dpt" (weights / depth_weights: DPT folders, default the built-in model; classes:
    dynamic class ids, default the model's) or "gt" (synthetic ground truth). threshold: T in
    M = [C > T]; floor: M_w = M * max(floor, (Dmax - D) / Dmax); dilate: pixels; max_side: DPT
    working size (default the model's); tiles, tile_overlap, batch_size: foreground.predict_maps.
    """
    problem = fg.settings_problem(batch_size, tiles, tile_overlap)
    if problem:  # before anything is read or written
        raise ConfigError(problem)
    check_settings(threshold, floor, dilate, max_side, classes)
    if source not in ("dpt", "gt"):
        raise ConfigError(f"mask.source = {source!r}: must be dpt or gt")
    root = Path(data)
    if not root.is_dir():
        raise DataError(f"{root}: mask.data is not a folder")
    poses.recover(root)  # a `poses` run killed while swapping this dataset in: finished first
    _refuse_if_busy(root)
    recover(root)
    tpath = root / "transforms.json"
    meta = io.read_json(tpath)
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not frames:
        raise DataError(f"{tpath}: no frames")
    _check_outputs(root, meta, overwrite)
    folders.check_folder(root, "mask.data")  # this user may write the masks into it, before any is made
    images = [_image_path(root, f) for f in frames]
    for p in images:
        if not p.is_file():
            raise DataError(f"{p}: image file not found (listed in {tpath})")
    params = {"threshold": threshold, "floor": floor, "dilate": dilate}
    if source == "gt":
        label = "ground-truth"
        maps = ((m, d, None, None) for m, d in _gt_frames(root, frames))
    else:
        label = "dpt"
        maps = _dpt_maps(images, weights, depth_weights, classes, max_side, batch_size, tiles, tile_overlap, params)
    stage = root / STAGING
    try:
        stage.mkdir()  # exclusive: two processes cannot both stage into one dataset
    except FileExistsError:
        _refuse_if_busy(root)
        raise DataError(f"{stage}: a staging folder appeared while masking began; run again") from None
    staging.write_owner(stage)
    try:  # an error before the commit point (a corrupt photo, a full disk) leaves no staging folder
        for name in OUTPUT_DIRS:
            (stage / name).mkdir(parents=True, exist_ok=True)
        shares, confidences = [], []
        for i, (frame, ipath, (a, depth, prob, conf)) in enumerate(
                progress_lib.bar(zip(frames, images, maps), total=len(frames), desc="mask", unit="frame",
                                 enabled=progress)):
            frame.update(_write_frame(stage, frame, i, ipath, a, depth, prob, threshold, floor, dilate))
            frame.pop("dpt_confidence", None)
            if conf is not None:
                frame["dpt_confidence"] = round(conf, 4)
                confidences.append(conf)
            shares.append(frame["masked_share"])
        if not any((stage / "dpt_depth").iterdir()):
            (stage / "dpt_depth").rmdir()
            for frame in frames:
                frame.pop("dpt_depth_path", None)
        meta["mask_source"] = label
        meta["mask_params"] = params
        domain = domain_verdict(shares, confidences) if label == "dpt" else None
        meta.pop("mask_domain", None)
        if domain is not None:
            meta["mask_domain"] = domain
        io.write_json(stage / "transforms.json", meta)
        staged = [name for name in OUTPUT_DIRS if (stage / name).is_dir()]
        # the commit point: from here on a kill is rolled forward by `recover`
        io.atomic_write_bytes(stage / COMPLETE, ("\n".join(staged) + "\n").encode("utf-8"))
    except BaseException:
        recover(root)  # discards the incomplete staging folder; the dataset is as it was
        raise
    _swap_in(root)
    if domain is not None:  # printed even when quiet: it decides whether the masks can be used
        print(domain_line(domain))
    if progress:
        print(f"wrote masks for {len(frames)} frames ({label}) into {root}")
    return {"root": root, "source": label, "frames": len(frames), "params": params, "domain": domain}
