"""ViT encoder of DPT: patch embedding, CLS token, resized position embeddings, pre-LN blocks.

params = {"patch": conv [p, p, 3, D], "cls": [D], "pos": [1 + G*G, D] (G = image_size/patch),
          "blocks": [{"ln1", "q", "k", "v", "o", "ln2", "fc1", "fc2"}, ...], "ln_final"}
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnerf_grid.masks.dpt.ops import (
    conv2d,
    gelu,
    init_conv,
    init_linear,
    init_norm,
    layer_norm,
    linear,
    normal,
    resize_bilinear,
    split,
)


def init(key, cfg) -> dict:
    d, p = cfg.hidden_size, cfg.patch_size
    keys = split(key, cfg.num_hidden_layers + 3)
    patch = init_conv(keys[0], p, cfg.num_channels, d)
    patch["w"] = patch["w"] * 0.5
    blocks = []
    for i in range(cfg.num_hidden_layers):
        k = split(keys[3 + i], 6)
        blocks.append({
            "ln1": init_norm(d), "ln2": init_norm(d),
            "q": init_linear(k[0], d, d, cfg.qkv_bias), "k": init_linear(k[1], d, d, cfg.qkv_bias),
            "v": init_linear(k[2], d, d, cfg.qkv_bias), "o": init_linear(k[3], d, d),
            "fc1": init_linear(k[4], d, cfg.intermediate_size), "fc2": init_linear(k[5], cfg.intermediate_size, d),
        })
    return {
        "patch": patch,
        "cls": normal(keys[1], (d,), 0.02),
        "pos": normal(keys[2], (cfg.num_positions, d), 0.02),
        "blocks": blocks,
        "ln_final": init_norm(d),
    }


def resize_pos_embed(pos, grid_h: int, grid_w: int):
    """Position embeddings for a grid_h x grid_w patch grid (bilinear, half-pixel, no antialias,
    as HF's `_resize_pos_embed`). pos: [1 + G*G, D] -> [1 + grid_h*grid_w, D]."""
    g = int(round((pos.shape[0] - 1) ** 0.5))
    grid = pos[1:].reshape(1, g, g, -1)
    grid = resize_bilinear(grid, grid_h, grid_w, align_corners=False)
    return jnp.concatenate([pos[:1], grid.reshape(grid_h * grid_w, -1)], axis=0)


def embed(params: dict, cfg, pixel_values):
    """pixel_values: [B, H, W, 3] (H, W multiples of the patch size) -> tokens [B, 1 + h*w, D]."""
    b, h, w, _ = pixel_values.shape
    p = cfg.patch_size
    x = conv2d(params["patch"], pixel_values, stride=p)          # [B, h/p, w/p, D]
    gh, gw = h // p, w // p
    x = x.reshape(b, gh * gw, -1)
    cls = jnp.broadcast_to(params["cls"], (b, 1, x.shape[-1])).astype(x.dtype)
    x = jnp.concatenate([cls, x], axis=1)
    return x + resize_pos_embed(params["pos"], gh, gw).astype(x.dtype)


def attention(p: dict, x, num_heads: int):
    """Multi-head self-attention. x: [B, N, D] -> [B, N, D].

    Heads are moved ahead of the tokens ([B, heads, N, hd]) so both products are plain batched
    matmuls; on XLA CPU that is about twice as fast as the equivalent einsums over [B, N, heads, hd].
    The softmax's division is applied after the product with V (softmax(S) V = (e V) / sum(e),
    e = exp(S - max S)): a pass over [N, hd] instead of over [N, N].
    """
    b, n, d = x.shape
    hd = d // num_heads
    heads_first = lambda t: t.reshape(b, n, num_heads, hd).transpose(0, 2, 1, 3)  # noqa: E731
    q = heads_first(linear(p["q"], x) * (hd ** -0.5))
    k, v = heads_first(linear(p["k"], x)), heads_first(linear(p["v"], x))
    scores = q @ k.swapaxes(-1, -2)                                                # [B, heads, N, N]
    e = jnp.exp(scores - jax.lax.stop_gradient(jnp.max(scores, axis=-1, keepdims=True)))
    out = (e @ v) / jnp.sum(e, axis=-1, keepdims=True)                             # [B, heads, N, hd]
    return linear(p["o"], out.transpose(0, 2, 1, 3).reshape(b, n, d))


def block(p: dict, cfg, x):
    """One pre-LayerNorm transformer block. x: [B, N, D] -> [B, N, D]."""
    x = x + attention(p, layer_norm(p["ln1"], x, cfg.layer_norm_eps), cfg.num_attention_heads)
    y = linear(p["fc2"], gelu(linear(p["fc1"], layer_norm(p["ln2"], x, cfg.layer_norm_eps))))
    return x + y


def apply(params: dict, cfg, pixel_values):
    """pixel_values: [B, H, W, 3] -> list of hidden states [B, 1 + h*w, D] after the blocks
    `cfg.backbone_out_indices` (0-based; before the final LayerNorm, as HF's DPT uses them)."""
    x = embed(params, cfg, pixel_values)
    wanted = set(cfg.backbone_out_indices)
    last = max(wanted)
    outs = {}
    for i, p in enumerate(params["blocks"][: last + 1]):
        x = block(p, cfg, x)
        if i in wanted:
            outs[i] = x
    return [outs[i] for i in cfg.backbone_out_indices]
