"""The run config: `RunConfig` (the dataset folder, `models.ModelConfig`, `TrainConfig`), made by
`make_config` (a method's defaults with overrides merged on top, checked by `config.validate` and
`models.validate`) and settled on a dataset by `config.resolve` inside `train.train`.

Its own module so that what reads a config (`views`, `runs`, `report`, `evaluate`) does not import
the training step for a type; `train` names these too (`train.RunConfig`, `train.make_config`).
`resolve_devices` is what `train.num_devices` means on this machine.
"""

from __future__ import annotations

import dataclasses
import typing

import jax

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.masks import robust as robust_lib
from jaxnerf_grid.nerf import models
from jaxnerf_grid.util.io import DataError


@dataclasses.dataclass(frozen=True)
class RobustConfig:
    """train.robust: the photometric evidence (`masks/robust.py`, docs/ROBUST.md).

    mode: "off" (the loss weights of TrainConfig), "robust" (no masks: the weight is the
      evidence of the residuals) or "dpt+robust" (the dataset's 1 - M_w, whatever use_masks
      says, sets how strict the evidence is per pixel); when on, training draws
      batch_rays / patch^2 patches of patch^2 rays. `--set train.robust=MODE` sets it (SHORTHAND).
    quantile, flagged_quantile: the inlier quantile of the batch's residuals for an unflagged
      pixel (prior 1) and a flagged one (prior 0; linear in between);
    patch: patch side in pixels; patch_stride: the distance in pixels between a patch's
      neighbouring pixels (1: adjacent); patch_share: a patch with fewer pixels passing the 3x3
      vote is a transient patch; floor: a residual (squared error) at most this is always an
      inlier; spread: k of the spread bound (robust.spread_thresholds: a residual within
      median + k MAD-sigmas of the batch is an inlier whatever the quantile says; 0 = the
      quantile alone); warmup: the fraction of max_steps trained on the prior alone before the
      evidence applies (robust.warmup_steps);
    confirm: multi-view confirmation (`photo_consistency.py`): a pixel whose 3x3 neighbourhood a
      neighbouring training photo shows again at the pixel's rendered 3-D point, with a mean
      squared difference at most this, is an inlier whatever its residual (0 = off); views: how
      many neighbouring photos (nearest camera centres) are looked at;
    scattered: the share of batch_rays drawn as single pixels scattered over the frames instead
      of patches (`scattered_rays`); a scattered ray has no neighbours to vote, so its weight is
      its own inlier test (`robust.pixel_inliers`), confirmation included (0 = patches only);
    refine: the fraction of max_steps after which the evidence is judged once on whole training
      frames and frozen (`refine.py`): every training frame is rendered, the rule is applied to
      it (`robust.frame_evidence`), and the rest of the run trains on scattered rays with those
      weights, as a run with masks does (0 = patches to the end);
    prior_grow: dpt+robust only: pixels within this many px of a masked pixel are flagged in the
      prior too (`train.grown_masks`), so the rims of the transients that the DPT's masks fall
      short of are not trained on before the evidence decides (0 = the masks as they are);
    strict_readmit: a flagged pixel (prior < 1/2) is re-admitted only when its residual is an
      inlier *and* a neighbouring photo confirms it (`robust.pixel_inliers`); off, either
      suffices. Once re-admitted a pixel is trained on and its residual falls, so a transient
      re-admitted on its residual alone stays in (docs/ROBUST.md). None (the default): on unless
      `mask` judged the dataset's DPT masks out of their domain (`config.strict_readmit_auto`).
    """

    mode: str = "off"
    quantile: float = 0.8
    flagged_quantile: float = 0.5
    patch: int = 4
    patch_stride: int = 1
    patch_share: float = 0.6
    floor: float = 1e-3
    spread: float = 1.5
    warmup: float = 0.2
    confirm: float = 0.01
    views: int = 8
    scattered: float = 0.0
    refine: float = 0.0
    prior_grow: int = 0
    strict_readmit: bool | None = None

    SHORTHAND: typing.ClassVar[str] = "mode"  # `--set train.robust=robust` sets the mode
    # allowed values, checked by config.validate (docs/RELIABILITY.md)
    RANGES: typing.ClassVar[dict] = {
        "quantile": config_lib.UNIT, "flagged_quantile": config_lib.UNIT, "patch": config_lib.AT_LEAST_ONE,
        "patch_stride": config_lib.AT_LEAST_ONE, "patch_share": config_lib.UNIT, "floor": config_lib.NONNEGATIVE,
        "spread": config_lib.NONNEGATIVE, "warmup": config_lib.UNIT, "confirm": config_lib.NONNEGATIVE,
        "views": config_lib.AT_LEAST_ONE, "scattered": config_lib.FRACTION, "refine": config_lib.FRACTION,
        "prior_grow": config_lib.NONNEGATIVE}


