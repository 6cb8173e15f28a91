"""experiments/train_builtin_dpt.evaluate: mask scores against a pixel-by-pixel count.

The DPT is replaced by fixed probability maps, so what is tested is the scoring: which pixels
count as hits, misses, false alarms, and as visible tower the mask takes from training.
"""

import cv2
import numpy as np
import pytest

from experiments import train_builtin_dpt as tbd


def brute_force_scores(preds, gts, semantics):
    """Loops over every pixel of every frame: pooled IoU / precision / recall / tower covered."""
    tp = fp = fn = tower = tower_masked = 0
    for pred, gt, sem in zip(preds, gts, semantics):
        for i in range(pred.shape[0]):
            for j in range(pred.shape[1]):
                p, g = bool(pred[i, j]), bool(gt[i, j])
                tp += p and g
                fp += p and not g
                fn += g and not p
                if sem[i, j] in (1, 2) and not g:  # tower or conductor, not behind a distractor
                    tower += 1
                    tower_masked += p
    return {"iou": tp / (tp + fp + fn), "precision": tp / (tp + fp), "recall": tp / (tp + fn),
            "tower_covered": tower_masked / tower}


def test_evaluate_scores_match_a_pixel_count(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    h, w, n = 6, 8, 3
    probs = [rng.uniform(size=(h, w)).astype(np.float32) for _ in range(n)]
    gts = [rng.uniform(size=(h, w)) < 0.4 for _ in range(n)]
    semantics = [rng.integers(0, 9, size=(h, w)).astype(np.uint8) for _ in range(n)]
    frames = []
    for k in range(n):
        cv2.imwrite(str(tmp_path / f"im{k}.png"), np.zeros((h, w, 3), np.uint8))
        # bit 0 marks a distractor; bit 1 set on some pixels must not count
        raw = gts[k].astype(np.uint8) | (2 * (rng.uniform(size=(h, w)) < 0.5)).astype(np.uint8)
        cv2.imwrite(str(tmp_path / f"dm{k}.png"), raw)
        cv2.imwrite(str(tmp_path / f"sem{k}.png"), semantics[k])
        frames.append({"file_path": f"im{k}.png", "distractor_mask_path": f"dm{k}.png",
                       "semantic_file_path": f"sem{k}.png"})
    (tmp_path / "transforms.json").write_text(__import__("json").dumps({"frames": frames}))

    def fake_predict_maps(seg, depth, images, classes, **kw):
        for prob, _ in zip(probs, images):
            yield prob, None

    monkeypatch.setattr(tbd.fg, "predict_maps", fake_predict_maps)
    got = tbd.evaluate(None, [tmp_path], threshold=0.5)
    want = brute_force_scores([p > 0.5 for p in probs], gts, semantics)
    assert got["num_frames"] == n
    for key, value in want.items():
        assert got["pooled"][key] == pytest.approx(value, abs=1e-12), key
