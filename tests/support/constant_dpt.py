"""A tiny built-in-format DPT whose every pixel is one class, for tests of what scores and rules do
with a model that masks all or nothing."""

import numpy as np

from jaxnerf_grid.masks import dpt


def constant_dpt(folder, winner: int):
    """A tiny 9-class DPT saved to `folder` whose classifier is its bias alone, `winner` far ahead:
    every pixel is that class (6-8 dynamic). Returns folder."""
    cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                        image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                        neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=9,
                        heads=("segmentation",))
    model = dpt.init(0, cfg)
    cls = model.params["segmentation"]["cls"]
    cls["w"] = np.zeros_like(np.asarray(cls["w"]))
    cls["b"] = np.where(np.arange(9) == winner, 50.0, 0.0).astype(np.float32)
    dpt.save(model, folder, dtype="float32", extra={"dynamic_classes": [6, 7, 8], "max_side": 32})
    return folder
