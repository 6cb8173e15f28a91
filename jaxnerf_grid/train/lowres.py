"""A resolution schedule: the first steps of a run train on its frames at a lower resolution.

`train.lowres_share` of the steps (0 = off) draw their rays from the training frames shrunk by
`train.lowres_factor` (each f x f block of pixels one pixel: its colours' mean, the least of its
loss weights, so a block touching a masked pixel is not drawn), with the intrinsics divided by f:
a low-resolution pixel's ray passes through the centre of its block. The rest of the run trains
at the working resolution. Each ray costs the same at either size, so a step does too; what
changes is the target, a mean over a block, which fits the large structure before the detail.
Only the plain step (train.robust off) has the schedule: the robust step judges photometric
evidence per pixel of the working frames.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data import working
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.train import ray_pool


def end_step(tcfg) -> int:
    """The first step that trains at the working resolution: round(lowres_share x max_steps)
    (0 when the schedule is off). tcfg: a TrainConfig."""
    if tcfg.lowres_share <= 0 or tcfg.lowres_factor <= 1:
        return 0
    if tcfg.robust.mode != "off":
        raise ConfigError("train.lowres_share needs train.robust off: the robust step judges each pixel of the "
                          "working frames (set train.lowres_share=0 or train.robust.mode=off)")
    return int(round(tcfg.lowres_share * tcfg.max_steps))


def block_mean_uint8(image: np.ndarray, factor: int) -> np.ndarray:
    """[H, W, C] uint8 (or float in [0, 1], rounded to 8 bits first) -> [H // f, W // f, C] uint8:
    each f x f block's mean, rounded half up, in integers (rows and columns past the last whole
    block are dropped)."""
    codes = working.to_uint8(image)
    h, w, c = codes.shape
    hh, ww = h // factor, w // factor
    total = codes[:hh * factor, :ww * factor].reshape(hh, factor, ww, factor, c).astype(np.int32).sum(axis=(1, 3))
    area = factor * factor
    return ((total + area // 2) // area).astype(np.uint8)


def block_min(weights: np.ndarray, factor: int) -> np.ndarray:
    """[H, W] float32 -> [H // f, W // f] float32: the least weight of each f x f block."""
    h, w = weights.shape
    hh, ww = h // factor, w // factor
    return weights[:hh * factor, :ww * factor].reshape(hh, factor, ww, factor).min(axis=(1, 3))


def scaled_intrinsics(intrinsics: np.ndarray, factor: int) -> np.ndarray:
    """[N, 4] (fx, fy, cx, cy) in working pixels -> the same in pixels f times larger: the ray
    through low-resolution pixel centre (i + 0.5) is the working frame's ray through f (i + 0.5)."""
    return (np.asarray(intrinsics, np.float32) / np.float32(factor)).astype(np.float32)


def lowres_dataset(dataset: Dataset, cfg) -> Dataset:
    """The dataset's training frames shrunk by train.lowres_factor for the pool of the first steps,
    one frame at a time (a shrunk copy is 1 / f^2 of the frames; the others are left black):
    images [N, H/f, W/f, 3] uint8 (block means), weights [N, H/f, W/f] the block minimum of the run's loss weights
    (`ray_pool.frame_weights`, the mask floor applied; None when the run uses none), intrinsics
    divided by f. Only what the plain pool reads is kept. cfg: a RunConfig."""
    t = cfg.train
    f = int(t.lowres_factor)
    if dataset.height < f or dataset.width < f:
        raise ConfigError(f"train.lowres_factor {f} is larger than the frames ({dataset.width}x{dataset.height})")
    n, h, w = dataset.num_frames, dataset.height // f, dataset.width // f
    images = np.zeros((n, h, w, 3), np.uint8)
    masked = t.use_masks and dataset.weights is not None
    weights = np.zeros((n, h, w), np.float32) if masked else None
    for i in np.asarray(dataset.split["train"], np.int64):  # the pool reads the training frames only
        images[i] = block_mean_uint8(dataset.images[i], f)
        if weights is not None:
            assert dataset.weights is not None
            full = ray_pool.frame_weights(dataset.weights[i], None if dataset.masks is None else dataset.masks[i],
                                          True, t.mask_weight_floor, (dataset.height, dataset.width))
            weights[i] = block_min(full, f)
    return dataclasses.replace(dataset, images=images, weights=weights, masks=None,
                               intrinsics=scaled_intrinsics(dataset.intrinsics, f), clean_images=None, depth=None,
                               semantics=None, distractor_masks=None)
