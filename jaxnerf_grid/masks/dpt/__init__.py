"""DPT (Ranftl et al. 2021) in pure JAX: ViT encoder, Reassemble, Fusion, segmentation and
depth heads, as init/apply functions on plain pytrees, plus Hugging Face checkpoint import.

    model = dpt.load_pretrained("path/to/dpt-large-ade")   # HF layout or native
    out = dpt.apply(model, dpt.normalize(rgb))              # rgb: [B, H, W, 3] in [0, 1]
    out["logits"]  # [B, H, W, num_labels]   (segmentation models)
    out["depth"]   # [B, H, W] relative inverse depth (depth models)
"""

from jaxnerf_grid.masks.dpt.dpt_config import DPTConfig
from jaxnerf_grid.masks.dpt.model import Model, apply, forward, init, normalize
from jaxnerf_grid.masks.dpt.weights import load_pretrained, params_to_hf, save

__all__ = ["DPTConfig", "Model", "apply", "forward", "init", "normalize", "load_pretrained", "save",
           "params_to_hf"]
