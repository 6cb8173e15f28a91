"""How well `jaxnerf-grid poses` puts a synthetic scene with noisy GPS in metres and in its CRS
(docs/GEOREFERENCE.md). The photos and the truth come from `synth --gps-origin`, the dataset
from `poses` on them:

    jaxnerf-grid synth --out SYN --preset tower-small --width 320 --height 240 --num-train 30 --num-test 1 \\
        --distractors low --gps-origin 47.3769,8.5417,410
    jaxnerf-grid poses --images SYN/photos_gps --out POSES --single-camera [--gcp SYN/gcp.csv]
    python -m benchmarks.gps_alignment --synth SYN --poses POSES [--out FILE.json]

The recovered cameras (POSES/transforms.json frames through `georeference.scene_to_crs`) are
compared with the true ones (SYN/gps_truth.json `true_crs`): the similarity from the true to the
recovered centres (Umeyama) gives the scale error (its scale - 1), the tilt (the angle of its
z axis from the vertical) and where the tower's base (the synthetic world's origin,
`tower_base_crs`) lands, in metres from the truth; the centres' errors, the RMS distance of the
recovered centres from that similarity (the reconstruction's own departure from the true shape,
`sfm_shape_rms_m`), and with --gcp the
control and check points' RMS errors, are reported too.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from jaxnerf_grid import io
from jaxnerf_grid.data.georef import apply_similarity, umeyama


def score(synth_dir, poses_dir) -> dict:
    """The scores of the module docstring. Returns a dict (metres and degrees)."""
    truth = io.read_json(Path(synth_dir) / "gps_truth.json")
    data = io.read_json(Path(poses_dir) / "transforms.json")
    geo = data["georeference"]
    if geo.get("units") != "metres":
        raise io.DataError(f"{poses_dir}: the dataset is not georeferenced (units {geo.get('units')})")
    to_crs = np.asarray(geo["scene_to_crs"], np.float64)
    names = [Path(f["file_path"]).name for f in data["frames"]]
    found = np.stack([to_crs[:3, :3] @ np.asarray(f["transform_matrix"])[:3, 3] + to_crs[:3, 3]
                      for f in data["frames"]])
    true = np.stack([truth["photos"][n]["true_crs"] for n in names])
    base = np.asarray(truth["tower_base_crs"], np.float64)
    sim = umeyama(true - base, found - base)
    base_found = apply_similarity(sim, np.zeros(3)) + base
    tilt = float(np.degrees(np.arccos(np.clip(sim[1][2, 2], -1.0, 1.0))))
    centre = np.linalg.norm(found - true, axis=1)
    shape = np.linalg.norm(apply_similarity(sim, true - base) - (found - base), axis=1)  # SfM's own error
    return {"photos": len(names), "source": geo["source"], "crs": geo["crs"], "rotation": geo.get("rotation"),
            "scale_error_percent": round(100.0 * (sim[0] - 1.0), 3), "tilt_deg": round(tilt, 3),
            "base_error_m": round(float(np.linalg.norm(base_found - base)), 3),
            "base_error_horizontal_m": round(float(np.hypot(*(base_found - base)[:2])), 3),
            "centre_error_median_m": round(float(np.median(centre)), 3),
            "centre_error_max_m": round(float(centre.max()), 3), "gps_rms_m": geo["gps"]["rms_m"],
            "sfm_shape_rms_m": round(float(np.sqrt(np.mean(shape ** 2))), 3),
            **{f"{label}_points_rms_m": geo["gcp"][label]["rms_m"] for label in ("control", "check")
               if label in geo.get("gcp", {})}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--synth", required=True, help="the synth dataset (with gps_truth.json)")
    p.add_argument("--poses", required=True, help="the dataset poses wrote from SYN/photos_gps")
    p.add_argument("--out", default=None, help="also write the scores as JSON")
    args = p.parse_args(argv)
    result = score(args.synth, args.poses)
    print(json.dumps(result, indent=1))
    if args.out:
        io.write_json(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
