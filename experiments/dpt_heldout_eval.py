"""Score DPT weights on whole held-out synthetic scenes, frame by frame as `jaxnerf-grid mask` runs
them: IoU / precision / recall of M = [C > 0.5], recall per class and per distractor size
(`mask_scores`), per preset and pooled.

    python -m experiments.dpt_heldout_eval --weights DIR [DIR ...] --scenes SCENE [SCENE ...]
        [--out RESULTS.json]

SCENE: a folder written by `jaxnerf-grid synth` / `experiments.dpt_scenes` (with
`semantic_file_path`), of a seed no model was trained on (7101+). Unlike `dpt_mix_eval` (augmented
crops drawn from a cache) every frame is used whole, at its rendered size: the model runs at its
working size (`masking.model_max_side`) and C is upsampled back (`foreground.predict_maps`). A
scene's preset is its folder name up to the first "_" (`dpt_scenes` names them
<preset>_<level>_<seed>).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from experiments import mask_scores
from experiments.dpt_data import DYNAMIC

CLASS_NAMES = {6: "person", 7: "vehicle", 8: "bird"}


def scene_counts(model, weights: Path, root: Path) -> dict:
    """`mask_scores.add_counts` summed over every frame of one scene with a semantic map."""
    import cv2

    from jaxnerf_grid.masks import foreground as fg
    from jaxnerf_grid.masks import write as masking
    from jaxnerf_grid.util import io

    meta = io.read_json(root / "transforms.json")
    frames = [f for f in meta["frames"] if "semantic_file_path" in f]
    if not frames:
        raise SystemExit(f"{root}: no frame with a semantic_file_path (not a synth scene)")
    images = (io.read_image(root / f["file_path"]) for f in frames)
    maps = fg.predict_maps(model, None, images, list(DYNAMIC), max_side=masking.model_max_side(weights), batch_size=8)
    total = None
    for f, (prob, _depth) in zip(frames, maps):
        labels = cv2.imread(str(root / f["semantic_file_path"]), cv2.IMREAD_UNCHANGED)
        pred = np.asarray(fg.binary_mask(prob, 0.5)).astype(bool)
        total = mask_scores.add_counts(total, mask_scores.frame_counts(pred, labels, CLASS_NAMES))
    return total


def score_weights(weights: Path, scenes: list[Path]) -> dict:
    """{"all": scores, "<preset>": scores, ...} of one model over the scenes (pooled pixel counts)."""
    from jaxnerf_grid.masks import dpt

    model = dpt.load_pretrained(weights)
    by_preset: dict = {}
    for root in scenes:
        counts = scene_counts(model, weights, root)
        preset = root.name.split("_")[0]
        by_preset[preset] = mask_scores.add_counts(by_preset.get(preset), counts)
        print(f"{weights}: {root.name} done", flush=True)
    total = None
    for counts in by_preset.values():
        total = mask_scores.add_counts(total, counts)
    return {"all": mask_scores.scores(total), **{k: mask_scores.scores(v) for k, v in sorted(by_preset.items())}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", nargs="+", required=True)
    p.add_argument("--scenes", nargs="+", required=True)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    scenes = [Path(s) for s in args.scenes]
    for s in scenes:
        if not (s / "transforms.json").is_file():
            raise SystemExit(f"{s}: no transforms.json (not a dataset folder)")
    results = {w: score_weights(Path(w), scenes) for w in args.weights}
    rows = {f"{w} / {k}": s for w, r in results.items() for k, s in r.items()}
    print("\n".join(mask_scores.markdown(rows)))
    if args.out:
        Path(args.out).write_text(json.dumps({"scenes": [s.name for s in scenes], "scores": results},
                                             indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
