"""Two results files of one table, row against row, paired by seed: what a variant changed.

Usage:
  python -m experiments.paired_rows BASE.json OTHER.json [--rows REGEX] [--metrics psnr psnr_tower ...]
  python -m experiments.paired_rows RESULTS.json --replace OLD NEW [--rows REGEX] [--metrics ...]

Two files: for every row present in both (matched on the row's labels, e.g. Table 1's scene set
and condition) with `--rows` matching its label, and every metric in both aggregates, it prints
the base mean, the other mean and OTHER - BASE paired by seed (mean ± std over the seeds both ran,
and each seed's difference), as `tables.add_paired_delta` computes the tables' Δ columns. Used to
compare Table 1 with the fine-tuned DPT candidate's masks against the shipped model's
(experiments/results/builtin_dpt.md).

One file with `--replace OLD NEW`: two rows of the same file, each row whose label contains OLD
(the base) against the row whose label is the same with OLD replaced by NEW. In the sampling
benchmark's results (labels such as 'disparity + hierarchical / 16'), `--replace hierarchical
proposal` pairs proposal sampling against coarse/fine at each warp and sample count, and
`--replace disparity log --rows hierarchical` pairs log against disparity with coarse/fine
(docs/EXPERIMENTS.md, sampling-scheme benchmark).
"""

from __future__ import annotations

import argparse
import json
import re
import sys

from experiments import tables

DEFAULT_METRICS = ("psnr", "psnr_tower", "geometry_f", "distractor_psnr", "psnr_near_ground",
                   "psnr_far_background", "mask_iou", "mask_recall")


def row_label(row: dict) -> str:
    """The row's string and integer fields other than its aggregate, joined:
    'B: plad-like ... / built-in DPT masks + Eq. 7', 'disparity + hierarchical / 16'."""
    return " / ".join(str(v) for k, v in row.items()
                      if k != "aggregate" and isinstance(v, (str, int)) and not isinstance(v, bool))


def paired_rows(base: dict, other: dict, metrics=DEFAULT_METRICS, rows: str | None = None,
                replace: tuple[str, str] | None = None) -> list[dict]:
    """[{row, metric, base, other, delta}] for the rows and metrics both results files have;
    base / other: the row's {mean, std, values}, delta: OTHER - BASE paired by seed, or None when
    no seed is shared. row: the base row's label (`rows` is searched in it). replace=(OLD, NEW):
    only base rows whose label contains OLD, each matched with the other file's row labelled
    label.replace(OLD, NEW) (pass one file as both to pair two rows of it); other_row: that label."""
    other_rows = {row_label(r): r["aggregate"] for r in other["rows"] if r.get("aggregate")}
    out = []
    for r in base["rows"]:
        label, base_agg = row_label(r), r.get("aggregate")
        if replace and replace[0] not in label:
            continue
        other_label = label.replace(*replace) if replace else label
        agg = other_rows.get(other_label)
        if not base_agg or not agg or (rows and not re.search(rows, label)):
            continue
        for m in metrics:
            if not agg.get(m) or not base_agg.get(m):
                continue
            paired = dict(agg)
            tables.add_paired_delta(paired, base_agg, m, "delta")
            out.append({"row": label, "other_row": other_label, "metric": m, "base": base_agg[m],
                        "other": agg[m], "delta": paired.get("delta")})
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("base")
    p.add_argument("other", nargs="?", default=None, help="left out with --replace: pair rows of BASE")
    p.add_argument("--rows", default=None, metavar="REGEX", help="only base rows whose label matches (re.search)")
    p.add_argument("--replace", nargs=2, default=None, metavar=("OLD", "NEW"),
                   help="pair each row whose label contains OLD with the row labelled with NEW in its place")
    p.add_argument("--metrics", nargs="+", default=list(DEFAULT_METRICS))
    args = p.parse_args(argv)
    if args.other is None and not args.replace:
        p.error("give two results files, or one with --replace OLD NEW")
    try:
        with open(args.base) as fb:
            base = json.load(fb)
        other = base
        if args.other is not None:
            with open(args.other) as fo:
                other = json.load(fo)
    except (OSError, json.JSONDecodeError) as e:
        p.error(f"cannot read a results file: {e}")
    pairs = paired_rows(base, other, args.metrics, args.rows, tuple(args.replace) if args.replace else None)
    if not pairs:
        print("no rows to pair (check --rows / --replace against the files' row labels)", file=sys.stderr)
        return 1
    last = None
    for c in pairs:
        if c["row"] != last:
            print(c["row"] if c["other_row"] == c["row"] else f"{c['other_row']}  against  {c['row']}")
            last = c["row"]
        d = c["delta"]
        if not d:
            paired = "no shared seed"
        elif len(d["values"]) == 1:
            paired = f"{d['mean']:+.3f} (one shared seed)"
        else:
            paired = f"{d['mean']:+.3f} ± {d['std']:.3f} (" + ", ".join(f"{v:+.2f}" for v in d["values"]) + ")"
        print(f"  {c['metric']}: {c['base']['mean']:.3f} -> {c['other']['mean']:.3f}, paired {paired}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
