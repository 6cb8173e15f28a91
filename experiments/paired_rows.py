"""Two results files of one table, row against row, paired by seed: what a variant changed.

Usage:
  python -m experiments.paired_rows BASE.json OTHER.json [--rows REGEX] [--metrics psnr psnr_tower ...]

For every row present in both files (matched on the row's labels, e.g. Table 1's scene set and
condition) with `--rows` matching its label, and every metric in both aggregates, it prints the
base mean, the other mean and OTHER - BASE paired by seed (mean ± std over the seeds both ran, and
each seed's difference), as `common.add_paired_delta` computes the tables' Δ columns. Used to
compare Table 1 with the fine-tuned DPT candidate's masks against the shipped model's
(experiments/results/builtin_dpt.md).
"""

from __future__ import annotations

import argparse
import json
import re
import sys

from experiments import common

DEFAULT_METRICS = ("psnr", "psnr_tower", "geometry_f", "distractor_psnr", "psnr_near_ground",
                   "psnr_far_background", "mask_iou", "mask_recall")


def row_label(row: dict) -> str:
    """The row's string fields other than its aggregate, joined: 'B: plad-like ... / built-in DPT masks + Eq. 7'."""
    return " / ".join(str(v) for k, v in row.items() if k != "aggregate" and isinstance(v, str))


def paired_rows(base: dict, other: dict, metrics=DEFAULT_METRICS, rows: str | None = None) -> list[dict]:
    """[{row, metric, base, other, delta}] for the rows and metrics both results files have;
    base / other: the row's {mean, std, values}, delta: OTHER - BASE paired by seed, or None when
    no seed is shared."""
    base_rows = {row_label(r): r["aggregate"] for r in base["rows"] if r.get("aggregate")}
    out = []
    for r in other["rows"]:
        label, agg = row_label(r), r.get("aggregate")
        if not agg or label not in base_rows or (rows and not re.search(rows, label)):
            continue
        for m in metrics:
            if not agg.get(m) or not base_rows[label].get(m):
                continue
            paired = dict(agg)
            common.add_paired_delta(paired, base_rows[label], m, "delta")
            out.append({"row": label, "metric": m, "base": base_rows[label][m], "other": agg[m],
                        "delta": paired.get("delta")})
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("base")
    p.add_argument("other")
    p.add_argument("--rows", default=None, metavar="REGEX", help="only rows whose label matches (re.search)")
    p.add_argument("--metrics", nargs="+", default=list(DEFAULT_METRICS))
    args = p.parse_args(argv)
    with open(args.base) as fb, open(args.other) as fo:
        base, other = json.load(fb), json.load(fo)
    last = None
    for c in paired_rows(base, other, args.metrics, args.rows):
        if c["row"] != last:
            print(c["row"])
            last = c["row"]
        d = c["delta"]
        paired = (f"{d['mean']:+.3f} ± {d['std']:.3f} (" + ", ".join(f"{v:+.2f}" for v in d["values"]) + ")"
                  if d else "no shared seed")
        print(f"  {c['metric']}: {c['base']['mean']:.3f} -> {c['other']['mean']:.3f}, paired {paired}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
