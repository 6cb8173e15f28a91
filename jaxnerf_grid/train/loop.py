"""Training: jaxopt-driven steps, pmap data parallelism, checkpoints, exact resume.

The run config (`RunConfig` = model + train) is made by `run_config.make_config` (a method's
defaults with overrides merged on top) and settled on the dataset by `config.resolve` inside `train`.

Training step (one `jax.pmap` over the local devices, axis "batch"):
  * the ray pool (ray_pool.py: every training pixel with loss weight > 0; the frames as 8 bits,
    split over the devices, each holding 1/n of them) is uploaded once;
  * from the state's PRNG key each device draws the same *global* batch of `batch_rays`
    pixel ids (uniform, with replacement) and per-ray keys; the devices holding the rays'
    frames look the pixels up, one psum gives every device the whole batch, and each takes its
    own slice, so the global batch does not depend on the device count;
  * the host reads a step's finite flag when the loss is logged (or after MAX_UNREAD steps),
    not after every step, so it can queue the next steps meanwhile;
  * per-device loss = sum_r w_r l_r / W with W the psum of the weights over the global batch
    (losses.weighted_mean), gradients psum-ed over devices (= the gradient of the global
    loss), then `optim.guarded_apply` (jaxopt's OptaxSolver update with clipping inside Adam)
    skips a non-finite step; the host logs every skipped step;
  * the learning rate warms up linearly then decays log-linearly (optim.make_lr_schedule).
  * with train.robust on (`_make_robust_step`, robust.py, docs/ROBUST.md) the batch is square
    patches drawn over whole frames and each pixel's weight is the photometric evidence of the
    residuals (their quantiles taken over the all-gathered global batch); the state then also
    holds "robust_record", the per-pixel average of the weights used, written at the end as
    RUN/weights/NAME.png; with train.robust.refine the evidence is judged once on whole frames
    at that step (`refine.py`), the record becomes those 0 / 1 weights, and the run goes on with
    the plain step on scattered rays among the pixels they keep.

The state is {"params", "opt_state", "key"} plus the host step counter; checkpoints
(checkpoint.save_checkpoint: atomic, last k kept) hold exactly that, so a resumed run replays
the same batches and reaches the same parameters as an uninterrupted one.

Rendering a trained model is `views.py`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.config import schema as config_lib

# the run config lives in run_config.py; train.RunConfig / train.make_config stay for their callers
from jaxnerf_grid.config.run_config import (  # noqa: F401
    RunConfig,
    TrainConfig,
    check_robust,
    make_config,
    resolve_devices,
    scattered_rays,
)
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data import working
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.masks import photo_consistency
from jaxnerf_grid.masks import robust as robust_lib
from jaxnerf_grid.nerf import fields, losses, models
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.train import checkpoint, distributed, error_map, lowres, optim, ray_pool, refine, sparse_depth
from jaxnerf_grid.util import io, parallel
from jaxnerf_grid.util import progress as progress_lib
from jaxnerf_grid.util.io import DataError

logger = logging.getLogger(__name__)
AXIS = parallel.AXIS


# --------------------------------------------------------------------------- ray pool


def loss_weights(dataset: Dataset, cfg: TrainConfig) -> np.ndarray:
    """Per-pixel loss weights of every frame (`ray_pool.frame_weights` of each). Returns [N, H, W]
    float32 in [0, 1]."""
    return ray_pool.frame_weights(dataset.weights, dataset.masks, cfg.use_masks, cfg.mask_weight_floor,
                                  dataset.images.shape[:3])


def grown_masks(masks: np.ndarray, pixels: int) -> np.ndarray:
    """Binary masks grown by `pixels` (OpenCV dilation with an elliptical disc of that radius, as
    `foreground.dilate`). masks: [N, H, W], masked where > 0.5 -> [N, H, W] bool."""
    binary = np.asarray(masks) > 0.5
    if pixels <= 0:
        return binary
    cv2 = io.opencv()
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * pixels + 1, 2 * pixels + 1))
    return np.stack([cv2.dilate(m.astype(np.uint8), disc) > 0 for m in binary])


def prior_weights(dataset: Dataset, cfg: TrainConfig) -> np.ndarray:
    """The per-pixel prior of the photometric evidence (train.robust on). [N, H, W] in [0, 1]:
    ones for "robust"; for "dpt+robust" the dataset's 1 - M_w (with mask_weight_floor), which
    must exist, and 0 within train.robust.prior_grow pixels of a masked pixel (`grown_masks`;
    needs the binary masks)."""
    check_robust(dataclasses.replace(cfg, batch_rays=cfg.robust.patch ** 2,
                                     robust=dataclasses.replace(cfg.robust, scattered=0.0)), 1, dataset)
    if cfg.robust.mode == "robust":
        return np.ones(dataset.images.shape[:3], np.float32)
    prior = loss_weights(dataset, dataclasses.replace(cfg, use_masks=True))
    if cfg.robust.prior_grow > 0:
        if dataset.masks is None:
            raise DataError(f"{dataset.root}: train.robust.prior_grow needs the dataset's binary masks "
                            "(mask_path, written by jaxnerf-grid mask)")
        prior = np.where(grown_masks(dataset.masks, cfg.robust.prior_grow), 0.0, prior).astype(np.float32)
    return prior


def _training_frames(dataset: Dataset, cfg: RunConfig) -> tuple[np.ndarray, np.ndarray, dict]:
    """What `build_pool` and `robust_pool` share: (train_ids [T], weights [T, H, W] float32 (the
    evidence's prior with train.robust on, else the loss weights), {"c2w", "intrinsics", "frame",
    "near", "far"[, "neighbours"]})."""
    train_ids = np.asarray(dataset.split["train"], np.int64)
    if train_ids.size == 0:
        raise DataError(f"{dataset.root}: the dataset has no training frames")
    robust_on = cfg.train.robust.mode != "off"
    weights = (prior_weights(dataset, cfg.train) if robust_on else loss_weights(dataset, cfg.train))[train_ids]
    if weights.size == 0 or not (robust_on or np.any(weights > 0)):
        raise DataError(f"{dataset.root}: every training pixel has loss weight 0 (check the masks)")
    near, far = config_lib.near_far(cfg.model, dataset)
    if not 0 < near < far:
        raise ConfigError(f"near/far: need 0 < near < far, got {near}, {far}")
    c2w = np.asarray(dataset.c2w[train_ids], np.float32)
    rest = {"c2w": c2w, "intrinsics": np.asarray(dataset.intrinsics[train_ids], np.float32),
            "frame": train_ids.astype(np.int32), "near": near, "far": far}
    if robust_on and cfg.train.robust.confirm > 0:
        rest["neighbours"] = photo_consistency.neighbour_frames(c2w, cfg.train.robust.views)
    return train_ids, weights, rest


def build_pool(dataset: Dataset, cfg: RunConfig) -> dict:
    """Training data for on-device batch drawing (host NumPy arrays, float32): the reference the
    robust step's lean pool (`robust_pool`) and the plain step's 8-bit pool (ray_pool.py) are
    tested against.

    Returns {"pixels": [P] int32 flat ids (frame-in-train * H*W + row * W + col) of every
    training pixel with weight > 0, "images": [T, H, W, 3], "weights": [T, H, W],
    "c2w": [T, 4, 4], "intrinsics": [T, 4], "frame": [T] int32 dataset frame ids,
    "near", "far": floats}. With train.robust on, "weights" is the evidence's prior
    (`prior_weights`) and "pixels" every training pixel, the flagged ones included (patches
    are drawn over whole frames); with train.robust.confirm > 0 also "neighbours": [T, K]
    int32 (`photo_consistency.neighbour_frames`, indices into the pool's frames).
    """
    train_ids, weights, rest = _training_frames(dataset, cfg)
    robust_on = cfg.train.robust.mode != "off"
    pixels = (np.arange(weights.size) if robust_on else np.flatnonzero(weights.reshape(-1) > 0)).astype(np.int32)
    return {"pixels": pixels, "images": working.as_float(dataset.images[train_ids]), "weights": weights, **rest}


def robust_pool(dataset: Dataset, cfg: RunConfig) -> dict:
    """The robust step's pool (train.robust on): `build_pool`'s without "pixels" (the step draws
    flat ids over whole frames), its images and weights held by `ray_pool.lean_frames` (8-bit
    frames as uint8, the weights as uint8 codes with "levels" [256] where a table codes them), so
    `gather_batch`, the confirmation and refine.py read the same float32 values from it."""
    if cfg.train.robust.mode == "off":
        raise ValueError("robust_pool: train.robust is off (the plain step's pool is ray_pool.build)")
    train_ids, weights, rest = _training_frames(dataset, cfg)
    every = np.array_equal(train_ids, np.arange(len(dataset.images)))
    images = dataset.images if every else dataset.images[train_ids]  # no copy when every frame trains
    return {**ray_pool.lean_frames(images, weights), **rest}


def gather_batch(pool: dict, ids: jnp.ndarray) -> dict:
    """Rays and targets of flat pixel ids. pool: `build_pool`'s or `robust_pool`'s (decoded
    here); ids: [B] -> dict of [B, ...] (origins, directions, near, far, rgb, weight, image_index)."""
    _, height, width, _ = pool["images"].shape
    frame = ids // (height * width)
    pix = ids % (height * width)
    row, col = pix // width, pix % width
    intr = pool["intrinsics"][frame]
    r = rays_lib.rays_for_pixels(pool["c2w"][frame], intr[:, 0], intr[:, 1], intr[:, 2], intr[:, 3],
                                 col.astype(jnp.float32) + 0.5, row.astype(jnp.float32) + 0.5,
                                 pool["near"], pool["far"])
    return {"origins": r.origins, "directions": r.directions, "near": r.near, "far": r.far,
            "rgb": ray_pool.colours(pool["images"], frame, row, col),
            "weight": ray_pool.weights_at(pool, frame, row, col),
            "image_index": pool["frame"][frame]}


# --------------------------------------------------------------------------- the step


# The parameters that train.sparse_adam updates lazily: every hash grid's table (fields/hashgrid.py).
LAZY_ADAM_KEYS = ("table",)


def make_optimizer(cfg: TrainConfig) -> optim.GradientTransformation:
    """The run's Adam: the learning-rate schedule, Adam's settings, clipping; with
    train.sparse_adam lazy on the hash tables (LAZY_ADAM_KEYS)."""
    schedule = optim.make_lr_schedule(cfg.lr_init, cfg.lr_final, cfg.warmup, cfg.max_steps)
    return optim.adam(schedule, b1=cfg.adam_b1, b2=cfg.adam_b2, eps=cfg.adam_eps, max_grad_norm=cfg.max_grad_norm,
                      lazy_keys=LAZY_ADAM_KEYS if cfg.sparse_adam else ())


def init_state(cfg: RunConfig, frames_shape: tuple | None = None) -> dict:
    """{"params", "opt_state", "key"} on the host (unreplicated); with train.robust on also
    "robust_record": [T, H, W] the per-pixel moving average of the weights training used
    (`robust.ema_update`), ones at first; with train.error_share on "error_map": [tiles] the
    tiles' error record (error_map.py); frames_shape = (T, H, W) of the training frames
    (`train_frames_shape`) is then needed."""
    key = jax.random.PRNGKey(cfg.train.seed)
    key, k_init = jax.random.split(key)
    params = models.init(k_init, cfg.model)
    state = {"params": params, "opt_state": make_optimizer(cfg.train).init(params), "key": key}
    if error_map.error_rays(cfg.train):
        if frames_shape is None:
            raise ValueError("init_state: train.error_share is on, give the training frames' shape")
        frames, height, width = frames_shape
        state["error_map"] = error_map.init(frames, height, width, cfg.train.error_tile)
    if cfg.train.robust.mode != "off":
        if frames_shape is None:
            raise ValueError("init_state: train.robust is on, give the training frames' shape")
        state["robust_record"] = np.ones(tuple(frames_shape), np.float32)
    return state


def train_frames_shape(dataset: Dataset) -> tuple[int, int, int]:
    """(T, H, W): training frames, height, width."""
    return (len(dataset.split["train"]), dataset.height, dataset.width)


def final_rgb(outputs: dict) -> jnp.ndarray:
    """The picture's colour of a models.render_rays output, [B, 3] (the final pass)."""
    return outputs["final"]["rgb"]


def batch_terms(params: dict, cfg: RunConfig, batch: dict, ray_keys) -> tuple[dict, dict]:
    """A batch's render (models.render_rays) and per-ray loss terms (losses.per_ray_loss).
    batch: gather_batch's dict of [B, ...]; ray_keys: [B, 2]. Returns (outputs, terms)."""
    mcfg, tcfg = cfg.model, cfg.train
    out = models.render_rays(params, mcfg, batch["origins"], batch["directions"], batch["near"], batch["far"],
                             ray_keys, batch["image_index"])
    terms = losses.per_ray_loss(out, batch["rgb"], mcfg.use_transient, mcfg.lambda_u, tcfg.coarse_loss_weight,
                                tcfg.interlevel_loss_weight, tcfg.distortion_loss_weight)
    return out, terms


def depth_term(params: dict, cfg: RunConfig, table: dict, key, count, num_devices: int) -> tuple:
    """train.depth's term on this device (sparse_depth.py): the global draw of train.depth.rays
    depth rays from the pool's replicated "depth" table and their keys (from `key`, the same for
    any device count), this device's slice rendered. Returns (weight(count) x sum of this
    device's ray losses / rays: the psum over the devices is the global mean, that mean of this
    device's share unweighted)."""
    mcfg, dcfg = cfg.model, cfg.train.depth
    per_device = dcfg.rays // num_devices
    k_draw, k_rays = jax.random.split(key)
    rays = sparse_depth.draw(table, k_draw, dcfg.rays)
    keys = jax.random.split(k_rays, dcfg.rays)
    start = jax.lax.axis_index(AXIS) * per_device

    def mine(x):
        return jax.lax.dynamic_slice_in_dim(x, start, per_device)

    rays, keys = jax.tree_util.tree_map(mine, rays), mine(keys)
    near = jnp.broadcast_to(table["near"], rays["t"].shape)
    far = jnp.broadcast_to(table["far"], rays["t"].shape)
    out = models.render_rays(params, mcfg, rays["origins"], rays["directions"], near, far, keys, rays["camera"])
    per_ray = sparse_depth.ray_loss(out["final"]["t_edges"], out["final"]["weights"], rays["t"], dcfg.tolerance)
    weight = sparse_depth.weight_at(count, dcfg.weight, dcfg.decay, cfg.train.max_steps, dcfg.start)
    return weight * jnp.sum(per_ray) / dcfg.rays, jnp.sum(per_ray) / dcfg.rays


def depth_enabled(tcfg: TrainConfig) -> bool:
    """train.depth is on (a positive weight)."""
    return tcfg.depth.weight > 0


def depth_table(dataset: Dataset, cfg: RunConfig) -> tuple[dict | None, str]:
    """The depth rays of train.depth (`sparse_depth.dataset_rays` on the training frames), those
    whose point lies between the run's near and far, with "near" and "far" added: (table of host
    arrays, or None when there are none, and a sentence saying what was used or why not)."""
    dcfg = cfg.train.depth
    rays, why = sparse_depth.dataset_rays(dataset, dataset.split["train"], dcfg.max_error_px, dcfg.min_views)
    if rays is None:
        return None, why
    near, far = config_lib.near_far(cfg.model, dataset)
    keep = (rays["t"] > near) & (rays["t"] < far)
    if not np.any(keep):
        return None, f"none of the {len(keep)} depth rays' points lies between near ({near:.3g}) and far ({far:.3g})"
    table = {k: v[keep] for k, v in rays.items()}
    table.update(near=np.float32(near), far=np.float32(far))
    dropped = int(np.sum(~keep))
    return table, why + (f"; {dropped} nearer than near or beyond far left out" if dropped else "")


def with_depth(pool: dict, table: dict | None, n: int) -> dict:
    """A device pool with the depth table replicated on its n devices under "depth" (unchanged when
    the table is None)."""
    return pool if table is None else dict(pool, depth=parallel.replicate(table, n))


DEPTH_FOLD = 7  # the depth rays' keys are folded off the batch key: the colour batch's draws stay as they were


def make_train_step(cfg: RunConfig, num_devices: int):
    """The pmapped step of `cfg` on `num_devices` devices (see `_make_train_step`). The dataset
    path does not shape the step, so it is left out of the cache key: the same model on two
    copies of a dataset shares one compilation."""
    return _make_train_step(dataclasses.replace(cfg, data=None), num_devices)


def plus_depth_term(loss, params: dict, cfg: RunConfig, pool: dict, k_batch, count, num_devices: int) -> tuple:
    """(loss + train.depth's term, the depth loss) inside a step; (loss, 0) when train.depth is
    off. The depth rays' key is folded off the batch key (DEPTH_FOLD)."""
    if not depth_enabled(cfg.train):
        return loss, jnp.float32(0.0)
    extra, depth = depth_term(params, cfg, pool["depth"], jax.random.fold_in(k_batch, DEPTH_FOLD), count,
                              num_devices)
    return loss + extra, depth


@functools.lru_cache(maxsize=8)
def _make_train_step(cfg: RunConfig, num_devices: int):
    """The pmapped step: (state [n, ...], pool [n, ...]) -> (state, stats {loss, mse, finite}).
    The pool: `ray_pool.upload` of a `ray_pool` pool (train.robust off), else `robust_pool`'s
    (or `build_pool`'s) replicated.

    Cached per (config, device count), so runs with the same config share one compilation.
    """
    tcfg = cfg.train
    if tcfg.batch_rays % num_devices:
        raise ConfigError(f"train.batch_rays ({tcfg.batch_rays}) must divide by the device count ({num_devices})")
    per_device = tcfg.batch_rays // num_devices
    opt = make_optimizer(tcfg)
    depth_on = depth_enabled(tcfg)
    if depth_on and tcfg.depth.rays % num_devices:
        raise ConfigError(f"train.depth.rays ({tcfg.depth.rays}) must divide by the device count ({num_devices})")
    if tcfg.robust.mode != "off":
        return _make_robust_step(cfg, num_devices, opt)

    from_errors = error_map.error_rays(tcfg)

    def step(state, pool):
        key, k_batch, k_rays = jax.random.split(state["key"], 3)
        batch = ray_pool.device_batch(pool, k_batch, tcfg.batch_rays, per_device, AXIS,
                                      state.get("error_map"), from_errors, tcfg.error_tile)
        ray_keys = jax.random.split(k_rays, tcfg.batch_rays)
        start = jax.lax.axis_index(AXIS) * per_device
        ray_keys = jax.lax.dynamic_slice_in_dim(ray_keys, start, per_device)
        total = jax.lax.psum(jnp.sum(batch["weight"]), AXIS)

        def loss_fn(params):
            _, terms = batch_terms(params, cfg, batch, ray_keys)
            loss = losses.weighted_mean(terms["loss"], batch["weight"], total)
            loss, depth = plus_depth_term(loss, params, cfg, pool, k_batch, state["opt_state"].count, num_devices)
            return loss, (losses.weighted_mean(terms["mse"], batch["weight"], total), depth, terms["mse"])

        (loss, (mse, depth, ray_mse)), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["params"])
        loss, mse, depth, grads = jax.lax.psum((loss, mse, depth, grads), AXIS)
        params, opt_state, finite = optim.guarded_apply(opt, state["params"], state["opt_state"], grads, loss)
        # other state (a robust run's frozen record, train.robust.refine) passes through unchanged
        new_state = dict(state, params=params, opt_state=opt_state, key=key)
        if from_errors:  # every device records the whole batch's errors: the maps stay equal
            whole = jnp.zeros((2, tcfg.batch_rays), jnp.float32)
            whole = jax.lax.dynamic_update_slice(whole, jnp.stack([ray_mse, batch["weight"]]), (0, start))
            whole = jax.lax.psum(whole, AXIS)
            new_state["error_map"] = jnp.where(finite, error_map.update(state["error_map"], batch["tiles"], whole[0],
                                                                        whole[1]), state["error_map"])
            if from_errors < tcfg.batch_rays:  # the logged fit is the uniform share's (the map's over-weights errors)
                uniform = (jnp.arange(tcfg.batch_rays) < tcfg.batch_rays - from_errors) * whole[1]
                mse = losses.weighted_mean(whole[0], uniform)
        stats = {"loss": loss, "mse": mse, "finite": finite}
        if depth_on:
            stats["depth_loss"] = depth
        return new_state, stats

    return jax.pmap(step, axis_name=AXIS, donate_argnums=(0,), devices=parallel.devices(num_devices))