@dataclasses.dataclass(frozen=True)
class DepthConfig:
    """train.depth: the capture's sparse points as a depth prior (`train/sparse_depth.py`).

    weight: the term's weight at the first step (0 = off); decay: its weight at the end of the
      run is weight * decay (log-linear in between, a fraction of max_steps); rays: depth rays
      rendered each step beside the batch (split over the devices like it); tolerance: the
      relative distance within which a ray's weight costs nothing; max_error_px: points with a
      larger reprojection error are not used; min_views: a point must be seen by this many
      training photos; start: the term is off for this share of max_steps, while the colours
      alone lay out the scene. `--set train.depth=W` sets the weight (SHORTHAND).
    """

    weight: float = 0.0
    decay: float = 0.1
    rays: int = 128
    tolerance: float = 0.01
    max_error_px: float = 2.0
    min_views: int = 2
    start: float = 0.0

    SHORTHAND: typing.ClassVar[str] = "weight"
    RANGES: typing.ClassVar[dict] = {
        "weight": config_lib.NONNEGATIVE, "decay": config_lib.POSITIVE, "rays": config_lib.AT_LEAST_ONE,
        "tolerance": config_lib.NONNEGATIVE, "max_error_px": config_lib.POSITIVE,
        "min_views": config_lib.AT_LEAST_ONE, "start": config_lib.FRACTION}


# Older train dicts held the robust settings flat: train.robust the mode string, the others as
# train.robust_<key> (robust_quantile, robust_patch, ...): `upgrade_flat_robust` reads them.
FLAT_ROBUST_PREFIX = "robust_"


def upgrade_flat_robust(train: dict) -> dict:
    """A train dict with the older flat robust keys nested in train.robust: a mode string
    becomes {"mode": ...}, robust_X becomes robust.X (laid over a robust dict it holds; an
    unknown X is named by `config.from_dict`). Returned unchanged when it has neither; the
    input is not changed."""
    if not isinstance(train, dict):
        return train
    flat = {k[len(FLAT_ROBUST_PREFIX):]: v for k, v in train.items() if k.startswith(FLAT_ROBUST_PREFIX)}
    current = train.get("robust")
    if not flat and not isinstance(current, str):
        return train
    robust = dict(current) if isinstance(current, dict) else ({} if current is None else {"mode": current})
    out = {k: v for k, v in train.items() if not k.startswith(FLAT_ROBUST_PREFIX)}
    out["robust"] = {**robust, **flat}
    return out


def flat_robust(train: dict) -> dict:
    """A train dict (as `to_dict` writes it) in the older flat layout: train.robust the mode,
    the other robust settings as robust_X keys (what the experiments' run keys hash)."""
    robust = train.get("robust")
    if not isinstance(robust, dict):
        return train
    out = {k: v for k, v in train.items() if k != "robust"}
    out["robust"] = robust.get("mode", "off")
    out.update({FLAT_ROBUST_PREFIX + k: v for k, v in robust.items() if k != "mode"})
    return out


