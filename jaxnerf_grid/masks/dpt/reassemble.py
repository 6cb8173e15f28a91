"""Reassemble (DPT Eq. 3-4): tokens -> image-like feature maps at four resolutions.

Read (readout handling of the CLS token t0, for patch tokens t1..tNp):
  ignore:  {t1, ..., tNp}
  add:     {t1 + t0, ..., tNp + t0}
  project: {GELU(Linear(cat(ti, t0)))}
then Concatenate (tokens to the patch grid), a 1x1 projection to `neck_hidden_sizes[i]` and
Resample by the factor (4, 2: transposed conv with kernel = stride = factor; 1: identity;
0.5: 3x3 conv, stride 2, torch padding 1), then the neck's 3x3 conv to `fusion_hidden_size`.

params = {"readout": [linear 2D -> D] * 4 (project only), "proj": [conv1x1] * 4,
          "resample": [conv_transpose | conv3x3 | {}] * 4, "convs": [conv3x3, no bias] * 4}
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.masks.dpt.ops import conv2d, conv_transpose_nonoverlap, gelu, init_conv, init_linear, linear, split


def init(key, cfg) -> dict:
    d = cfg.hidden_size
    n = len(cfg.neck_hidden_sizes)
    keys = split(key, 4 * n)
    params: dict[str, list] = {"proj": [], "resample": [], "convs": []}
    if cfg.readout_type == "project":
        params["readout"] = [init_linear(keys[4 * i], 2 * d, d) for i in range(n)]
    for i, (c, f) in enumerate(zip(cfg.neck_hidden_sizes, cfg.reassemble_factors)):
        params["proj"].append(init_conv(keys[4 * i + 1], 1, d, c))
        if f > 1:
            k = int(f)
            w = init_conv(keys[4 * i + 2], k, c, c)
            params["resample"].append({"w": np.transpose(w["w"], (2, 0, 1, 3)), "b": w["b"]})
        elif f == 1:
            params["resample"].append({})
        else:
            params["resample"].append(init_conv(keys[4 * i + 2], 3, c, c))
        params["convs"].append(init_conv(keys[4 * i + 3], 3, c, cfg.fusion_hidden_size, bias=False))
    return params


def read(readout_type: str, tokens, readout_params=None):
    """The readout operation. tokens: [B, 1 + N, D] (CLS first) -> [B, N, D]."""
    cls, rest = tokens[:, :1], tokens[:, 1:]
    if readout_type == "ignore":
        return rest
    if readout_type == "add":
        return rest + cls
    if readout_type == "project":
        cat = jnp.concatenate([rest, jnp.broadcast_to(cls, rest.shape)], axis=-1)
        return gelu(linear(readout_params, cat))
    raise ValueError(f"unknown readout type {readout_type!r}")


def resample(p: dict, factor, x):
    """x: [B, h, w, C] -> [B, h*factor, w*factor, C] (0.5: ceil(h/2) as torch's conv)."""
    if factor > 1:
        return conv_transpose_nonoverlap(p, x)
    if factor == 1:
        return x
    return conv2d(p, x, stride=int(round(1 / factor)), padding=1)


def apply(params: dict, cfg, hidden_states, grid_h: int, grid_w: int):
    """hidden_states: list of [B, 1 + grid_h*grid_w, D] -> list of [B, h_i, w_i, fusion_hidden_size]."""
    out = []
    for i, tokens in enumerate(hidden_states):
        rp = params["readout"][i] if cfg.readout_type == "project" else None
        x = read(cfg.readout_type, tokens, rp)
        x = x.reshape(x.shape[0], grid_h, grid_w, x.shape[-1])                # Concatenate
        x = conv2d(params["proj"][i], x)                                       # 1x1 projection
        x = resample(params["resample"][i], cfg.reassemble_factors[i], x)      # Resample
        out.append(conv2d(params["convs"][i], x, padding=1))                   # neck 3x3 conv
    return out
