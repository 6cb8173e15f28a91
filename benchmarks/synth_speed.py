"""Time `jaxnerf-grid synth --preset tower-small` and record the realised distractor coverages.

Usage:
  JAX_PLATFORMS=cpu python -m benchmarks.synth_speed [--workers 2] [--levels low medium high]
      [--preset tower-small] [--out benchmarks/results/synth_speed.json]

For each distractor level it renders the preset into a temporary folder and records wall time,
CPU seconds (this process + worker processes), the machine's load average (the 2-core CI box
is shared, so wall time alone can mislead) and the per-view coverage statistics from
transforms.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path


def _cpu_seconds() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def run(preset: str, level: str, workers: int, seed: int) -> dict:
    from jaxnerf_grid.data.synthetic.generate import generate_scene

    with tempfile.TemporaryDirectory() as tmp:
        load_before = os.getloadavg()
        cpu0, t0 = _cpu_seconds(), time.perf_counter()
        path = generate_scene(preset, Path(tmp) / "scene", seed=seed, distractors=level, progress=True, workers=workers)
        wall, cpu = time.perf_counter() - t0, _cpu_seconds() - cpu0
        meta = json.loads(path.read_text())
    train = [f for f in meta["frames"] if f["split"] == "train"]
    covs = [f["distractor_coverage"] for f in train]
    return {
        "preset": preset, "distractors": level, "seed": seed, "workers": workers,
        "views": len(meta["frames"]), "train_views": len(train), "size": [meta["w"], meta["h"]],
        "supersample": meta["generator"]["supersample"],
        "wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
        "load_avg_1min_before": round(load_before[0], 2), "load_avg_1min_after": round(os.getloadavg()[0], 2),
        "coverage_mean": round(sum(covs) / max(len(covs), 1), 4), "coverage_min": round(min(covs, default=0), 4),
        "coverage_max": round(max(covs, default=0), 4),
        "distractors_per_view_mean": round(sum(f["num_distractors"] for f in train) / max(len(train), 1), 1),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="tower-small")
    p.add_argument("--levels", nargs="+", default=["medium"], choices=["none", "low", "medium", "high"])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "synth_speed.json"))
    args = p.parse_args(argv)
    results = [run(args.preset, level, args.workers, args.seed) for level in args.levels]
    report = {"benchmark": "synth_speed", "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "cpu_count": os.cpu_count(), "python": platform.python_version(), "runs": results}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    for r in results:
        print(f"{r['preset']} {r['distractors']:6s} {r['views']} views {r['size'][0]}x{r['size'][1]}: "
              f"wall {r['wall_s']:.1f} s, cpu {r['cpu_s']:.1f} s, load {r['load_avg_1min_before']}, "
              f"coverage mean {r['coverage_mean']:.3f} [{r['coverage_min']:.3f}, {r['coverage_max']:.3f}]")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