def upgrade_run_dict(data: dict) -> dict:
    """A run config dict (config.json, a --config file, overrides) with the older layouts read
    where they can be without the defaults: the flat sampler keys (samplers/legacy.py) and the
    flat robust keys. (Each field kind's stray keys are read by its `Config.upgrade_dict`.)"""
    if not isinstance(data, dict):
        return data
    out = dict(data)
    if isinstance(out.get("model"), dict):
        out["model"] = models.ModelConfig.upgrade_dict(out["model"])
    if isinstance(out.get("train"), dict):
        out["train"] = upgrade_flat_robust(out["train"])
    return out


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimisation and I/O settings.

    batch_rays: global rays per step (split over devices; must divide by the device count).
    lr_init, lr_final, warmup: learning-rate schedule; max_grad_norm: clipping (0 = off);
    adam_b1, adam_b2, adam_eps: Adam's moments and epsilon (Instant-NGP: 0.9, 0.99, 1e-15).
    sparse_adam: lazy Adam on the hash grids' tables (optim.adam's lazy_keys, docs/GRID.md): a table
      row no ray of the batch reached keeps its moments and value (False: dense Adam).
    use_masks: weight the loss by the dataset's `1 - M_w` (False: every pixel weight 1).
    mask_weight_floor: with masks, a masked pixel's weight is at most 1 - floor (docs/CONVENTIONS.md:
      Eq. 7 gives a bird against the sky a weight near 1; floor 1 excludes every masked pixel).
    checkpoint_every, keep_checkpoints, log_every: steps; chunk: rays per rendering chunk.
    num_devices: devices to use (0 = all local devices).
    appearance_steps, appearance_lr, appearance_rays: NeRF-W test-time embedding fit.
    max_side: the working resolution (data/working.py): the run trains, and eval / render render,
      at the photos' size divided by the smallest integer factor that brings the long side to at
      most max_side px, intrinsics scaled (0 = full size; `--max-side`, docs/DATASET.md).
    coarse_loss_weight: weight of the MSE of each level before the final one that renders colour
      (the hierarchical sampler's first pass; losses.per_ray_loss's level_weight);
    interlevel_loss_weight: weight of mip-NeRF 360's proposal loss (levels without colour);
    distortion_loss_weight: weight of mip-NeRF 360's distortion loss, in s (0 = off).
    lowres_share, lowres_factor: the resolution schedule (train/lowres.py): the first
      lowres_share of the steps train on the frames shrunk by lowres_factor (block means), the
      rest at the working resolution (0 = off; only with train.robust off).
    error_share, error_tile: error-map sampling (train/error_map.py): error_share of each batch
      drawn from tiles of error_tile x error_tile working pixels in proportion to their recent
      error, the rest uniformly (0 = off; only with train.robust and the resolution schedule off).
    robust: the photometric evidence's settings (`RobustConfig`, docs/ROBUST.md).
    depth: the sparse points' depth prior (`DepthConfig`, off by default; `demo --data` turns it
      on for a capture from `poses`).
    """

    batch_rays: int = 1024
    max_steps: int = 2000
    lr_init: float = 5e-4
    lr_final: float = 5e-5
    warmup: int = 100
    max_grad_norm: float = 1.0
    adam_eps: float = 1e-6
    adam_b1: float = 0.9
    adam_b2: float = 0.999
    sparse_adam: bool = False
    use_masks: bool = True
    mask_weight_floor: float = 0.0
    coarse_loss_weight: float = 1.0
    interlevel_loss_weight: float = 1.0
    distortion_loss_weight: float = 0.0
    seed: int = 0
    checkpoint_every: int = 500
    keep_checkpoints: int = 3
    log_every: int = 25
    chunk: int = 4096
    num_devices: int = 0
    appearance_steps: int = 30
    appearance_lr: float = 0.05
    appearance_rays: int = 1024
    max_side: int = 640
    lowres_share: float = 0.0
    lowres_factor: int = 2
    error_share: float = 0.0
    error_tile: int = 16
    robust: RobustConfig = RobustConfig()
    depth: DepthConfig = DepthConfig()

    # `--set train.robust_X` (the older flat name) is refused naming train.robust.X
    RENAMED_PREFIXES: typing.ClassVar[dict] = {FLAT_ROBUST_PREFIX: "robust."}
    # allowed values, checked by config.validate (docs/RELIABILITY.md)
    RANGES: typing.ClassVar[dict] = {
        "batch_rays": config_lib.AT_LEAST_ONE, "max_steps": config_lib.AT_LEAST_ONE,
        "lr_init": config_lib.POSITIVE, "lr_final": config_lib.POSITIVE, "warmup": config_lib.NONNEGATIVE,
        "max_grad_norm": config_lib.NONNEGATIVE, "adam_eps": config_lib.POSITIVE,
        "adam_b1": config_lib.FRACTION, "adam_b2": config_lib.FRACTION, "mask_weight_floor": config_lib.UNIT,
        "coarse_loss_weight": config_lib.NONNEGATIVE, "interlevel_loss_weight": config_lib.NONNEGATIVE,
        "distortion_loss_weight": config_lib.NONNEGATIVE, "seed": config_lib.Range(0, 2**32 - 1),
        "checkpoint_every": config_lib.AT_LEAST_ONE, "keep_checkpoints": config_lib.AT_LEAST_ONE,
        "log_every": config_lib.AT_LEAST_ONE, "chunk": config_lib.AT_LEAST_ONE,
        "num_devices": config_lib.NONNEGATIVE, "appearance_steps": config_lib.NONNEGATIVE,
        "appearance_lr": config_lib.POSITIVE, "appearance_rays": config_lib.AT_LEAST_ONE,
        "max_side": config_lib.NONNEGATIVE, "lowres_share": config_lib.UNIT,
        "lowres_factor": config_lib.AT_LEAST_ONE, "error_share": config_lib.UNIT,
        "error_tile": config_lib.AT_LEAST_ONE}

    @staticmethod
    def upgrade_dict(data: dict) -> dict:
        """An older train dict (flat robust_* keys, train.robust a mode string) nested."""
        return upgrade_flat_robust(data)


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that decides a run: the dataset folder (set by `runs.train_run`; None in a
    recipe or a bare config), the model and the training. config.json is its `to_dict`."""

    data: str | None = None
    model: models.ModelConfig = models.ModelConfig()
    train: TrainConfig = TrainConfig()


