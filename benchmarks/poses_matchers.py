"""Time and accuracy of `jaxnerf-grid poses` per matcher on Strecha scenes (docs/POSES.md).

Collects datasets written by

    jaxnerf-grid poses --images STRECHA/SCENE/images --out RUNS/TAG --matcher M [--overlap K]
    python -m benchmarks.poses_accuracy --strecha STRECHA/SCENE --dataset RUNS/TAG --out RUNS/TAG_acc.json

(TAG any name; the photos and the datasets stay outside the repository) into one JSON and a
markdown table:

    python -m benchmarks.poses_matchers --runs RUNS --out benchmarks/results/strecha_e2e/poses_matchers

Each row: the scene, the matcher that ran and its overlap, the image pairs it matches
(`pair_count`), photos registered and kept, the seconds of each stage (the poses record's
`timings_s`) and in all, and the rotation error against the surveyed cameras (median / max).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def pair_count(num_photos: int, matcher: str, overlap: int | None) -> int:
    """Image pairs matched: every pair (exhaustive), or each photo with its next `overlap`
    photos in name order (sequential, no quadratic overlap nor loop detection)."""
    if matcher == "sequential":
        return sum(min(overlap, num_photos - 1 - i) for i in range(num_photos))
    return num_photos * (num_photos - 1) // 2


def collect(runs: Path) -> list[dict]:
    """One row per RUNS/TAG holding transforms.json and RUNS/TAG_acc.json, sorted by scene and tag."""
    rows = []
    for dataset in sorted(p for p in runs.iterdir() if (p / "transforms.json").is_file()):
        accuracy = runs / f"{dataset.name}_acc.json"
        if not accuracy.is_file():
            continue
        record = json.loads((dataset / "transforms.json").read_text())["poses"]
        acc = json.loads(accuracy.read_text())
        score = acc["rows"][0]
        rows.append({"scene": score["case"].split(":", 1)[-1], "tag": dataset.name, "matcher": record["matcher"],
                     "overlap": record.get("overlap"), "max_side": record.get("max_side"),
                     "pairs": pair_count(record["photos"], record["matcher"], record.get("overlap")),
                     "photos": record["photos"], "registered": record["registered"],
                     "in_dataset": record["in_dataset"], "seconds": record["seconds"],
                     "timings_s": record.get("timings_s"),
                     "rotation_deg_median": round(score["rotation_deg_median"], 3),
                     "rotation_deg_max": round(score["rotation_deg_max"], 3),
                     "load_avg_1min_after": round(acc["load_avg_1min_end"], 1)})
    return sorted(rows, key=lambda r: (r["scene"], r["tag"]))


def markdown(rows: list[dict], note: str) -> str:
    lines = ["# `jaxnerf-grid poses` per matcher on Strecha scenes", "", note, "",
             "| scene | long side | matcher | pairs | registered / kept | photos s | features s | matching s "
             "| mapping s | writing s | total s | rotation median / max (deg) | load after |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = r["timings_s"] or {}
        matcher = r["matcher"] + (f" (next {r['overlap']})" if r["overlap"] else "")
        size = f"{r['max_side']} px" if r["max_side"] else "full"
        lines.append(f"| {r['scene']} | {size} | {matcher} | {r['pairs']} | {r['registered']}/{r['photos']} / "
                     f"{r['in_dataset']} | " + " | ".join(str(t.get(k, "-")) for k in
                                                      ("photos", "features", "matching", "mapping", "writing"))
                     + f" | {r['seconds']} | {r['rotation_deg_median']:.3f} / {r['rotation_deg_max']:.3f} "
                       f"| {r['load_avg_1min_after']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", required=True, help="folder of poses datasets and their _acc.json scores")
    p.add_argument("--out", required=True, help="output path without suffix: writes OUT.json and OUT.md")
    p.add_argument("--note", default="", help="a line on the machine (shared or idle) for both files")
    args = p.parse_args(argv)
    rows = collect(Path(args.runs))
    # the runs folder is this machine's: the command is recorded with RUNS in its place
    payload = {"command": f"python -m benchmarks.poses_matchers --runs RUNS --out {args.out}",
               "note": args.note, "rows": rows}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(payload, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown(rows, args.note))
    print(markdown(rows, args.note))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
