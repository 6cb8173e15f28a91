"""The sparse points' depth rays (`train.depth`) of a `poses` dataset, checked against a generated
scene's true depth and classes.

    python -m benchmarks.depth_rays_truth --syn SYN --data DATA [--out FILE.json]

SYN: a folder `jaxnerf-grid synth` wrote (true cameras, depth/*.exr z-depth, semantic/*.png);
DATA: the dataset `jaxnerf-grid poses` made from SYN's photos (DATA/sparse/0, transforms.json).
The depth rays are built as training builds them (`sparse_depth.from_model` on DATA's cameras),
then carried into SYN's frame by the similarity that maps DATA's camera centres onto SYN's, and
projected with SYN's cameras. Per class of the pixel each ray lands on: how many rays, the share
whose point lies within 2 % of the true surface there, and the share whose point lies more than
5 % behind it (the ray passes through something the photos show: its term thins that thing).
For the rays on a tower pixel, the distance in pixels from the silhouette's edge (percentiles).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

from jaxnerf_grid.capture import georef
from jaxnerf_grid.export import fuse
from jaxnerf_grid.train import sparse_depth
from jaxnerf_grid.util import io

BEHIND = 0.05  # a point more than this share behind the true surface at its pixel
ON = 0.02      # a point within this share of it


def stem(path: str) -> str:
    return Path(path).stem


def rays_in_truth_frame(syn: Path, data: Path) -> tuple[dict, dict, list[dict], np.ndarray]:
    """(rays in SYN's frame as `sparse_depth.observations` gives them, SYN's transforms.json, the
    SYN frames the rays' "camera" indexes, their c2w [T, 4, 4])."""
    truth = json.loads((syn / "transforms.json").read_text())
    posed = json.loads((data / "transforms.json").read_text())
    by_stem = {stem(f["file_path"]): f for f in posed["frames"]}
    frames = [f for f in truth["frames"]
              if stem(f["file_path"]).startswith("train") and stem(f["file_path"]) in by_stem]
    c2w = np.asarray([f["transform_matrix"] for f in frames], np.float64)
    data_c2w = np.asarray([by_stem[stem(f["file_path"])]["transform_matrix"] for f in frames], np.float64)
    intrinsics = np.asarray([[by_stem[stem(f["file_path"])].get(k, posed.get(k)) for k in ("fl_x", "fl_y", "cx", "cy")]
                             for f in frames], np.float64)
    names = [Path(by_stem[stem(f["file_path"])]["file_path"]).name for f in frames]
    rays, why = sparse_depth.from_model(data / "sparse" / "0", names, data_c2w, intrinsics,
                                        int(posed["w"]), int(posed["h"]))
    if rays is None:
        sys.exit(f"depth_rays_truth: {why}")
    scale, rot, shift = georef.umeyama(data_c2w[:, :3, 3], c2w[:, :3, 3])
    points = rays["origins"] + rays["directions"] * rays["t"][:, None]
    points = scale * points.astype(np.float64) @ rot.T + shift
    origins = c2w[rays["camera"], :3, 3]
    dist = np.linalg.norm(points - origins, axis=1)
    return ({"origins": origins, "directions": (points - origins) / dist[:, None], "t": dist,
             "camera": rays["camera"]}, truth, frames, c2w)


def classify(syn: Path, truth: dict, frames: list[dict], c2w: np.ndarray, rays: dict) -> dict:
    """Per class: {"rays", "on_surface", "behind", "edge_px" (tower rays behind, percentiles)}."""
    classes = truth["semantic_classes"]
    fx, fy, cx, cy = (float(truth[k]) for k in ("fl_x", "fl_y", "cx", "cy"))
    width, height = int(truth["w"]), int(truth["h"])
    rel, label, edge = [], [], []
    for k, frame in enumerate(frames):
        sel = rays["camera"] == k
        if not np.any(sel):
            continue
        depth = np.asarray(io.read_exr(syn / frame["depth_file_path"])).reshape(height, width, -1)[..., 0]
        sem = np.asarray(Image.open(syn / "semantic" / f"{stem(frame['file_path'])}.png"))
        sem = sem[..., 0] if sem.ndim == 3 else sem
        inside = ndimage.distance_transform_edt(sem == classes.index("tower"))
        points = rays["origins"][sel] + rays["directions"][sel] * rays["t"][sel][:, None]
        u_px, v_px, z = fuse.project(points, c2w[k], (fx, fy, cx, cy))
        u = np.clip(u_px.astype(int), 0, width - 1)
        v = np.clip(v_px.astype(int), 0, height - 1)
        rel.append(z / depth[v, u] - 1)
        label.append(sem[v, u])
        edge.append(inside[v, u])
    rel_all, label_all, edge_all = np.concatenate(rel), np.concatenate(label), np.concatenate(edge)
    out = {}
    for c in np.unique(label_all):
        sel = label_all == c
        name = classes[int(c)] if int(c) < len(classes) else str(int(c))
        behind = rel_all[sel] > BEHIND
        out[name] = {"rays": int(sel.sum()), "on_surface": float(np.mean(np.abs(rel_all[sel]) < ON)),
                     "behind": float(np.mean(behind))}
        if name == "tower" and np.any(behind):
            quartiles = np.percentile(edge_all[sel][behind], [25, 50, 75, 90])
            out[name]["edge_px_of_rays_behind"] = [float(q) for q in quartiles]
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--syn", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    for folder in (args.syn, args.data):
        if not (folder / "transforms.json").is_file():
            sys.exit(f"depth_rays_truth: {folder}: no transforms.json")
    rays, truth, frames, c2w = rays_in_truth_frame(args.syn, args.data)
    command = " ".join(["python -m benchmarks.depth_rays_truth", *(argv or sys.argv[1:])])
    record = {"benchmark": "depth_rays_truth", "command": command,
              "rays": int(len(rays["t"])), "by_class": classify(args.syn, truth, frames, c2w, rays)}
    text = json.dumps(record, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