def _make_robust_step(cfg: RunConfig, num_devices: int, opt):
    """The pmapped step with photometric evidence (train.robust on; robust.py): the global batch
    is (batch_rays - S) / p^2 patches of p x p pixels and S scattered pixels (S =
    `scattered_rays`, train.robust.scattered) drawn from the state's key (the same for any
    device count), each device renders its share of whole patches then its share of the
    scattered pixels (`robust.device_layout`); the residuals (final pass,
    stop-gradient) are all-gathered so every device takes the quantiles of the same global
    batch; each pixel's loss weight is `robust.batch_weights` (its patch's evidence, or a
    scattered pixel's own inlier test) with the pool's
    weight as the prior, after the first `robust.warmup_steps` optimiser steps (Adam's count,
    so resume is exact), and the prior itself before them; with train.robust.confirm > 0 a pixel
    that a neighbouring photo confirms at its rendered median depth is an inlier
    (`photo_consistency.py`). The state's robust_record takes the
    batch's weights (all-gathered, the same update on every device). Stats add
    "robust_weight": the mean weight of the batch."""
    tcfg = cfg.train
    check_robust(tcfg, num_devices)
    p = tcfg.robust.patch
    scattered = scattered_rays(tcfg)
    num_patches = (tcfg.batch_rays - scattered) // (p * p)
    per_device = tcfg.batch_rays // num_devices
    local_patch_rays = num_patches * p * p // num_devices  # each device: its patches, then its scattered rays
    layout = robust_lib.device_layout(num_patches * p * p, scattered, num_devices)
    warmup_steps = robust_lib.warmup_steps(tcfg.robust.warmup, tcfg.max_steps)
    confirm = tcfg.robust.confirm > 0
    depth_on = depth_enabled(tcfg)

    def confirmed_pixels(pool, ids, batch, depth):
        """[B] 1.0 where a neighbouring photo confirms the pixel at its rendered depth."""
        points = batch["origins"] + batch["directions"] * depth[:, None]
        return photo_consistency.confirmed_at_ids(pool["images"], pool["c2w"], pool["intrinsics"],
                                                  pool["neighbours"], ids, points, tcfg.robust.confirm,
                                                  ray_pool.byte_table(pool["images"]))

    def step(state, pool):
        key, k_batch, k_rays = jax.random.split(state["key"], 3)
        frames, height, width = pool["weights"].shape
        ids = robust_lib.draw_patches(k_batch, num_patches, frames, height, width, p, tcfg.robust.patch_stride)
        ray_keys = jax.random.split(k_rays, tcfg.batch_rays)
        if scattered:  # the same global batch for any device count, laid out device by device
            ids = jnp.concatenate([ids, robust_lib.draw_pixels(jax.random.fold_in(k_batch, 1), scattered,
                                                               frames, height, width)])[layout]
            ray_keys = ray_keys[layout]
        start = jax.lax.axis_index(AXIS) * per_device
        local_ids = jax.lax.dynamic_slice_in_dim(ids, start, per_device)
        ray_keys = jax.lax.dynamic_slice_in_dim(ray_keys, start, per_device)
        batch = gather_batch(pool, local_ids)

        def loss_fn(params):
            out, terms = batch_terms(params, cfg, batch, ray_keys)
            residual = jax.lax.stop_gradient(losses.squared_error(final_rgb(out), batch["rgb"]))
            everyone = jax.lax.all_gather(residual, AXIS, tiled=True)
            confirmed = None
            if confirm:
                depth = jax.lax.stop_gradient(out["final"]["median_depth"])
                confirmed = confirmed_pixels(pool, local_ids, batch, depth)
            evidence = robust_lib.batch_weights(residual, batch["weight"], everyone, local_patch_rays, p,
                                                tcfg.robust.quantile, tcfg.robust.flagged_quantile,
                                                tcfg.robust.patch_share, tcfg.robust.floor, tcfg.robust.spread,
                                                confirmed, tcfg.robust.strict_readmit)
            weight = jnp.where(state["opt_state"].count < warmup_steps, batch["weight"], evidence)
            total = jax.lax.psum(jnp.sum(weight), AXIS)
            loss = losses.weighted_mean(terms["loss"], weight, total)
            loss, depth = plus_depth_term(loss, params, cfg, pool, k_batch, state["opt_state"].count, num_devices)
            return loss, (losses.weighted_mean(terms["mse"], weight, total), weight, depth)

        (loss, (mse, weight, depth)), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["params"])
        loss, mse, depth, grads = jax.lax.psum((loss, mse, depth, grads), AXIS)
        params, opt_state, finite = optim.guarded_apply(opt, state["params"], state["opt_state"], grads, loss)
        all_weights = jax.lax.all_gather(weight, AXIS, tiled=True)
        record = robust_lib.ema_update(state["robust_record"], ids, all_weights)
        new_state = {"params": params, "opt_state": opt_state, "key": key, "robust_record": record}
        stats = {"loss": loss, "mse": mse, "finite": finite, "robust_weight": jnp.mean(all_weights)}
        if depth_on:
            stats["depth_loss"] = depth
        return new_state, stats

    return jax.pmap(step, axis_name=AXIS, donate_argnums=(0,), devices=parallel.devices(num_devices))


