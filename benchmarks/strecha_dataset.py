"""A transforms.json dataset from a Strecha scene's surveyed cameras (the photos stay where they are).

    python -m benchmarks.strecha_dataset FOLDER OUT [--overwrite]

FOLDER is one scene of the Strecha benchmark (e.g. Benchmarking_Camera_Calibration_2008/
fountain-P11 of the repository openMVG/SfM_quality_evaluation): images/NNNN.jpg and
gt_dense_cameras/NNNN.jpg.camera. Each .camera file holds 26 numbers (the layout openMVG's
Strecha reader uses): K (3 rows), a distortion row (3 numbers, zero in these scenes), R (3 rows:
the camera-to-world rotation, OpenCV camera axes x right, y down, z forward), the camera centre
C in world coordinates (metres), and the image size W H. A world point X is seen at
K R^T (X - C).

OUT gets transforms.json (docs/DATASET.md): per frame the photo's path relative to OUT, the
surveyed pinhole intrinsics (fl_x, fl_y, cx, cy as the file gives them: the half-pixel origin of
Strecha's K is not stated; it moves a ray by 0.5 px at full size), the OpenGL camera-to-world
pose [R diag(1, -1, -1) | C] turned z-up and normalised by `normalize.z_up_normalization`
(cameras method: the optical axes' focus in the unit sphere's centre, the cameras at 2 units)
and that record as `scene_normalization`; near / far are the loader's defaults. Nothing is written into
FOLDER; the photos are not
copied (the dataset's masks and the working-resolution cache go into OUT).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from jaxnerf_grid.data.formats import CV_TO_GL, DEFAULT_FAR, DEFAULT_NEAR, transforms_top
from jaxnerf_grid.data.normalize import z_up_normalization
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError


def read_camera(path) -> dict:
    """One Strecha .camera file. Returns {"K": [3, 3], "dist": [3], "R": [3, 3] camera-to-world
    (OpenCV axes), "C": [3] centre, "size": (W, H)}; DataError naming the file when it is not 26
    numbers."""
    path = Path(path)
    try:
        values = [float(v) for v in path.read_text().split()]
    except (OSError, ValueError) as err:
        raise DataError(f"{path}: not a Strecha camera file ({err})") from None
    if len(values) != 26:
        raise DataError(f"{path}: a Strecha camera file holds 26 numbers (K, distortion, R, C, W H), "
                        f"this one {len(values)}")
    v = np.asarray(values, np.float64)
    return {"K": v[0:9].reshape(3, 3), "dist": v[9:12], "R": v[12:21].reshape(3, 3), "C": v[21:24],
            "size": (int(v[24]), int(v[25]))}


def camera_to_world_gl(camera: dict) -> np.ndarray:
    """The OpenGL camera-to-world [4, 4] of a Strecha camera: [R diag(1, -1, -1) | C]."""
    c2w = np.eye(4)
    c2w[:3, :3] = camera["R"]
    c2w[:3, 3] = camera["C"]
    return c2w @ CV_TO_GL


def strecha_dataset(folder, out, overwrite: bool = False) -> Path:
    """Writes OUT/transforms.json for the Strecha scene FOLDER (module docstring). Returns its path."""
    folder, out = Path(folder), Path(out)
    cams_dir, images_dir = folder / "gt_dense_cameras", folder / "images"
    cam_files = sorted(cams_dir.glob("*.camera")) if cams_dir.is_dir() else []
    if not cam_files:
        raise DataError(f"{cams_dir}: no .camera files (expected a Strecha scene folder)")
    target = out / "transforms.json"
    if target.exists() and not overwrite:
        raise DataError(f"{target}: exists; pass --overwrite to replace it")
    cameras, photos = [], []
    for f in cam_files:
        photo = images_dir / f.name[:-len(".camera")]
        if not photo.is_file():
            raise DataError(f"{photo}: the photo of {f.name} is missing")
        cam = read_camera(f)
        if np.any(cam["dist"] != 0):
            raise DataError(f"{f}: lens distortion {cam['dist'].tolist()} is not supported by this converter")
        cameras.append(cam)
        photos.append(photo)
    c2w, norm = z_up_normalization(np.stack([camera_to_world_gl(c) for c in cameras]))
    out.mkdir(parents=True, exist_ok=True)
    frames = []
    for cam, photo, pose in zip(cameras, photos, c2w):
        k = cam["K"]
        frames.append({"file_path": os.path.relpath(photo.resolve(), out.resolve()),
                       "transform_matrix": pose.tolist(), "fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]),
                       "cx": float(k[0, 2]), "cy": float(k[1, 2]), "w": cam["size"][0], "h": cam["size"][1]})
    w, h = cameras[0]["size"]
    top = transforms_top(w, h, DEFAULT_NEAR, DEFAULT_FAR, norm, {}, out, out)  # the loader's defaults
    top["source"] = {"strecha_scene": folder.name, "cameras": "gt_dense_cameras (surveyed)"}
    top["frames"] = frames
    io.write_json(target, top)
    return target


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.strecha_dataset", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", help="a Strecha scene: images/ and gt_dense_cameras/")
    p.add_argument("out", help="dataset folder to write (transforms.json)")
    p.add_argument("--overwrite", action="store_true")
    args = p.parse_args(argv)
    try:
        path = strecha_dataset(args.folder, args.out, args.overwrite)
    except DataError as err:
        print(f"strecha_dataset: error: {err}", file=sys.stderr)
        return 1
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
