"""Pinhole rays: projecting a point along a ray lands back on its pixel; OpenGL axes."""

import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.nerf import rays


def project(point, c2w, fx, fy, cx, cy):
    """Independent pinhole projection with OpenGL camera axes (looks down -z, y up)."""
    w2c = np.linalg.inv(c2w)
    p = w2c[:3, :3] @ point + w2c[:3, 3]
    return np.array([fx * p[0] / -p[2] + cx, -fy * p[1] / -p[2] + cy]), -p[2]


def test_rays_reproject_to_pixel_centres():
    c2w = np.asarray(rays.look_at([4.0, -3.0, 2.0], [0.0, 0.0, 0.5]))
    fx, fy, cx, cy, w, h = 50.0, 55.0, 15.5, 11.0, 32, 24
    bundle = rays.generate_rays(jnp.asarray(c2w), fx, fy, cx, cy, w, h, near=0.1, far=10.0)
    assert bundle.origins.shape == (h, w, 3) and bundle.near.shape == (h, w)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(bundle.directions), axis=-1), 1.0, atol=1e-6)
    for j, i in [(0, 0), (5, 17), (23, 31)]:
        t = 3.7
        point = np.asarray(bundle.origins[j, i] + t * bundle.directions[j, i])
        uv, z = project(point, c2w, fx, fy, cx, cy)
        np.testing.assert_allclose(uv, [i + 0.5, j + 0.5], atol=1e-3)
        np.testing.assert_allclose(z, t * float(bundle.cos_to_axis[j, i]), rtol=1e-5)


def test_look_at_points_camera_at_target():
    eye, target = np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.0])
    c2w = np.asarray(rays.look_at(eye, target))
    forward = -c2w[:3, 2]
    np.testing.assert_allclose(forward, (target - eye) / np.linalg.norm(target - eye), atol=1e-6)
    np.testing.assert_allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-6)
    assert np.linalg.det(c2w[:3, :3]) > 0
    assert c2w[2, 1] > 0  # camera up has a positive world-z component
    np.testing.assert_allclose(rays.focal_from_fov(np.pi / 2, 100), 50.0, rtol=1e-6)