def write_robust_record(run_dir, dataset: Dataset, record: np.ndarray) -> Path:
    """Writes the weights training used (the state's robust_record [T, H, W]) as 8-bit PNGs
    run_dir/weights/NAME.png, one per training frame (NAME: the frame's file stem, frame_0007
    without paths; white = used, black = ignored). Returns the folder."""
    folder = Path(run_dir) / "weights"
    folder.mkdir(parents=True, exist_ok=True)
    for k, frame in enumerate(np.asarray(dataset.split["train"], np.int64)):
        name = Path(dataset.frame_paths[frame]).stem if dataset.frame_paths else f"frame_{int(frame):04d}"
        io.write_png(folder / f"{name}.png", np.asarray(record[k], np.float32))
    return folder


ACTIVATION_COPIES = 4  # a sample's activations: forward values, pre-activations and both gradients


def field_floats(f: fields.FieldConfig) -> int:
    """Rough float32 activations of one sample through a field (encoding, trunk, colour branch,
    heads); a hash grid also gathers 8 corners per level."""
    enc = fields.encoding_floats(f)
    transient = f.transient_depth * f.transient_width if f.transient_dim else 0
    return (enc + f.depth * f.width + fields.dir_input_size(f) + f.view_depth * f.view_width
            + f.appearance_dim + f.transient_dim + transient + 8)


