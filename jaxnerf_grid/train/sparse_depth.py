"""Depth from the capture's sparse points as a training prior (train.depth, docs/RECIPES.md).

`poses` leaves the structure-from-motion model in DATA/sparse/0: every 3-D point with the photos
that see it. A point seen by a training photo fixes where that photo's ray towards it should
stop, which the photos' colours alone pin poorly where few photos overlap (the ends of an arc, a
facade seen by eight photos). As DS-NeRF (Deng et al. 2022) and Urban Radiance Fields do, the
step renders a few of those rays beside its colour batch and pulls each ray's weights towards
the point's distance:

    l_r = sum_i w_i * min(max(|log t_i - log t*_r| - tol, 0), cap)

with w_i the final pass's weights and t_i its bin midpoints: zero when all of the ray's weight
lies within a relative `tol` of the point, growing with the weight in front of it (a floater)
or behind it (a hole). The weight of the term decays log-linearly from `weight` to
`weight * decay` over the run (a fraction of max_steps, so it stretches with the budget): the
points shape the geometry early and the colours finish it.

Only points that at least `min_views` training photos see, with a reprojection error of at most
`max_error_px`, are used, so no held-out photo decides a training target. The rays are the
camera centre towards the point (no pixel rounding); the table is built on the host once.
"""

from __future__ import annotations

import logging
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.capture import georef
from jaxnerf_grid.data.formats import colmap_model

logger = logging.getLogger(__name__)

SPARSE_FOLDER = ("sparse", "0")
# The model's camera centres, moved by the fitted similarity, must land on the dataset's within
# this share of the cameras' spread, else the model is not the dataset's and is not used.
CENTRE_TOLERANCE = 1e-3


def model_folder(root) -> Path:
    """DATA/sparse/0, where `poses` writes its model."""
    return Path(root).joinpath(*SPARSE_FOLDER)


def observations(points: np.ndarray, seen_by: list[np.ndarray], c2w: np.ndarray, intrinsics: np.ndarray,
                 width: int, height: int, min_views: int = 2) -> dict:
    """The depth rays of points seen by training cameras.

    points: [P, 3] in the cameras' frame; seen_by: P arrays of the training cameras (indices
    into c2w) that see each point; c2w: [T, 4, 4] OpenGL camera-to-world; intrinsics: [T, 4]
    (fx, fy, cx, cy) in pixels of width x height frames. A point counts when at least min_views
    training cameras see it; each such (point, camera) pair whose point projects in front of
    the camera and inside its frame is a ray.
    Returns {"origins": [R, 3], "directions": [R, 3] unit, "t": [R] distance to the point,
    "camera": [R] int32 index into c2w}, float32.
    """
    origins, directions, dist, camera = [], [], [], []
    for p, cams in zip(np.asarray(points, np.float64), seen_by):
        cams = np.unique(np.asarray(cams, np.int64))
        if cams.size < min_views:
            continue
        for k in cams:
            rot, centre = c2w[k, :3, :3].astype(np.float64), c2w[k, :3, 3].astype(np.float64)
            local = rot.T @ (p - centre)  # OpenGL: the camera looks down -z
            if local[2] >= 0:
                continue
            fx, fy, cx, cy = intrinsics[k]
            u = cx + fx * local[0] / -local[2]
            v = cy - fy * local[1] / -local[2]
            if not (0 <= u < width and 0 <= v < height):
                continue
            t = float(np.linalg.norm(p - centre))
            origins.append(centre)
            directions.append((p - centre) / t)
            dist.append(t)
            camera.append(k)
    as32 = lambda a, shape: np.asarray(a, np.float32).reshape(shape)  # noqa: E731
    return {"origins": as32(origins, (-1, 3)), "directions": as32(directions, (-1, 3)), "t": as32(dist, (-1,)),
            "camera": np.asarray(camera, np.int32)}


