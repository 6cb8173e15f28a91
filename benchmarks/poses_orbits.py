"""`jaxnerf-grid poses` with its defaults on generated orbits, scored against the true cameras.

    python -m benchmarks.poses_orbits SCENE [SCENE ...] [--variants gps,bare] --work DIR --out FILE.json

Each SCENE is a folder `jaxnerf-grid synth --gps-origin ...` wrote (its transforms.json holds the
true cameras). Variants: `gps` runs `poses_from_images` on the scene's photos_gps/train_*.jpg
(JPEGs with EXIF GPS), `bare` on images/train_*.png (no GPS). Every option is the default
(`--matcher auto`, the vetting), but accept_few_cameras: a camera set the default would refuse
is written and scored, and the refusal recorded (`refused`: the verdict). Per run: photos,
registered, kept, the rotation error of every kept camera after a similarity alignment of the
centres (`poses_accuracy.compare`; `per_photo`: each camera's rotation and centre error, the
centre's in orbit radii), the camera-set record, the GPS residual RMS, the wall time, and
`vetting_fails`: the photos the vetting leaves out, with its reasons. With `--keep-all` (`poses
--keep-all`) none is left out, so every registered camera is scored: what the vetting would
have left out is then measured against the truth (the alignment fitted on the photos it keeps).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.poses_accuracy import compare, frames_by_name


def photos_of(scene: Path, variant: str, work: Path) -> Path:
    """A folder of the scene's train photos for `variant` (gps: photos_gps/*.jpg; bare:
    images/*.png), copied under `work`."""
    src, pattern = (scene / "photos_gps", "train_*.jpg") if variant == "gps" else (scene / "images", "train_*.png")
    out = work / f"{scene.name}-{variant}-photos"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    for path in sorted(src.glob(pattern)):
        shutil.copyfile(path, out / path.name)
    return out


def run_one(scene: Path, variant: str, work: Path, keep_all: bool = False) -> dict:
    from jaxnerf_grid.capture.poses import poses_from_images
    from jaxnerf_grid.util.io import DataError

    photos = photos_of(scene, variant, work)
    out = work / f"{scene.name}-{variant}-poses"
    row = {"scene": scene.name, "variant": variant}
    t0 = time.perf_counter()
    try:  # accept_few_cameras: a thin camera set is written (to be scored), its verdict recorded
        summary = poses_from_images(photos, out, overwrite=True, progress=False, accept_few_cameras=True,
                                     keep_all=keep_all)
    except DataError as err:
        row.update(error=str(err), wall_s=time.perf_counter() - t0)
        return row
    row["wall_s"] = time.perf_counter() - t0
    verdict = (summary.get("camera_set") or {}).get("verdict")
    if verdict:
        row["refused"] = verdict
    true = {Path(k).stem: v for k, v in frames_by_name(scene / "transforms.json").items()}
    found = {Path(k).stem: v for k, v in frames_by_name(out / "transforms.json").items()}
    fails = {r["name"]: r["reasons"] for r in summary["vetting"]["photos"] if not r["kept"]}
    errors = compare(true, found, align_on=set(found) - {Path(name).stem for name in fails})
    geo = summary.get("georeference") or {}
    row.update(photos=summary["photos"], registered=summary["registered"], kept=summary["in_dataset"],
               matcher=summary["matcher"], unregistered=summary["unregistered"],
               left_out=summary["vetting"]["left_out"], camera_set=summary.get("camera_set"),
               gps_rms_m=(geo.get("gps") or {}).get("rms_m"), timings_s=summary.get("timings_s"),
               rotation_deg_median=errors["rotation_deg_median"], rotation_deg_max=errors["rotation_deg_max"],
               centre_median=errors["centre_median"], centre_max=errors["centre_max"],
               per_photo={name: {"rotation_deg": e["rotation_deg"], "centre": e["centre"]}
                          for name, e in errors["per_photo"].items()},
               vetting_fails=fails)
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+")
    p.add_argument("--variants", default="gps,bare")
    p.add_argument("--work", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--keep-all", action="store_true",
                   help="poses --keep-all: every registered photo scored, none left out by the vetting")
    args = p.parse_args(argv)
    rows = []
    for scene in args.scenes:
        for variant in args.variants.split(","):
            row = run_one(Path(scene), variant, Path(args.work), args.keep_all)
            rows.append(row)
            if "error" in row:
                print(f"{row['scene']} {variant}: {row['error']}", flush=True)
                continue
            print(f"{row['scene']} {variant}: {row['registered']}/{row['photos']} registered, {row['kept']} kept "
                  f"({100 * row['kept'] / row['photos']:.0f} %), rotation {row['rotation_deg_median']:.2f} / "
                  f"{row['rotation_deg_max']:.2f} deg, {row['wall_s']:.0f} s"
                  + (f", GPS RMS {row['gps_rms_m']} m" if row.get("gps_rms_m") is not None else "")
                  + (" (refused by default)" if "refused" in row else ""), flush=True)
    kept = [r["kept"] / r["photos"] for r in rows if "kept" in r]
    payload = {"command": "python -m benchmarks.poses_orbits " + " ".join(sys.argv[1:] if argv is None else argv),
               "cpu_count": os.cpu_count(), "load_avg_1min_end": os.getloadavg()[0],
               "kept_share_min": float(np.min(kept)) if kept else None, "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(payload, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
