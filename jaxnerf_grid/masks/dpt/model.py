"""DPT as composition: ViT -> Reassemble -> Fusion -> heads.

A model is `Model(config, params)`; `params` is a plain pytree:
  {"vit": ..., "reassemble": ..., "fusion": ..., "segmentation"?: ..., "auxiliary"?: ..., "depth"?: ...}

Output resolution (matches transformers' behaviour, checked by tests/masks/test_dpt_parity.py): HF's
finest fused map is at 8x the (deepest, halved) patch grid (ours is kept at 4x, before its x2,
which the heads fold into their first conv; see fusion.py) and both heads upsample it x2, so
HF's raw logits / predicted depth have `32 * ceil(g / 2)` rows for a g-row patch grid, i.e.
exactly the input size for patch 16 and inputs that are multiples of 32 (Intel/dpt-large*),
twice the input for patch 8, and more than the input for odd grids. `apply` returns the raw maps under
`logits_raw` / `depth_raw` and, under `logits` / `depth`, the same maps resized to the input
size with half-pixel bilinear (what HF's post-processing does for logits; HF's depth
post-processing uses bicubic, we use bilinear) -- a no-op for patch 16.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxnerf_grid.masks.dpt import fusion, heads, reassemble, vit
from jaxnerf_grid.masks.dpt.dpt_config import DPTConfig
from jaxnerf_grid.masks.dpt.ops import SHAPES, resize_bilinear, rng, split


class Model(NamedTuple):
    config: DPTConfig
    params: dict


def init(seed, cfg: DPTConfig) -> Model:
    """Random parameters for training from scratch (host-side numpy; `seed`: int, jax PRNG key
    or np.random.Generator). Returns Model(cfg, params), params on the default device."""
    return Model(cfg, jax.device_put(init_params(rng(seed), cfg)))


def param_shapes(cfg: DPTConfig) -> dict:
    """The params pytree with zero-cost placeholder leaves of the right shapes."""
    return init_params(SHAPES, cfg)


def init_params(key, cfg: DPTConfig) -> dict:
    """The params pytree of `init`; `key`: np.random.Generator or layers.SHAPES."""
    k = split(key, 6)
    params = {"vit": vit.init(k[0], cfg), "reassemble": reassemble.init(k[1], cfg),
              "fusion": fusion.init(k[2], cfg)}
    if "segmentation" in cfg.heads:
        params["segmentation"] = heads.init_segmentation(k[3], cfg)
        if cfg.use_auxiliary_head:
            params["auxiliary"] = heads.init_segmentation(k[4], cfg)
    if "depth" in cfg.heads:
        params["depth"] = heads.init_depth(k[5], cfg)
    return params


def check_input_shape(cfg: DPTConfig, shape) -> None:
    if len(shape) != 4 or shape[-1] != cfg.num_channels:
        raise ValueError(f"dpt: pixel_values must be [B, H, W, {cfg.num_channels}], got {tuple(shape)}")
    h, w = shape[1], shape[2]
    if h % cfg.patch_size or w % cfg.patch_size:
        raise ValueError(f"dpt: input {h}x{w} is not a multiple of the patch size {cfg.patch_size}")


def forward(params: dict, cfg: DPTConfig, pixel_values, auxiliary: bool = False) -> dict:
    """Pure forward pass. pixel_values: [B, H, W, 3], normalised with mean = std = 0.5.

    Returns a dict with (per head) `logits_raw` [B, h, w, L], `depth_raw` [B, h, w], and
    `logits` [B, H, W, L] / `depth` [B, H, W] at the input size; with `auxiliary=True` (and an
    auxiliary head in `params`) also `aux_logits` [B, h/2, w/2, L]. The auxiliary head is a
    training aid that costs as much as the main head (a 3x3 conv on the finest map); HF runs it
    on every forward and drops the result, we run it only when asked.
    """
    check_input_shape(cfg, pixel_values.shape)
    _, h, w, _ = pixel_values.shape
    gh, gw = h // cfg.patch_size, w // cfg.patch_size
    hidden = vit.apply(params["vit"], cfg, pixel_values)
    feats = reassemble.apply(params["reassemble"], cfg, hidden, gh, gw)
    fused = fusion.apply(params["fusion"], feats)
    x = fused[cfg.head_in_index]
    out = {}
    if "segmentation" in cfg.heads:
        logits = heads.segmentation(params["segmentation"], x)
        out["logits_raw"] = logits
        out["logits"] = resize_bilinear(logits, h, w, align_corners=False)
        if auxiliary and "auxiliary" in params:
            out["aux_logits"] = heads.auxiliary(params["auxiliary"], fused[-1])
    if "depth" in cfg.heads:
        d = heads.depth(params["depth"], x)
        out["depth_raw"] = d
        out["depth"] = resize_bilinear(d[..., None], h, w, align_corners=False)[..., 0]
    return out


@functools.partial(jax.jit, static_argnums=(1, 3))
def _forward_jit(params, cfg, pixel_values, auxiliary):
    return forward(params, cfg, pixel_values, auxiliary)


def apply(model: Model, pixel_values, auxiliary: bool = False) -> dict:
    """Jitted forward (one compile per input shape). pixel_values: [B, H, W, 3] in HF's
    normalisation ((rgb - 0.5) / 0.5). See `forward` for the returned keys (`auxiliary=True`
    adds `aux_logits`)."""
    pixel_values = jnp.asarray(pixel_values, jnp.float32)
    check_input_shape(model.config, pixel_values.shape)
    return _forward_jit(model.params, model.config, pixel_values, bool(auxiliary))


def normalize(rgb):
    """rgb in [0, 1]: [..., 3] -> HF DPT processor normalisation (mean = std = 0.5)."""
    return (rgb - 0.5) / 0.5
