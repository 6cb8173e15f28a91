"""How well GPS at a given accuracy scales a real reconstruction: the alignment step of `poses`
(docs/GEOREFERENCE.md) on a Strecha scene's registration, with the surveyed camera centres plus
GPS-like noise standing in for the photos' GPS.

    python -m benchmarks.strecha_dataset ...   (not needed: the surveyed cameras are read directly)
    jaxnerf-grid poses --images STRECHA/fountain-P11/images --out DATA      (the registration)
    python -m benchmarks.strecha_gps_scale STRECHA/fountain-P11 DATA [--sigmas 0.02,0.5,1,3] [--draws 400]
        [--out FILE.json]

STRECHA/SCENE holds the benchmark's `gt_dense_cameras/*.camera` (surveyed centres in metres;
`fetch github:openMVG/SfM_quality_evaluation`, docs/POSES.md); DATA is the dataset `poses` wrote
(transforms.json, z up, arbitrary scale). The surveyed frame has z pointing down (the photos'
image-down axis lies along +z), so it is turned 180 degrees about x to be z up, as GPS heights are.

For each horizontal sigma (vertical 1.5 x sigma, as consumer receivers are worse in height) and
each of `draws` noise draws, the centres are aligned exactly as `georef.align_model` aligns GPS
alone: `georef.ransac_similarity` (yaw-only, inliers within `georef.INLIER_METRES`) then
`georef.umeyama` over its inliers. The scale error is that similarity's scale over the
noise-free one's, minus 1: every length measured on the model is off by it. Reported per sigma:
the median and 95th percentile of |scale error| in per cent, and the camera baseline (largest
distance between two surveyed centres), because the error is roughly sigma over the baseline;
and the noise-free yaw-only fit's RMS distance (the registration's shape and up axis against
the survey).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.strecha_dataset import read_camera
from jaxnerf_grid.capture.georef import INLIER_METRES, apply_similarity, ransac_similarity, umeyama
from jaxnerf_grid.util import io

Z_DOWN_TO_UP = np.diag([1.0, -1.0, -1.0])  # 180 degrees about x
VERTICAL_FACTOR = 1.5


def surveyed_centres(scene_dir) -> dict:
    """{photo name: [3] centre in metres, z up} from SCENE/gt_dense_cameras/NAME.camera."""
    folder = Path(scene_dir) / "gt_dense_cameras"
    files = sorted(folder.glob("*.camera"))
    if not files:
        raise io.DataError(f"{folder}: no Strecha .camera files")
    return {f.name[: -len(".camera")]: Z_DOWN_TO_UP @ read_camera(f)["C"] for f in files}


def model_centres(dataset_dir) -> dict:
    """{photo name: [3] camera centre in the dataset's scene units} from DATA/transforms.json."""
    frames = io.read_json(Path(dataset_dir) / "transforms.json")["frames"]
    return {Path(f["file_path"]).name: np.asarray(f["transform_matrix"], np.float64)[:3, 3] for f in frames}


def gps_scale(src: np.ndarray, dst: np.ndarray, seed: int) -> float:
    """The scale of the GPS-only alignment of `georef.align_model` from src [N, 3] to dst [N, 3]."""
    _, inliers = ransac_similarity(src, dst, INLIER_METRES, yaw_only=True, seed=seed)
    return float(umeyama(src[inliers], dst[inliers], yaw_only=True)[0])


def scale_errors(src: np.ndarray, truth: np.ndarray, sigma: float, draws: int, seed: int = 0) -> np.ndarray:
    """|scale error| of `draws` alignments to truth + noise (horizontal sigma, vertical
    VERTICAL_FACTOR x sigma), relative to the noise-free alignment. Returns [draws]."""
    reference = gps_scale(src, truth, seed)
    rng = np.random.default_rng(seed)
    spread = np.array([sigma, sigma, VERTICAL_FACTOR * sigma])
    return np.array([abs(gps_scale(src, truth + rng.normal(size=truth.shape) * spread, seed + k) / reference - 1.0)
                     for k in range(draws)])


def run(scene_dir, dataset_dir, sigmas, draws: int) -> dict:
    truth_all, model_all = surveyed_centres(scene_dir), model_centres(dataset_dir)
    names = sorted(set(truth_all) & set(model_all))
    if len(names) < 3:
        raise io.DataError(f"{dataset_dir}: {len(names)} photo(s) in common with {scene_dir}; need 3")
    truth = np.stack([truth_all[n] for n in names])
    src = np.stack([model_all[n] for n in names])
    baseline = float(np.max(np.linalg.norm(truth[:, None] - truth[None], axis=-1)))
    _, inliers = ransac_similarity(src, truth, INLIER_METRES, yaw_only=True, seed=0)
    sim = umeyama(src[inliers], truth[inliers], yaw_only=True)
    shape_rms = float(np.sqrt(np.mean(np.sum((apply_similarity(sim, src) - truth) ** 2, axis=1))))
    rows = []
    for sigma in sigmas:
        err = scale_errors(src, truth, sigma, draws)
        rows.append({"sigma_m": sigma, "median_pct": 100 * float(np.median(err)),
                     "p95_pct": 100 * float(np.percentile(err, 95))})
    return {"scene": Path(scene_dir).name, "photos": len(names), "baseline_m": baseline,
            "metres_per_unit_noise_free": float(sim[0]),
            "noise_free_rms_m": shape_rms, "draws": draws, "vertical_factor": VERTICAL_FACTOR, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="a Strecha scene folder with gt_dense_cameras/")
    ap.add_argument("dataset", help="the dataset jaxnerf-grid poses made from its photos")
    ap.add_argument("--sigmas", default="0.02,0.5,1,3", help="horizontal GPS sigmas in metres, comma-separated")
    ap.add_argument("--draws", type=int, default=400)
    ap.add_argument("--out", help="write the results as JSON here")
    args = ap.parse_args(argv)
    try:
        sigmas = [float(v) for v in args.sigmas.split(",")]
        result = run(args.scene, args.dataset, sigmas, args.draws)
    except (io.DataError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"{result['scene']}: {result['photos']} photos, baseline {result['baseline_m']:.1f} m, noise-free "
          f"yaw-only fit RMS {result['noise_free_rms_m']:.3f} m")
    for r in result["rows"]:
        print(f"  GPS sigma {r['sigma_m']:g} m: |scale error| median {r['median_pct']:.2f} %, "
              f"95th percentile {r['p95_pct']:.2f} %")
    if args.out:
        io.write_json(Path(args.out), result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
