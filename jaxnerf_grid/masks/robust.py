"""Photometric evidence: a robust per-pixel loss weight from the training residuals.

In the spirit of RobustNeRF (Sabour et al. 2023): a pixel whose residual is large compared
with the rest of the batch is probably a transient (a person, a bird) that the static model
cannot and should not explain, so it is left out of the loss. Training draws square patches
of rays (`draw_patches`) so that the evidence can be judged over neighbourhoods; every array
below is laid out [P, p, p] (P patches of p x p pixels) unless said otherwise.

The rule, per training step (`evidence`):

1. threshold: the larger of two figures of the *global* batch's residuals (squared error of
   the final pass, stop-gradient):
   - the residual at the quantile q(prior), with q(prior) = q_flagged + (q - q_flagged) *
     prior per pixel (`pixel_quantiles`);
   - the spread bound (m + k(prior) 1.4826 MAD)^2 (`spread_thresholds`; m and MAD the median
     and the median absolute deviation of the root residuals, 1.4826 MAD the standard
     deviation of a normal sample): a residual is only an outlier when its RMS error lies k
     robust standard deviations above the batch's typical one. A quantile alone cuts its
     share of every batch for ever, so on a static scene it ignores 1 - q of the pixels (the
     textured, high-contrast ones); the spread bound keeps a residual distribution without
     outliers whole and still cuts the far tail that transients make;
   a pixel is an inlier when its residual is at most max(threshold, floor) (the floor keeps
   pixels the model fits to within noise);
2. 3x3 vote: the share of inliers among the pixel's 3x3 neighbours inside its patch (itself
   included; `smooth_3x3`); the vote passes at a share of at least 1/2, which re-admits
   isolated outliers in a static region (thin detail) and drops isolated inliers inside a
   transient;
3. patch rule: a patch where fewer than `patch_share` of the pixels pass the vote is judged a
   transient patch; there a pixel counts only when it passes the vote *and* is itself an
   inlier; elsewhere the vote decides.

The weight is 1 for a pixel that counts, 0 otherwise.

Multi-view confirmation (train.robust.confirm > 0, `photo_consistency.py`): before the vote,
a pixel that a neighbouring photo confirms (its 3x3 neighbourhood seen again at its rendered
3-D point, mean squared difference at most train.robust.confirm) is an inlier whatever its
residual: static detail the model has not learnt yet is not a transient, and the spread bound
can then be tighter (train.robust.spread) without ignoring it.

Warm-up: for the first `warmup_steps` of a run (train.robust.warmup, a fraction of
max_steps) the weight is the prior itself (1 everywhere in mode `robust`, 1 - M_w in
`dpt+robust`). A model that has not formed the scene's geometry yet explains every pixel
badly, and any rule that drops the worst-fitted pixels then drops the textured, high-contrast
ones, exactly those that would force the geometry; the run settles on a backdrop at the far
bound (measured on fountain-P11, docs/ROBUST.md).

The prior (`dpt+robust`): the dataset's weight 1 - M_w (DPT masks with the depth weighting
of Eq. 7) does not multiply the weight; it sets how strict the evidence is for each pixel.
An unflagged pixel (prior 1) is an inlier up to the q quantile (0.8: the worst 20 % of the
batch are outliers, so a transient the DPT missed is down-weighted); a fully flagged pixel
(prior 0) only up to q_flagged (0.5: it must be fitted better than the batch median, so the
static model must really explain it before it is re-admitted; with a spread k > 0 the flagged
bound below is never under the median, so it, not q_flagged, decides); the spread bound scales with
the prior the same way (k for an unflagged pixel, k / 3 for a flagged one: within one robust
standard deviation of the batch's typical error at k = 3; the default k is 1.5, with
multi-view confirmation on). Mode `robust` is the same
rule with prior 1 everywhere. Training's per-pixel record of the weights it used is
`ema_update` (docs/ROBUST.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

MODES = ("off", "robust", "dpt+robust")
VOTE = 0.5        # the 3x3 vote passes at this share of inliers
EMA_RATE = 0.5    # a pixel's recorded weight moves this far towards each new weight it gets


def warmup_steps(warmup: float, max_steps: int) -> int:
    """The steps trained on the prior alone before the evidence applies: round(warmup x
    max_steps) (train.robust.warmup, a fraction of the run)."""
    return int(round(float(warmup) * int(max_steps)))


def refine_step(refine: float, max_steps: int) -> int | None:
    """The optimiser step after which the evidence is frozen on whole frames (train.robust.refine,
    `refine.py`): round(refine x max_steps), at least 1; None when refine is 0 (off)."""
    if float(refine) <= 0:
        return None
    return max(1, int(round(float(refine) * int(max_steps))))


def late_ignored_share(log: list[dict], max_steps: int, tail: float = 0.25) -> float | None:
    """The share of the drawn pixels training ignored late in a run: 1 - the mean
    "robust_weight" (each logged batch's mean weight) of the log records in the last `tail` of
    max_steps. Every batch is a fresh random draw, so this is unbiased for the pixels training
    saw, unlike the per-pixel record, where pixels never drawn keep their 1. None when no
    record there has the figure. log: metrics.jsonl records ({"step", "robust_weight", ...})."""
    start = (1.0 - tail) * max_steps
    late = [float(r["robust_weight"]) for r in log
            if "robust_weight" in r and float(r.get("step", 0)) > start]
    return 1.0 - sum(late) / len(late) if late else None


def pixel_quantiles(prior: jnp.ndarray, quantile: float, flagged_quantile: float) -> jnp.ndarray:
    """Each pixel's inlier quantile: q_flagged + (q - q_flagged) * prior. prior: [...] in [0, 1]
    -> [...]."""
    return flagged_quantile + (quantile - flagged_quantile) * jnp.clip(prior, 0.0, 1.0)


def quantile_of(values: jnp.ndarray, q: jnp.ndarray) -> jnp.ndarray:
    """Linear-interpolation quantiles (NumPy's default method) of `values` [N] (any shape,
    flattened) at q [...] in [0, 1] -> [...]. Sorts once, then interpolates per q."""
    ranked = jnp.sort(values.reshape(-1))
    pos = jnp.clip(q, 0.0, 1.0) * (ranked.shape[0] - 1)
    return jnp.interp(pos, jnp.arange(ranked.shape[0], dtype=pos.dtype), ranked)


MAD_TO_SIGMA = 1.4826  # the standard deviation of a normal sample is 1.4826 x its MAD
FLAGGED_SPREAD = 1.0 / 3.0  # a fully flagged pixel's spread bound uses this share of k


def pixel_spreads(prior: jnp.ndarray, spread: float) -> jnp.ndarray:
    """Each pixel's k: spread * (FLAGGED_SPREAD + (1 - FLAGGED_SPREAD) * prior), so k for an
    unflagged pixel and k / 3 for a flagged one. prior: [...] -> [...]."""
    return spread * (FLAGGED_SPREAD + (1.0 - FLAGGED_SPREAD) * jnp.clip(prior, 0.0, 1.0))


def spread_thresholds(batch_residuals: jnp.ndarray, prior: jnp.ndarray, spread: float) -> jnp.ndarray:
    """The spread bound, in squared error: (m + k(prior) * MAD_TO_SIGMA * MAD)^2 (k(prior) =
    `pixel_spreads`), with m
    and MAD the median and the median absolute deviation of the root residuals (the RMS colour
    error of each pixel, sqrt of `batch_residuals` [N], any shape, flattened; squared errors
    are too skewed for a median-and-spread rule). prior: [...] in [0, 1] -> [...]."""
    root = jnp.sqrt(jnp.maximum(batch_residuals, 0.0))
    median = quantile_of(root, jnp.asarray(0.5))
    mad = quantile_of(jnp.abs(root - median), jnp.asarray(0.5))
    return (median + pixel_spreads(prior, spread) * MAD_TO_SIGMA * mad) ** 2


def inliers(residuals: jnp.ndarray, thresholds: jnp.ndarray, floor: float) -> jnp.ndarray:
    """residuals, thresholds: [...] -> [...] float 1.0 where residual <= max(threshold, floor)."""
    return (residuals <= jnp.maximum(thresholds, floor)).astype(jnp.float32)


def smooth_3x3(x: jnp.ndarray) -> jnp.ndarray:
    """Mean of x over each pixel's 3x3 neighbourhood within its patch (neighbours outside the
    patch are not counted: a corner averages 4 pixels, an edge 6). x: [P, h, w] (patches, or
    whole frames) -> [P, h, w]."""
    pad = lambda a: jnp.pad(a, ((0, 0), (1, 1), (1, 1)))  # noqa: E731
    h, w = x.shape[-2:]

    def box(a):
        a = pad(a)
        return sum(a[:, i:i + h, j:j + w] for i in range(3) for j in range(3))

    return box(x) / box(jnp.ones_like(x))


def evidence(inlier: jnp.ndarray, patch_share: float) -> jnp.ndarray:
    """The 3x3 vote and the patch rule on an inlier indicator. inlier: [P, p, p] in {0, 1}
    -> [P, p, p] weights in {0, 1}: vote AND (patch kept OR inlier), where vote = smooth_3x3
    >= 1/2 and a patch is kept when at least `patch_share` of its pixels pass the vote: each
    patch is a frame of one tile (`frame_evidence`)."""
    return frame_evidence(inlier, inlier.shape[-1], patch_share)


def frame_evidence(inlier: jnp.ndarray, patch: int, patch_share: float) -> jnp.ndarray:
    """`evidence` on whole frames (train.robust.refine, `refine.py`): the 3x3 vote over each
    pixel's neighbours in its frame (not only in its patch), and the patch rule over the frame
    cut into patch x patch tiles from the top-left corner (the last row and column of tiles
    cut short by the frame's edge, their share taken over the pixels they hold).
    inlier: [T, H, W] in {0, 1} -> [T, H, W] weights in {0, 1}."""
    inlier = jnp.asarray(inlier, jnp.float32)
    frames, height, width = inlier.shape
    vote = (smooth_3x3(inlier) >= VOTE).astype(jnp.float32)
    rows, cols = -(-height // patch), -(-width // patch)
    pad = ((0, 0), (0, rows * patch - height), (0, cols * patch - width))

    def tile_sums(a):
        return jnp.pad(a, pad).reshape(frames, rows, patch, cols, patch).sum(axis=(2, 4))

    share = tile_sums(vote) / tile_sums(jnp.ones_like(vote))
    kept = (share >= patch_share).astype(jnp.float32)
    kept = jnp.repeat(jnp.repeat(kept, patch, axis=1), patch, axis=2)[:, :height, :width]
    return vote * jnp.maximum(kept, inlier)


def pixel_inliers(residuals: jnp.ndarray, prior: jnp.ndarray, batch_residuals: jnp.ndarray,
                  quantile: float, flagged_quantile: float, floor: float, spread: float = 0.0,
                  confirmed: jnp.ndarray | None = None, strict_readmit: bool = False) -> jnp.ndarray:
    """Step 1 of the rule, pixel by pixel: 1.0 where a pixel is an inlier (its residual at most
    its threshold or the floor, or confirmed by another photo), else 0.0. With strict_readmit
    (train.robust.strict_readmit) a flagged pixel (prior < 1/2) needs both: its residual within
    its threshold *and* another photo's confirmation (none without confirmation), so a transient
    the model has begun to fit is not re-admitted on its residual alone.

    residuals, prior: [...] (prior 1 = unflagged, 0 = flagged); batch_residuals: [N] the
    residuals of the whole global batch (all devices), which the thresholds are figures of;
    spread: k of the spread bound (0: the quantile alone); confirmed: None or [...] in {0, 1},
    pixels another photo confirms (`photo_consistency`). Returns [...] in {0, 1}. The weight of
    a scattered ray (train.robust.scattered) is this alone: it has no neighbours to vote.
    """
    thresholds = jnp.maximum(quantile_of(batch_residuals, pixel_quantiles(prior, quantile, flagged_quantile)),
                             spread_thresholds(batch_residuals, prior, spread))
    inlier = inliers(residuals, thresholds, floor)
    either = inlier if confirmed is None else jnp.maximum(inlier, confirmed)
    if not strict_readmit:
        return either
    both = inlier * confirmed if confirmed is not None else jnp.zeros_like(inlier)
    return jnp.where(jnp.asarray(prior) < 0.5, both, either)


def robust_weights(residuals: jnp.ndarray, prior: jnp.ndarray, batch_residuals: jnp.ndarray,
                   quantile: float, flagged_quantile: float, patch_share: float,
                   floor: float, spread: float = 0.0, confirmed: jnp.ndarray | None = None,
                   strict_readmit: bool = False) -> jnp.ndarray:
    """The loss weight of each pixel of the patches (the module docstring's rule): `evidence`
    of `pixel_inliers`. residuals, prior, confirmed: [P, p, p] (this device's patches);
    batch_residuals: [N]. Returns [P, p, p] in {0, 1}."""
    inlier = pixel_inliers(residuals, prior, batch_residuals, quantile, flagged_quantile, floor, spread, confirmed,
                           strict_readmit)
    return evidence(inlier, patch_share)


def batch_weights(residuals: jnp.ndarray, prior: jnp.ndarray, batch_residuals: jnp.ndarray, patch_rays: int,
                  patch: int, quantile: float, flagged_quantile: float, patch_share: float, floor: float,
                  spread: float = 0.0, confirmed: jnp.ndarray | None = None,
                  strict_readmit: bool = False) -> jnp.ndarray:
    """The weights of one device's rays: its first `patch_rays` rays are whole p x p patches
    (patch-major) weighted by `robust_weights`, the rest scattered pixels weighted by
    `pixel_inliers` alone. residuals, prior, confirmed (or None): [B]; batch_residuals: [N].
    Returns [B] in {0, 1}."""
    def split(a):
        return a[:patch_rays].reshape(-1, patch, patch), a[patch_rays:]

    (res_p, res_s), (prior_p, prior_s) = split(residuals), split(prior)
    conf_p, conf_s = split(confirmed) if confirmed is not None else (None, None)
    on_patches = robust_weights(res_p, prior_p, batch_residuals, quantile, flagged_quantile, patch_share,
                                floor, spread, conf_p, strict_readmit).reshape(-1)
    if residuals.shape[0] == patch_rays:
        return on_patches
    on_pixels = pixel_inliers(res_s, prior_s, batch_residuals, quantile, flagged_quantile, floor, spread, conf_s,
                              strict_readmit)
    return jnp.concatenate([on_patches, on_pixels])


def draw_pixels(key, count: int, num_frames: int, height: int, width: int) -> jnp.ndarray:
    """Flat pixel ids (frame * H * W + row * W + col) of `count` pixels drawn uniformly over the
    frames (train.robust.scattered's scattered rays). Returns [count] int32."""
    return jax.random.randint(key, (count,), 0, num_frames * height * width).astype(jnp.int32)


def device_layout(patch_rays: int, scattered: int, num_devices: int) -> jnp.ndarray:
    """The order in which the devices take a batch of `patch_rays` patch rays (patch-major) then
    `scattered` scattered rays: each device's share of whole patches, then its share of the
    scattered rays. Returns [patch_rays + scattered] int32 indices into that batch (the identity
    for one device or no scattered rays). Both counts must divide by num_devices."""
    per_patch, per_scattered = patch_rays // num_devices, scattered // num_devices
    order = [jnp.concatenate([jnp.arange(d * per_patch, (d + 1) * per_patch),
                              patch_rays + jnp.arange(d * per_scattered, (d + 1) * per_scattered)])
             for d in range(num_devices)]
    return jnp.concatenate(order).astype(jnp.int32)


def patch_span(patch: int, stride: int = 1) -> int:
    """The side in pixels that a p x p patch of pixels `stride` apart covers: (p - 1) stride + 1."""
    return (int(patch) - 1) * int(stride) + 1


def draw_patches(key, num_patches: int, num_frames: int, height: int, width: int, patch: int,
                 stride: int = 1) -> jnp.ndarray:
    """Flat pixel ids (frame * H * W + row * W + col) of `num_patches` random p x p patches lying
    inside the frames, patch-major; a patch's pixels are `stride` apart along rows and columns
    (train.robust.patch_stride; 1 = adjacent). Returns [num_patches * p * p] int32."""
    k_frame, k_row, k_col = jax.random.split(key, 3)
    span = patch_span(patch, stride)
    frame = jax.random.randint(k_frame, (num_patches,), 0, num_frames)
    row0 = jax.random.randint(k_row, (num_patches,), 0, height - span + 1)
    col0 = jax.random.randint(k_col, (num_patches,), 0, width - span + 1)
    offs = jnp.arange(patch) * stride
    rows = row0[:, None, None] + offs[None, :, None]
    cols = col0[:, None, None] + offs[None, None, :]
    ids = frame[:, None, None] * (height * width) + rows * width + cols
    return ids.reshape(-1).astype(jnp.int32)


def ema_update(record: jnp.ndarray, ids: jnp.ndarray, weights: jnp.ndarray) -> jnp.ndarray:
    """Moves the recorded weight of the pixels `ids` EMA_RATE of the way to `weights`.
    record: [T, H, W]; ids: [N] flat pixel ids; weights: [N]. Returns [T, H, W]. A pixel drawn
    twice in one batch (overlapping patches) takes one of its two updates."""
    flat = record.reshape(-1)
    new = flat[ids] + EMA_RATE * (weights - flat[ids])
    return flat.at[ids].set(new).reshape(record.shape)