def from_model(folder, frame_names: list[str], c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int,
               max_error_px: float = 2.0, min_views: int = 2) -> tuple[dict | None, str]:
    """The depth rays of the sparse model in `folder` for the training cameras named frame_names
    (matched to the model's images by file name; c2w [T, 4, 4] and intrinsics [T, 4] as the
    dataset holds them). The model is moved onto the dataset's cameras by the similarity that
    maps its camera centres onto theirs. Returns (rays as `observations` gives them, or None, and
    a sentence saying what was used or why nothing was)."""
    folder = Path(folder)
    if colmap_model.find_model_files(folder) is None:
        return None, f"no sparse model in {folder}"
    _, images, points = colmap_model.read_model(folder)
    index = {Path(name).name: k for k, name in enumerate(frame_names)}
    image_to_camera = {img.id: index[Path(img.name).name] for img in images.values()
                       if Path(img.name).name in index}
    if len(image_to_camera) < 3:
        return None, f"{folder}: {len(image_to_camera)} of its photos are training frames (need 3)"
    ids = list(image_to_camera)
    model_centres = np.stack([-colmap_model.qvec_to_rotmat(images[i].qvec).T @ images[i].tvec for i in ids])
    data_centres = np.asarray(c2w, np.float64)[[image_to_camera[i] for i in ids], :3, 3]
    scale, rot, shift = georef.umeyama(model_centres, data_centres)
    spread = float(np.max(np.linalg.norm(data_centres - data_centres.mean(0), axis=1)))
    misfit = float(np.max(np.linalg.norm(scale * model_centres @ rot.T + shift - data_centres, axis=1)))
    if not spread > 0 or misfit > CENTRE_TOLERANCE * spread:
        return None, (f"{folder}: its cameras do not match the dataset's (off by {misfit:.3g}, spread "
                      f"{spread:.3g}); the sparse points are not used")
    kept = [pt for pt in points.values() if pt.error <= max_error_px]
    xyz = np.asarray([pt.xyz for pt in kept], np.float64).reshape(-1, 3) * scale @ rot.T + shift
    seen = [np.asarray([image_to_camera[i] for i in pt.track[:, 0] if i in image_to_camera], np.int64)
            for pt in kept]
    rays = observations(xyz, seen, np.asarray(c2w), np.asarray(intrinsics), width, height, min_views)
    count = len(rays["t"])
    if count == 0:
        return None, f"{folder}: no sparse point is seen by {min_views} training photos"
    return rays, (f"{count} depth rays from {len(kept)} sparse points (reprojection error <= "
                  f"{max_error_px:g} px, seen by >= {min_views} training photos)")


def dataset_rays(dataset, train_ids: np.ndarray, max_error_px: float, min_views: int) -> tuple[dict | None, str]:
    """`from_model` on the dataset's DATA/sparse/0 and its training frames; "camera" becomes the
    dataset's frame id (the appearance embedding's index)."""
    train_ids = np.asarray(train_ids, np.int64)
    if not dataset.frame_paths:
        return None, "the dataset names no frame files"
    names = [dataset.frame_paths[int(i)] for i in train_ids]
    rays, why = from_model(model_folder(dataset.root), names, np.asarray(dataset.c2w)[train_ids],
                           np.asarray(dataset.intrinsics)[train_ids], dataset.width, dataset.height,
                           max_error_px, min_views)
    if rays is not None:
        rays["camera"] = train_ids[rays["camera"]].astype(np.int32)
    return rays, why


def ray_loss(t_edges: jnp.ndarray, weights: jnp.ndarray, t_target: jnp.ndarray, tolerance: float,
             cap: float = 1.0) -> jnp.ndarray:
    """The module docstring's l_r. t_edges: [B, S + 1] bin edges (distance); weights: [B, S];
    t_target: [B]. Returns [B]."""
    mid = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
    gap = jnp.abs(jnp.log(jnp.maximum(mid, 1e-6)) - jnp.log(jnp.maximum(t_target, 1e-6))[..., None])
    return jnp.sum(weights * jnp.minimum(jnp.maximum(gap - tolerance, 0.0), cap), axis=-1)


def weight_at(step, weight: float, decay: float, max_steps: int, start: float = 0.0) -> jnp.ndarray:
    """The term's weight at optimiser step `step` (traceable): zero before start * max_steps, then
    weight * decay ** (step / max_steps), held at weight * decay after max_steps. Returns float32 []."""
    u = jnp.clip(jnp.asarray(step, jnp.float32) / max(int(max_steps), 1), 0.0, 1.0)
    return jnp.where(u < start, 0.0, jnp.float32(weight) * jnp.power(jnp.float32(decay), u)).astype(jnp.float32)


RAY_KEYS = ("origins", "directions", "t", "camera")


def draw(table: dict, key, count: int) -> dict:
    """`count` rays of the table drawn uniformly with replacement from `key`: dict of [count, ...]
    (RAY_KEYS; the table's other entries, such as its near and far, are not per ray)."""
    pick = jax.random.randint(key, (count,), 0, table["t"].shape[0])
    return {k: table[k][pick] for k in RAY_KEYS}
