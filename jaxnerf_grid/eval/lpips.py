"""LPIPS (Zhang et al. 2018, v0.1, AlexNet trunk) in pure JAX.

The distance between images x0, x1 in [0, 1]:
  1. map to [-1, 1] (2x - 1), then the LPIPS "scaling layer" (x - shift) / scale per channel;
  2. AlexNet features after relu1..relu5 (conv1 11x11/4 pad 2, maxpool 3/2, conv2 5x5 pad 2,
     maxpool 3/2, conv3..conv5 3x3 pad 1; the final maxpool is not used);
  3. each feature vector normalised to unit length over channels (eps 1e-10 on the norm);
  4. squared difference, a 1x1 linear layer without bias (non-negative learned weights
     `lin_l`), spatial mean, sum over the five layers.

No weights ship with this package and nothing is downloaded. `load_lpips(path)` reads a
user-supplied .npz (written by `scripts/convert_lpips_weights.py` from the `lpips` package with
torchvision's ImageNet AlexNet); with no path, or a path that does not exist, it returns None and
the metric is reported as unavailable (`metrics.evaluate_image` gives "lpips": None).

Weights file (.npz) keys, torch layouts, float32:
  conv{k}.weight  [out, in, kh, kw]   for k = 1..5: [64,3,11,11] [192,64,5,5] [384,192,3,3]
                                                    [256,384,3,3] [256,256,3,3]
  conv{k}.bias    [out]
  lin{l}.weight   [1, C_l, 1, 1]      for l = 0..4, C = 64, 192, 384, 256, 256
  format          optional 0-d string "jaxnerf-grid-lpips-alex-v0.1"
Parameters in memory are the plain pytree {"conv1": {"w": [O,I,kh,kw], "b": [O]}, ...,
"lin": ([64], [192], [384], [256], [256])}.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.util.io import DataError, load_error_reason

FORMAT = "jaxnerf-grid-lpips-alex-v0.1"
# name, out channels, in channels, kernel, stride, padding
CONVS = (
    ("conv1", 64, 3, 11, 4, 2),
    ("conv2", 192, 64, 5, 1, 2),
    ("conv3", 384, 192, 3, 1, 1),
    ("conv4", 256, 384, 3, 1, 1),
    ("conv5", 256, 256, 3, 1, 1),
)
LIN_CHANNELS = (64, 192, 384, 256, 256)
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
MIN_SIZE = 31  # smallest side for which relu5 is non-empty


def expected_shapes() -> dict[str, tuple[int, ...]]:
    """Key -> shape of every array a weights file must hold."""
    shapes: dict[str, tuple[int, ...]] = {}
    for name, o, i, k, _, _ in CONVS:
        shapes[f"{name}.weight"] = (o, i, k, k)
        shapes[f"{name}.bias"] = (o,)
    for l, c in enumerate(LIN_CHANNELS):
        shapes[f"lin{l}.weight"] = (1, c, 1, 1)
    return shapes


def params_from_arrays(arrays, source: str = "<arrays>") -> dict:
    """Validated parameter pytree from a mapping key -> array (keys as in the module docstring).

    Raises DataError naming `source` for a missing key or a wrong shape.
    """
    for key, shape in expected_shapes().items():
        if key not in arrays:
            raise DataError(f"{source}: LPIPS weights lack key '{key}'")
        got = tuple(np.shape(arrays[key]))
        if got != shape:
            raise DataError(f"{source}: LPIPS key '{key}' has shape {got}, expected {shape}")
    params: dict[str, Any] = {name: {"w": jnp.asarray(arrays[f"{name}.weight"], jnp.float32),
                     "b": jnp.asarray(arrays[f"{name}.bias"], jnp.float32)}
              for name, *_ in CONVS}
    params["lin"] = tuple(jnp.asarray(arrays[f"lin{l}.weight"], jnp.float32).reshape(-1)
                          for l in range(len(LIN_CHANNELS)))
    return params


def save_lpips(path: str | os.PathLike, arrays) -> None:
    """Write a weights file. arrays: mapping key -> array (validated first)."""
    params_from_arrays(arrays, str(path))
    out: dict[str, Any] = {k: np.asarray(arrays[k], np.float32) for k in expected_shapes()}
    out["format"] = np.array(FORMAT)
    with open(path, "wb") as f:
        np.savez(f, **out)


def load_lpips(path: str | os.PathLike | None) -> dict | None:
    """Parameters from an .npz weights file, or None when `path` is None or does not exist
    (LPIPS unavailable; a warning names the missing file). A file that exists but is not a valid
    weights file raises DataError naming it."""
    if path is None:
        return None
    p = Path(path)
    if not p.exists():
        warnings.warn(f"{p}: LPIPS weights file not found; LPIPS reported as unavailable", stacklevel=2)
        return None
    try:
        with np.load(p, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # not a zip / corrupt
        raise DataError(f"{p}: cannot read LPIPS weights (.npz expected): {load_error_reason(e)}") from None
    if "format" in arrays and str(arrays["format"]) != FORMAT:
        raise DataError(f"{p}: LPIPS weights format '{arrays['format']}', expected '{FORMAT}'")
    return params_from_arrays(arrays, str(p))


def _conv(x, w, b, stride: int, pad: int):
    """x: [N, H, W, I]; w: [O, I, k, k]; b: [O] -> [N, H', W', O]."""
    y = jax.lax.conv_general_dilated(
        x, w, window_strides=(stride, stride), padding=((pad, pad), (pad, pad)),
        dimension_numbers=("NHWC", "OIHW", "NHWC"),
        precision=jax.lax.Precision.HIGHEST)
    return y + b


def _maxpool(x):
    """3x3 max pool, stride 2, no padding. x: [N, H, W, C] -> [N, (H-3)//2+1, (W-3)//2+1, C]."""
    return jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 3, 3, 1), (1, 2, 2, 1), "VALID")


