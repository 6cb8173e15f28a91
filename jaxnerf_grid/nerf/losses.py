"""Losses: per-ray terms, and their weighted mean with weights normalised by their sum.

Every loss here is first a per-ray value l_r; the batch loss is

    L = sum_r w_r l_r / W,     W = sum of the weights over the *global* batch

where w_r = 1 - M_w for "ours" (the foreground-exclusion weight, 0 = never a target) and 1
for the baselines. Passing W explicitly (the trainer psums it over devices) makes the loss of a
batch split over devices exactly the sum of the per-device losses, so data-parallel gradients
equal single-device ones.

NeRF-W (Martin-Brualla et al. 2021, Eq. 13), per ray of the final pass:
    |C - C_hat|^2 / (2 beta^2) + log(beta^2) / 2 + lambda_u * mean_k sigma_transient_k
with beta = sum_k w_t,k beta_k + beta_min; here |.|^2 is the mean over the 3 channels (the
same scale as the MSE used elsewhere). Earlier levels that render colour (plain static fields)
use the MSE.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def squared_error(rgb: jnp.ndarray, target: jnp.ndarray) -> jnp.ndarray:
    """Mean over channels of the squared error. rgb, target: [..., 3] -> [...]."""
    return jnp.mean(jnp.square(rgb - target), axis=-1)


def nerfw_ray_loss(rgb: jnp.ndarray, target: jnp.ndarray, beta: jnp.ndarray,
                   transient_sigma_mean: jnp.ndarray, lambda_u: float) -> jnp.ndarray:
    """NeRF-W's per-ray loss. rgb, target: [..., 3]; beta (> 0), transient_sigma_mean: [...].

    Returns [...]: squared_error / (2 beta^2) + log(beta^2) / 2 + lambda_u * sigma_t mean.
    """
    return (squared_error(rgb, target) / (2.0 * jnp.square(beta)) + jnp.log(jnp.square(beta)) / 2.0
            + lambda_u * transient_sigma_mean)


def weighted_mean(per_ray: jnp.ndarray, weights: jnp.ndarray, total_weight=None) -> jnp.ndarray:
    """sum(w * l) / W. per_ray, weights: [B]; total_weight: scalar W (default sum(weights)).

    A zero total gives 0 (no valid target), never NaN.
    """
    total = jnp.sum(weights) if total_weight is None else jnp.asarray(total_weight, per_ray.dtype)
    return jnp.sum(weights * per_ray) / jnp.maximum(total, 1e-12)


def per_ray_loss(outputs: dict, target: jnp.ndarray, use_transient: bool = False,
                 lambda_u: float = 0.01, level_weight: float = 1.0, interlevel_weight: float = 1.0,
                 distortion_weight: float = 0.0) -> dict:
    """Per-ray loss of a models.render_rays output.

    outputs: {"levels": [{"s_edges", "weights"[, "rgb"]}, ...], "final": {...}} (the last level
    is the final pass); target: [B, 3].
    Returns {"loss": [B] total, "mse": [B] of the final pass, "mse_levels": [[B] per earlier
    level with colour], "interlevel", "distortion": [B] where they apply}:
    total = level_weight * sum of mse_levels + (final term: NeRF-W loss when use_transient,
    else the MSE) + interlevel_weight * sum over the earlier levels without colour of
    interlevel_ray_loss against the final pass + distortion_weight * distortion_ray_loss of the
    final pass (in s).
    """
    final, earlier = outputs["final"], outputs["levels"][:-1]
    out = {"loss": jnp.zeros(target.shape[:-1], target.dtype), "mse_levels": []}
    for lvl in earlier:
        if "rgb" in lvl:
            mse = squared_error(lvl["rgb"], target)
            out["mse_levels"].append(mse)
            out["loss"] = out["loss"] + level_weight * mse
    out["mse"] = squared_error(final["rgb"], target)
    if use_transient:
        term = nerfw_ray_loss(final["rgb"], target, final["beta"], final["transient_sigma_mean"], lambda_u)
    else:
        term = out["mse"]
    out["loss"] = out["loss"] + term
    proposals = [lvl for lvl in earlier if "rgb" not in lvl]
    if proposals:
        inter = sum(interlevel_ray_loss(final["s_edges"], final["weights"], p["s_edges"], p["weights"])
                    for p in proposals)
        out["interlevel"] = inter
        out["loss"] = out["loss"] + interlevel_weight * inter
    if distortion_weight > 0:
        dist = distortion_ray_loss(final["s_edges"], final["weights"])
        out["distortion"] = dist
        out["loss"] = out["loss"] + distortion_weight * dist
    return out


def mse_to_psnr(mse) -> jnp.ndarray:
    """PSNR in dB of a mean squared error for data range 1."""
    return -10.0 * jnp.log10(jnp.maximum(jnp.asarray(mse, jnp.float32), 1e-10))


# --------------------------------------------------------------------------- proposal / distortion


def _overlap_mass(edges_main: jnp.ndarray, edges_prop: jnp.ndarray, weights_prop: jnp.ndarray) -> jnp.ndarray:
    """For each main interval, the total proposal weight of the proposal intervals that
    overlap it (share more than a point: p_lo < b and p_hi > a for main interval [a, b]).

    edges_main: [n + 1]; edges_prop: [m + 1]; weights_prop: [m] -> [n]. One ray (vmap it).
    """
    cum = jnp.concatenate([jnp.zeros((1,), weights_prop.dtype), jnp.cumsum(weights_prop)])
    m = weights_prop.shape[-1]
    lo, hi = edges_main[:-1], edges_main[1:]
    # first proposal interval j with p_hi = edges_prop[j + 1] > a
    first = jnp.clip(jnp.searchsorted(edges_prop, lo, side="right") - 1, 0, m)
    # one past the last interval j with p_lo = edges_prop[j] < b
    stop = jnp.clip(jnp.searchsorted(edges_prop, hi, side="left"), 0, m)
    return jnp.maximum(cum[stop] - cum[first], 0.0)


def interlevel_ray_loss(edges_main: jnp.ndarray, weights_main: jnp.ndarray, edges_prop: jnp.ndarray,
                        weights_prop: jnp.ndarray, eps: float = 1e-7) -> jnp.ndarray:
    """mip-NeRF 360's proposal loss (Barron et al. 2022, Eq. 13), per ray.

    L = sum_i max(0, w_i - bound_i)^2 / (w_i + eps), where bound_i is the proposal weight
    overlapping main interval i. The main weights are held fixed (stop-gradient): only the
    proposal field learns to bound them. Edges are in s (both passes share [0, 1]).
    edges_main: [..., n + 1]; weights_main: [..., n]; edges_prop: [..., m + 1];
    weights_prop: [..., m]. Returns [...].
    """
    w = jax.lax.stop_gradient(weights_main)
    e_main = jax.lax.stop_gradient(edges_main)
    e_prop = jax.lax.stop_gradient(edges_prop)
    batch = w.shape[:-1]
    flat = lambda a: a.reshape(-1, a.shape[-1])  # noqa: E731
    bound = jax.vmap(_overlap_mass)(flat(e_main), flat(e_prop), flat(weights_prop)).reshape(w.shape)
    return jnp.sum(jnp.square(jnp.maximum(w - bound, 0.0)) / (w + eps), axis=-1).reshape(batch)


def distortion_ray_loss(edges: jnp.ndarray, weights: jnp.ndarray) -> jnp.ndarray:
    """mip-NeRF 360's distortion loss (Eq. 15), per ray, in O(n):

    L = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (e_{i+1} - e_i),   m_i bin midpoints.

    With sorted midpoints, sum_{i,j} w_i w_j |m_i - m_j| = 2 sum_i w_i (m_i W_<i - S_<i) where
    W_<i and S_<i are the sums of w and w m over the bins before i. Computed in the normalised
    s space so near and far floaters count alike. edges: [..., n + 1]; weights: [..., n] -> [...].
    """
    mid = 0.5 * (edges[..., 1:] + edges[..., :-1])
    width = edges[..., 1:] - edges[..., :-1]
    w_before = jnp.cumsum(weights, axis=-1) - weights
    wm = weights * mid
    wm_before = jnp.cumsum(wm, axis=-1) - wm
    inter = 2.0 * jnp.sum(weights * (mid * w_before - wm_before), axis=-1)
    intra = jnp.sum(jnp.square(weights) * width, axis=-1) / 3.0
    return inter + intra
