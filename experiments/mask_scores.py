"""Scores of a transient mask against labelled ground truth: IoU / precision / recall of the mask,
recall and IoU per distractor class, and recall per distractor size (connected components).

Counts are summed over frames (`add_counts`) and turned into scores once (`scores`), so pooled
figures weight every pixel equally.
"""

from __future__ import annotations

import numpy as np

# Size buckets of one distractor (an 8-connected component of the dynamic classes), in pixels at
# the scoring resolution: (name, smallest area, largest area).
SIZE_BUCKETS = (("1-4 px", 1, 4), ("5-32 px", 5, 32), ("33-256 px", 33, 256), (">256 px", 257, None))


def frame_counts(pred: np.ndarray, labels: np.ndarray, dynamic: dict, pred_labels: np.ndarray | None = None) -> dict:
    """Pixel counts of one frame.

    pred [H, W] bool (the mask M), labels [H, W] int (ground-truth classes; pixels of the `dynamic`
    classes {id: name} are the distractors), pred_labels [H, W] int (the model's argmax class,
    optional: for the per-class IoU). Returns {"tp", "fp", "fn", "class": {name: {"pixels",
    "masked", "inter", "union"}}, "size": {bucket: {"objects", "pixels", "masked", "found"}}} where
    an object is "found" when M covers at least half of its pixels."""
    import cv2

    pred = np.asarray(pred, bool)
    gt = np.isin(labels, list(dynamic))
    out = {"tp": int(np.sum(pred & gt)), "fp": int(np.sum(pred & ~gt)), "fn": int(np.sum(~pred & gt)),
           "class": {}, "size": {}}
    for cid, name in dynamic.items():
        is_c = labels == cid
        rec = {"pixels": int(is_c.sum()), "masked": int(np.sum(is_c & pred)), "inter": 0, "union": 0}
        if pred_labels is not None:
            is_p = pred_labels == cid
            rec["inter"], rec["union"] = int(np.sum(is_c & is_p)), int(np.sum(is_c | is_p))
        out["class"][name] = rec
    n, comp, stats, _ = cv2.connectedComponentsWithStats(gt.astype(np.uint8), connectivity=8)
    masked_per_comp = np.bincount(comp[pred], minlength=n)
    for name, _lo, _hi in SIZE_BUCKETS:
        out["size"][name] = {"objects": 0, "pixels": 0, "masked": 0, "found": 0}
    for c in range(1, n):
        area, masked = int(stats[c, cv2.CC_STAT_AREA]), int(masked_per_comp[c])
        for name, lo, hi in SIZE_BUCKETS:
            if area >= lo and (hi is None or area <= hi):
                rec = out["size"][name]
                rec["objects"] += 1
                rec["pixels"] += area
                rec["masked"] += masked
                rec["found"] += int(2 * masked >= area)
    return out


def add_counts(total: dict | None, counts: dict) -> dict:
    """The sum of two `frame_counts` results (total None: a copy of counts)."""
    if total is None:
        return {"tp": counts["tp"], "fp": counts["fp"], "fn": counts["fn"],
                "class": {k: dict(v) for k, v in counts["class"].items()},
                "size": {k: dict(v) for k, v in counts["size"].items()}}
    for k in ("tp", "fp", "fn"):
        total[k] += counts[k]
    for group in ("class", "size"):
        for name, rec in counts[group].items():
            for k, v in rec.items():
                total[group][name][k] += v
    return total


def scores(total: dict) -> dict:
    """Scores from summed counts: {"iou", "precision", "recall", "tp", "fp", "fn", "class": {name:
    {"recall", "iou", "pixels"}}, "size": {bucket: {"recall", "found", "objects"}}}; a ratio with
    nothing to count is None (e.g. the recall of a class absent from every frame)."""
    ratio = lambda a, b: (a / b) if b else None  # noqa: E731
    tp, fp, fn = total["tp"], total["fp"], total["fn"]
    return {"iou": ratio(tp, tp + fp + fn), "precision": ratio(tp, tp + fp), "recall": ratio(tp, tp + fn),
            "tp": tp, "fp": fp, "fn": fn,
            "class": {k: {"recall": ratio(v["masked"], v["pixels"]), "iou": ratio(v["inter"], v["union"]),
                          "pixels": v["pixels"]} for k, v in total["class"].items()},
            "size": {k: {"recall": ratio(v["masked"], v["pixels"]), "found": ratio(v["found"], v["objects"]),
                         "objects": v["objects"]} for k, v in total["size"].items()}}


def markdown(rows: dict) -> list[str]:
    """Markdown lines: one table of {row name: `scores`} (IoU, precision, recall, per-class and
    per-size recall; '-' where there was nothing to count)."""
    f = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    first = next(iter(rows.values()))
    classes, sizes = list(first["class"]), list(first["size"])
    head = ["", "IoU", "precision", "recall", *[f"recall {c}" for c in classes], *[f"recall {s}" for s in sizes]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, s in rows.items():
        cells = [name, f(s["iou"]), f(s["precision"]), f(s["recall"]),
                 *[f(s["class"][c]["recall"]) for c in classes], *[f(s["size"][b]["recall"]) for b in sizes]]
        lines.append("| " + " | ".join(cells) + " |")
    return lines
