"""photo_consistency.py: projection against the rays it inverts and against np.linalg.inv,
confirmation errors against a NumPy loop, and the idea itself on an analytic textured wall
seen by three cameras: static texture is confirmed, a square pasted in one photo is not."""

import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.masks import photo_consistency as pc
from jaxnerf_grid.nerf import rays


def cameras(xs, height=3.0):
    """c2w [T, 4, 4] of cameras at (x, 0, height) looking at (x / 2, 0, 0) (OpenGL axes)."""
    return np.stack([np.asarray(rays.look_at(jnp.array([x, 0.1 * x, height]), jnp.array([0.5 * x, 0.0, 0.0]),
                                             up=(0.0, 1.0, 0.0))) for x in xs]).astype(np.float32)


def test_neighbours_are_the_nearest_other_cameras():
    rng = np.random.default_rng(0)
    c2w = np.tile(np.eye(4, dtype=np.float32), (7, 1, 1))
    c2w[:, :3, 3] = rng.normal(size=(7, 3))
    got = pc.neighbour_frames(c2w, 3)
    for i in range(7):
        dist = sorted((float(np.linalg.norm(c2w[i, :3, 3] - c2w[j, :3, 3])), j) for j in range(7) if j != i)
        assert list(got[i]) == [j for _, j in dist[:3]]
    assert pc.neighbour_frames(c2w, 50).shape == (7, 6)
    assert pc.neighbour_frames(c2w[:1], 4).shape == (1, 0)


def test_projection_inverts_the_rays_and_matches_the_inverse_matrix():
    rng = np.random.default_rng(1)
    c2w = cameras([-0.4, 0.0, 0.7])
    intr = np.array([[40.0, 42.0, 16.5, 12.0], [35.0, 35.0, 15.0, 11.0], [50.0, 48.0, 17.0, 13.5]], np.float32)
    u = rng.uniform(0, 32, 20).astype(np.float32)
    v = rng.uniform(0, 24, 20).astype(np.float32)
    for k in range(3):
        r = rays.rays_for_pixels(c2w[k], *intr[k], jnp.asarray(u), jnp.asarray(v))
        pts = r.origins + r.directions * jnp.asarray(rng.uniform(0.5, 9.0, (20, 1)), jnp.float32)
        pu, pv, ahead = pc.project(pts, jnp.asarray(c2w[k]), jnp.asarray(intr[k]))
        np.testing.assert_allclose(np.asarray(pu), u, atol=2e-3)
        np.testing.assert_allclose(np.asarray(pv), v, atol=2e-3)
        assert np.all(np.asarray(ahead))
        # the same with the inverse matrix and the pinhole formula written out (OpenGL: -z ahead)
        cam = (np.linalg.inv(c2w[k].astype(np.float64)) @ np.c_[np.asarray(pts), np.ones(20)].T).T
        fx, fy, cx, cy = intr[k]
        np.testing.assert_allclose(np.asarray(pu), cx + fx * cam[:, 0] / -cam[:, 2], atol=2e-3)
        np.testing.assert_allclose(np.asarray(pv), cy - fy * cam[:, 1] / -cam[:, 2], atol=2e-3)
    behind = jnp.asarray(c2w[0, :3, 3] + c2w[0, :3, 2] * 2.0)  # +z of the camera: behind it
    assert not bool(pc.project(behind, jnp.asarray(c2w[0]), jnp.asarray(intr[0]))[2])


def reference_errors(images, c2w, intr, neighbours, frame, row, col, points):
    """The docstring's rule with loops and np.linalg.inv."""
    _, height, width, _ = images.shape

    def hood(t, r, c):
        return np.array([images[t, min(max(r + dy, 0), height - 1), min(max(c + dx, 0), width - 1)]
                         for dy in (-1, 0, 1) for dx in (-1, 0, 1)])

    out = []
    for f, r, c, x in zip(frame, row, col, points):
        best = np.inf
        for j in neighbours[f]:
            cam = np.linalg.inv(c2w[j].astype(np.float64)) @ np.r_[x, 1.0]
            if -cam[2] <= 1e-6:
                continue
            fx, fy, cx, cy = intr[j]
            pu, pv = np.floor(cx + fx * cam[0] / -cam[2]), np.floor(cy - fy * cam[1] / -cam[2])
            if not (1 <= pu <= width - 2 and 1 <= pv <= height - 2):
                continue
            best = min(best, float(np.mean((hood(j, int(pv), int(pu)) - hood(f, r, c)) ** 2)))
        out.append(best)
    return np.array(out)


def test_confirmation_errors_match_a_numpy_loop():
    rng = np.random.default_rng(2)
    c2w = cameras([-0.6, -0.2, 0.2, 0.6])
    intr = np.tile(np.array([[30.0, 30.0, 10.0, 8.0]], np.float32), (4, 1))
    images = rng.uniform(size=(4, 16, 20, 3)).astype(np.float32)
    neighbours = pc.neighbour_frames(c2w, 2)
    frame = rng.integers(0, 4, 60)
    row, col = rng.integers(0, 16, 60), rng.integers(0, 20, 60)
    points = rng.uniform([-1.5, -1.2, -0.5], [1.5, 1.2, 0.5], (60, 3)).astype(np.float32)
    got = np.asarray(pc.confirmation_errors(*map(jnp.asarray, (images, c2w, intr, neighbours, frame, row, col,
                                                               points))))
    want = reference_errors(images, c2w, intr, neighbours, frame, row, col, points)
    assert np.isfinite(want).sum() > 20 and np.isinf(want).sum() > 0  # both cases are exercised
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], rtol=1e-5, atol=1e-7)


