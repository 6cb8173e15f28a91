"""Fusion (DPT's RefineNet-style decoder): residual conv units, deepest stage first, x2
align-corners bilinear upsampling, 1x1 projection.

A stage's output is `proj(up2(rcu2(prev + rcu1(feature))))` (the deepest stage has no `prev`:
`proj(up2(rcu2(feature)))`), computed as the equal `up2(proj(...))`. If `feature` and `prev`
differ in size (inputs whose patch grid is not a multiple of 2), the feature is resized to
`prev`'s size with half-pixel bilinear, as HF does.

params = [{"rcu1": rcu, "rcu2": rcu, "proj": conv1x1}] * 4 (index 0 = deepest stage), with
rcu = {"conv1", "conv2"[, "bn1", "bn2"]}.
"""

from __future__ import annotations

import jax
import jax.nn

from jaxnerf_grid.dpt.layers import batch_norm, conv2d, init_conv, init_norm, resize_bilinear, split


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
    """One fusion stage. feature: [B, h, w, C]; prev: [B, h', w', C] or None -> [B, 2h', 2w', C]."""
    if prev is None:
        x = feature
    else:
        if feature.shape[1:3] != prev.shape[1:3]:
            feature = resize_bilinear(feature, prev.shape[1], prev.shape[2], align_corners=False)
        x = prev + residual_conv_unit(p["rcu1"], feature)
    x = residual_conv_unit(p["rcu2"], x)
    # HF upsamples, then projects. Both are linear and the bilinear weights of each output pixel
    # sum to 1 (so the bias passes through unchanged), hence they commute; projecting first costs
    # a quarter of the multiply-adds.
    x = conv2d(p["proj"], x)
    return resize_bilinear(x, 2 * x.shape[1], 2 * x.shape[2], align_corners=True)


def apply(params: list, features: list) -> list:
    """features: reassembled maps, shallowest (largest) first -> fused maps, deepest stage first
    (the last one is the finest, at 8x the patch grid for the default factors)."""
    fused, prev = [], None
    for p, feature in zip(params, features[::-1]):
        prev = fuse(p, feature, prev)
        fused.append(prev)
    return fused
