"""Where do a mask variant's errors fall? The tower's own pixels it covers, and distractors it misses.

Usage:
  python -m experiments.mask_tower_overlap VARIANT [VARIANT ...]
  python -m experiments.mask_tower_overlap --tower-rules SCENE [SCENE ...]

VARIANT: a folder made by Table 1 / Table 4 (`experiments/.cache/variants/<scene>__<name>`), whose
transforms.json keeps the synthetic scene's semantic and distractor-mask paths. Over its training
views it prints:
  * tower_covered: the share of visible tower pixels (semantic classes 1 tower, 2 conductor, not
    behind a distractor) that the mask M covers: training signal the tower loses;
  * recall: the share of distractor pixels (bit 0 of the distractor mask) that M covers;
  * missed_whole: the share of distractor pixels lying in connected distractor regions that M does
    not touch at all (no dilation reaches those), and the share of those in regions under 10 px.

--tower-rules runs the built-in DPT on a synthetic scene's training views (at its working size,
160 px, the class probabilities upsampled bilinearly as `jaxnerf-grid mask` upsamples C) and prints
tower_covered and recall for masks that use the DPT's own tower classes (`rule_masks`): plain
C > 0.5, and C > 0.5 less the pixels whose argmax is a tower class, or whose tower probability
is at least 0.1 or 0.2. Analysis only; `mask` has no such rule.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from jaxnerf_grid.data.synthetic import CLASSES
from jaxnerf_grid.data.synthetic import DISTRACTOR_CLASSES as DISTRACTOR_NAMES
from jaxnerf_grid.util import io

TOWER_CLASSES = (1, 2)
DISTRACTOR_CLASSES = tuple(CLASSES.index(name) for name in DISTRACTOR_NAMES)
SPECK_PX = 10


def visible_tower(semantic: np.ndarray, distractor: np.ndarray) -> np.ndarray:
    """The tower pixels a view trains on: semantic [H, W] int in TOWER_CLASSES, not behind a
    distractor (distractor: [H, W] bool) -> [H, W] bool."""
    return np.isin(semantic, TOWER_CLASSES) & ~distractor


def frame_counts(mask: np.ndarray, distractor: np.ndarray, semantic: np.ndarray) -> np.ndarray:
    """Pixel counts of one view. mask, distractor: [H, W] bool; semantic: [H, W] int ->
    [tower, tower covered, distractor, distractor covered, in untouched regions, in untouched specks]."""
    import cv2

    tower = visible_tower(semantic, distractor)
    n, labels = cv2.connectedComponents(distractor.astype(np.uint8))
    sizes = np.bincount(labels.ravel(), minlength=n)
    touched = np.bincount(labels.ravel(), weights=mask.ravel().astype(float), minlength=n) > 0
    untouched = [i for i in range(1, n) if not touched[i]]
    return np.array([tower.sum(), (tower & mask).sum(), distractor.sum(), (distractor & mask).sum(),
                     sum(sizes[i] for i in untouched), sum(sizes[i] for i in untouched if sizes[i] < SPECK_PX)],
                    dtype=float)


def variant_shares(variant: Path) -> dict:
    """{tower_covered, recall, missed_whole, missed_whole_specks} pooled over the training views."""
    total = np.zeros(6)
    for f in io.read_json(variant / "transforms.json")["frames"]:
        if f.get("split", "train") != "train" or "mask_path" not in f:
            continue
        mask = io.read_mask(variant / f["mask_path"]) > 0.5
        distractor = io.read_distractor_mask(variant / f["distractor_mask_path"])
        semantic, _ = io.decode_raw(variant / f["semantic_file_path"], "semantic map")
        total += frame_counts(mask, distractor, semantic)
    return {**covered_and_recall(total), "missed_whole": total[4] / max(total[2], 1.0),
            "missed_whole_specks": total[5] / max(total[4], 1.0)}


def covered_and_recall(total: np.ndarray) -> dict:
    """{tower_covered, recall} from pooled `frame_counts`."""
    return {"tower_covered": total[1] / max(total[0], 1.0), "recall": total[3] / max(total[2], 1.0)}


def rule_masks(prob: np.ndarray, threshold: float = 0.5) -> dict:
    """Masks from class probabilities by rules that spare the tower. prob: [H, W, L] (softmax over
    the synthetic classes) -> {rule name: bool [H, W]}."""
    c = prob[..., list(DISTRACTOR_CLASSES)].sum(-1)
    tower_p = prob[..., list(TOWER_CLASSES)].sum(-1)
    base = c > threshold
    return {"C > T": base,
            "C > T, argmax not tower": base & ~np.isin(prob.argmax(-1), TOWER_CLASSES),
            "C > T, P(tower) < 0.1": base & (tower_p < 0.1),
            "C > T, P(tower) < 0.2": base & (tower_p < 0.2)}


def tower_rule_shares(scene: Path) -> dict:
    """{rule: {tower_covered, recall}} over a synthetic scene's training views, built-in DPT at
    its own working size (as `mask` runs it)."""
    from jaxnerf_grid.masks import foreground as fg
    from jaxnerf_grid.masks import write as masking

    seg, _, wdir = masking.load_models(None, None)
    max_side = masking.model_max_side(wdir)
    totals = {}
    for f in io.read_json(scene / "transforms.json")["frames"]:
        if f.get("split", "train") != "train":
            continue
        prob = fg.class_probabilities(seg, io.read_image(scene / f["file_path"]), max_side)
        distractor = io.read_distractor_mask(scene / f["distractor_mask_path"])
        semantic, _ = io.decode_raw(scene / f["semantic_file_path"], "semantic map")
        for name, mask in rule_masks(prob).items():
            totals[name] = totals.get(name, 0) + frame_counts(mask, distractor, semantic)
    return {name: covered_and_recall(t) for name, t in totals.items()}


def main(argv=None) -> int:
    args = list(argv if argv is not None else sys.argv[1:])

    def line(label: str, shares: dict) -> None:
        print(label + ": " + ", ".join(f"{k} {x:.3f}" for k, x in shares.items()))

    if args[:1] == ["--tower-rules"]:
        for scene in args[1:]:
            for name, shares in tower_rule_shares(Path(scene)).items():
                line(f"{Path(scene).name}: {name}", shares)
        return 0
    for v in args:
        line(Path(v).name, variant_shares(Path(v)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