def make_config(method: str, overrides: dict | None = None) -> RunConfig:
    """The defaults of `method` with `overrides` (a nested dict, e.g. from --config) on top."""
    base = {"model": models.method_defaults(method), "train": {"use_masks": method == "ours"}}
    overrides = upgrade_run_dict(overrides or {})  # older flat sampler / robust keys, over the old defaults
    merged = config_lib.merge(config_lib.to_dict(RunConfig()), base)
    merged = config_lib.merge(merged, overrides)
    if "model" in overrides and "method" in overrides["model"] and overrides["model"]["method"] != method:
        raise ConfigError(f"config: model.method {overrides['model']['method']!r} contradicts run.method {method!r}")
    cfg = config_lib.from_dict(RunConfig, merged)
    config_lib.validate(cfg)
    check_robust(cfg.train)
    models.validate(dataclasses.replace(cfg.model, num_images=max(cfg.model.num_images, 1)))
    return cfg


def resolve_devices(cfg: TrainConfig) -> int:
    """Local devices used: cfg.num_devices (0 = all)."""
    available = jax.local_device_count()
    n = cfg.num_devices or available
    if n > available:
        raise ConfigError(f"train.num_devices = {n} but only {available} local devices exist")
    return n


def scattered_rays(cfg: TrainConfig) -> int:
    """How many of a robust batch's rays are scattered single pixels: batch_rays x
    robust.scattered, rounded."""
    return int(round(cfg.batch_rays * cfg.robust.scattered))


def check_robust(cfg: TrainConfig, num_devices: int = 1, dataset: Dataset | None = None) -> None:
    """ConfigError unless train.robust.mode is a known mode and, when on, the batch splits into
    whole patches, and the patches over the devices; with a dataset, also that a patch fits in
    its frames (ConfigError) and that dpt+robust has masks (DataError)."""
    r = cfg.robust
    if r.mode not in robust_lib.MODES:
        raise ConfigError(f"train.robust.mode = {r.mode!r}: must be one of {', '.join(robust_lib.MODES)}")
    if r.mode == "off":
        return
    area = r.patch ** 2
    scattered = scattered_rays(cfg)
    patch_rays = cfg.batch_rays - scattered
    if patch_rays <= 0 or patch_rays % area or (patch_rays // area) % num_devices:
        raise ConfigError(f"train.batch_rays = {cfg.batch_rays}: with train.robust on, its patch part "
                          f"({patch_rays} rays after train.robust.scattered's {scattered}) must be a positive "
                          f"multiple of train.robust.patch^2 ({area}) times the device count ({num_devices})")
    if scattered % num_devices:
        raise ConfigError(f"train.robust.scattered = {r.scattered}: its {scattered} scattered rays "
                          f"must divide over the {num_devices} devices")
    if dataset is None:
        return
    span = robust_lib.patch_span(r.patch, r.patch_stride)
    if min(dataset.height, dataset.width) < span:
        raise ConfigError(f"train.robust.patch = {r.patch} at train.robust.patch_stride = "
                          f"{r.patch_stride}: spans {span} px, more than the "
                          f"{dataset.width}x{dataset.height} images")
    if r.mode == "dpt+robust" and dataset.weights is None:
        raise DataError(f"{dataset.root}: train.robust = dpt+robust needs the dataset's masks "
                        "(run jaxnerf-grid mask first, or use train.robust = robust)")
