"""The built-in DPT's training data mix (experiments/dpt_data.py), its mask scorer
(experiments/mask_scores.py) and its trainer (experiments/train_dpt_mix.py): a hand-made scored
case, the mix of a tiny cache (real backgrounds, empty masks, every distractor size), pasting
that leaves the mask exactly the pasted pixels, and a tiny training run whose weights `mask` uses.
"""

import json

import cv2
import numpy as np
import pytest

from experiments import dpt_data, mask_scores
from jaxnerf_grid.util import io

DYN = {6: "person", 7: "vehicle", 8: "bird"}
H, W = 24, 32
MAGENTA = (255, 0, 255)


def test_scores_of_a_hand_made_case():
    labels = np.zeros((8, 10), np.uint8)          # sky everywhere
    labels[1:3, 1:3] = 6                          # a person, 4 px
    labels[6, 8] = 8                              # a bird, 1 px
    labels[5:7, 1:4] = 7                          # a vehicle, 6 px
    pred = np.zeros_like(labels, bool)
    pred[1:3, 1:3] = True                         # the person, whole
    pred[5, 1:4] = True                           # the vehicle's top row: 3 of 6
    pred[0, 9] = pred[3, 5] = True                # two false alarms; the bird missed
    pred_labels = np.where(pred, 6, 0)            # every masked pixel called "person"
    s = mask_scores.scores(mask_scores.frame_counts(pred, labels, DYN, pred_labels))
    tp, fp, fn = 4 + 3, 2, 3 + 1
    assert (s["tp"], s["fp"], s["fn"]) == (tp, fp, fn)
    assert s["iou"] == pytest.approx(tp / (tp + fp + fn))
    assert s["precision"] == pytest.approx(tp / (tp + fp)) and s["recall"] == pytest.approx(tp / (tp + fn))
    assert s["class"]["person"]["recall"] == 1.0 and s["class"]["vehicle"]["recall"] == 0.5
    assert s["class"]["bird"]["recall"] == 0.0
    assert s["class"]["person"]["iou"] == pytest.approx(4 / 9)   # 4 person pixels in a 9-pixel "person" call
    assert s["class"]["vehicle"]["iou"] == 0.0
    tiny, small = s["size"]["1-4 px"], s["size"]["5-32 px"]
    assert tiny["objects"] == 2 and tiny["recall"] == pytest.approx(4 / 5) and tiny["found"] == 0.5
    assert small["objects"] == 1 and small["recall"] == 0.5 and small["found"] == 1.0
    assert s["size"][">256 px"]["recall"] is None
    twice = mask_scores.add_counts(mask_scores.add_counts(None, mask_scores.frame_counts(pred, labels, DYN)),
                                   mask_scores.frame_counts(pred, labels, DYN))
    assert mask_scores.scores(twice)["iou"] == pytest.approx(s["iou"])   # pooling two equal frames
    assert mask_scores.scores(twice)["tp"] == 2 * tp


def write_scene(root, n=3):
    """A synth-like scene at exactly the cache size: ground / sky, a 1-px bird, a 5-px person (a plus
    sign) and an 8x8 vehicle per frame (so sprites of three size buckets), depth 2 everywhere."""
    frames = []
    for k in range(n):
        sem = np.full((H, W), 3, np.uint8)
        sem[:8] = 0
        sem[3, 5 + k] = 8
        sem[10:13, 5] = sem[11, 4:7] = 6       # a plus: a sprite that is not its box
        sem[12:20, 14 + k:22 + k] = 7
        rgb = np.zeros((H, W, 3), np.float32)
        rgb[sem == 0], rgb[sem == 3] = (0.5, 0.7, 1.0), (0.3, 0.5, 0.2)
        rgb[sem == 6], rgb[sem == 7], rgb[sem == 8] = (0.9, 0.1, 0.1), (0.1, 0.1, 0.9), (0.0, 0.0, 0.0)
        io.write_png(root / f"images/f{k}.png", rgb)
        clean = np.where((sem == 0)[..., None], (0.5, 0.7, 1.0), (0.3, 0.5, 0.2)).astype(np.float32)
        io.write_png(root / f"clean/f{k}.png", clean)
        io.write_exr(root / f"clean_depth/f{k}.exr", np.full((H, W), 4.0, np.float32))
        (root / "semantic").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / f"semantic/f{k}.png"), sem)
        io.write_exr(root / f"depth/f{k}.exr", np.full((H, W), 2.0, np.float32))
        frames.append({"file_path": f"images/f{k}.png", "semantic_file_path": f"semantic/f{k}.png",
                       "depth_file_path": f"depth/f{k}.exr", "split": "train",
                       "clean_file_path": f"clean/f{k}.png", "clean_depth_file_path": f"clean_depth/f{k}.exr",
                       "transform_matrix": np.eye(4).tolist()})
    io.write_json(root / "transforms.json", {"fl_x": 30.0, "w": W, "h": H, "frames": frames,
                                             "generator": {"seed": 7001}})
    return root


def write_photos(folder, n=2):
    """Static 'real photos' (larger than the cache size, another aspect): smooth gradients."""
    folder.mkdir(parents=True)
    for k in range(n):
        y, x = np.mgrid[0:60, 0:100]
        img = np.stack([x * 2, y * 3 + 20 * k, np.full_like(x, 90)], -1).astype(np.uint8)
        cv2.imwrite(str(folder / f"p{k}.jpg"), img)
    return folder