def wall_views(c2w, intr, height=24, width=32):
    """Photos of the textured wall z = 0 and each pixel's distance to it: [T, H, W, 3], [T, H, W]."""
    images, depths = [], []
    for k in range(len(c2w)):
        r = rays.generate_rays(jnp.asarray(c2w[k]), *intr[k], width, height)
        o, d = np.asarray(r.origins, np.float64), np.asarray(r.directions, np.float64)
        t = -o[..., 2] / d[..., 2]
        x = o + d * t[..., None]
        colour = 0.5 + 0.35 * np.stack([np.sin(1.5 * x[..., 0]), np.cos(1.3 * x[..., 1]),
                                        np.sin(1.1 * (x[..., 0] + x[..., 1]))], -1)
        images.append(colour)
        depths.append(t)
    return np.asarray(images, np.float32), np.asarray(depths, np.float32)


def test_a_static_wall_is_confirmed_and_a_pasted_square_is_not():
    c2w = cameras([-0.3, 0.0, 0.3])
    intr = np.tile(np.array([[30.0, 30.0, 16.0, 12.0]], np.float32), (3, 1))
    images, depth = wall_views(c2w, intr)
    images[1, 8:15, 12:19] = [1.0, 0.0, 1.0]  # a magenta transient in the middle photo only
    rows, cols = np.mgrid[0:24, 0:32]
    frame = np.ones(24 * 32, np.int32)
    r = rays.generate_rays(jnp.asarray(c2w[1]), *intr[1], 32, 24)
    points = np.asarray(r.origins).reshape(-1, 3) + np.asarray(r.directions).reshape(-1, 3) * depth[1].reshape(-1, 1)
    err = np.asarray(pc.confirmation_errors(jnp.asarray(images), jnp.asarray(c2w), jnp.asarray(intr),
                                            jnp.asarray(pc.neighbour_frames(c2w, 2)), jnp.asarray(frame),
                                            jnp.asarray(rows.ravel()), jnp.asarray(cols.ravel()),
                                            jnp.asarray(points))).reshape(24, 32)
    inside = err[9:14, 13:18]
    assert inside.min() > 0.1, inside  # nobody else saw magenta there
    static = np.ones((24, 32), bool)
    static[6:17, 10:21] = False  # clear of the square and its 3x3 neighbourhoods
    static[:, :3] = static[:, -3:] = static[:2] = static[-2:] = False  # seen by some neighbour
    assert np.all(err[static] < 0.005), err[static].max()
    # the same pixels at a wrong depth (halfway to the camera) match their neighbours worse
    wrong = np.asarray(pc.confirmation_errors(jnp.asarray(images), jnp.asarray(c2w), jnp.asarray(intr),
                                              jnp.asarray(pc.neighbour_frames(c2w, 2)), jnp.asarray(frame),
                                              jnp.asarray(rows.ravel()), jnp.asarray(cols.ravel()),
                                              jnp.asarray(points * 0.5 + np.asarray(c2w[1, :3, 3]) * 0.5)))
    wrong = wrong.reshape(24, 32)[static]
    assert np.mean(wrong[np.isfinite(wrong)]) > 3 * np.mean(err[static]), (wrong.mean(), err[static].mean())


def test_confirmed_at_ids_splits_flat_ids_as_numpy_unravels_them():
    """The training step's join: flat pixel ids into [T, H, W] frames (H = 16 != W = 20, so rows
    and columns cannot be crossed unseen) -> frame, row, col by np.unravel_index -> the NumPy
    loop's errors -> 1 at most the threshold (the middle one of them: both answers occur, and one error
    equals it), else 0."""
    rng = np.random.default_rng(7)
    c2w = cameras([-0.6, -0.2, 0.2, 0.6])
    intr = np.tile(np.array([[30.0, 30.0, 10.0, 8.0]], np.float32), (4, 1))
    images = rng.uniform(size=(4, 16, 20, 3)).astype(np.float32)
    neighbours = pc.neighbour_frames(c2w, 2)
    ids = rng.integers(0, 4 * 16 * 20, 80)
    points = rng.uniform([-1.5, -1.2, -0.5], [1.5, 1.2, 0.5], (80, 3)).astype(np.float32)
    frame, row, col = np.unravel_index(ids, (4, 16, 20))
    want_err = reference_errors(images, c2w, intr, neighbours, frame, row, col, points)
    threshold = float(np.sort(want_err[np.isfinite(want_err)])[np.isfinite(want_err).sum() // 2])  # one of them
    got = np.asarray(pc.confirmed_at_ids(*map(jnp.asarray, (images, c2w, intr, neighbours, ids, points)), threshold))
    want = (want_err <= threshold).astype(np.float32)
    assert 10 < want.sum() < 70 and got.dtype == np.float32
    np.testing.assert_array_equal(got, want)
