"""Foreground exclusion (paper Eq. 6-8): dynamic-foreground probability, binary mask, depth
weighting, filtered image, and per-pixel training weights.

  Eq. 6  C = sum_{k in classes} softmax(logits)_k           (per pixel, classes configurable)
         M = [C > T]                                        (`binary_mask`)
  Eq. 7  M_w = M * max(floor, (Dmax - D) / Dmax)            (`depth_weighted_mask`; floor = 0 is
                                                             Eq. 7 exactly, floor = 1 gives M_w = M)
  Eq. 8  I_filtered = (1 - M_w) * I                         (`filter_image`, for visualisation)
  training weight w = 1 - M_w                               (`training_weights`; 0 = ignored pixel)

D is a depth (not disparity). DPT's depth head predicts *relative inverse depth* r (unknown scale
and shift); `inverse_depth_to_depth` takes D = 1 / max(r, eps * max(r)) per image. Eq. 7 only
uses D / Dmax, so the unknown scale cancels; the shift is ignored (assumed 0), and the clamp
makes pixels with r ~ 0 (sky) the farthest, D = Dmax. Dmax is the per-image maximum by default.

Eq. 7's weakness: a distractor far away (a bird against the sky) has D near Dmax and so keeps
weight ~1 in training; `floor` > 0 guarantees masked pixels are down-weighted at least that much.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.masks import dpt
from jaxnerf_grid.util import io, parallel

# ADE20K-150 (0-based ids as in HF's Intel/dpt-large-ade id2label) classes that move.
# ADE20K has no bird class: birds fall under "animal".
ADE20K_DYNAMIC = {12: "person", 20: "car", 76: "boat", 80: "bus", 83: "truck", 90: "airplane",
                  102: "van", 103: "ship", 116: "minibike", 126: "animal", 127: "bicycle"}
# Classes of the synthetic benchmark (jaxnerf_grid.data.synthetic) that are distractors.
SYNTHETIC_DYNAMIC = {6: "person", 7: "vehicle", 8: "bird"}


def foreground_probability(logits, classes) -> jnp.ndarray:
    """Eq. 6: C. logits: [..., L]; classes: sequence of class ids -> C: [...] in [0, 1]."""
    idx = jnp.asarray(sorted(set(int(c) for c in classes)), jnp.int32)
    prob = jax.nn.softmax(jnp.asarray(logits, jnp.float32), axis=-1)
    return jnp.clip(jnp.sum(jnp.take(prob, idx, axis=-1), axis=-1), 0.0, 1.0)


def max_class_probability(logits) -> jnp.ndarray:
    """The segmentation's confidence per pixel: the largest softmax probability over all labels.
    logits: [..., L] -> [...] in [1/L, 1]. Its mean over a frame is `mask`'s `dpt_confidence`
    (a model sure of every pixel scores near 1; one guessing among L labels near 1/L)."""
    return jnp.max(jax.nn.softmax(jnp.asarray(logits, jnp.float32), axis=-1), axis=-1)


def binary_mask(prob, threshold: float) -> jnp.ndarray:
    """M = [C > T] as float32 {0, 1}. prob: [...] -> [...]."""
    return (jnp.asarray(prob) > threshold).astype(jnp.float32)


def inverse_depth_to_depth(inv_depth, eps: float = 1e-3) -> jnp.ndarray:
    """Relative inverse depth r: [..., H, W] (>= 0) -> depth D = 1 / max(r, eps * max_img(r)).

    Up to an unknown global scale per image (harmless for Eq. 7). An all-zero map gives D = 1/eps.
    """
    r = jnp.asarray(inv_depth, jnp.float32)
    rmax = jnp.max(r, axis=(-2, -1), keepdims=True)
    lo = jnp.maximum(eps * rmax, 1e-12)
    return 1.0 / jnp.maximum(r, jnp.where(rmax > 0, lo, eps))


def depth_weighted_mask(mask, depth, floor: float = 0.0, dmax=None) -> jnp.ndarray:
    """Eq. 7 with a floor: M_w = M * max(floor, (Dmax - D) / Dmax).

    mask: [..., H, W] in {0, 1}; depth: [..., H, W] > 0, +inf allowed (= Dmax); dmax: None
    (per-image max of the finite depths)
    or a scalar / [...] array. floor in [0, 1]. Returns M_w: [..., H, W] in [0, 1].
    """
    if not 0.0 <= floor <= 1.0:
        raise ValueError(f"depth_weighted_mask: floor must be in [0, 1], got {floor}")
    m = jnp.asarray(mask, jnp.float32)
    d = jnp.asarray(depth, jnp.float32)
    finite = jnp.isfinite(d)
    if dmax is None:
        dmax = jnp.max(jnp.where(finite, d, 0.0), axis=(-2, -1), keepdims=True)
    else:
        dmax = jnp.asarray(dmax, jnp.float32)
        dmax = dmax[..., None, None] if dmax.ndim else dmax
    d = jnp.where(finite, d, dmax)  # +inf (sky in synthetic ground truth) counts as the farthest
    w = jnp.clip((dmax - d) / jnp.maximum(dmax, 1e-12), 0.0, 1.0)
    return m * jnp.maximum(floor, w)


def filter_image(image, weighted_mask) -> jnp.ndarray:
    """Eq. 8: (1 - M_w) * I. image: [..., H, W, C]; weighted_mask: [..., H, W]."""
    return (1.0 - jnp.asarray(weighted_mask, jnp.float32))[..., None] * jnp.asarray(image, jnp.float32)


def training_weights(weighted_mask) -> jnp.ndarray:
    """Per-pixel loss weights 1 - M_w: [..., H, W] (0 = never a training target)."""
    return 1.0 - jnp.asarray(weighted_mask, jnp.float32)


def dilate(mask: np.ndarray, pixels: int) -> np.ndarray:
    """Grey dilation (max filter over an elliptical disc of radius `pixels`), OpenCV.

    mask: [H, W] float (binary M or weighted M_w; on M_w it spreads each object's weight).
    """
    if pixels <= 0:
        return np.asarray(mask, np.float32)
    import cv2

    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * pixels + 1, 2 * pixels + 1))
    return cv2.dilate(np.asarray(mask, np.float32), k)


def overlay(image: np.ndarray, mask: np.ndarray, weighted_mask: np.ndarray) -> np.ndarray:
    """A check-at-a-glance picture: left the photo with M_w tinted red and M's outline in yellow,
    right Eq. 8's filtered image. image: [H, W, 3]; mask, weighted_mask: [H, W] -> [H, 2W, 3]."""
    import cv2

    img = np.asarray(image, np.float32)
    mw = np.asarray(weighted_mask, np.float32)[..., None]
    tinted = img * (1 - 0.6 * mw) + 0.6 * mw * np.array([1.0, 0.0, 0.0], np.float32)
    m8 = (np.asarray(mask) > 0.5).astype(np.uint8)
    edge = cv2.morphologyEx(m8, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    tinted[edge] = (1.0, 1.0, 0.0)
    filtered = np.asarray(filter_image(img, mw[..., 0]))
    return np.clip(np.concatenate([tinted, filtered], axis=1), 0.0, 1.0)


# ----------------------------------------------------------------- inference on photos
def working_size(height: int, width: int, max_side: int = 384, multiple: int = 32) -> tuple[int, int]:
    """(h, w): aspect kept, longest side ~max_side, each a multiple of `multiple` (>= multiple)."""
    s = max_side / max(height, width)
    h = max(multiple, int(round(height * s / multiple)) * multiple)
    w = max(multiple, int(round(width * s / multiple)) * multiple)
    return h, w


def resize_map(x: np.ndarray, height: int, width: int) -> np.ndarray:
    """A float map [h, w] or [h, w, C] resized to (height, width): `io.resize` in float32,
    taking the size height first as the rest of this module does."""
    return io.resize(np.asarray(x, np.float32), (width, height))


def tile_starts(length: int, tile: int, overlap: int) -> list[int]:
    """Starts of the fewest windows of size `tile` that cover [0, length) with neighbours sharing
    at least `overlap` pixels, spread evenly: the first at 0, the last at length - tile.
    (A single window at 0 when tile >= length.) Needs 0 <= overlap < tile."""
    if not 0 <= overlap < tile:
        raise ValueError(f"tile_starts: need 0 <= overlap < tile, got overlap {overlap}, tile {tile}")
    if tile >= length:
        return [0]
    n = 1 + -(-(length - tile) // (tile - overlap))
    return [round(k * (length - tile) / (n - 1)) for k in range(n)]


class TileLayout(NamedTuple):
    """How a photo is covered by DPT tiles: the photo is resized to `resized` (h, w), cut into windows
    of `tile` (h, w) starting at every (y, x) in starts_y x starts_x (row-major), neighbours sharing
    at least `overlap` pixels, over which they are cross-faded."""
    resized: tuple[int, int]
    tile: tuple[int, int]
    starts_y: list[int]
    starts_x: list[int]
    overlap: int


def tile_layout(height: int, width: int, max_side: int, multiple: int, tiles: int, overlap: float) -> TileLayout:
    """`tiles` square windows along the photo's longer side, each of the working size (side ~max_side,
    a multiple of `multiple`), sharing a fraction `overlap` of a window with each neighbour. The
    photo is resized (aspect kept) so that they span its longer side exactly; the shorter side gets
    as many windows as it needs, or one narrower window (a multiple too) when the side is shorter
    than a window. tiles = 1: one window, the plain working size of `working_size`."""
    if tiles == 1:
        resized = working_size(height, width, max_side, multiple)
        return TileLayout(resized, resized, [0], [0], 0)
    side = working_size(max_side, max_side, max_side, multiple)[0]
    over = int(round(overlap * side))
    scale = (side + (tiles - 1) * (side - over)) / max(height, width)
    resized = (max(multiple, round(height * scale)), max(multiple, round(width * scale)))
    tile = (min(side, resized[0] // multiple * multiple), min(side, resized[1] // multiple * multiple))
    over = min(over, min(tile) - 1)
    return TileLayout(resized, tile, tile_starts(resized[0], tile[0], over), tile_starts(resized[1], tile[1], over),
                      over)


def _ramp(size: int, overlap: int) -> np.ndarray:
    """Cross-fade weights of one window along one axis: rising over the first `overlap` pixels,
    1 in the middle, falling over the last `overlap`; never 0. [size]."""
    dist = np.minimum(np.arange(size) + 1, size - np.arange(size)).astype(np.float32)
    return np.minimum(1.0, dist / (overlap + 1))


def blend_tiles(values: np.ndarray, layout: TileLayout) -> np.ndarray:
    """Cross-fades per-window maps into one map at the resized photo's size: each pixel is the average of the
    windows covering it, weighted by their ramps (a window's weight falls towards its edges, so
    no seam shows; a photo border, where no neighbour is, keeps whatever covers it).

    values: [n_tiles, th, tw] in layout order -> [fine_h, fine_w].
    """
    (th, tw), resized = layout.tile, layout.resized
    weight = _ramp(th, layout.overlap)[:, None] * _ramp(tw, layout.overlap)[None, :]
    num = np.zeros(resized, np.float64)
    den = np.zeros(resized, np.float64)
    k = 0
    for y in layout.starts_y:
        for x in layout.starts_x:
            num[y:y + th, x:x + tw] += weight * values[k]
            den[y:y + th, x:x + tw] += weight
            k += 1
    return (num / den).astype(np.float32)


def _predict_tiled(seg_model, depth_model, images, classes, max_side, batch_size, tiles, overlap, multiple,
                   with_confidence=False):
    """predict_maps with tiles > 1: C from overlapping windows of a finer copy of each photo,
    depth (relative, so not comparable between windows) from the whole photo at working size;
    the confidence is the mean over every window's pixels."""
    for image in images:
        image = np.asarray(image, np.float32)
        h, w = image.shape[:2]
        lay = tile_layout(h, w, max_side, multiple, tiles, overlap)
        resized = resize_map(image, *lay.resized)
        (th, tw) = lay.tile
        crops = np.stack([resized[y:y + th, x:x + tw] for y in lay.starts_y for x in lay.starts_x])
        probs, conf = [], []
        size = min(batch_size, len(crops))  # same window count for every photo of a size: one compile
        for i in range(0, len(crops), size):
            chunk = crops[i:i + size]
            out = dpt.apply(seg_model, dpt.normalize(parallel.pad_to_multiple(chunk, size)[0]))
            probs.append(np.asarray(foreground_probability(out["logits"], classes))[:len(chunk)])
            conf.append(np.asarray(max_class_probability(out["logits"]))[:len(chunk)])
        prob = resize_map(blend_tiles(np.concatenate(probs), lay), h, w)
        inv = None
        if depth_model is not None:
            whole = resize_map(image, *working_size(h, w, max_side, multiple))
            inv = np.maximum(resize_map(np.asarray(dpt.apply(depth_model, dpt.normalize(whole[None]))["depth"][0]),
                                        h, w), 0.0)
        yield (prob, inv, float(np.mean(np.concatenate(conf)))) if with_confidence else (prob, inv)


MAX_TILE_OVERLAP = 0.75


def settings_problem(batch_size: int | None, tiles: int, tile_overlap: float) -> str | None:
    """What is wrong with `predict_maps`'s batch / tiling settings (named by their keys,
    `mask.batch_size`, ...; the CLI shows its flags), or None. Callers raise it as their own error type."""
    if batch_size is not None and (int(batch_size) != batch_size or batch_size < 1):
        return f"mask.batch_size must be an integer >= 1, got {batch_size}"
    if int(tiles) != tiles or tiles < 1:
        return f"mask.tiles must be an integer >= 1, got {tiles}"
    if not 0.0 <= tile_overlap <= MAX_TILE_OVERLAP:
        return f"mask.tile_overlap must be between 0 and {MAX_TILE_OVERLAP}, got {tile_overlap}"
    return None


def default_batch_size() -> int:
    """Images per DPT call: 1 on CPU, 4 on an accelerator. On the 2-core CPU, batching made
    DPT-base at 384 px slower: 0.46 images/s at batch 4, against 0.58-0.71 at batch 1
    (benchmarks/dpt_speed.py --batch 4). The built-in model at a 320 px working size was slower
    too: 0.26 s per photo at batch 2-8 against 0.17 at batch 1. At 160 px batching gained about
    15 % (0.05 against 0.06 s; benchmarks/mask_speed.py). XLA CPU gains nothing from the larger
    matmuls, and the intermediate maps outgrow the cache."""
    return 1 if jax.default_backend() == "cpu" else 4


def to_working_size(image: np.ndarray, max_side: int, multiple: int) -> np.ndarray:
    """One photo [H, W, 3] resized to the working size DPT sees (`working_size`) -> [h, w, 3]
    float32. `predict_maps` and `class_probabilities` both go through it."""
    image = np.asarray(image, np.float32)
    return resize_map(image, *working_size(image.shape[0], image.shape[1], max_side, multiple))


def class_probabilities(seg_model, image, max_side: int = 384) -> np.ndarray:
    """Every class's softmax probability for one photo, at full resolution: [H, W, 3] -> [H, W, L].

    The same working size and bilinear upsampling as `predict_maps` (bilinear resizing is
    linear, so summing this over `classes` gives predict_maps' C to float rounding). For studies
    of rules that use more classes than Eq. 6's sum (experiments/mask_tower_overlap.py)."""
    image = np.asarray(image, np.float32)
    x = to_working_size(image, max_side, 2 * seg_model.config.patch_size)[None]
    prob = np.asarray(jax.nn.softmax(dpt.apply(seg_model, dpt.normalize(x))["logits"][0], axis=-1))
    return resize_map(prob, *image.shape[:2])


def predict_maps(seg_model, depth_model, images, classes, max_side: int = 384, batch_size: int | None = None,
                 tiles: int = 1, tile_overlap: float = 0.25, with_confidence: bool = False):
    """Runs DPT on photos of any size in bounded memory.

    Each image is resized to a working size (aspect kept, multiple of 2 x patch, longest side
    ~max_side), images of the same working shape are batched (one compile per working shape),
    and the outputs come back at full resolution: C (Eq. 6, computed at working size, then
    bilinearly upsampled) and the relative inverse depth.

    With tiles > 1, C comes instead from `tiles` overlapping windows along the photo's longer side
    (each window the working size, `tile_overlap` of it shared with each neighbour, cross-faded;
    see `tile_layout`), so small distractors (a bird in a 20 MP photo) keep more pixels; the
    windows are batched. Depth still comes from the whole photo at the working size: DPT's
    inverse depth is relative, with a scale of its own per window.

    seg_model: a dpt.Model with a segmentation head; depth_model: a dpt.Model with a depth head,
    the same model, or None. images: iterable of [H, W, 3] float in [0, 1]. batch_size: images
    (or windows) per DPT call, None for `default_batch_size()`.
    Yields (C [H, W], inv_depth [H, W] or None) per image, in order; with_confidence: (C,
    inv_depth, confidence), the confidence a float, the mean of `max_class_probability` over
    the pixels DPT saw (working size; all windows when tiled).
    """
    problem = settings_problem(batch_size, tiles, tile_overlap)
    if problem:
        raise ValueError(f"predict_maps: {problem}")
    batch_size = default_batch_size() if batch_size is None else int(batch_size)
    models = [seg_model] + ([depth_model] if depth_model is not None and depth_model is not seg_model else [])
    multiple = 2 * max(m.config.patch_size for m in models)
    if tiles > 1:
        yield from _predict_tiled(seg_model, depth_model, images, classes, max_side, batch_size, tiles,
                                  tile_overlap, multiple, with_confidence)
        return
    both = depth_model is seg_model

    def flush(batch):
        x = parallel.pad_to_multiple(np.stack([b[1] for b in batch]), batch_size)[0]  # one compiled shape
        out = dpt.apply(seg_model, dpt.normalize(x))
        prob = np.asarray(foreground_probability(out["logits"], classes))
        conf = np.asarray(jnp.mean(max_class_probability(out["logits"]), axis=(1, 2)))
        if both:
            inv = np.asarray(out["depth"])
        elif depth_model is not None:
            inv = np.asarray(dpt.apply(depth_model, dpt.normalize(x))["depth"])
        else:
            inv = None
        for i, (shape, _) in enumerate(batch):
            maps = (resize_map(prob[i], *shape), None if inv is None else np.maximum(resize_map(inv[i], *shape), 0.0))
            yield maps + (float(conf[i]),) if with_confidence else maps

    batch: list = []
    key = None
    for image in images:
        image = np.asarray(image, np.float32)
        x = to_working_size(image, max_side, multiple)
        if batch and (x.shape[:2] != key or len(batch) == batch_size):
            yield from flush(batch)
            batch = []
        key = x.shape[:2]
        batch.append((image.shape[:2], x))
    if batch:
        yield from flush(batch)
