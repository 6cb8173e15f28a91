"""experiments/train_builtin_dpt.evaluate: mask scores against a pixel-by-pixel count.

The DPT is replaced by fixed probability maps, so what is tested is the scoring: which pixels
count as hits, misses, false alarms, and as visible tower the mask takes from training.
"""

import json

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


def write_scene(root, rng, gts, semantics):
    """A scene folder holding just what evaluate reads: images, distractor masks, semantic maps."""
    root.mkdir()
    frames = []
    for k, (gt, sem) in enumerate(zip(gts, semantics)):
        cv2.imwrite(str(root / f"im{k}.png"), np.zeros(gt.shape + (3,), np.uint8))
        # bit 0 marks a distractor; bit 1 set on some pixels must not count
        raw = gt.astype(np.uint8) | (2 * (rng.uniform(size=gt.shape) < 0.5)).astype(np.uint8)
        cv2.imwrite(str(root / f"dm{k}.png"), raw)
        cv2.imwrite(str(root / f"sem{k}.png"), sem)
        frames.append({"file_path": f"im{k}.png", "distractor_mask_path": f"dm{k}.png",
                       "semantic_file_path": f"sem{k}.png"})
    (root / "transforms.json").write_text(json.dumps({"frames": frames}))


def test_evaluate_scores_match_a_pixel_count(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    h, w, n = 6, 8, 5
    probs = [rng.uniform(size=(h, w)).astype(np.float32) for _ in range(n)]
    gts = [rng.uniform(size=(h, w)) < 0.4 for _ in range(n)]
    semantics = [rng.integers(0, 9, size=(h, w)).astype(np.uint8) for _ in range(n)]
    split = 3  # frames 0-2 in scene "a", 3-4 in scene "b"
    write_scene(tmp_path / "a", rng, gts[:split], semantics[:split])
    write_scene(tmp_path / "b", rng, gts[split:], semantics[split:])
    served = iter(probs)

    def fake_predict_maps(seg, depth, images, classes, **kw):
        for _ in images:
            yield next(served), None

    monkeypatch.setattr(tbd.fg, "predict_maps", fake_predict_maps)
    got = tbd.evaluate(None, [tmp_path / "a", tmp_path / "b"], threshold=0.5)
    preds = [p > 0.5 for p in probs]
    assert got["num_frames"] == n
    for where, want in [(got["pooled"], brute_force_scores(preds, gts, semantics)),
                        (got["by_scene"]["a"], brute_force_scores(preds[:split], gts[:split], semantics[:split])),
                        (got["by_scene"]["b"], brute_force_scores(preds[split:], gts[split:], semantics[split:]))]:
        for key, value in want.items():
            assert where[key] == pytest.approx(value, abs=1e-12), key