def ray_bytes(cfg: models.ModelConfig) -> int:
    """Rough bytes of one training ray's step (forward + backward) over every pass."""
    floats = sum(n * field_floats(f) for n, f in models.field_evaluations(cfg))
    return 4 * ACTIVATION_COPIES * (floats + 64)


def device_memory() -> int:
    """Bytes one step may use: the first device's memory limit (GPU), else the host's RAM (CPU
    devices share it)."""
    import os

    dev = jax.local_devices()[0]
    stats = dev.memory_stats() if hasattr(dev, "memory_stats") else None
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"])
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def check_batch(cfg: RunConfig, num_devices: int, available: int | None = None) -> None:
    """Refuses a batch that does not divide over the devices or whose estimated step memory
    (`ray_bytes` x rays per device; on CPU all devices share the host's RAM) exceeds `available`
    (default `device_memory()`), suggesting a batch_rays that fits. A rough estimate: it only
    catches batches far too large, not a tight fit."""
    tcfg = cfg.train
    if tcfg.batch_rays % num_devices:
        raise ConfigError(f"train.batch_rays = {tcfg.batch_rays}: must divide by the device count ({num_devices})")
    available = device_memory() if available is None else available
    shared = jax.local_devices()[0].platform == "cpu"
    # on CPU this process's devices share its host's RAM (all of n in one process)
    rays = tcfg.batch_rays * parallel.local_count(num_devices) // num_devices if shared \
        else tcfg.batch_rays // num_devices
    need = rays * ray_bytes(cfg.model)
    if need > available:
        fit = max(1, available // ray_bytes(cfg.model) // (1 if shared else num_devices))
        fit = max(num_devices, (2 ** int(np.log2(fit)) // num_devices) * num_devices)
        raise ConfigError(f"train.batch_rays = {tcfg.batch_rays}: a step needs about {need / 2**30:.0f} GiB, "
                          f"more than the {available / 2**30:.0f} GiB available; try batch_rays = {fit} or less")


def step_devices(cfg: TrainConfig) -> int:
    """Devices of the train step: `resolve_devices` in one process; in a multi-process run
    (docs/DISTRIBUTED.md) every device of every process, the global count (then num_devices
    must be 0 or this process's local device count). Rendering stays on the local devices."""
    if not distributed.is_distributed():
        return resolve_devices(cfg)
    available = jax.local_device_count()
    if cfg.num_devices not in (0, available):
        raise ConfigError(f"train.num_devices = {cfg.num_devices}: a multi-process run uses every local "
                          f"device ({available} here); leave it 0")
    return jax.device_count()


def _log_record(line: str) -> dict | None:
    """One metrics.jsonl line as a dict; None for a blank, torn or foreign line."""
    try:
        record = json.loads(line)
    except json.JSONDecodeError:
        return None
    return record if isinstance(record, dict) and isinstance(record.get("step", 0), (int, float)) else None


def read_log(path) -> list[dict]:
    """The records of a run's metrics.jsonl that parse (torn or foreign lines skipped); [] when
    the file is missing."""
    path = Path(path)
    if not path.is_file():
        return []
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    return [r for r in map(_log_record, lines) if r is not None]


def _trim_log(path: Path, step: int) -> dict | None:
    """Drops metrics.jsonl lines logged after `step` (they are replayed after a resume) and any
    line that does not parse (a torn last line from a kill or a full disk), rewriting the file
    atomically. Returns the last record kept (None when none)."""
    if not path.exists():
        return None
    text = path.read_text(encoding="utf-8", errors="replace")
    records = [(line, _log_record(line)) for line in text.splitlines()]
    keep = [(line, r) for line, r in records if r is not None and r.get("step", 0) <= step]
    new = "".join(line + "\n" for line, _ in keep)
    if new != text:
        io.atomic_write_bytes(path, new.encode("utf-8"))
    return keep[-1][1] if keep else None


def _run_step(p_step, state_r, pool, step: int):
    """One pmapped step; in a multi-process run a failed collective (a peer died) becomes a
    DistributedError naming the step, and the result is waited for so it surfaces here."""
    if not distributed.is_distributed():
        return p_step(state_r, pool)
    try:
        out = p_step(state_r, pool)
        jax.block_until_ready(out[1]["loss"])
        return out
    except Exception as err:  # XlaRuntimeError / ValueError from gloo or NCCL
        raise distributed.DistributedError(
            f"step {step + 1}: a collective across the {jax.process_count()} processes failed; another "
            f"process of the run has probably died or lost its network ({type(err).__name__}: "
            f"{str(err).splitlines()[0][:300]})") from err


DEPTH_RECORD = "depth_prior.json"  # the run's record of train.depth: used or not, and why
MAX_UNREAD = 64  # steps whose finite flag may wait unread (bounds what the host keeps)


def _read_finite(unread: list, skipped: list) -> None:
    """Reads the finite flags of the steps in `unread` ((step, finite [n], loss [n]), emptied),
    appending each non-finite step to `skipped` and logging it (optim.log_nonfinite)."""
    for step, finite, loss in unread:
        if not bool(finite[0]):
            skipped.append(step)
            optim.log_nonfinite(step, loss[0])
    unread.clear()


def _freeze_evidence(state_r, pool_host: dict, dataset: Dataset, frozen_cfg: RunConfig, n: int, progress: bool):
    """train.robust.refine's switch (refine.py): judges the evidence on every training frame with
    the current parameters, puts the weights in the state's robust_record, and returns (state
    [n, ...], the frozen pool [n, ...], the plain step of `frozen_cfg`: robust off, the weights'
    mean)."""
    state = parallel.unreplicate(state_r)
    weights = refine.judge_frames(state["params"], frozen_cfg, dataset, pool_host, progress)
    state["robust_record"] = weights
    pool = ray_pool.upload(ray_pool.from_host_pool(refine.frozen_pool(pool_host, weights), dataset.root), n)
    return parallel.replicate(state, n), pool, make_train_step(frozen_cfg, n), float(np.mean(weights))


@dataclasses.dataclass
class TrainResult:
    """params; step: the step reached; seconds: this call's wall time; skipped_steps: non-finite
    steps of this call; last_loss, last_psnr: the last logged values (NaN when none was logged);
    steps_run: steps this call trained (0 when the run was already finished)."""

    params: dict
    step: int
    seconds: float
    skipped_steps: list
    last_loss: float
    last_psnr: float
    steps_run: int = 0



def device_pool(dataset: Dataset, cfg: RunConfig, n: int) -> dict:
    """The training step's pool on n devices, as `train` lays it out: the robust step's lean pool
    replicated (`robust_pool`), else the 8-bit frames split over the devices (`ray_pool`)."""
    if cfg.train.robust.mode != "off":
        return parallel.replicate(robust_pool(dataset, cfg), n)
    return ray_pool.upload(ray_pool.build(dataset, cfg), n)

def train(dataset: Dataset, cfg: RunConfig, run_dir, *, progress: bool = True,
          stop_at: int | None = None, on_step=None) -> TrainResult:
    """Trains (or resumes) a run in `run_dir` up to cfg.train.max_steps (or `stop_at`).

    Resumes from the newest checkpoint in run_dir when there is one. Writes checkpoints
    every `checkpoint_every` steps and at the end, and metrics.jsonl every `log_every` steps.
    on_step: optional callable(step) run on the host after each step (tests, callbacks).
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    cfg = config_lib.resolve(cfg, dataset)
    mcfg, tcfg = cfg.model, cfg.train
    n = step_devices(tcfg)
    robust_on = tcfg.robust.mode != "off"
    depth_rays = None
    if depth_enabled(tcfg):
        depth_rays, why = depth_table(dataset, cfg)
        if depth_rays is None:
            logger.warning("train.depth is on but no depth prior is used: %s", why)
            cfg = dataclasses.replace(cfg, train=dataclasses.replace(
                tcfg, depth=dataclasses.replace(tcfg.depth, weight=0.0)))
            tcfg = cfg.train
        else:
            why += f"; off for the first {tcfg.depth.start:.0%} of the steps" if tcfg.depth.start > 0 else ""
            logger.info("depth prior: %s", why)
        if distributed.is_main():
            io.write_json(run_dir / DEPTH_RECORD, {"used": depth_rays is not None, "why": why,
                                                   "rays": 0 if depth_rays is None else int(len(depth_rays["t"]))})
    # the robust step draws patches over replicated lean frames (robust_pool); the plain step
    # its rays from 8-bit frames split over the devices (ray_pool)
    pool_host = robust_pool(dataset, cfg) if robust_on else ray_pool.build(dataset, cfg)
    lowres_end = lowres.end_step(tcfg)  # the steps before it draw from the shrunk frames (lowres.py)
    state = init_state(cfg, train_frames_shape(dataset))
    step = 0
    main = distributed.is_main()  # process 0 (always, in one process) writes logs and checkpoints
    restored = checkpoint.restore_latest(run_dir, state) if main else None
    if restored is not None:
        state, step = restored
        logger.info("resumed %s at step %d", run_dir, step)
    if distributed.is_distributed():  # every process resumes from process 0's checkpoint
        state, step = distributed.broadcast_from_main((state, np.int32(step)))
        step = int(step)
    log_path = run_dir / "metrics.jsonl"
    last_record = _trim_log(log_path, step) if main else None
    lowres_host = ray_pool.build(lowres.lowres_dataset(dataset, cfg), cfg) if step < lowres_end else None
    check_batch(cfg, n)
    check_robust(tcfg, n)
    refine_at = robust_lib.refine_step(tcfg.robust.refine, tcfg.max_steps) if tcfg.robust != "off" else None
    frozen_cfg = dataclasses.replace(cfg, train=dataclasses.replace(
        tcfg, robust=dataclasses.replace(tcfg.robust, mode="off")))
    frozen_mean = None  # the frozen weights' mean, once the evidence is frozen (train.robust.refine)
    if refine_at is not None and step > refine_at:  # resumed after the evidence was frozen: its record holds it
        frozen = refine.frozen_pool(pool_host, state["robust_record"])
        frozen_mean = float(np.mean(frozen["weights"]))
        pool = ray_pool.upload(ray_pool.from_host_pool(frozen, dataset.root), n)
    elif robust_on:
        pool = parallel.replicate(pool_host, n)
    elif lowres_host is not None:  # the working frames are uploaded at lowres_end
        pool = ray_pool.upload(lowres_host, n)
    else:
        pool = ray_pool.upload(pool_host, n)
        pool_host = {}  # the devices hold the frames now (on CPU the very same memory)
    pool = with_depth(pool, depth_rays, n)
    state_r = parallel.replicate(state, n)
    p_step = make_train_step(cfg if frozen_mean is None else frozen_cfg, n)
    end = min(tcfg.max_steps, stop_at if stop_at is not None else tcfg.max_steps)
    first_step = step
    schedule = optim.make_lr_schedule(tcfg.lr_init, tcfg.lr_final, tcfg.warmup, tcfg.max_steps)
    skipped: list[int] = []
    unread: list = []  # (step, finite [n], loss [n]) of the steps whose finite flag is not read yet
    # a run already at its last step trains no step: report its last logged loss and PSNR
    last_loss = float((last_record or {}).get("loss", float("nan")))
    last_psnr = float((last_record or {}).get("psnr", float("nan")))
    bar = None
    if progress and main:
        bar = progress_lib.bar(total=end, initial=step, desc=f"train {mcfg.method}", unit="step")
    start_time = time.perf_counter()
    window_start, window_steps = time.perf_counter(), 0
    try:
        while step < end:
            if step == refine_at:  # freeze the evidence on whole frames (refine.py), then scattered rays
                state_r, pool, p_step, frozen_mean = _freeze_evidence(state_r, pool_host, dataset, frozen_cfg, n,
                                                                      progress and main)
                pool = with_depth(pool, depth_rays, n)
                logger.info("step %d: the evidence, judged on whole frames, ignores %.1f %% of the training pixels",
                            step, 100 * (1.0 - frozen_mean))
            if lowres_host is not None and step == lowres_end:  # the resolution schedule's switch
                pool = with_depth(ray_pool.upload(pool_host, n), depth_rays, n)
                pool_host, lowres_host = {}, None
                logger.info("step %d: training at the working resolution from here", step)
            state_r, stats = _run_step(p_step, state_r, pool, step)
            step += 1
            window_steps += 1
            # the finite flags are read when the loss is logged, not after every step (a read
            # waits for the step, and the host then cannot queue the next one meanwhile)
            unread.append((step, stats["finite"], stats["loss"]))
            if step % tcfg.log_every == 0 or step == end or len(unread) >= MAX_UNREAD:
                _read_finite(unread, skipped)
            if step % tcfg.log_every == 0 or step == end:
                last_loss = float(stats["loss"][0])
                last_psnr = float(losses.mse_to_psnr(stats["mse"][0]))
                elapsed = time.perf_counter() - window_start
                record = {"step": step, "loss": last_loss, "psnr": last_psnr,
                          "lr": float(schedule(step - 1)), "skipped_total": len(skipped),
                          "rays_per_s": window_steps * tcfg.batch_rays / max(elapsed, 1e-9),
                          "time": time.perf_counter() - start_time}
                if "depth_loss" in stats:
                    record["depth_loss"] = float(stats["depth_loss"][0])
                if "robust_weight" in stats:
                    record["robust_weight"] = float(stats["robust_weight"][0])
                elif frozen_mean is not None:  # the frozen weights' mean (train.robust.refine)
                    record["robust_weight"] = frozen_mean
                if main:
                    with io.naming_path(log_path), open(log_path, "a") as fh:  # a full disk names the file
                        fh.write(json.dumps(record) + "\n")
                window_start, window_steps = time.perf_counter(), 0
                if bar is not None:
                    bar.set_postfix(loss=f"{last_loss:.4f}", psnr=f"{last_psnr:.2f}")
            if bar is not None:
                bar.update(1)
            if (step % tcfg.checkpoint_every == 0 or step == end) and main:
                _read_finite(unread, skipped)
                checkpoint.save_checkpoint(run_dir, step, parallel.unreplicate(state_r), keep=tcfg.keep_checkpoints)
            if on_step is not None:
                on_step(step)
    finally:
        if bar is not None:
            bar.close()
    _read_finite(unread, skipped)
    final = parallel.unreplicate(state_r)
    if "robust_record" in final and main:
        write_robust_record(run_dir, dataset, final["robust_record"])
    return TrainResult(params=final["params"], step=step, seconds=time.perf_counter() - start_time,
                       skipped_steps=skipped, last_loss=last_loss, last_psnr=last_psnr,
                       steps_run=step - first_step)


def load_params(run_dir, cfg: RunConfig, dataset: Dataset) -> tuple[dict, int]:
    """Parameters of the newest checkpoint of a run of `cfg` on `dataset`. Returns (params, step).
    The checkpoint's template is abstract (`jax.eval_shape` of `init_state`): no parameters are
    drawn and nothing is compiled for it (drawing them compiled about 50 small functions, seconds
    before every render, eval and export)."""
    template = jax.eval_shape(lambda: init_state(config_lib.resolve(cfg, dataset, bounds=False),
                                                 train_frames_shape(dataset)))
    restored = checkpoint.restore_latest(run_dir, template)
    if restored is None:
        raise DataError(f"{Path(run_dir) / checkpoint.CHECKPOINT_DIR}: no checkpoint to load")
    state, step = restored
    return state["params"], step
