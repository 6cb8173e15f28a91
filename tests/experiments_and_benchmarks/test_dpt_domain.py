"""The DPT domain benchmark (benchmarks/dpt_domain.py) on a folder of photos and on weights given
by folder: every model scores every set, each photo's share is what the model masks."""

import json

import numpy as np
import pytest

from benchmarks import dpt_domain
from jaxnerf_grid.masks import dpt
from jaxnerf_grid.util import io


def _constant_dpt(folder, winner: int):
    """A tiny 9-class DPT whose classifier is its bias alone: every pixel is class `winner`."""
    cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                        image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                        neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=9,
                        heads=("segmentation",))
    model = dpt.init(0, cfg)
    cls = model.params["segmentation"]["cls"]
    cls["w"] = np.zeros_like(np.asarray(cls["w"]))
    cls["b"] = np.where(np.arange(9) == winner, 50.0, 0.0).astype(np.float32)
    dpt.save(model, folder, dtype="float32", extra={"dynamic_classes": [6, 7, 8], "max_side": 32})
    return str(folder)


def test_every_model_scores_every_photo_folder(tmp_path):
    for name in ("a.jpg", "b.png", "c.JPG"):
        io.write_png(tmp_path / "site" / name, np.full((20, 30, 3), 0.4, np.float32))
    (tmp_path / "site" / "notes.txt").write_text("not a photo")
    masks_all = _constant_dpt(tmp_path / "w" / "masks_all", 8)
    masks_none = _constant_dpt(tmp_path / "w" / "masks_none", 0)
    assert dpt_domain.main(["--photos", str(tmp_path / "site"), "--no-skimage", "--no-synthetic",
                            "--weights", masks_all, masks_none, "--out", str(tmp_path / "out")]) == 0
    rows = json.loads((tmp_path / "out.json").read_text())["rows"]
    assert [(r["weights"], r["set"]) for r in rows] == [("w/masks_all", "site"), ("w/masks_none", "site")]
    assert rows[0]["shares"] == [1.0, 1.0, 1.0] and rows[0]["verdict"]["out_of_domain"] is True
    assert rows[1]["shares"] == [0.0, 0.0, 0.0] and rows[1]["verdict"]["out_of_domain"] is False
    assert "| w/masks_all | site | real | 3 |" in (tmp_path / "out.md").read_text()


def test_a_photo_folder_without_photos_is_a_one_line_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="--photos .*empty: no .jpg / .png photos"):
        dpt_domain.main(["--photos", str(tmp_path / "empty"), "--no-skimage", "--no-synthetic",
                         "--out", str(tmp_path / "out")])
