"""Output heads on the finest fused map (x: [B, h, w, F], F = fusion_hidden_size).

segmentation: conv3x3 (no bias) -> BN -> ReLU -> conv1x1 -> x2 align-corners bilinear;
auxiliary:    conv3x3 (no bias) -> BN -> ReLU -> conv1x1 (no upsampling; training aid in HF);
depth:        [conv3x3 256 -> ReLU, if add_projection] -> conv3x3 F/2 -> x2 align-corners
              bilinear -> conv3x3 32 -> ReLU -> conv1x1 1 -> ReLU  (relative inverse depth).
"""

from __future__ import annotations

import jax
import jax.nn

from jaxnerf_grid.dpt.layers import batch_norm, conv2d, init_conv, init_norm, resize_bilinear, split


def _up2(x):
    return resize_bilinear(x, 2 * x.shape[1], 2 * x.shape[2], align_corners=True)


def init_segmentation(key, cfg) -> dict:
    f, n = cfg.fusion_hidden_size, cfg.num_labels
    k1, k2 = split(key, 2)
    return {"conv": init_conv(k1, 3, f, f, bias=False), "bn": init_norm(f, running=True),
            "cls": init_conv(k2, 1, f, n)}


def segmentation(p: dict, x):
    """x: [B, h, w, F] -> logits [B, 2h, 2w, num_labels] (as HF: the x2 comes after the classifier)."""
    return _up2(auxiliary(p, x))


def auxiliary(p: dict, x):
    """x: [B, h, w, F] -> logits [B, h, w, num_labels]."""
    y = jax.nn.relu(batch_norm(p["bn"], conv2d(p["conv"], x, padding=1)))
    return conv2d(p["cls"], y)


def init_depth(key, cfg) -> dict:
    f = cfg.fusion_hidden_size
    k = split(key, 4)
    p = {"conv1": init_conv(k[0], 3, f, f // 2), "conv2": init_conv(k[1], 3, f // 2, 32),
         "conv3": init_conv(k[2], 1, 32, 1)}
    if cfg.add_projection:
        p["projection"] = init_conv(k[3], 3, 256, 256)
    return p


def depth(p: dict, x):
    """x: [B, h, w, F] -> relative inverse depth [B, 2h, 2w] (>= 0)."""
    if "projection" in p:
        x = jax.nn.relu(conv2d(p["projection"], x, padding=1))
    y = _up2(conv2d(p["conv1"], x, padding=1))
    y = jax.nn.relu(conv2d(p["conv2"], y, padding=1))
    return jax.nn.relu(conv2d(p["conv3"], y))[..., 0]
