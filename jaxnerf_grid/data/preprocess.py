"""The paper's uniform preprocessing: scale to a common size, normalise, enhance.

Sec. 4.1 of the paper: "all images underwent uniform preprocessing, including scaling to a
unified size, normalization, and enhancement". Here:
- scaling: every image is resized to one size (W, H), given outright or as a long side (the
  size then follows the first image's aspect ratio), with cv2.INTER_AREA when shrinking;
  intrinsics are rescaled per frame (fx' = fx W'/W, cx' = cx W'/W: pixel centres at +0.5).
  Images with differing sizes are allowed here (that is what this step is for).
- normalisation: pixels always become float in [0, 1]; `normalize=True` adds a per-image
  contrast stretch between the 1st and 99th percentiles (all channels together).
- enhancement: `clahe=True` applies CLAHE (OpenCV) to the L channel of CIE-LAB, leaving
  colour (a, b) as it is.
EXIF orientation of JPEGs is honoured (the written PNGs carry the rotated pixels).

Input: a plain folder of images (written to `out/images/`, with `out/preprocess.json`), any
dataset `formats.load_dataset` understands (written as a transforms.json dataset with
per-frame intrinsics, extras resized alongside), or an in-memory `Dataset`. Nothing is
overwritten without `overwrite=True` (`--overwrite`), and that clears only a folder preprocess
wrote (the marker rule, docs/RELIABILITY.md).

CLI: `python -m jaxnerf_grid.data.preprocess SRC OUT [--size W H | --long-side N] [--clahe]
[--normalize] [--overwrite]`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from jaxnerf_grid.data import formats
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.data.formats.writing import DATASET_OUTPUTS
from jaxnerf_grid.util import folders, io, progress
from jaxnerf_grid.util.io import DataError


def target_size(width: int, height: int, size) -> tuple[int, int]:
    """(W', H') for an image of (width, height): `size` is (W, H), an int long side, or None."""
    if size is None:
        return int(width), int(height)
    if isinstance(size, (int, np.integer)):
        if size <= 0:
            raise ValueError(f"long side must be positive, got {size}")
        k = size / max(width, height)
        return max(1, int(round(width * k))), max(1, int(round(height * k)))
    w, h = (int(v) for v in size)
    if w <= 0 or h <= 0:
        raise ValueError(f"size must be positive, got {size}")
    return w, h


def clahe_lab(image: np.ndarray, clip_limit: float = 2.0, tile_grid: int = 8) -> np.ndarray:
    """CLAHE on the L channel of CIE-LAB. image: [H, W, 3] RGB in [0, 1]. Returns [H, W, 3].

    L is equalised at 16-bit precision (OpenCV's CLAHE takes 8- or 16-bit input).
    """
    cv2 = io.opencv()
    img = np.clip(np.asarray(image, np.float32), 0.0, 1.0)
    lab = cv2.cvtColor(img, cv2.COLOR_RGB2LAB)  # float input: L in [0, 100]
    l16 = np.round(lab[..., 0] / 100.0 * 65535.0).astype(np.uint16)
    clahe = cv2.createCLAHE(clipLimit=float(clip_limit), tileGridSize=(int(tile_grid), int(tile_grid)))
    lab[..., 0] = clahe.apply(l16).astype(np.float32) / 65535.0 * 100.0
    return np.clip(cv2.cvtColor(lab, cv2.COLOR_LAB2RGB), 0.0, 1.0)


def normalize_intensity(image: np.ndarray, low: float = 1.0, high: float = 99.0) -> np.ndarray:
    """Per-image contrast stretch: the `low`/`high` percentiles map to 0/1 (clipped).

    image: [H, W, 3] in [0, 1]. A flat image is returned unchanged. Returns [H, W, 3].
    """
    img = np.asarray(image, np.float32)
    lo, hi = np.percentile(img, [low, high])
    if hi - lo < 1e-6:
        return img
    return np.clip((img - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


def enhance(image: np.ndarray, *, clahe: bool = False, normalize: bool = False,
            clahe_clip: float = 2.0, clahe_grid: int = 8) -> np.ndarray:
    """The photometric part of preprocessing. image: [H, W, 3] in [0, 1]. Returns [H, W, 3]."""
    if normalize:
        image = normalize_intensity(image)
    if clahe:
        image = clahe_lab(image, clahe_clip, clahe_grid)
    return np.asarray(image, np.float32)


def _list_images(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix in formats.IMAGE_EXTENSIONS)
    if not files:
        raise DataError(f"{folder}: no images (.png / .jpg) found")
    stems: dict = {}
    for p in files:
        if p.stem in stems:
            raise DataError(f"{p}: has the same name as {stems[p.stem].name}; the outputs would collide")
        stems[p.stem] = p
    return files


# What preprocessing writes into its folder, so what its overwrite=True clears in a folder holding its
# marker (folders.MARKERS["preprocess"]): preprocess.json and images/ (a folder of images), or a
# transforms.json dataset's outputs (formats.writing.DATASET_OUTPUTS).
OUTPUTS = ("preprocess.json", *DATASET_OUTPUTS)


def _is_older_preprocess(out: Path) -> bool:
    """Whether `out` holds the output of a preprocess run from before the marker: a
    preprocess.json, or a transforms.json whose top level has a "preprocess" record."""
    if (out / "preprocess.json").is_file():
        return True
    try:
        meta = io.read_json(out / "transforms.json")
    except DataError:
        return False
    return isinstance(meta, dict) and isinstance(meta.get("preprocess"), dict)


def _read_source(src, out: Path, load_extras: bool, loader_kwargs: dict) -> tuple[str, Any]:
    """("dataset", the Dataset), ("scene", a dataset's `formats.Scene`) or ("images", the image
    files) of `src`, read and checked before anything is written. DataError when `src` is none
    of them, or when it and `out` lie one inside the other (overwrite=True would clear the
    source, or the outputs would be added to it)."""
    if isinstance(src, Dataset):
        return "dataset", src
    src = Path(src)
    folders.check_outside(out, src, "preprocess.out")
    if folders.inside(src, out):
        raise DataError(f"{src}: the source lies inside preprocess.out {out}; choose an output folder outside it")
    try:
        formats.detect_format(src)
    except DataError:
        if not src.is_dir():
            raise DataError(f"{src}: not a folder of images nor a dataset") from None
        return "images", _list_images(src)
    return "scene", formats.collect_scene(src, load_extras=load_extras, **loader_kwargs)


def preprocess_images(src, out_dir, *, size=None, clahe: bool = False, normalize: bool = False,
                      clahe_clip: float = 2.0, clahe_grid: int = 8, overwrite: bool = False,
                      load_extras: bool = True, **loader_kwargs) -> Path:
    """Uniform preprocessing of a folder of images or of a dataset (see module docstring).

    src: a folder of images, a dataset path, or a `Dataset`; out_dir: the output folder, under
    the marker rule (`folders.prepare_output`, docs/RELIABILITY.md): refused when it exists and
    is not empty, unless `overwrite`, which clears only a folder preprocess wrote (its marker, or
    an older run's preprocess record) and in it only OUTPUTS, after the source is read and
    checked; size: (W, H), an int long side, or None (keep each dataset's first image size).
    Returns `out_dir` as a Path.
    """
    out = Path(out_dir)
    legacy = _is_older_preprocess(out)
    folders.check_output(out, "preprocess", OUTPUTS, "preprocess.out", overwrite, legacy)  # before reading
    opts: dict[str, Any] = dict(clahe=clahe, normalize=normalize, clahe_clip=clahe_clip, clahe_grid=clahe_grid)
    record = {"size": list(size) if isinstance(size, (tuple, list)) else size, **opts}
    kind, source = _read_source(src, out, load_extras, loader_kwargs)
    folders.prepare_output(out, "preprocess", OUTPUTS, "preprocess.out", overwrite, legacy)
    if kind == "dataset":
        return _preprocess_dataset(source, out, size, opts)
    if kind == "scene":
        return _preprocess_scene(source, out, size, opts, load_extras)
    files = source
    common: Any = None
    entries: list = []
    for path in progress.bar(files, desc="preprocessing", unit="image", enabled=len(files) >= 16, leave=False):
        img = io.read_image(path)  # EXIF orientation honoured
        h, w = img.shape[:2]
        common = common or target_size(w, h, size)
        img = enhance(io.resize(img, common, "area"), **opts)
        rel = f"images/{path.stem}.png"
        io.write_png(out / rel, img)
        entries.append({"source": path.name, "file_path": rel, "source_size": [w, h],
                        "scale": [common[0] / w, common[1] / h]})
    io.write_json(out / "preprocess.json", {**record, "output_size": list(common), "images": entries})
    return out


def _preprocess_scene(scene: formats.Scene, out: Path, size, opts: dict, load_extras: bool) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    names = formats.split_names(scene.split, len(scene.frames))
    common: Any = None
    frames: list = []
    num = len(scene.frames)
    for i in progress.bar(range(num), desc="preprocessing", unit="frame", enabled=num >= 16, leave=False):
        fr = formats.read_frame(scene, i, load_extras)
        h, w = fr["image"].shape[:2]
        common = common or target_size(w, h, size)
        fr = formats.resize_frame(fr, common)
        extras = dict(fr["extras"])
        if "clean_images" in extras:
            extras["clean_images"] = enhance(extras["clean_images"], **opts)
        if fr["valid"] is not None:  # undistortion left pixels without a source: weight 0
            base = extras.get("weights")
            if base is None:
                base = 1.0 - extras["masks"] if "masks" in extras else np.ones(common[::-1], np.float32)
            extras["weights"] = base * fr["valid"]
        stem = f"{i:05d}_{scene.frames[i].image_path.stem}"
        frames.append(formats.write_frame(out, stem, enhance(fr["image"], **opts), fr["intrinsics"],
                                          scene.c2w[i], names[i], extras))
    top = formats.transforms_top(common[0], common[1], scene.near, scene.far, scene.normalization,
                                 scene.meta, scene.root, out)
    top["preprocess"] = {"size": list(common), **opts, "source": str(scene.root)}
    top["frames"] = frames
    io.write_json(out / "transforms.json", top)
    return out


def _preprocess_dataset(ds: Dataset, out: Path, size, opts: dict) -> Path:
    common = target_size(ds.width, ds.height, size)
    sx, sy = common[0] / ds.width, common[1] / ds.height
    resized: dict[str, Any] = {}
    for name, interp in (("clean_images", "area"), ("depth", "nearest"), ("semantics", "nearest"),
                         ("distractor_masks", "nearest"), ("masks", "area"), ("weights", "area")):
        arr = getattr(ds, name)
        if arr is not None:
            arr = arr.astype(np.uint8) if arr.dtype == bool else arr
            arr = np.stack([io.resize(a, common, interp) for a in arr])
            if name == "clean_images":
                arr = np.stack([enhance(a, **opts) for a in arr])
            resized[name] = arr
    import dataclasses

    new = dataclasses.replace(
        ds, images=np.stack([enhance(io.resize(a, common, "area"), **opts) for a in ds.images]),
        intrinsics=formats.scale_intrinsics(ds.intrinsics, sx, sy).astype(np.float32), **resized)
    formats.write_transforms_json(new, out)  # into the folder preprocess_images prepared
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m jaxnerf_grid.data.preprocess",
                                     description="Uniform preprocessing: common size, normalisation, CLAHE.")
    parser.add_argument("src", help="a folder of images, or a dataset (transforms.json, Blender, "
                                    "COLMAP, LLFF)")
    parser.add_argument("out", help="output folder")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="resize every image to W x H")
    group.add_argument("--long-side", type=int, help="resize so the long side is this many pixels")
    parser.add_argument("--clahe", action="store_true", help="CLAHE on the L channel of LAB")
    parser.add_argument("--clahe-clip", type=float, default=2.0)
    parser.add_argument("--clahe-grid", type=int, default=8)
    parser.add_argument("--normalize", action="store_true", help="per-image 1-99 percentile contrast stretch")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    args = parser.parse_args(argv)
    size = tuple(args.size) if args.size else args.long_side
    out = preprocess_images(args.src, args.out, size=size, clahe=args.clahe, normalize=args.normalize,
                            clahe_clip=args.clahe_clip, clahe_grid=args.clahe_grid, overwrite=args.overwrite)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except DataError as err:
        print(f"preprocess: error: {str(err).replace('overwrite=True', '--overwrite')}", file=sys.stderr)
        sys.exit(1)
