"""Accuracy of `jaxnerf-grid poses` on synthetic scenes, where the true cameras are known.

    python -m benchmarks.poses_accuracy [--cases NAME,...] [--views 30] [--out benchmarks/results/poses_accuracy.json]
    python -m benchmarks.poses_accuracy --strecha STRECHA/fountain-P11 [--max-side 1024] --out FILE.json
    python -m benchmarks.poses_accuracy --strecha STRECHA/fountain-P11 --dataset DATA --out FILE.json
    python -m benchmarks.poses_accuracy --reference REF/transforms.json --photos PHOTOS --dataset DATA --out FILE.json

Each case renders a synthetic scene (`generate_scene`), copies its photos (train and test, in
the order of the flight, true poses hidden) into a bare folder, runs
`data.poses.poses_from_images` on it (exhaustive matching, one camera) and compares the
recovered cameras with the true ones after a similarity alignment of the centres (Umeyama
1991): the share of photos registered, the rotation error per camera (degrees), the centre
error as a fraction of the orbit radius (the median distance of the true centres to the
tower's axis) and the tilt of the recovered +z from the true up. Prints a table and writes JSON.
With --strecha, one real scene of Strecha's benchmark (photos with surveyed cameras; the photos
are not part of the repository) instead: rotation error per photo, the vetting and the bounds;
with --dataset, the cameras of a dataset `poses` already wrote for that scene (no new run).
With --reference, a dataset `poses` wrote from the photos in --photos against the cameras of a
capture's own transforms.json (a video's frames posed by another tool): the same errors, the
centres in the reference's units.
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

from benchmarks import strecha_dataset as strecha
from jaxnerf_grid.capture import georef
from jaxnerf_grid.capture.poses import similarity_fit  # Umeyama 1991

ROOT = Path(__file__).resolve().parents[1]

# name: (preset, clutter, width, height)
CASES = {
    "tower-small-low": ("tower-small", "low", 320, 240),
    "tower-small-medium": ("tower-small", "medium", 320, 240),
    "tower-small-high": ("tower-small", "high", 320, 240),
    "ttpla-like-medium": ("ttpla-like", "medium", 320, 180),
}


def angle_deg(r1: np.ndarray, r2: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r1 @ r2.T) - 1.0) / 2.0, -1.0, 1.0))))


def frames_by_name(transforms: Path) -> dict:
    meta = json.loads(transforms.read_text())
    return {Path(f["file_path"]).name: np.asarray(f["transform_matrix"], np.float64) for f in meta["frames"]}


def orientation_alignment(found: np.ndarray, true: np.ndarray) -> np.ndarray:
    """The rotation A that best maps the found camera orientations onto the true ones, A found_i
    ~ true_i in the chordal (Frobenius) sense: the projection of sum_i true_i found_i^T onto
    SO(3). found, true: [N, 3, 3]. Returns [3, 3]."""
    return georef.nearest_rotation(np.einsum("nij,nkj->ik", true, found))


def compare(true: dict, found: dict, align_on=None) -> dict:
    """Errors of `found` ({name: c2w [4, 4]}) against `true` after a similarity alignment of the
    centres; the rotation errors also after aligning the orientations themselves
    (`orientation_alignment`): a ring of centres at one height fixes the tilt of the centres'
    fit poorly, so an error shared by every camera there is the alignment's, not the cameras'.
    align_on: the names both alignments are fitted on (at least 3 of them; default every
    photo), every photo scored: a camera 100 degrees off otherwise turns the fit of the rest.
    "per_photo": {name: {rotation_deg, rotation_deg_oriented, centre}}."""
    names = sorted(set(true) & set(found))
    t = np.stack([true[n] for n in names])
    f = np.stack([found[n] for n in names])
    fit = np.array([align_on is None or n in align_on for n in names])
    if fit.sum() < 3:
        fit[:] = True
    scale, rot, shift = similarity_fit(f[fit, :3, 3], t[fit, :3, 3])
    centres = scale * f[:, :3, 3] @ rot.T + shift
    radius = float(np.median(np.linalg.norm(t[:, :2, 3], axis=1)))  # the tower's axis is x = y = 0
    centre_err = np.linalg.norm(centres - t[:, :3, 3], axis=1) / radius
    rot_err = np.array([angle_deg(rot @ f[i, :3, :3], t[i, :3, :3]) for i in range(len(names))])
    oriented = orientation_alignment(f[fit, :3, :3], t[fit, :3, :3])
    rot_oriented = np.array([angle_deg(oriented @ f[i, :3, :3], t[i, :3, :3]) for i in range(len(names))])
    up = rot @ np.array([0.0, 0.0, 1.0])
    return {"aligned": len(names), "rotation_deg_median": float(np.median(rot_err)),
            "rotation_deg_max": float(rot_err.max()),
            "rotation_deg_oriented_median": float(np.median(rot_oriented)),
            "rotation_deg_oriented_max": float(rot_oriented.max()), "centre_median": float(np.median(centre_err)),
            "centre_max": float(centre_err.max()), "up_tilt_deg": float(np.degrees(np.arccos(np.clip(up[2], -1, 1)))),
            "per_photo": {n: {"rotation_deg": float(rot_err[i]), "rotation_deg_oriented": float(rot_oriented[i]),
                              "centre": float(centre_err[i])} for i, n in enumerate(names)}}


def strecha_cameras(folder) -> dict:
    """{photo name: c2w [4, 4] OpenGL} from a Strecha scene's surveyed cameras (`gt_dense_cameras/
    NAME.camera`, read by `strecha_dataset.read_camera`), in metres."""
    return {path.name[:-len(".camera")]: strecha.camera_to_world_gl(strecha.read_camera(path))
            for path in sorted(Path(folder).glob("*.camera"))}


def run_strecha(scene: Path, work: Path, max_side: int) -> dict:
    """`poses` on a Strecha scene's photos (scene/images, scaled to `max_side`) against its
    surveyed cameras (scene/gt_dense_cameras): rotation errors per photo, the vetting table and
    the scene bounds. Centre errors are in metres."""
    from jaxnerf_grid.capture.poses import poses_from_images

    out = work / f"{scene.name}-{max_side}-poses"
    t0 = time.perf_counter()
    summary = poses_from_images(scene / "images", out, matcher="exhaustive", single_camera=True, max_side=max_side,
                                overwrite=True, progress=False)
    wall = time.perf_counter() - t0
    row = strecha_errors(scene, out)
    return {"case": f"strecha:{scene.name}", "max_side": max_side, "photos": summary["photos"],
            "registered": summary["registered"], "in_dataset": summary["in_dataset"],
            "left_out": summary["vetting"]["left_out"], "vetting": summary["vetting"]["photos"], **row,
            "wall_s": wall}


def strecha_errors(scene: Path, dataset: Path) -> dict:
    """The cameras of a `poses` dataset against a Strecha scene's surveyed ones (`reference_errors`)."""
    return reference_errors(strecha_cameras(scene / "gt_dense_cameras"), dataset)


def reference_errors(true: dict, dataset: Path) -> dict:
    """The cameras of a `poses` dataset against reference cameras `true` ({photo name: c2w [4, 4]
    OpenGL}), after a similarity alignment of the centres: {"per_photo": {name: {rotation_deg,
    centre_m}} (centre_m in the reference's units), "rotation_deg_median", "rotation_deg_max",
    "scene_bounds", "near_points"}."""
    found = frames_by_name(dataset / "transforms.json")
    if not set(true) & set(found):   # the generator writes PNGs, the photos given to `poses` were JPEGs
        true = {Path(n).stem: c for n, c in true.items()}
        found = {Path(n).stem: c for n, c in found.items()}
    names = sorted(set(true) & set(found))
    t, f = np.stack([true[n] for n in names]), np.stack([found[n] for n in names])
    scale, rot, shift = similarity_fit(f[:, :3, 3], t[:, :3, 3])
    per_photo = {n: {"rotation_deg": angle_deg(rot @ found[n][:3, :3], true[n][:3, :3]),
                     "centre_m": float(np.linalg.norm(scale * found[n][:3, 3] @ rot.T + shift - true[n][:3, 3]))}
                 for n in names}
    oriented = orientation_alignment(f[:, :3, :3], t[:, :3, :3])
    for i, n in enumerate(names):  # the orientations aligned themselves: for centres too close to fix the turn
        per_photo[n]["rotation_deg_oriented"] = angle_deg(oriented @ f[i, :3, :3], t[i, :3, :3])
    meta = json.loads((dataset / "transforms.json").read_text())
    rot_err = [v["rotation_deg"] for v in per_photo.values()]
    oriented_err = [v["rotation_deg_oriented"] for v in per_photo.values()]
    return {"rotation_deg_median": float(np.median(rot_err)), "rotation_deg_max": float(np.max(rot_err)),
            "rotation_deg_oriented_median": float(np.median(oriented_err)),
            "rotation_deg_oriented_p95": float(np.percentile(oriented_err, 95)),
            "per_photo": per_photo, "scene_bounds": meta.get("scene_bounds"), "near_points": meta.get("near")}


def run_case(name: str, views: int, work: Path, seed: int) -> dict:
    from jaxnerf_grid.capture.poses import poses_from_images
    from jaxnerf_grid.data.synthetic.generate import generate_scene
    from jaxnerf_grid.util.io import DataError

    preset, clutter, w, h = CASES[name]
    scene = work / f"{name}-s{seed}-{views}"
    if not (scene / "transforms.json").is_file():
        num_test = max(1, views // 8)
        generate_scene(preset, scene, seed=seed, distractors=clutter, overwrite=True, progress=False,
                       width=w, height=h, num_train=views - num_test, num_test=num_test)
    photos = work / f"{scene.name}-photos"
    shutil.rmtree(photos, ignore_errors=True)
    photos.mkdir(parents=True)
    true = frames_by_name(scene / "transforms.json")
    for n in true:
        shutil.copy(scene / "images" / n, photos / n)
    out = work / f"{scene.name}-poses"
    t0, c0 = time.perf_counter(), time.process_time()
    row = {"case": name, "preset": preset, "clutter": clutter, "size": [w, h], "views": views, "seed": seed}
    try:
        summary = poses_from_images(photos, out, matcher="exhaustive", single_camera=True, overwrite=True,
                                    progress=False)
    except DataError as exc:
        row.update(registered=0, error=str(exc), wall_s=time.perf_counter() - t0)
        return row
    row.update(registered=summary["registered"], relaxed=summary["relaxed_mapping"],
               points3d=summary["points3d"], reprojection_px=summary["mean_reprojection_error"],
               wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0)
    row.update(compare(true, frames_by_name(out / "transforms.json")))
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="all")
    p.add_argument("--views", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--work", default=str(ROOT / "benchmarks" / ".cache" / "poses"))
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "poses_accuracy.json"))
    p.add_argument("--strecha", default=None,
                   help="a Strecha scene folder (images/, gt_dense_cameras/): run it instead of the synthetic cases")
    p.add_argument("--max-side", type=int, default=1024, help="working size of the Strecha photos")
    p.add_argument("--dataset", default=None,
                   help="with --strecha: score this existing `poses` dataset of the scene instead of running poses")
    p.add_argument("--reference", default=None,
                   help="with --dataset and --photos: score the dataset against the cameras of this transforms.json "
                        "(nerfstudio / instant-ngp: OpenGL camera-to-world, frames named by their file_path)")
    p.add_argument("--photos", default=None, help="with --reference: the folder of photos the dataset was posed from")
    args = p.parse_args(argv)
    names = [] if args.strecha or args.reference else list(CASES) if args.cases == "all" else args.cases.split(",")
    rows = []
    if args.reference and args.dataset and args.photos:
        dataset, folder = Path(args.dataset), Path(args.photos)
        found = frames_by_name(dataset / "transforms.json")
        photos = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
        row = {"case": f"reference:{folder.name}", "dataset": str(dataset.name), "photos": len(photos),
               "in_dataset": len(found), "left_out": [n for n in photos if n not in found],
               **reference_errors(frames_by_name(Path(args.reference)), dataset)}
        rows.append(row)
        print(f"{row['case']}: {row['in_dataset']}/{row['photos']} in the dataset ({len(row['left_out'])} left out), "
              f"rotation {row['rotation_deg_median']:.2f} / {row['rotation_deg_max']:.2f} deg; orientations aligned: "
              f"median {row['rotation_deg_oriented_median']:.2f}, 95th percentile "
              f"{row['rotation_deg_oriented_p95']:.2f} deg", flush=True)
    elif args.strecha and args.dataset:
        scene, dataset = Path(args.strecha), Path(args.dataset)
        found = frames_by_name(dataset / "transforms.json")
        photos = sorted(p.name for p in (scene / "images").iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
        row = {"case": f"strecha:{scene.name}", "dataset": str(dataset.name), "photos": len(photos),
               "in_dataset": len(found), "left_out": [n for n in photos if n not in found],
               **strecha_errors(scene, dataset)}
        rows.append(row)
        print(f"{row['case']}: {row['in_dataset']}/{row['photos']} in the dataset (left out: "
              f"{', '.join(row['left_out']) or 'none'}), rotation {row['rotation_deg_median']:.2f} / "
              f"{row['rotation_deg_max']:.2f} deg", flush=True)
    elif args.strecha:
        row = run_strecha(Path(args.strecha), Path(args.work), args.max_side)
        rows.append(row)
        print(f"{row['case']}: {row['in_dataset']}/{row['photos']} in the dataset ({row['registered']} registered, "
              f"left out: {', '.join(row['left_out']) or 'none'}), rotation {row['rotation_deg_median']:.2f} / "
              f"{row['rotation_deg_max']:.2f} deg, {row['wall_s']:.1f} s wall", flush=True)
        for name, err in row["per_photo"].items():
            print(f"  {name}: {err['rotation_deg']:.3f} deg, centre {err['centre_m']:.3f} m", flush=True)
        print("scene_bounds:", json.dumps(row["scene_bounds"]), flush=True)
    for name in names:
        row = run_case(name, args.views, Path(args.work), args.seed)
        rows.append(row)
        if "rotation_deg_median" in row:
            print(f"{name}: {row['registered']}/{row['views']} registered, rotation {row['rotation_deg_median']:.2f} / "
                  f"{row['rotation_deg_max']:.2f} deg (orientations aligned: "
                  f"{row['rotation_deg_oriented_median']:.2f} / {row['rotation_deg_oriented_max']:.2f}), "
                  f"centre {100 * row['centre_median']:.2f} / "
                  f"{100 * row['centre_max']:.2f} % of the orbit radius, up tilt {row['up_tilt_deg']:.2f} deg, "
                  f"{row['wall_s']:.1f} s wall", flush=True)
        else:
            print(f"{name}: {row['error']} ({row['wall_s']:.1f} s)", flush=True)
    payload = {"command": "python -m benchmarks.poses_accuracy " + " ".join(sys.argv[1:] if argv is None else argv),
               "cpu_count": os.cpu_count(), "load_avg_1min_end": os.getloadavg()[0], "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(payload, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
