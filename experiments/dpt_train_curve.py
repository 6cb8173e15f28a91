"""The loss curve of a `train_dpt_mix` run rebuilt from its train.log lines alone (for a run cut
short before it wrote train_log.json and loss_curve.png, e.g. by a device's time budget).

    python -m experiments.dpt_train_curve TRAIN.log --out DIR

Writes DIR/train_log.json ({"log": [training records], "val": [validation records], "source":
the log's file name}) and DIR/loss_curve.png (`train_dpt_mix.save_curve_png`). Only the lines
the trainer prints are read: the training line every 100 steps (and step 25) and every
validation line; anything else is skipped.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

# "step 100: loss 0.8487 (ce 1.037, static 0.116, l1 0.154, acc 0.795), lr 8.44e-04, 12.10 steps/s, ..."
TRAIN_LINE = re.compile(r"step (\d+): loss ([\d.eE+-]+) \(ce ([\d.eE+-]+), static ([\d.eE+-]+), "
                        r"l1 ([\d.eE+-]+), acc ([\d.eE+-]+)\), lr ([\d.eE+-]+), ([\d.eE+-]+) steps/s")
# "step 360: val IoU 0.413 precision 0.501 recall 0.700 bird recall 0.586 static share 0.0117...; best ..."
VAL_LINE = re.compile(r"step (\d+): val IoU ([\d.]+) precision ([\d.]+) recall ([\d.]+) "
                      r"bird recall ([\d.]+) static share ([\d.eE+-]+|None)")


def parse_log(text: str) -> tuple[list[dict], list[dict]]:
    """(training records, validation records) from a train.log's text, in the order printed.

    A training record: {"step", "loss", "ce", "static", "l1", "acc", "lr", "steps_per_s"}; a
    validation record: {"step", "iou", "precision", "recall", "bird_recall", "static_share"
    (None when the run had no empty real photos)}."""
    log, vals = [], []
    for line in text.splitlines():
        m = TRAIN_LINE.search(line)
        if m:
            names = ("loss", "ce", "static", "l1", "acc", "lr", "steps_per_s")
            log.append({"step": int(m.group(1)), **{k: float(v) for k, v in zip(names, m.groups()[1:])}})
            continue
        m = VAL_LINE.search(line)
        if m:
            share = None if m.group(6) == "None" else float(m.group(6))
            vals.append({"step": int(m.group(1)), "iou": float(m.group(2)), "precision": float(m.group(3)),
                         "recall": float(m.group(4)), "bird_recall": float(m.group(5)), "static_share": share})
    return log, vals


def main(argv=None) -> int:
    from experiments.train_dpt_mix import save_curve_png

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("log", help="a train.log written by experiments.train_dpt_mix")
    p.add_argument("--out", required=True, help="folder for train_log.json and loss_curve.png")
    args = p.parse_args(argv)
    path = Path(args.log)
    if not path.is_file():
        raise SystemExit(f"{path}: no such training log")
    log, vals = parse_log(path.read_text())
    if not log:
        raise SystemExit(f"{path}: no training lines of experiments.train_dpt_mix in it")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "train_log.json").write_text(json.dumps({"source": path.name, "log": log, "val": vals}, indent=1) + "\n")
    save_curve_png(log, vals, out / "loss_curve.png")
    best = max(vals, key=lambda v: v["iou"]) if vals else None
    print(f"{out}: {len(log)} training records (last step {log[-1]['step']}), {len(vals)} validations"
          + (f", best val IoU {best['iou']:.3f} at step {best['step']}" if best else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
