"""Where do a mask variant's errors fall? The tower's own pixels it covers, and distractors it misses.

Usage:
  python -m experiments.mask_tower_overlap VARIANT [VARIANT ...]

VARIANT: a folder made by Table 1 / Table 4 (`experiments/.cache/variants/<scene>__<name>`), whose
transforms.json keeps the synthetic scene's semantic and distractor-mask paths. Over its training
views it prints:
  * tower_covered: the share of visible tower pixels (semantic classes 1 tower, 2 conductor, not
    behind a distractor) that the mask M covers: training signal the tower loses;
  * recall: the share of distractor pixels (bit 0 of the distractor mask) that M covers;
  * missed_whole: the share of distractor pixels lying in connected distractor regions that M does
    not touch at all (no dilation reaches those), and the share of those in regions under 10 px.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from jaxnerf_grid import io

TOWER_CLASSES = (1, 2)
SPECK_PX = 10


def frame_counts(mask: np.ndarray, distractor: np.ndarray, semantic: np.ndarray) -> np.ndarray:
    """Pixel counts of one view. mask, distractor: [H, W] bool; semantic: [H, W] int ->
    [tower, tower covered, distractor, distractor covered, in untouched regions, in untouched specks]."""
    import cv2

    tower = np.isin(semantic, TOWER_CLASSES) & ~distractor
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
    return {"tower_covered": total[1] / max(total[0], 1.0), "recall": total[3] / max(total[2], 1.0),
            "missed_whole": total[4] / max(total[2], 1.0), "missed_whole_specks": total[5] / max(total[4], 1.0)}


def main(argv=None) -> int:
    for v in argv if argv is not None else sys.argv[1:]:
        shares = variant_shares(Path(v))
        print(Path(v).name + ": " + ", ".join(f"{k} {x:.3f}" for k, x in shares.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
