"""Output heads on the finest fused map. HF's heads take that map after the last fusion stage's
x2 upsampling; ours take it before (x: [B, h, w, F], F = fusion_hidden_size) and fold the x2 into
their first 3x3 conv (`layers.conv2d_upsampled`: the same numbers for a quarter of the
multiply-adds). The depth head's second x2 is folded into its next conv the same way.

segmentation: conv3x3 (no bias) -> BN -> ReLU -> conv1x1 -> x2 align-corners bilinear;
auxiliary:    conv3x3 (no bias) -> BN -> ReLU -> conv1x1 (no upsampling; training aid in HF);
depth:        [conv3x3 256 -> ReLU, if add_projection] -> conv3x3 F/2 -> x2 align-corners
              bilinear -> conv3x3 32 -> ReLU -> conv1x1 1 -> ReLU  (relative inverse depth).
"""

from __future__ import annotations

import jax
import jax.nn

from jaxnerf_grid.masks.dpt.ops import batch_norm, conv2d, conv2d_upsampled, init_conv, init_norm, split, up2


def _conv3x3_up2(p: dict, x):
    """conv3x3(up2(x)) with padding 1. x: [B, h, w, Cin] -> [B, 2h, 2w, Cout]."""
    return conv2d_upsampled(p, x, 2 * x.shape[1], 2 * x.shape[2], padding=1)


def init_segmentation(key, cfg) -> dict:
    f, n = cfg.fusion_hidden_size, cfg.num_labels
    k1, k2 = split(key, 2)
    return {"conv": init_conv(k1, 3, f, f, bias=False), "bn": init_norm(f, running=True),
            "cls": init_conv(k2, 1, f, n)}


def segmentation(p: dict, x):
    """x: [B, h, w, F] (before the x2) -> logits [B, 4h, 4w, num_labels] (as HF: the head's own
    x2 comes after the classifier)."""
    return up2(auxiliary(p, x))


def auxiliary(p: dict, x):
    """x: [B, h, w, F] (before the x2) -> logits [B, 2h, 2w, num_labels]."""
    y = jax.nn.relu(batch_norm(p["bn"], _conv3x3_up2(p["conv"], x)))
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
    """x: [B, h, w, F] (before the x2) -> relative inverse depth [B, 4h, 4w] (>= 0)."""
    if "projection" in p:
        y = conv2d(p["conv1"], jax.nn.relu(_conv3x3_up2(p["projection"], x)), padding=1)
    else:
        y = _conv3x3_up2(p["conv1"], x)
    y = jax.nn.relu(_conv3x3_up2(p["conv2"], y))
    return jax.nn.relu(conv2d(p["conv3"], y))[..., 0]
