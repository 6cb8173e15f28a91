"""Fusion (DPT's RefineNet-style decoder): residual conv units, deepest stage first, x2
align-corners bilinear upsampling, 1x1 projection.

HF's stage output is `proj(up2(rcu2(prev + rcu1(feature))))` (the deepest stage has no `prev`:
`proj(up2(rcu2(feature)))`). Both `proj` (1x1) and `up2` are linear and the bilinear weights of
each output pixel sum to 1 (so the bias passes through unchanged), hence they commute: a stage
here returns `proj(rcu2(...))` at the feature's resolution, a quarter of the projection's
multiply-adds, and leaves the x2 to its consumer: the next stage upsamples it, and the heads
fold the last one into their first convolution (`layers.conv2d_upsampled`). If `feature` and
the upsampled `prev` differ in size (inputs whose patch grid is not a multiple of 2), the
feature is resized to that size with half-pixel bilinear, as HF does.

params = [{"rcu1": rcu, "rcu2": rcu, "proj": conv1x1}] * 4 (index 0 = deepest stage), with
rcu = {"conv1", "conv2"[, "bn1", "bn2"]}.
"""

from __future__ import annotations

import jax
import jax.nn

from jaxnerf_grid.masks.dpt.ops import batch_norm, conv2d, init_conv, init_norm, resize_bilinear, split, up2


def _init_rcu(key, cfg) -> dict:
    c = cfg.fusion_hidden_size
    k1, k2 = split(key, 2)
    p = {"conv1": init_conv(k1, 3, c, c, cfg.fusion_bias), "conv2": init_conv(k2, 3, c, c, cfg.fusion_bias)}
    p["conv2"]["w"] = p["conv2"]["w"] * 0.1  # start near the identity
    if cfg.use_batch_norm_in_fusion_residual:
        p["bn1"], p["bn2"] = init_norm(c, running=True), init_norm(c, running=True)
    return p


def init(key, cfg) -> list:
    c = cfg.fusion_hidden_size
    out = []
    for k in split(key, len(cfg.neck_hidden_sizes)):
        k1, k2, k3 = split(k, 3)
        out.append({"rcu1": _init_rcu(k1, cfg), "rcu2": _init_rcu(k2, cfg), "proj": init_conv(k3, 1, c, c)})
    return out


def residual_conv_unit(p: dict, x):
    """Pre-activation residual unit: x + [BN](conv2(relu([BN](conv1(relu(x)))))). x: [B, H, W, C]."""
    y = conv2d(p["conv1"], jax.nn.relu(x), padding=1)
    if "bn1" in p:
        y = batch_norm(p["bn1"], y)
    y = conv2d(p["conv2"], jax.nn.relu(y), padding=1)
    if "bn2" in p:
        y = batch_norm(p["bn2"], y)
    return x + y


def fuse(p: dict, feature, prev=None):
    """One fusion stage, before its x2 upsampling (HF's output is `up2` of this).

    feature: [B, h, w, C]; prev: the previous stage's result [B, h', w', C] (before its x2) or
    None -> [B, h, w, C] (h, w = 2h', 2w' when prev is given).
    """
    if prev is None:
        x = feature
    else:
        prev = up2(prev)
        if feature.shape[1:3] != prev.shape[1:3]:
            feature = resize_bilinear(feature, prev.shape[1], prev.shape[2], align_corners=False)
        x = prev + residual_conv_unit(p["rcu1"], feature)
    x = residual_conv_unit(p["rcu2"], x)
    return conv2d(p["proj"], x)


def apply(params: list, features: list) -> list:
    """features: reassembled maps, shallowest (largest) first -> fused maps, deepest stage first,
    each before its x2 upsampling (HF's fused map i is `up2(result[i])`; the last one, the finest,
    is at 4x the patch grid for the default factors)."""
    fused, prev = [], None
    for p, feature in zip(params, features[::-1]):
        prev = fuse(p, feature, prev)
        fused.append(prev)
    return fused
