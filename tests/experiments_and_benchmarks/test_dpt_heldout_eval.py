"""Scoring DPT weights on whole held-out synthetic scenes (experiments/dpt_heldout_eval.py):
pooled per preset over every frame with a semantic map, against counts made by hand."""

import json

import cv2
import numpy as np
import pytest

from experiments import dpt_heldout_eval
from jaxnerf_grid.util import io
from tests.support.constant_dpt import constant_dpt


def _scene(root, labels_per_frame):
    """A synth-like folder: one grey photo and one semantic map (uint8 class ids) per frame."""
    frames = []
    for i, labels in enumerate(labels_per_frame):
        io.write_png(root / f"images/{i}.png", np.full((*labels.shape, 3), 0.5, np.float32))
        (root / "semantic").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / f"semantic/{i}.png"), labels.astype(np.uint8))
        frames.append({"file_path": f"images/{i}.png", "semantic_file_path": f"semantic/{i}.png"})
    frames.append({"file_path": "images/0.png"})   # no semantic map: not scored
    (root / "transforms.json").write_text(json.dumps({"frames": frames}))


def test_a_model_that_masks_everything_scores_the_distractor_share(tmp_path):
    a = np.zeros((24, 32), np.uint8)
    a[2:4, 2:4] = 8                      # a bird of 4 px
    a[10:20, 10:20] = 6                  # a person of 100 px
    b = np.zeros((24, 32), np.uint8)
    b[0, 0] = 8                          # a bird of 1 px
    _scene(tmp_path / "tower-small_low_7101", [a, b])
    c = np.zeros((24, 32), np.uint8)
    c[5:11, 5:11] = 7                    # a vehicle of 36 px
    _scene(tmp_path / "plad-like_low_7102", [c])
    scenes = [tmp_path / "tower-small_low_7101", tmp_path / "plad-like_low_7102"]

    everything = dpt_heldout_eval.score_weights(constant_dpt(tmp_path / "all", 8), scenes)
    pixels = 3 * 24 * 32
    assert everything["all"]["recall"] == 1.0
    assert everything["all"]["precision"] == pytest.approx((4 + 100 + 1 + 36) / pixels)
    assert everything["all"]["iou"] == pytest.approx((4 + 100 + 1 + 36) / pixels)
    assert everything["tower-small"]["precision"] == pytest.approx(105 / (2 * 24 * 32))
    assert everything["plad-like"]["precision"] == pytest.approx(36 / (24 * 32))
    assert everything["all"]["class"]["bird"]["pixels"] == 5
    sizes = everything["all"]["size"]
    assert sizes["1-4 px"]["objects"] == 2 and sizes["33-256 px"]["objects"] == 2

    nothing = dpt_heldout_eval.score_weights(constant_dpt(tmp_path / "none", 0), scenes)
    assert nothing["all"]["recall"] == 0.0 and nothing["all"]["tp"] == 0 and nothing["all"]["fn"] == 141


def test_a_folder_without_transforms_is_a_one_line_error(tmp_path):
    with pytest.raises(SystemExit, match="nowhere: no transforms.json"):
        dpt_heldout_eval.main(["--weights", str(tmp_path), "--scenes", str(tmp_path / "nowhere")])
