"""What `train.robust.refine`'s whole-frame rule (jaxnerf_grid/train/refine.py) makes of a trained
run's training frames, against the scene's distractor masks (the synthetic scenes'): the share
of distractor and of static pixels it ignores, beside the DPT prior alone (and, for the rule,
what it does with the distractor pixels the DPT missed and found), the rule without multi-view
confirmation, the prior dilated by 1-3 px, tighter spread bounds, and strict re-admission
(`train.robust.strict_readmit`); with the scene's semantics, also the share of the tower's and
conductors' pixels (classes 1-2, distractors excluded) each ignores.

    python scripts/refine_offline.py RUN STEP

RUN: a robust run on a synthetic scene with masks (a Table 1 `dpt+robust` run); STEP: one of its
checkpoints (the switch step of a robust_refine run reproduces its frozen weights). docs/ROBUST.md
quotes it.
"""

from __future__ import annotations

import dataclasses
import sys

import cv2
import numpy as np

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.train import checkpoint, refine
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train.runs import load_run_and_dataset

TOWER_CLASSES = (1, 2)  # the synthetic scenes' tower and conductor (semantic_classes)


def shares(weights: np.ndarray, distractor: np.ndarray, tower: np.ndarray | None = None) -> str:
    """'distractor ignored X, static ignored Y[, tower ignored Z]' of [T, H, W] weights against
    [T, H, W] bool masks (tower: the static tower pixels, or None)."""
    ignored = weights < 0.5
    text = f"distractor ignored {ignored[distractor].mean():.3f}, static ignored {ignored[~distractor].mean():.3f}"
    return text if tower is None else f"{text}, tower ignored {ignored[tower].mean():.3f}"


def dilated_prior(prior: np.ndarray, masks: np.ndarray, px: int) -> np.ndarray:
    """The prior with 0 wherever the binary masks [T, H, W], grown by px, reach: what
    train.robust.prior_grow = px gives (`train.grown_masks`)."""
    return np.where(train.grown_masks(masks, px), 0.0, prior).astype(np.float32)


def rendered_run(run: str, step: int):
    """(cfg, dataset, pool, training frame ids, residual [T, H, W], confirmed [T, H, W]) of RUN's
    training frames rendered at checkpoint STEP; SystemExit unless the dataset has distractor
    masks and DPT masks."""
    cfg, _, ds = load_run_and_dataset(run, None, False, False, False)
    cfg = config_lib.resolve(cfg, ds)
    if ds.distractor_masks is None or ds.masks is None:
        raise SystemExit(f"{run}: its dataset needs distractor masks and DPT masks")
    state = checkpoint.load_checkpoint(checkpoint.checkpoint_path(run, step),
                                       train.init_state(cfg, train.train_frames_shape(ds)))
    pool = train.build_pool(ds, cfg)
    residual, points = refine.render_training_frames(state["params"], cfg, ds, pool["frame"])
    confirmed = refine.confirmed_frames(pool, points, cfg.train.robust.confirm)
    return cfg, ds, pool, np.asarray(ds.split["train"]), residual, confirmed


def main(argv: list[str]) -> int:
    cfg, ds, pool, ids, residual, confirmed = rendered_run(argv[0], int(argv[1]))
    truth = np.asarray(ds.distractor_masks[ids], bool)
    masks = np.asarray(ds.masks[ids]) > 0.5
    prior = pool["weights"]
    rule = refine.refined_weights(residual, prior, cfg, confirmed)
    tower = None
    if ds.semantics is not None:
        tower = np.isin(np.asarray(ds.semantics[ids]), TOWER_CLASSES) & ~truth
    print(f"distractor pixels: {truth.mean():.3f} of the training pixels")
    print("DPT prior alone:", shares(prior, truth, tower))
    print("rule, DPT prior:", shares(rule, truth, tower))
    strict = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, robust_strict_readmit=True))
    print("rule, DPT prior, strict re-admission:", shares(refine.refined_weights(residual, prior, strict, confirmed),
                                                          truth, tower))
    missed, found = truth & ~masks, truth & masks
    areas = [a for m in missed for a in cv2.connectedComponentsWithStats(m.astype(np.uint8))[2][1:, 4]]
    print(f"  of the distractor pixels the DPT missed, the rule ignores {(rule[missed] < 0.5).mean():.3f} "
          f"(their connected pieces: median area {np.median(areas):.0f} px); of those it found, the rule "
          f"re-admits {(rule[found] >= 0.5).mean():.3f}")
    print("rule, DPT prior, no confirmation:", shares(refine.refined_weights(residual, prior, cfg), truth))
    for px in (1, 2, 3):
        grown = dilated_prior(prior, masks, px)
        print(f"prior dilated {px} px alone:", shares(grown, truth))
        print(f"rule, prior dilated {px} px:", shares(refine.refined_weights(residual, grown, cfg, confirmed), truth))
    for k in (1.0, 0.75):
        tight = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, robust_spread=k))
        print(f"rule, DPT prior, spread {k}:", shares(refine.refined_weights(residual, prior, tight, confirmed), truth))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