@pytest.fixture
def cache(tmp_path):
    scene = write_scene(tmp_path / "scene")
    photos = write_photos(tmp_path / "photos")
    summary = dpt_data.build_cache([scene], [photos], tmp_path / "cache.npz", H, W)
    return tmp_path / "cache.npz", summary


def test_cache_holds_real_photos_and_sprites_of_every_class_and_size(cache):
    path, summary = cache
    assert summary["synthetic"] == 6 and summary["real"] == 2   # 3 views and their 3 clean twins
    assert summary["by_class"] == {"person": 3, "vehicle": 3, "bird": 3}
    c = dpt_data.load_cache(path)
    sprites = dpt_data.unpack_sprites(c)
    sizes = sorted({(int(m.sum()), cls) for _, m, cls in sprites})
    assert sizes == [(1, 8), (5, 6), (64, 7)]
    for rgb, m, cls in sprites:   # the colours cut out are the distractor's own
        expected = {6: (229, 26, 26), 7: (26, 26, 229), 8: (0, 0, 0)}[cls]
        np.testing.assert_allclose(rgb[m].mean(0), expected, atol=2)
    assert json.loads(path.with_suffix(".json").read_text())["real_dirs"] == ["photos"]
    cluttered, clean = c["syn_y"][0::2], c["syn_y"][1::2]
    assert np.isin(cluttered, [6, 7, 8]).sum() == 3 * (1 + 5 + 64)
    assert not np.isin(clean, [6, 7, 8]).any()                        # the twins: empty masks
    np.testing.assert_array_equal(clean == dpt_data.STATIC_UNKNOWN, np.isin(cluttered, [6, 7, 8]))
    np.testing.assert_allclose(c["syn_inv"][1::2].astype(np.float32), 0.25)   # the clean depth, 4


def test_batches_mix_synthetic_pasted_and_empty_real_frames(cache):
    c = dpt_data.load_cache(cache[0])
    sprites = dpt_data.unpack_sprites(c)
    b = dpt_data.sample_batch(c, sprites, 60, (16, 24), np.random.default_rng(0))
    assert b["x"].shape == (60, 16, 24, 3) and b["y"].shape == (60, 16, 24)
    kinds = b["kind"]
    assert set(kinds.tolist()) == {0, 1, 2}
    assert np.array_equal(b["has_depth"], kinds == 0)
    real = kinds > 0
    assert np.all(b["y"][kinds == 0] <= dpt_data.STATIC_UNKNOWN)
    assert np.isin(b["inv"][kinds == 0], np.float32([0.5, 0.25])).all()   # 1 / depth 2, the clean twins' 1 / 4
    empty = b["y"][kinds == 2]
    assert np.all(empty == dpt_data.STATIC_UNKNOWN)                        # empty masks on static photos
    pasted = b["y"][kinds == 1]
    assert np.isin(pasted, [dpt_data.STATIC_UNKNOWN, 6, 7, 8]).all()
    assert np.isin(pasted, [6, 7, 8]).any(axis=(1, 2)).mean() > 0.8       # nearly every one gets a sprite
    assert not np.any(b["inv"][real])


def test_pasting_marks_exactly_the_pasted_pixels(cache):
    c = dpt_data.load_cache(cache[0])
    sprites = dpt_data.unpack_sprites(c)
    rng = np.random.default_rng(1)
    for _ in range(20):
        img = np.empty((40, 50, 3), np.uint8)
        img[:] = MAGENTA
        lab = np.full((40, 50), dpt_data.STATIC_UNKNOWN, np.uint8)
        dpt_data.paste(img, lab, sprites, rng, coverage=0.2)
        changed = np.any(img != MAGENTA, axis=-1)
        assert np.array_equal(changed, np.isin(lab, [6, 7, 8]))
        assert changed.mean() > 0


@pytest.mark.slow
def test_tiny_training_run_writes_weights_that_mask_uses(cache, tmp_path, monkeypatch):
    from experiments import train_dpt_mix
    from jaxnerf_grid.masks import dpt
    from jaxnerf_grid.masks import write as masking

    def tiny_config(name, max_side):   # a few-thousand-parameter DPT: the run, not the model, is tested
        return dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                             image_size=16, patch_size=8, backbone_out_indices=(0, 0, 1, 1),
                             neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=9,
                             heads=("segmentation", "depth"), use_auxiliary_head=False)

    monkeypatch.setattr(train_dpt_mix, "arch_config", tiny_config)
    out, logs = tmp_path / "w", tmp_path / "logs"
    assert train_dpt_mix.main(["--cache", str(cache[0]), "--steps", "30", "--minutes", "2", "--batch", "4",
                               "--max-side", "32", "--val-frames", "6", "--val-every", "0", "--workers", "1",
                               "--out", str(out), "--log-dir", str(logs)]) == 0
    result = json.loads((logs / "train_log.json").read_text())
    assert result["steps"] == 30 and result["cache"] == {"synthetic": 6, "real": 2, "sprites": 9}
    assert result["log"] and all(np.isfinite(r["loss"]) for r in result["log"])
    assert (logs / "loss_curve.png").stat().st_size > 0 and (logs / "train.log").read_text()
    model = dpt.load_pretrained(out)
    assert model.config.hidden_size == 16 and "depth" in model.config.heads
    data = write_scene(tmp_path / "data")
    done = masking.write_masks(data, weights=str(out), progress=False)
    assert done["frames"] == 3 and done["domain"] is not None
    meta = io.read_json(data / "transforms.json")
    assert meta["mask_params"]["classes"] == [6, 7, 8]
    assert io.read_mask(data / meta["frames"][0]["mask_path"]).shape == (H, W)
