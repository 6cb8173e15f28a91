"""Image quality metrics: PSNR, SSIM, MS-SSIM (and LPIPS via `jaxnerf_grid.eval.lpips`).

Every metric takes images `[..., H, W, C]` float in [0, 1] (data range 1) and returns one value
per leading index (a scalar for a single `[H, W, C]` image). All functions are pure JAX and
jit-able; shape-dependent choices (number of MS-SSIM scales) are made from static shapes.

SSIM is the formula the NeRF literature uses (Wang et al. 2004 with a Gaussian window of size 11,
sigma 1.5, K1 = 0.01, K2 = 0.03), computed as `pytorch_msssim` does: separable 1-D Gaussian
filtering *without padding* ("valid"), so the SSIM map covers the `(H-10) x (W-10)` pixels whose
window lies inside the image; per-channel mean, then mean over channels. This equals
`skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1)`: skimage filters with reflect
padding but then crops (win_size - 1) // 2 = 5 pixels from every border before averaging, which
leaves exactly the valid positions.

MS-SSIM follows the TF / pytorch_msssim algorithm: at each scale the contrast-structure term
`cs` (relu-clamped) is taken, then both images are average-pooled 2x2; at the last scale the
full SSIM (relu-clamped) is taken; the result is prod_i value_i ** weight_i per channel, then the
channel mean. Odd sizes are pooled as `torch.nn.functional.avg_pool2d(kernel_size=2,
padding=1)` does (one zero row/column on each side, divisor always 4), to match pytorch_msssim.
(TF's `tf.image.ssim_multiscale` instead repeats the last row/column (symmetric padding at the
end), so the two references, and we with them, differ slightly when a scale has an odd side;
for even sides at every scale, e.g. 512 x 512, they should agree; TF is not installed here, so
that is not tested.)
Five scales need min(H, W) > 10 * 2**4 = 160. For smaller images we use the largest number of
scales n with min(H, W) > 10 * 2**(n-1) and the first n standard weights renormalised to sum to
one; `ms_ssim_scales(h, w)` tells how many, and `evaluate_image` reports it.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.eval import lpips as _lpips

WIN_SIZE = 11
WIN_SIGMA = 1.5
K1 = 0.01
K2 = 0.03
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)


def _check_pair(pred, target, name: str):
    if pred.shape != target.shape:
        raise ValueError(f"{name}: pred and target shapes differ: {pred.shape} vs {target.shape}")
    if pred.ndim < 3:
        raise ValueError(f"{name}: expected images [..., H, W, C], got shape {pred.shape}")


def psnr(pred, target, mask=None):
    """Peak signal-to-noise ratio in dB for data range 1.

    pred, target: [..., H, W, C] float in [0, 1].
    mask: optional [..., H, W] non-negative pixel weights (broadcast against the leading axes);
      the MSE is then the weighted mean over pixels (channels averaged), for region PSNR.
    Returns [...] (a scalar for one image). Identical images give +inf; a mask with zero total
    weight gives nan.
    """
    pred = jnp.asarray(pred, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    _check_pair(pred, target, "psnr")
    sq = jnp.mean((pred - target) ** 2, axis=-1)  # [..., H, W]
    if mask is None:
        mse = jnp.mean(sq, axis=(-2, -1))
    else:
        w = jnp.broadcast_to(jnp.asarray(mask, jnp.float32), sq.shape)
        mse = jnp.sum(w * sq, axis=(-2, -1)) / jnp.sum(w, axis=(-2, -1))
    return -10.0 * jnp.log10(mse)


def gaussian_window(size: int = WIN_SIZE, sigma: float = WIN_SIGMA) -> np.ndarray:
    """Normalised 1-D Gaussian window, centred: [size] float32 (static constant)."""
    x = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).astype(np.float32)


def _shifted_sum(x, win, axis: int):
    """'Valid' 1-D correlation along `axis`: sum_i win[i] * x[i : i + n - k + 1] (a fori_loop
    over the k taps keeps XLA compile time small; the result does not depend on that choice).

    x: [..., n, ...]; win: [k] -> [..., n - k + 1, ...].
    """
    k = win.shape[0]
    n_out = x.shape[axis] - k + 1
    out_shape = x.shape[:axis] + (n_out,) + x.shape[axis + 1:]

    def tap(i, acc):
        return acc + win[i] * jax.lax.dynamic_slice_in_dim(x, i, n_out, axis=axis)

    return jax.lax.fori_loop(0, k, tap, jnp.zeros(out_shape, x.dtype))


def _filter_valid(x, win: np.ndarray):
    """Separable 'valid' filtering of the two spatial axes (no padding).

    x: [..., H, W, C]; win: [k] -> [..., H-k+1, W-k+1, C].
    """
    win = jnp.asarray(win, x.dtype)
    return _shifted_sum(_shifted_sum(x, win, x.ndim - 3), win, x.ndim - 2)


def _ssim_and_cs(x, y):
    """Per-channel SSIM and contrast-structure means.

    x, y: [..., H, W, C] with H, W >= 11 -> (ssim [..., C], cs [..., C]).
    """
    c = x.shape[-1]
    c1 = K1**2
    c2 = K2**2
    stats = _filter_valid(jnp.concatenate([x, y, x * x, y * y, x * y], axis=-1), gaussian_window())
    mu1, mu2, xx, yy, xy = (stats[..., i * c:(i + 1) * c] for i in range(5))
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1 = xx - mu1_sq
    s2 = yy - mu2_sq
    s12 = xy - mu12
    cs_map = (2.0 * s12 + c2) / (s1 + s2 + c2)
    ssim_map = (2.0 * mu12 + c1) / (mu1_sq + mu2_sq + c1) * cs_map
    return jnp.mean(ssim_map, axis=(-3, -2)), jnp.mean(cs_map, axis=(-3, -2))


def _check_min_size(shape, name: str):
    h, w = shape[-3], shape[-2]
    if min(h, w) < WIN_SIZE:
        raise ValueError(f"{name}: image {h}x{w} is smaller than the {WIN_SIZE}-pixel SSIM window")


def ssim(pred, target):
    """SSIM (Gaussian window 11, sigma 1.5, data range 1, valid filtering), channel mean.

    pred, target: [..., H, W, C] float in [0, 1], H, W >= 11. Returns [...].
    """
    pred = jnp.asarray(pred, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    _check_pair(pred, target, "ssim")
    _check_min_size(pred.shape, "ssim")
    return _ssim_core(pred, target)


@jax.jit
def _ssim_core(pred, target):
    """pred, target: [..., H, W, C] -> [...]."""
    s, _ = _ssim_and_cs(pred, target)
    return jnp.mean(s, axis=-1)


def ms_ssim_scales(h: int, w: int) -> int:
    """Number of MS-SSIM scales used for an h x w image: the largest n <= 5 with
    min(h, w) > 10 * 2**(n-1) (so the coarsest scale still holds an 11-pixel window)."""
    side = min(int(h), int(w))
    if side < WIN_SIZE:
        raise ValueError(f"ms_ssim: image {h}x{w} is smaller than the {WIN_SIZE}-pixel SSIM window")
    n = 1
    while n < len(MS_SSIM_WEIGHTS) and side > (WIN_SIZE - 1) * 2**n:
        n += 1
    return n


def ms_ssim_weights(num_scales: int) -> tuple[float, ...]:
    """Scale weights, finest first: the standard five for 5 scales, else the first
    `num_scales` of them renormalised to sum to one."""
    if not 1 <= num_scales <= len(MS_SSIM_WEIGHTS):
        raise ValueError(f"ms_ssim: num_scales must be in 1..5, got {num_scales}")
    if num_scales == len(MS_SSIM_WEIGHTS):
        return MS_SSIM_WEIGHTS
    w = MS_SSIM_WEIGHTS[:num_scales]
    total = math.fsum(w)
    return tuple(v / total for v in w)


def _avg_pool2(x):
    """2x2 average pooling as torch avg_pool2d(kernel_size=2, padding=H%2 / W%2).

    x: [..., H, W, C] -> [..., ceil(H/2), ceil(W/2), C]. An odd axis gets one zero on each side
    (count_include_pad: the divisor stays 4); the trailing pad is never reached.
    """
    h, w = x.shape[-3], x.shape[-2]
    ph, pw = h % 2, w % 2
    pad = [(0, 0)] * (x.ndim - 3) + [(ph, ph), (pw, pw), (0, 0)]
    x = jnp.pad(x, pad)
    oh, ow = (h + 2 * ph - 2) // 2 + 1, (w + 2 * pw - 2) // 2 + 1
    x = x[..., : 2 * oh, : 2 * ow, :]
    lead = x.shape[:-3]
    x = x.reshape(lead + (oh, 2, ow, 2, x.shape[-1]))
    return jnp.mean(x, axis=(-4, -2))


def ms_ssim(pred, target, num_scales: int | None = None):
    """Multi-scale SSIM (TF / pytorch_msssim algorithm, data range 1).

    pred, target: [..., H, W, C] float in [0, 1].
    num_scales: static int in 1..5; None = `ms_ssim_scales(H, W)` (5 when min(H, W) > 160).
      Fewer than 5 scales use the first weights renormalised (`ms_ssim_weights`).
    Returns [...].
    """
    pred = jnp.asarray(pred, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    _check_pair(pred, target, "ms_ssim")
    h, w = pred.shape[-3], pred.shape[-2]
    max_scales = ms_ssim_scales(h, w)
    if num_scales is None:
        num_scales = max_scales
    if num_scales > max_scales:
        raise ValueError(
            f"ms_ssim: {num_scales} scales need min(H, W) > {(WIN_SIZE - 1) * 2 ** (num_scales - 1)},"
            f" image is {h}x{w} (at most {max_scales} scales)")
    return _ms_ssim_core(pred, target, num_scales)


@functools.partial(jax.jit, static_argnums=2)
def _ms_ssim_core(pred, target, num_scales: int):
    """pred, target: [..., H, W, C] -> [...]."""
    weights = ms_ssim_weights(num_scales)
    x, y = pred, target
    terms = []
    for i, wt in enumerate(weights):
        s, cs = _ssim_and_cs(x, y)
        if i < num_scales - 1:
            val = jax.nn.relu(cs)
            x, y = _avg_pool2(x), _avg_pool2(y)
        else:
            val = jax.nn.relu(s)
        terms.append(val ** wt)  # [..., C]
    prod = functools.reduce(lambda a, b: a * b, terms)
    return jnp.mean(prod, axis=-1)


_psnr_jit = jax.jit(psnr)


def evaluate_image(pred, target, lpips_params=None, mask=None) -> dict:
    """All metrics for one image pair, as plain Python numbers.

    pred, target: [H, W, 3] float in [0, 1].
    lpips_params: parameters from `jaxnerf_grid.eval.lpips.load_lpips`, or None; with None the
      "lpips" entry is None (metric unavailable), never a number.
    mask: optional [H, W] pixel weights; adds "psnr_masked" (PSNR over the weighted pixels).
    Returns {"psnr", "ssim", "ms_ssim", "ms_ssim_scales", "lpips"[, "psnr_masked"]}.
    """
    pred = jnp.asarray(pred, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    _check_pair(pred, target, "evaluate_image")
    if pred.ndim != 3:
        raise ValueError(f"evaluate_image: expected one image [H, W, C], got shape {pred.shape}")
    n = ms_ssim_scales(pred.shape[0], pred.shape[1])
    out = {
        "psnr": float(_psnr_jit(pred, target)),
        "ssim": float(ssim(pred, target)),
        "ms_ssim": float(ms_ssim(pred, target, num_scales=n)),
        "ms_ssim_scales": n,
        "lpips": None,
    }
    if lpips_params is not None:
        out["lpips"] = float(_lpips.lpips_jit(lpips_params, pred, target))
    if mask is not None:
        out["psnr_masked"] = float(_psnr_jit(pred, target, jnp.asarray(mask, jnp.float32)))
    return out
