"""`jaxnerf-grid mask` on a hand-made dataset: ground-truth source against closed forms, the
DPT source with a native model, overwrite protection, transforms.json preservation."""


import numpy as np
import pytest

from jaxnerf_grid.cli.mask import main
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError


def _dataset(root, h=32, w=48, n=2):
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        io.write_png(root / f"images/f{i}.png", rng.uniform(size=(h, w, 3)))
        m = np.zeros((h, w), np.uint8)
        m[4:12, 8 + i: 20 + i] = 255                       # bit 0 set
        import cv2
        (root / "distractor").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / f"distractor/f{i}.png"), m)
        depth = np.tile(np.linspace(1.0, 5.0, w, dtype=np.float32), (h, 1))
        io.write_exr(root / f"depth/f{i}.exr", depth)
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": np.eye(4).tolist(),
                       "split": "train", "distractor_mask_path": f"distractor/f{i}.png",
                       "depth_file_path": f"depth/f{i}.exr", "custom": i})
    io.write_json(root / "transforms.json", {"fl_x": 40.0, "w": w, "h": h, "generator": {"seed": 3},
                                             "frames": frames})


def test_gt_source_closed_form_and_overwrite(tmp_path):
    _dataset(tmp_path)
    assert main(["--data", str(tmp_path), "--source", "gt", "--floor", "0.2", "--quiet"]) == 0
    meta = io.read_json(tmp_path / "transforms.json")
    assert meta["mask_source"] == "ground-truth" and meta["generator"] == {"seed": 3} and meta["fl_x"] == 40.0
    f = meta["frames"][1]
    assert f["custom"] == 1 and f["mask_path"] == "masks/f1.png" and f["weight_path"] == "weights/f1.exr"
    mask = io.read_mask(tmp_path / f["mask_path"])
    expect_m = np.zeros((32, 48), np.float32)
    expect_m[4:12, 9:21] = 1
    np.testing.assert_array_equal(mask, expect_m)
    weight = io.read_exr(tmp_path / f["weight_path"])
    d = np.tile(np.linspace(1.0, 5.0, 48, dtype=np.float32), (32, 1))
    expect_w = 1 - expect_m * np.maximum(0.2, (5.0 - d) / 5.0)
    np.testing.assert_allclose(weight, expect_w, atol=1e-6)
    assert (tmp_path / "overlays/f1.png").is_file() and (tmp_path / "dpt_depth/f1.exr").is_file()
    with pytest.raises(DataError, match="overwrite=True"):
        main(["--data", str(tmp_path), "--source", "gt", "--quiet"])
    assert main(["--data", str(tmp_path), "--source", "gt", "--quiet", "--overwrite", "--floor", "1"]) == 0
    np.testing.assert_allclose(io.read_exr(tmp_path / "weights/f0.exr"), 1 - io.read_mask(tmp_path / "masks/f0.png"))


def test_dpt_source_with_native_weights(tmp_path):
    from jaxnerf_grid.masks import dpt
    _dataset(tmp_path / "data")
    cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                        image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                        neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=3,
                        heads=("segmentation", "depth"))
    model = dpt.init(0, cfg)
    # bias the classifier so class 2 wins everywhere -> C ~ 1 with classes [2]
    model.params["segmentation"]["cls"]["b"] = np.array([0.0, 0.0, 50.0], np.float32)
    dpt.save(model, tmp_path / "w", dtype="float16", extra={"dynamic_classes": [2]})
    assert main(["--data", str(tmp_path / "data"), "--weights", str(tmp_path / "w"), "--quiet",
                 "--max-side", "64", "--floor", "1"]) == 0
    meta = io.read_json(tmp_path / "data/transforms.json")
    assert meta["mask_source"] == "dpt" and meta["mask_params"]["classes"] == [2]
    m = io.read_mask(tmp_path / "data" / meta["frames"][0]["mask_path"])
    assert m.shape == (32, 48) and m.min() == 1.0
    np.testing.assert_allclose(io.read_exr(tmp_path / "data/weights/f0.exr"), 0.0)
    # with classes [0] nothing is foreground
    assert main(["--data", str(tmp_path / "data"), "--weights", str(tmp_path / "w"), "--quiet",
                 "--max-side", "64", "--classes", "0", "--overwrite"]) == 0
    np.testing.assert_allclose(io.read_exr(tmp_path / "data/weights/f1.exr"), 1.0)
    # tiled: same all-foreground answer, and the tiling recorded
    assert main(["--data", str(tmp_path / "data"), "--weights", str(tmp_path / "w"), "--quiet",
                 "--max-side", "32", "--tiles", "2", "--floor", "1", "--overwrite"]) == 0
    meta = io.read_json(tmp_path / "data/transforms.json")
    assert meta["mask_params"]["tiles"] == 2 and meta["mask_params"]["tile_overlap"] == 0.25
    np.testing.assert_allclose(io.read_exr(tmp_path / "data/weights/f1.exr"), 0.0)


def test_missing_builtin_or_bad_data_is_one_line_error(tmp_path):
    from jaxnerf_grid.config.schema import ConfigError
    with pytest.raises(DataError, match="transforms.json"):
        main(["--data", str(tmp_path), "--source", "gt"])
    for bad in (["--tiles", "0"], ["--tiles", "2", "--tile-overlap", "0.9"]):
        with pytest.raises(ConfigError, match="mask.tile"):
            main(["--data", str(tmp_path)] + bad)


def test_builtin_model_is_shipped_and_default():
    """The built-in DPT (trained by experiments/train_builtin_dpt.py) loads as `mask`'s default."""
    from jaxnerf_grid.masks.write import BUILTIN, default_classes, load_models
    if not (BUILTIN / "config.json").is_file():
        pytest.skip("no built-in model in this build")
    seg, depth, wdir = load_models(None, None)
    assert depth is seg and seg.config.heads == ("segmentation", "depth")
    assert default_classes(seg, wdir) == [6, 7, 8]
    assert sum(f.stat().st_size for f in BUILTIN.iterdir()) < 5_000_000
    meta = io.read_json(BUILTIN / "config.json")
    assert meta["extra"]["steps"] > 0 and min(meta["extra"]["trained_on_seeds"]) >= 7000
