"""How well `jaxnerf-grid poses` puts a synthetic scene with noisy GPS in metres and in its CRS
(docs/GEOREFERENCE.md). The photos and the truth come from `synth --gps-origin`, the dataset
from `poses` on them:

    jaxnerf-grid synth --out SYN --preset tower-small --width 320 --height 240 --num-train 30 --num-test 1 \\
        --distractors low --gps-origin 47.3769,8.5417,410
    jaxnerf-grid poses --images SYN/photos_gps --out POSES --single-camera [--gcp SYN/gcp.csv]
    python -m benchmarks.gps_alignment --synth SYN --poses POSES [--export RUN/export] [--out FILE.json]

`--write-gcp LAYOUT` (with --synth only) writes a GCP layout's file into SYN without regenerating
the scene (`gps_scene.write_gcp`: `spread` -> SYN/gcp_spread.csv, control points spread in
height; `dense` -> SYN/gcp_dense.csv, a diagnostic; `ground` -> SYN/gcp.csv as synth writes
it), for `poses --gcp`.

The recovered cameras (POSES/transforms.json frames through `georeference.scene_to_crs`) are
compared with the true ones (SYN/gps_truth.json `true_crs`): the similarity from the true to the
recovered centres (Umeyama) gives the scale error (its scale - 1), the tilt (the angle of its
z axis from the vertical) and where the tower's base (the synthetic world's origin,
`tower_base_crs`) lands, in metres from the truth; the centres' errors, the RMS distance of the
recovered centres from that similarity (the reconstruction's own departure from the true shape,
`sfm_shape_rms_m`), and with --gcp the
control and check points' RMS errors, are reported too.

With --realign GCP..., the reconstruction POSES/sparse/0 is aligned anew with the GPS and each
GCP file and scored the same way (`realign`): GCP layouts compared on one SfM model.

With --export (the export folder of a run trained on POSES: `jaxnerf-grid demo --data POSES`,
then `jaxnerf-grid export --run RUN`), the whole chain is scored on the trained model
(`score_export`): the measured tower height (measurements.json `survey.height`, metres, with its
1-sigma) against the true one (the extent along z of SYN/tower.ply, over the synthetic scene's
`scene_units_per_metre`), and the measured base centre in the CRS (`survey.base_centre.crs`)
against `tower_base_crs`, horizontally and in 3-D.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jaxnerf_grid.capture.georef import apply_similarity, umeyama
from jaxnerf_grid.capture.gps_photos import write_gcp
from jaxnerf_grid.util import io


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
    return camera_scores(found, true, np.asarray(truth["tower_base_crs"], np.float64), geo)


def camera_scores(found: np.ndarray, true: np.ndarray, base: np.ndarray, geo: dict) -> dict:
    """`score`'s figures from the recovered and true camera centres [N, 3] (CRS metres), the
    tower's base [3] and the alignment's record (`georef.align_model`: source, gps, gcp)."""
    sim = umeyama(true - base, found - base)
    base_found = apply_similarity(sim, np.zeros(3)) + base
    tilt = float(np.degrees(np.arccos(np.clip(sim[1][2, 2], -1.0, 1.0))))
    centre = np.linalg.norm(found - true, axis=1)
    shape = np.linalg.norm(apply_similarity(sim, true - base) - (found - base), axis=1)  # SfM's own error
    return {"photos": len(found), "source": geo["source"], "crs": geo["crs"], "rotation": geo.get("rotation"),
            "scale_error_percent": round(100.0 * (sim[0] - 1.0), 3), "tilt_deg": round(tilt, 3),
            "base_error_m": round(float(np.linalg.norm(base_found - base)), 3),
            "base_error_horizontal_m": round(float(np.hypot(*(base_found - base)[:2])), 3),
            "centre_error_median_m": round(float(np.median(centre)), 3),
            "centre_error_max_m": round(float(centre.max()), 3), "gps_rms_m": geo["gps"]["rms_m"],
            "sfm_shape_rms_m": round(float(np.sqrt(np.mean(shape ** 2))), 3),
            **{f"{label}_points_rms_m": geo["gcp"][label]["rms_m"] for label in ("control", "check")
               if label in geo.get("gcp", {})}}


def realign(synth_dir, poses_dir, gcp_path, export_dir=None) -> dict:
    """The reconstruction `poses` kept (POSES/sparse/0, local metres) aligned anew with SYN's GPS
    photos and another GCP file, scored as `score` does: GCP layouts compared on one SfM model
    (COLMAP is not bit-reproducible run to run). sparse/0 holds the undistorted PINHOLE copy, its
    principal point where the photos' centre was less the crop, so each click is moved by that
    offset (synthetic photos have no lens distortion). Returns `camera_scores`' dict, with
    export_dir (a run's export trained on POSES) also "export": `score_export`'s figures moved
    through the new alignment (`moved_export`)."""
    import tempfile

    import pycolmap

    from jaxnerf_grid.capture import georef, gps

    truth = io.read_json(Path(synth_dir) / "gps_truth.json")
    model = pycolmap.Reconstruction(str(Path(poses_dir) / "sparse" / "0"))
    names = sorted(model.images[i].name for i in model.reg_image_ids())
    cam = next(iter(model.cameras.values()))
    w0, h0 = gps.upright_size(Path(synth_dir) / "photos_gps" / names[0])
    dx, dy = float(cam.principal_point_x) - w0 / 2.0, float(cam.principal_point_y) - h0 / 2.0
    every = sorted(path.name for path in (Path(synth_dir) / "photos_gps").glob("*.jpg"))
    rows = io.read_text(gcp_path).splitlines()
    moved = [rows[0]] + [",".join([r[0], f"{float(r[1]) + dx:.3f}", f"{float(r[2]) + dy:.3f}", *r[3:]])
                         for r in (line.split(",") for line in rows[1:] if line.strip())]
    with tempfile.TemporaryDirectory() as tmp:
        moved_path = Path(tmp) / Path(gcp_path).name
        moved_path.write_text("\n".join(moved) + "\n")
        positions = gps.read_all([Path(synth_dir) / "photos_gps" / n for n in names])
        sim, geo = georef.align_model(model, positions, crs_name=truth["crs"], gcp_path=moved_path,
                                      sizes={n: (int(cam.width), int(cam.height)) for n in every},
                                      ratios={n: (1.0, 1.0) for n in every}, source=Path(synth_dir) / "photos_gps")
    centres = georef.model_centres(model)
    found = apply_similarity(sim, np.stack([centres[n] for n in names])) + np.asarray(geo["origin"], np.float64)
    true = np.stack([truth["photos"][n]["true_crs"] for n in names])
    out = {"gcp": Path(gcp_path).name, **camera_scores(found, true, np.asarray(truth["tower_base_crs"], np.float64),
                                                        geo)}
    if export_dir is not None:
        old_origin = io.read_json(Path(poses_dir) / "transforms.json")["georeference"]["origin"]
        out["export"] = moved_export(synth_dir, export_dir, sim, np.asarray(old_origin, np.float64),
                                     np.asarray(geo["origin"], np.float64))
    return out


def moved_export(synth_dir, export_dir, sim, old_origin: np.ndarray, new_origin: np.ndarray) -> dict:
    """`score_export` after moving the export's figures from the alignment `poses` made (CRS =
    local + old_origin, sparse/0's frame) through another one (sim: sparse/0's frame -> local
    metres, CRS = local + new_origin): the height times sim's scale, the base centre through
    x -> sim(x - old_origin) + new_origin; the sigmas are the export's. Returns the same dict."""
    out = score_export(synth_dir, export_dir)
    truth = io.read_json(Path(synth_dir) / "gps_truth.json")
    height = out["height_m"] * float(sim[0])
    out.update({"height_m": round(height, 3), "height_error_m": round(height - out["true_height_m"], 3),
                "height_error_percent": round(100.0 * (height / out["true_height_m"] - 1.0), 3)})
    base = (io.read_json(Path(export_dir) / "measurements.json").get("survey") or {}).get("base_centre") or {}
    if base.get("crs") is not None:
        moved = apply_similarity(sim, np.asarray(base["crs"], np.float64) - old_origin) + new_origin
        d = moved - np.asarray(truth["tower_base_crs"], np.float64)
        out.update({"base_error_m": round(float(np.linalg.norm(d)), 3),
                    "base_error_horizontal_m": round(float(np.hypot(d[0], d[1])), 3)})
    return out