def features(params, x):
    """AlexNet relu1..relu5 activations of images already scaled by the LPIPS scaling layer.

    x: [N, H, W, 3] -> list of five [N, h_l, w_l, C_l].
    """
    feats = []
    for idx, (name, _, _, _, stride, pad) in enumerate(CONVS):
        if idx in (1, 2):
            x = _maxpool(x)
        x = jax.nn.relu(_conv(x, params[name]["w"], params[name]["b"], stride, pad))
        feats.append(x)
    return feats


def _unit(f, eps: float = 1e-10):
    """f: [..., C] -> f / (|f| + eps) over the channel axis."""
    return f / (jnp.sqrt(jnp.sum(f * f, axis=-1, keepdims=True)) + eps)


def lpips(params, pred, target):
    """LPIPS distance (v0.1, AlexNet), lower is more similar.

    params: from `load_lpips` / `params_from_arrays`.
    pred, target: [..., H, W, 3] float in [0, 1], H, W >= 31. Returns [...].
    """
    pred = jnp.asarray(pred, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    if pred.shape != target.shape:
        raise ValueError(f"lpips: pred and target shapes differ: {pred.shape} vs {target.shape}")
    if pred.ndim < 3 or pred.shape[-1] != 3:
        raise ValueError(f"lpips: expected RGB images [..., H, W, 3], got shape {pred.shape}")
    h, w = pred.shape[-3], pred.shape[-2]
    if min(h, w) < MIN_SIZE:
        raise ValueError(f"lpips: image {h}x{w} is too small for the AlexNet trunk (min {MIN_SIZE})")
    lead = pred.shape[:-3]
    both = jnp.concatenate([pred.reshape((-1, h, w, 3)), target.reshape((-1, h, w, 3))], axis=0)
    both = (2.0 * both - 1.0 - jnp.asarray(SHIFT)) / jnp.asarray(SCALE)
    n = both.shape[0] // 2
    dist = 0.0
    for f, lin in zip(features(params, both), params["lin"]):
        f = _unit(f)
        d = (f[:n] - f[n:]) ** 2  # [N, h, w, C]
        dist = dist + jnp.mean(jnp.sum(d * lin, axis=-1), axis=(-2, -1))
    return dist.reshape(lead)


lpips_jit = jax.jit(lpips)
