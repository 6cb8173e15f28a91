"""Small pure layers shared by the DPT stages (NHWC images, plain-dict parameters).

Conventions: a linear layer is {"w": [in, out], "b": [out]}; a conv is {"w": [kh, kw, in, out],
"b": [out]} (bias optional); layer / batch norm is {"scale", "bias"} (+ "mean", "var").
Every padding is explicit (torch's `padding=1` is ((1, 1), (1, 1)), which is not "SAME" for
stride 2), GELU is the exact erf form, and bilinear resizing is written out (no antialiasing,
both corner conventions) so it matches torch's `interpolate` bit for bit up to float rounding.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def gelu(x):
    """Exact GELU, x * Phi(x) (jax.nn.gelu defaults to the tanh approximation)."""
    return jax.nn.gelu(x, approximate=False)


def linear(p: dict, x):
    """x: [..., in] -> [..., out]."""
    y = x @ p["w"]
    return y + p["b"] if "b" in p else y


def layer_norm(p: dict, x, eps: float):
    """Normalises the last axis. x: [..., C]; p: {"scale": [C], "bias": [C]}."""
    mean = jnp.mean(x, axis=-1, keepdims=True)
    var = jnp.mean(jnp.square(x - mean), axis=-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + eps) * p["scale"] + p["bias"]


def batch_norm(p: dict, x, eps: float = 1e-5):
    """Inference-mode batch norm with running statistics. x: [..., C]."""
    inv = p["scale"] * jax.lax.rsqrt(p["var"] + eps)
    return (x - p["mean"]) * inv + p["bias"]


def conv2d(p: dict, x, stride: int = 1, padding: int = 0):
    """Cross-correlation as torch.nn.Conv2d. x: [B, H, W, Cin]; p["w"]: [kh, kw, Cin, Cout]."""
    y = jax.lax.conv_general_dilated(
        x, p["w"].astype(x.dtype), window_strides=(stride, stride),
        padding=((padding, padding), (padding, padding)),
        dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return y + p["b"] if "b" in p else y


def conv_transpose_nonoverlap(p: dict, x):
    """torch.nn.ConvTranspose2d with kernel_size == stride == k and padding 0 (the patches do
    not overlap, so it is an outer product per pixel).

    x: [B, H, W, Cin]; p["w"]: [Cin, k, k, Cout]; returns [B, k*H, k*W, Cout].
    """
    b, h, w, _ = x.shape
    k = p["w"].shape[1]
    y = jnp.einsum("bhwi,iklo->bhkwlo", x, p["w"])
    y = y.reshape(b, h * k, w * k, -1)
    return y + p["b"] if "b" in p else y


def _source_index(out_size: int, in_size: int, align_corners: bool):
    """Static 1-D interpolation table as torch computes it: (i0, i1, frac), each [out_size]."""
    dst = np.arange(out_size, dtype=np.float64)
    if align_corners:
        scale = (in_size - 1) / (out_size - 1) if out_size > 1 else 0.0
        src = dst * scale
    else:
        src = (dst + 0.5) * (in_size / out_size) - 0.5
        src = np.maximum(src, 0.0)
    i0 = np.minimum(np.floor(src).astype(np.int32), in_size - 1)
    i1 = np.minimum(i0 + 1, in_size - 1)
    frac = (src - i0).astype(np.float32)
    return i0, i1, frac


def resize_bilinear(x, out_h: int, out_w: int, align_corners: bool):
    """Bilinear resize without antialiasing, as torch's interpolate(mode="bilinear").

    x: [B, H, W, C] -> [B, out_h, out_w, C]. `align_corners=True` maps corner pixel centres to
    corner pixel centres ((in-1)/(out-1) scale); False uses half-pixel centres, clamped at 0.
    """
    _, h, w, _ = x.shape
    if (h, w) == (out_h, out_w):
        return x  # both conventions are the identity at equal size
    # two taps per output row / column (gathers, not dense interpolation matrices: those cost
    # O(out * in) per line, ~15 GFLOP for DPT-base's 150-class head at 384 px)
    i0, i1, f = _source_index(out_h, h, align_corners)
    f = jnp.asarray(f, x.dtype)[None, :, None, None]
    x = jnp.take(x, i0, axis=1) * (1 - f) + jnp.take(x, i1, axis=1) * f
    j0, j1, g = _source_index(out_w, w, align_corners)
    g = jnp.asarray(g, x.dtype)[None, None, :, None]
    return jnp.take(x, j0, axis=2) * (1 - g) + jnp.take(x, j1, axis=2) * g


def up2(x):
    """x2 align-corners bilinear upsampling (DPT's fusion and head upsampling). [B, h, w, C]."""
    return resize_bilinear(x, 2 * x.shape[1], 2 * x.shape[2], align_corners=True)


def _shifted_taps(out_size: int, in_size: int, kernel: int, padding: int):
    """Interpolation table of an upsampled line seen through a kernel: for output position i and
    tap t the upsampled sample i + t - padding, as two source indices and weights ([out, k] each;
    weight 0 where the sample falls in the zero padding)."""
    i0, i1, frac = _source_index(out_size, in_size, align_corners=True)
    pos = np.arange(out_size)[:, None] + np.arange(kernel)[None, :] - padding     # [out, k]
    valid = (pos >= 0) & (pos < out_size)
    pos = np.clip(pos, 0, out_size - 1)
    w1 = np.where(valid, frac[pos], 0.0).astype(np.float32)
    w0 = np.where(valid, 1.0 - frac[pos], 0.0).astype(np.float32)
    return i0[pos], i1[pos], w0, w1


def conv2d_upsampled(p: dict, z, out_h: int, out_w: int, padding: int):
    """`conv2d(p, resize_bilinear(z, out_h, out_w, align_corners=True), padding=padding)` (stride 1,
    square odd kernel), computed without forming the upsampled map.

    Both steps are linear, so each kernel tap's channel mixing is applied at the input resolution
    (one [h*w, Cin] x [Cin, k*k*Cout] matmul) and the taps are then interpolated to their shifted
    output positions and summed, rows then columns (two source samples per tap and axis). For a
    x2 upsampling that is a quarter of the direct multiply-adds plus an elementwise pass.

    z: [B, h, w, Cin]; p["w"]: [k, k, Cin, Cout] -> [B, out_h, out_w, Cout].
    """
    k = p["w"].shape[0]
    taps = jnp.einsum("bhwc,yxco->bhwyxo", z, p["w"].astype(z.dtype))          # [B, h, w, k, k, Cout]
    r0, r1, rw0, rw1 = _shifted_taps(out_h, z.shape[1], k, padding)
    rows: Any = 0.0
    for dy in range(k):  # -> [B, out_h, w, k(dx), Cout]
        t = taps[:, :, :, dy]
        rows = rows + (jnp.take(t, r0[:, dy], axis=1) * rw0[None, :, dy, None, None, None]
                       + jnp.take(t, r1[:, dy], axis=1) * rw1[None, :, dy, None, None, None])
    c0, c1, cw0, cw1 = _shifted_taps(out_w, z.shape[2], k, padding)
    out = 0.0
    for dx in range(k):  # -> [B, out_h, out_w, Cout]
        t = rows[:, :, :, dx]
        out = out + (jnp.take(t, c0[:, dx], axis=2) * cw0[None, None, :, dx, None]
                     + jnp.take(t, c1[:, dx], axis=2) * cw1[None, None, :, dx, None])
    return out + p["b"] if "b" in p else out


# ----- initialisers (for training from scratch; imported checkpoints replace all of these) -----
# Host-side numpy: `key` is a np.random.Generator (`rng(seed)`), or SHAPES to get zero-cost
# placeholders of the right shapes (used to check checkpoint shapes without drawing numbers).
# (Drawing with jax.random costs an XLA compile per call site: ~20 s for a small DPT on CPU.)

class _ShapeOnly:
    def spawn(self, n):
        return [self] * n


SHAPES = _ShapeOnly()


def rng(seed) -> np.random.Generator:
    """A numpy Generator from an int seed, a sequence of ints, or a jax PRNG key."""
    if isinstance(seed, np.random.Generator):
        return seed
    if hasattr(seed, "dtype") and jax.dtypes.issubdtype(seed.dtype, jax.dtypes.prng_key):
        seed = jax.random.key_data(seed)
    return np.random.default_rng(np.asarray(seed, np.uint32).ravel().tolist() if np.ndim(seed) else int(seed))


def split(key, n: int) -> list:
    return key.spawn(n)


def normal(key, shape, std: float = 1.0) -> np.ndarray:
    if isinstance(key, _ShapeOnly):
        return np.broadcast_to(np.float32(0), shape)
    return (std * key.standard_normal(shape)).astype(np.float32)


def init_linear(key, n_in: int, n_out: int, bias: bool = True, std: float = 0.02) -> dict:
    p = {"w": normal(key, (n_in, n_out), std)}
    if bias:
        p["b"] = np.zeros((n_out,), np.float32)
    return p


def init_conv(key, k: int, n_in: int, n_out: int, bias: bool = True) -> dict:
    """He-normal conv kernel [k, k, n_in, n_out]."""
    p = {"w": normal(key, (k, k, n_in, n_out), float(np.sqrt(2.0 / (k * k * n_in))))}
    if bias:
        p["b"] = np.zeros((n_out,), np.float32)
    return p


def init_norm(n: int, running: bool = False) -> dict:
    p = {"scale": np.ones((n,), np.float32), "bias": np.zeros((n,), np.float32)}
    if running:
        p["mean"] = np.zeros((n,), np.float32)
        p["var"] = np.ones((n,), np.float32)
    return p