def score_export(synth_dir, export_dir) -> dict:
    """The trained model's tower against the truth (module docstring, --export). Returns a dict
    (metres); the base centre's entries are None when the export measured no axis."""
    truth = io.read_json(Path(synth_dir) / "gps_truth.json")
    tower = io.read_ply_points(Path(synth_dir) / "tower.ply")
    true_height = float(np.ptp(tower[:, 2])) / float(truth["scene_units_per_metre"])
    meas = io.read_json(Path(export_dir) / "measurements.json")
    if meas.get("units") != "metres":
        raise io.DataError(f"{export_dir}: the export is not in metres (units {meas.get('units')})")
    survey = meas.get("survey") or {}
    height = survey.get("height") or {}
    if height.get("value") is None:
        raise io.DataError(f"{export_dir}/measurements.json: no height (no ground was found)")
    out = {"true_height_m": round(true_height, 3), "height_m": round(float(height["value"]), 3),
           "height_sigma_m": None if height.get("sigma") is None else round(float(height["sigma"]), 3),
           "height_error_m": round(float(height["value"]) - true_height, 3),
           "height_error_percent": round(100.0 * (float(height["value"]) / true_height - 1.0), 3),
           "base_error_m": None, "base_error_horizontal_m": None, "base_sigma_m": None}
    base = survey.get("base_centre") or {}
    if base.get("crs") is not None:
        d = np.asarray(base["crs"], np.float64) - np.asarray(truth["tower_base_crs"], np.float64)
        out.update({"base_error_m": round(float(np.linalg.norm(d)), 3),
                    "base_error_horizontal_m": round(float(np.hypot(d[0], d[1])), 3),
                    "base_sigma_m": None if base.get("sigma") is None else round(float(base["sigma"]), 3)})
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--synth", required=True, help="the synth dataset (with gps_truth.json)")
    p.add_argument("--poses", default=None, help="the dataset poses wrote from SYN/photos_gps")
    p.add_argument("--write-gcp", default=None, metavar="LAYOUT",
                   help="only write SYN's GCP file of LAYOUT (ground, spread, dense) and stop")
    p.add_argument("--export", default=None, help="a run's export folder (trained on POSES) to score too")
    p.add_argument("--realign", nargs="+", default=None, metavar="GCP",
                   help="also align POSES/sparse/0 anew with each GCP file and score it (layouts on one model)")
    p.add_argument("--out", default=None, help="also write the scores as JSON")
    args = p.parse_args(argv)
    if args.write_gcp is not None:
        try:
            print(f"wrote {write_gcp(args.synth, args.write_gcp)}")
        except io.DataError as err:
            print(f"gps_alignment: error: {err}", file=sys.stderr)
            return 1
        return 0
    if args.poses is None:
        p.error("--poses is required (unless --write-gcp)")
    result = score(args.synth, args.poses)
    if args.realign:
        result["realigned"] = [realign(args.synth, args.poses, path, args.export) for path in args.realign]
    if args.export:
        result["export"] = score_export(args.synth, args.export)
    print(json.dumps(result, indent=1))
    if args.out:
        io.write_json(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
