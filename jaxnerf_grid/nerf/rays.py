"""Cameras to rays: pinhole intrinsics, camera-to-world poses, OpenGL axes.

Conventions (docs/CONVENTIONS.md): `c2w` is camera-to-world, [3, 4] or [4, 4]; camera axes are
x right, y up, looking down -z (OpenGL / Blender / transforms.json). Pixel (i, j) with
column i and row j has its centre at (i + 0.5, j + 0.5) in pixel units; image row 0 is the
top of the picture. Ray directions are unit length, so `t` along a ray is metric distance;
z-depth (along the camera's -z axis) is `t * cos_to_axis`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp


class Rays(NamedTuple):
    """A bundle of rays; every field shares the leading batch shape [...].

    origins: [..., 3]; directions: [..., 3] unit; near, far: [...] metric distances;
    cos_to_axis: [...] cosine between ray and camera's viewing axis (z-depth = t * cos).
    """

    origins: jnp.ndarray
    directions: jnp.ndarray
    near: jnp.ndarray
    far: jnp.ndarray
    cos_to_axis: jnp.ndarray


def pixel_grid(width: int, height: int) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Pixel-centre coordinates. Returns (u [H, W], v [H, W]), u along columns, v along rows."""
    u, v = jnp.meshgrid(jnp.arange(width, dtype=jnp.float32) + 0.5,
                        jnp.arange(height, dtype=jnp.float32) + 0.5, indexing="xy")
    return u, v


def camera_directions(u: jnp.ndarray, v: jnp.ndarray, fx, fy, cx, cy) -> jnp.ndarray:
    """Unnormalised camera-frame directions for pixel coordinates.

    u, v: [...] pixel coordinates (centres at +0.5). Returns [..., 3] with z = -1.
    """
    x = (u - cx) / fx
    y = -(v - cy) / fy
    return jnp.stack([x, y, -jnp.ones_like(x)], axis=-1)


def generate_rays(c2w: jnp.ndarray, fx, fy, cx, cy, width: int, height: int,
                  near: float = 0.05, far: float = 1e3) -> Rays:
    """Pinhole rays through every pixel centre of one camera.

    c2w: [3, 4] or [4, 4] camera-to-world (OpenGL axes); fx, fy, cx, cy: scalars in pixels;
    near, far: scalars (metric distances along each unit ray).
    Returns Rays with batch shape [H, W].
    """
    u, v = pixel_grid(width, height)
    return rays_for_pixels(c2w, fx, fy, cx, cy, u, v, near, far)


def rays_for_pixels(c2w: jnp.ndarray, fx, fy, cx, cy, u: jnp.ndarray, v: jnp.ndarray,
                    near=0.05, far=1e3) -> Rays:
    """Rays through arbitrary pixel coordinates.

    c2w: [3, 4], [4, 4], or batched [..., 3|4, 4] broadcastable with u; u, v: [...].
    Returns Rays with batch shape [...].
    """
    c2w = jnp.asarray(c2w, jnp.float32)
    rotation = c2w[..., :3, :3]
    translation = c2w[..., :3, 3]
    cam_dirs = camera_directions(u, v, fx, fy, cx, cy)
    norm = jnp.linalg.norm(cam_dirs, axis=-1)
    world = jnp.einsum("...ij,...j->...i", rotation, cam_dirs)
    directions = world / jnp.linalg.norm(world, axis=-1, keepdims=True)
    origins = jnp.broadcast_to(translation, directions.shape)
    batch = directions.shape[:-1]
    return Rays(
        origins=origins,
        directions=directions,
        near=jnp.broadcast_to(jnp.asarray(near, jnp.float32), batch),
        far=jnp.broadcast_to(jnp.asarray(far, jnp.float32), batch),
        cos_to_axis=1.0 / norm,
    )


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> jnp.ndarray:
    """Camera-to-world [4, 4] for a camera at `eye` looking at `target` (OpenGL axes).

    eye, target, up: [3]. The camera's -z points at the target and +y is as close to `up`
    as possible.
    """
    eye = jnp.asarray(eye, jnp.float32)
    forward = jnp.asarray(target, jnp.float32) - eye
    forward = forward / jnp.linalg.norm(forward)
    right = jnp.cross(forward, jnp.asarray(up, jnp.float32))
    right = right / jnp.linalg.norm(right)
    true_up = jnp.cross(right, forward)
    rotation = jnp.stack([right, true_up, -forward], axis=-1)
    top = jnp.concatenate([rotation, eye[:, None]], axis=-1)
    return jnp.concatenate([top, jnp.array([[0.0, 0.0, 0.0, 1.0]])], axis=0)


def focal_from_fov(fov_x_radians: float, width: int) -> float:
    """Focal length in pixels from a horizontal field of view."""
    return 0.5 * width / float(jnp.tan(0.5 * fov_x_radians))
