"""The DPT domain benchmark (benchmarks/dpt_domain.py) on a folder of photos and on weights given
by folder: every model scores every set, each photo's share is what the model masks."""

import json

import numpy as np
import pytest

from benchmarks import dpt_domain
from jaxnerf_grid.util import io
from tests.support.constant_dpt import constant_dpt


def test_every_model_scores_every_photo_folder(tmp_path):
    for name in ("a.jpg", "b.png", "c.JPG"):
        io.write_png(tmp_path / "site" / name, np.full((20, 30, 3), 0.4, np.float32))
    (tmp_path / "site" / "notes.txt").write_text("not a photo")
    masks_all = str(constant_dpt(tmp_path / "w" / "masks_all", 8))
    masks_none = str(constant_dpt(tmp_path / "w" / "masks_none", 0))
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
