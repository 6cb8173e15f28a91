"""Multi-view confirmation: does another photo see this pixel's colour at its 3-D point?

The photometric evidence (`robust.py`) judges a pixel by how well the static model explains
it. That cannot tell a transient from static detail the model has not learnt yet: a thin
window frame, a drain pipe or a high-contrast edge leaves a large residual in every batch,
exactly as a bird does. The photos themselves can. Put the pixel at its rendered depth (the
ray's median depth: a 3-D point), project that point into neighbouring training photos and
compare the pixel's 3x3 neighbourhood in its own photo with the 3x3 neighbourhood at the
projection in each of them: a static point shows the same colours in some other photo; a
passer-by, a bird or a car is where it is in one photo only, and at its 3-D point (the static
surface behind it, where the model puts it) the other photos show the background.

`confirmation_errors` returns, per pixel, the smallest mean squared difference of the two
3x3 neighbourhoods over the neighbouring photos that see the point (in front of the camera,
the 3x3 neighbourhood inside the photo), +inf where none does. `robust.robust_weights` counts a
pixel whose error is at most train.robust.confirm as an inlier, whatever its residual
(docs/ROBUST.md has the measurements that chose the default). Nothing here is differentiated:
the depth is stop-gradient, the colours are photos.

Neighbours (`neighbour_frames`): for each training frame the K others whose cameras are
nearest (centre distance, ties broken by frame order); near viewpoints see the same surfaces
with the least occlusion and foreshortening, and K bounds the cost for captures of hundreds
of photos. Camera conventions are those of `rays.py` (OpenGL axes: the camera looks down -z,
+y up; pixel centres at +0.5).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

OFFSETS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1))  # the 3x3 neighbourhood


def neighbour_frames(c2w: np.ndarray, count: int) -> np.ndarray:
    """For each frame the `count` other frames with the nearest camera centres.

    c2w: [T, 3|4, 4]; count: K >= 1. Returns [T, min(K, T - 1)] int32 frame indices (into
    c2w), nearest first; [T, 0] for a single frame."""
    centres = np.asarray(c2w, np.float64)[:, :3, 3]
    frames = centres.shape[0]
    k = max(0, min(int(count), frames - 1))
    dist = np.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=-1)
    dist[np.arange(frames), np.arange(frames)] = np.inf
    return np.argsort(dist, axis=1, kind="stable")[:, :k].astype(np.int32)


def project(points: jnp.ndarray, c2w: jnp.ndarray, intrinsics: jnp.ndarray) -> tuple:
    """Pixel coordinates of world points in cameras (the inverse of `rays.rays_for_pixels`).

    points: [..., 3]; c2w: [..., 3|4, 4]; intrinsics: [..., 4] (fx, fy, cx, cy), broadcast
    together. Returns (u, v, in_front): [...] float pixel coordinates (centres at +0.5) and
    bool, True where the point lies in front of the camera."""
    rotation, centre = c2w[..., :3, :3], c2w[..., :3, 3]
    cam = jnp.einsum("...ji,...j->...i", rotation, points - centre)  # R^T (X - C)
    ahead = -cam[..., 2]
    safe = jnp.where(ahead > 1e-6, ahead, 1.0)
    u = intrinsics[..., 2] + intrinsics[..., 0] * cam[..., 0] / safe
    v = intrinsics[..., 3] - intrinsics[..., 1] * cam[..., 1] / safe
    return u, v, ahead > 1e-6


def neighbourhoods(images: jnp.ndarray, frame: jnp.ndarray, row: jnp.ndarray, col: jnp.ndarray,
                   table: jnp.ndarray | None = None) -> jnp.ndarray:
    """The 3x3 neighbourhood of pixels, rows and columns clamped to the photo.

    images: [T, H, W, 3] float, or uint8 codes read through `table` [256] (the float value of
    each byte: `ray_pool.BYTE_VALUES`); frame, row, col: [...] int. Returns [..., 9, 3] float
    (OFFSETS order)."""
    _, height, width, _ = images.shape
    rows = jnp.clip(row[..., None] + jnp.array([dy for dy, _ in OFFSETS]), 0, height - 1)
    cols = jnp.clip(col[..., None] + jnp.array([dx for _, dx in OFFSETS]), 0, width - 1)
    values = images[frame[..., None], rows, cols]
    return values if table is None else jnp.asarray(table)[values]


def confirmation_errors(images: jnp.ndarray, c2w: jnp.ndarray, intrinsics: jnp.ndarray,
                        neighbours: jnp.ndarray, frame: jnp.ndarray, row: jnp.ndarray, col: jnp.ndarray,
                        points: jnp.ndarray, table: jnp.ndarray | None = None) -> jnp.ndarray:
    """The smallest 3x3-neighbourhood colour difference of each pixel over its neighbour photos.

    images: [T, H, W, 3]; c2w: [T, 4, 4]; intrinsics: [T, 4]; neighbours: [T, K] frame
    indices (`neighbour_frames`); frame, row, col: [N] int the pixels; points: [N, 3] their
    3-D points (world); table: as `neighbourhoods`. Returns [N]: min over the K neighbours that see the point (in front,
    the whole 3x3 neighbourhood inside the photo) of mean((own - theirs)^2) over the 27
    values; +inf where no neighbour sees it (or K = 0)."""
    _, height, width, _ = images.shape
    own = neighbourhoods(images, frame, row, col, table)               # [N, 9, 3]
    others = neighbours[frame]                                         # [N, K]
    u, v, ahead = project(points[:, None, :], c2w[others], intrinsics[others])
    pu, pv = jnp.floor(u), jnp.floor(v)
    inside = ahead & (pu >= 1) & (pu <= width - 2) & (pv >= 1) & (pv <= height - 2)
    pu = jnp.clip(pu, 0, width - 1).astype(jnp.int32)
    pv = jnp.clip(pv, 0, height - 1).astype(jnp.int32)
    theirs = neighbourhoods(images, others, pv, pu, table)             # [N, K, 9, 3]
    error = jnp.mean((theirs - own[:, None]) ** 2, axis=(-2, -1))      # [N, K]
    return jnp.min(jnp.where(inside, error, jnp.inf), axis=-1, initial=jnp.inf)


def confirmed_at_ids(images: jnp.ndarray, c2w: jnp.ndarray, intrinsics: jnp.ndarray, neighbours: jnp.ndarray,
                     ids: jnp.ndarray, points: jnp.ndarray, threshold: float,
                     table: jnp.ndarray | None = None) -> jnp.ndarray:
    """Which pixels a neighbouring photo confirms: the training step's join.

    ids: [N] flat pixel indices into the training frames [T, H, W] (frame * H * W + row * W +
    col, as `robust.draw_patches` and `train.gather_batch` number them); points: [N, 3] each
    pixel's 3-D point (world); the rest as `confirmation_errors`. Returns [N] float32: 1.0 where
    the smallest 3x3 difference is at most `threshold`, else 0.0."""
    _, height, width, _ = images.shape
    frame, pixel = ids // (height * width), ids % (height * width)
    error = confirmation_errors(images, c2w, intrinsics, neighbours, frame, pixel // width, pixel % width, points,
                                table)
    return (error <= threshold).astype(jnp.float32)
