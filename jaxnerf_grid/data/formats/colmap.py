"""COLMAP sparse models (text or binary) as datasets: OpenCV world-to-camera to OpenGL c2w,
undistortion, near / far from the points each image sees."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.data.formats import colmap_model as colmap_io
from jaxnerf_grid.data.formats.frames import (
    CV_TO_GL,
    DEFAULT_FAR,
    DEFAULT_NEAR,
    Frame,
    Scene,
    check_split,
    default_split,
    min_ray_cosine,
    scene_to_dataset,
    validate_c2w,
)
from jaxnerf_grid.data.normalize import apply_normalization_to_points, z_up_normalization
from jaxnerf_grid.util.io import DataError


def colmap_w2c_to_c2w_gl(qvec, tvec) -> np.ndarray:
    """COLMAP world-to-camera (qvec (w, x, y, z), tvec [3], OpenCV axes) -> c2w [4, 4] OpenGL."""
    r = colmap_io.qvec_to_rotmat(qvec)
    c2w = np.eye(4)
    c2w[:3, :3] = r.T
    c2w[:3, 3] = -r.T @ np.asarray(tvec, np.float64)
    return c2w @ CV_TO_GL


def _find_colmap(path: Path, images_dir) -> tuple[Path, str, Path, Path]:
    """(model folder, ext, images folder, dataset root) for a scene folder or a model folder."""
    found = colmap_io.find_model_files(path)
    if found is not None:
        model_dir, ext = found
        candidates = [path.parent.parent / "images", path.parent / "images", path / "images"]
    else:
        subs = (path / "sparse" / "0", path / "sparse", path / "colmap" / "sparse" / "0")
        found = next((f for f in (colmap_io.find_model_files(sub) for sub in subs) if f is not None), None)
        if found is None:
            raise DataError(f"{path}: no COLMAP sparse model (looked for cameras.bin/.txt in "
                            f"{path}, {path / 'sparse' / '0'}, {path / 'sparse'})")
        model_dir, ext = found
        candidates = [path / "images"]
    if images_dir is not None:
        image_root = Path(images_dir)
    else:
        found_root = next((c for c in candidates if c.is_dir()), None)
        if found_root is None:
            raise DataError(f"{model_dir}: no images folder next to the COLMAP model "
                            f"(looked in {', '.join(str(c) for c in candidates)}); pass images_dir")
        image_root = found_root
    return model_dir, ext, image_root, image_root.parent


def observation_depths(c2w: np.ndarray, points: np.ndarray, observed: list) -> list[np.ndarray]:
    """Per photo, the z-depths of its observations of sparse points (those in front of it). c2w:
    [N, 3|4, 4] OpenGL; points: [P, 3]; observed: per photo an index array into points (or None).
    Returns N arrays [K_i] float64 (empty where a photo observes none)."""
    out = []
    for m, idx in zip(np.asarray(c2w, np.float64), observed):
        if idx is None or len(idx) == 0:
            out.append(np.zeros(0))
            continue
        z = -(np.asarray(points, np.float64)[np.asarray(idx)] - m[:3, 3]) @ m[:3, 2]  # depth along -z
        out.append(z[z > 0])
    return out


def _near_far_from_points(c2w: np.ndarray, points: np.ndarray, min_cos: float,
                          observed: list | None = None) -> tuple[float, float] | None:
    """Ray-distance bounds from point z-depths (see module docstring).

    c2w: [N, 4, 4] OpenGL, normalised; points: [P, 3] normalised; observed: per frame an index
    array into points (None, or a frame's None: all points, keeping those in front of the camera).
    """
    every = np.arange(len(points))
    per_frame = [every if observed is None or observed[i] is None else observed[i] for i in range(len(c2w))]
    depths = observation_depths(c2w, points, per_frame)
    if sum(len(d) for d in depths) == 0:
        return None
    z = np.concatenate(depths)
    near = max(0.9 * float(np.percentile(z, 0.5)), 1e-3)
    far = 1.1 * float(np.percentile(z, 99.5)) / min_cos
    return near, max(far, 2 * near)


def load_colmap(path, *, downscale: float = 1, load_extras: bool = True, **kwargs) -> Dataset:
    """Loads a COLMAP sparse model and its images; options as in `collect_colmap`."""
    scene = collect_colmap(path, load_extras=load_extras, **kwargs)
    return scene_to_dataset(scene, downscale=downscale, load_extras=False)


def collect_colmap(path, *, images_dir=None, undistort: bool = True, normalize: str | bool = "cameras",
                   honour_exif: bool = True, test_every: int = 8, load_extras: bool = True) -> Scene:
    """Collects a COLMAP sparse model (text or binary) and its images.

    path: a scene folder with sparse/0 (or sparse/) and images/, or the model folder itself
    (images then in ../../images or ../images). Frames sorted by image name; every
    `test_every`-th is a test frame. normalize: "cameras" | "points" | False; when normalising,
    the scene is also turned so the up axis found from the cameras is +z (COLMAP's world frame
    is arbitrary; `normalize.z_up_normalization`, the turn recorded as the "rotation").
    `load_extras` is accepted for a uniform signature (COLMAP has no extras).
    """
    del load_extras  # COLMAP has no extra per-frame files
    model_dir, ext, image_root, root = _find_colmap(Path(path), images_dir)
    cameras_file = model_dir / f"cameras{ext}"
    cameras, images, points3d = colmap_io.read_model(model_dir, ext)
    if not images:
        raise DataError(f"{model_dir / f'images{ext}'}: no registered images (empty split)")
    id_to_index = {pid: i for i, pid in enumerate(points3d)}
    xyz = np.array([p.xyz for p in points3d.values()], np.float64).reshape(-1, 3)
    frames, observed = [], []
    for im in sorted(images.values(), key=lambda im: im.name):
        if im.camera_id not in cameras:
            raise DataError(f"{model_dir / f'images{ext}'}: image {im.name} refers to camera "
                            f"{im.camera_id}, which {cameras_file.name} does not define")
        cam = cameras[im.camera_id]
        intr, dist = colmap_io.pinhole_and_distortion(cam, cameras_file)
        if not np.all(np.isfinite(cam.params)) or min(intr[0], intr[1], cam.width, cam.height) <= 0:
            raise DataError(f"{cameras_file}: camera {cam.id} has invalid parameters "
                            f"{cam.model} {cam.width}x{cam.height} {cam.params.tolist()}")
        source = f"{model_dir / f'images{ext}'} (image {im.name})"
        q = np.asarray(im.qvec, np.float64)
        if not np.all(np.isfinite(q)) or not np.all(np.isfinite(im.tvec)) or np.linalg.norm(q) < 1e-8:
            raise DataError(f"{source}: degenerate pose (non-finite or zero quaternion/translation)")
        c2w = validate_c2w(colmap_w2c_to_c2w_gl(q, im.tvec), source)
        frames.append(Frame(image_root / im.name, c2w, intr, (cam.width, cam.height), dist, None,
                             str(cameras_file)))
        ids = np.asarray(im.point3D_ids, np.int64)
        observed.append(np.array([id_to_index[p] for p in ids if p in id_to_index], np.int64)
                        if len(ids) else None)
    c2w = np.stack([f.c2w for f in frames])
    if normalize is False:
        norm = {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}
    else:
        method = "cameras" if normalize is True else normalize
        c2w, norm = z_up_normalization(c2w, xyz if len(xyz) else None, method=method)
    xyz_norm = apply_normalization_to_points(xyz, norm)
    min_cos = min(min_ray_cosine(f.intrinsics, *f.size) for f in frames)
    bounds = _near_far_from_points(c2w, xyz_norm, min_cos,
                                   observed if any(o is not None and len(o) for o in observed) else None)
    near, far = bounds if bounds is not None else (DEFAULT_NEAR, DEFAULT_FAR)
    split = check_split(default_split(len(frames), test_every), model_dir)
    meta = {"format": "colmap", "source": str(model_dir),
            "camera_models": sorted({cameras[im.camera_id].model for im in images.values()}),
            "points3d": xyz_norm.astype(np.float32), "observed": observed,
            "points3d_rgb": np.array([p.rgb for p in points3d.values()], np.uint8).reshape(-1, 3)}
    return Scene(root, frames, c2w, split, near, far, norm, meta, None, undistort, honour_exif)
