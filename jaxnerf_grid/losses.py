"""Losses: per-ray terms, and their weighted mean with weights normalised by their sum.

Every loss here is first a per-ray value l_r; the batch loss is

    L = sum_r w_r l_r / W,     W = sum of the weights over the *global* batch

where w_r = 1 - M_w for "ours" (the foreground-exclusion weight, 0 = never a target) and 1
for the baselines. Passing W explicitly (the trainer psums it over devices) makes the loss of a
batch split over devices exactly the sum of the per-device losses, so data-parallel gradients
equal single-device ones.

NeRF-W (Martin-Brualla et al. 2021, Eq. 13), per ray of the fine pass:
    |C - C_hat|^2 / (2 beta^2) + log(beta^2) / 2 + lambda_u * mean_k sigma_transient_k
with beta = sum_k w_t,k beta_k + beta_min; here |.|^2 is the mean over the 3 channels (the
same scale as the MSE used elsewhere). The coarse pass (a plain static field) uses the MSE.
"""

from __future__ import annotations

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
                 lambda_u: float = 0.01, coarse_weight: float = 1.0) -> dict:
    """Per-ray loss of a models.render_rays output.

    outputs: {"coarse": {...}, optional "fine": {...}}; target: [B, 3].
    Returns {"loss": [B] total, "mse_coarse": [B], optional "mse_fine": [B]}: total =
    coarse_weight * mse_coarse + (fine term: NeRF-W loss when use_transient, else the MSE).
    """
    mse_coarse = squared_error(outputs["coarse"]["rgb"], target)
    out = {"mse_coarse": mse_coarse, "loss": coarse_weight * mse_coarse}
    if "fine" in outputs:
        fine = outputs["fine"]
        mse_fine = squared_error(fine["rgb"], target)
        out["mse_fine"] = mse_fine
        if use_transient:
            term = nerfw_ray_loss(fine["rgb"], target, fine["beta"], fine["transient_sigma_mean"], lambda_u)
        else:
            term = mse_fine
        out["loss"] = out["loss"] + term
    return out


def mse_to_psnr(mse) -> jnp.ndarray:
    """PSNR in dB of a mean squared error for data range 1."""
    return -10.0 * jnp.log10(jnp.maximum(jnp.asarray(mse, jnp.float32), 1e-10))
