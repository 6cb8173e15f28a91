"""Loaders: COLMAP (text + binary), Blender, transforms.json with extras, LLFF, downscale,
undistortion, normalisation. References are built by hand (look_at poses, quaternions from
scipy, pinhole projection written out here), never by the loaders themselves."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxnerf_grid.data import formats
from jaxnerf_grid.data import normalize as formats_normalize
from jaxnerf_grid.data.formats import colmap_model as colmap_io
from jaxnerf_grid.data.normalize import (
    apply_normalization_to_points,
    compose_normalization,
    invert_normalization,
    normalize_poses,
    optical_axis_focus,
)
from jaxnerf_grid.nerf import rays
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError
from tests.support.blobs import blob, centroid

TARGET = np.array([0.3, -0.2, 1.0])
W, H = 40, 30
FX, FY, CX, CY = 36.0, 34.0, 19.0, 16.0


def _look_at_poses(n=6, radius=4.0, height=1.5, target=TARGET):
    eyes = [target + np.array([radius * np.cos(a), radius * np.sin(a), height])
            for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
    return np.stack([np.asarray(rays.look_at(e, target), np.float64) for e in eyes]), np.stack(eyes)


def _project(x, c2w_gl, fx, fy, cx, cy):
    """Pinhole projection written out independently: OpenGL camera looks down -z, v grows down."""
    rel = np.linalg.inv(c2w_gl) @ np.append(x, 1.0)
    xc, yc, zc = rel[:3]
    return fx * xc / -zc + cx, fy * -yc / -zc + cy


def _ray_miss(c2w, intr, u, v, x):
    """Distance from point x to the ray through pixel (u, v)."""
    r = rays.rays_for_pixels(np.asarray(c2w, np.float32), *[float(k) for k in intr],
                             np.float32(u), np.float32(v))
    o, d = np.asarray(r.origins, np.float64), np.asarray(r.directions, np.float64)
    rel = x - o
    return float(np.linalg.norm(rel - (rel @ d) * d))


def _write_colmap_scene(root, c2w_gl, ext, model="PINHOLE", params=(FX, FY, CX, CY), points=None,
                        images=None):
    """Writes a COLMAP model by hand from OpenGL c2w: w2c = inv(c2w_gl @ diag(1,-1,-1,1))."""
    cams = {1: colmap_io.Camera(1, model, W, H, np.array(params, float))}
    imgs = {}
    points = np.zeros((0, 3)) if points is None else points
    for i, m in enumerate(c2w_gl):
        c2w_cv = m @ np.diag([1.0, -1.0, -1.0, 1.0])
        rot = c2w_cv[:3, :3].T
        tvec = -rot @ c2w_cv[:3, 3]
        x, y, z, w = Rotation.from_matrix(rot).as_quat()
        imgs[i + 1] = colmap_io.Image(i + 1, np.array([w, x, y, z]), tvec, 1, f"img_{i:02d}.png",
                                      np.full((len(points), 2), 5.0), np.arange(1, len(points) + 1))
    pts = {j + 1: colmap_io.Point3D(j + 1, p, np.array([10, 20, 30], np.uint8), 0.5,
                                    np.array([[i + 1, j] for i in range(len(c2w_gl))]))
           for j, p in enumerate(points)}
    colmap_io.write_model(root / "sparse" / "0", cams, imgs, pts, ext=ext)
    for i in range(len(c2w_gl)):
        img = np.full((H, W, 3), 0.25, np.float32) if images is None else images[i]
        io.write_png(root / "images" / f"img_{i:02d}.png", img)
    return cams, imgs, pts


@pytest.mark.parametrize("ext", [".txt", ".bin"])
def test_colmap_roundtrip_matches_look_at(tmp_path, ext):
    c2w_ref, eyes = _look_at_poses()
    rng = np.random.default_rng(0)
    pts = TARGET + rng.uniform(-0.8, 0.8, size=(50, 3))
    cams, imgs, points = _write_colmap_scene(tmp_path, c2w_ref, ext, points=pts)
    # the readers give back exactly what was written
    cams2, imgs2, points2 = colmap_io.read_model(tmp_path / "sparse" / "0")
    assert cams2[1].model == "PINHOLE" and np.array_equal(cams2[1].params, cams[1].params)
    for k in imgs:
        assert imgs2[k].name == imgs[k].name
        np.testing.assert_array_equal(imgs2[k].qvec, imgs[k].qvec)
        np.testing.assert_array_equal(imgs2[k].tvec, imgs[k].tvec)
        np.testing.assert_array_equal(imgs2[k].point3D_ids, imgs[k].point3D_ids)
    assert len(points2) == 50 and np.array_equal(points2[3].track, points[3].track)
    np.testing.assert_array_equal(points2[7].xyz, points[7].xyz)

    ds = formats.load_colmap(tmp_path, normalize=False)
    assert formats.detect_format(tmp_path) == "colmap"
    np.testing.assert_allclose(ds.c2w, c2w_ref, atol=1e-5)
    np.testing.assert_allclose(ds.intrinsics, np.tile([FX, FY, CX, CY], (6, 1)), atol=1e-5)
    assert ds.images.shape == (6, H, W, 3)
    # a 3-D point projected by hand lies on the loader's ray through that pixel
    x = TARGET + np.array([0.2, 0.1, -0.3])
    for i in range(6):
        u, v = _project(x, c2w_ref[i], FX, FY, CX, CY)
        assert _ray_miss(ds.c2w[i], ds.intrinsics[i], u, v, x) < 1e-4
    # near/far bracket every point's ray distance
    dist = np.linalg.norm(pts[None] - eyes[:, None], axis=-1)
    assert ds.near <= dist.min() and ds.far >= dist.max()


def test_colmap_normalised_centre_and_scale(tmp_path):
    c2w_ref, eyes = _look_at_poses()
    rng = np.random.default_rng(1)
    pts = TARGET + rng.uniform(-0.6, 0.6, size=(200, 3))
    _write_colmap_scene(tmp_path, c2w_ref, ".bin", points=pts)
    ds = formats.load_colmap(tmp_path)  # via the model folder path too
    ds2 = formats.load_dataset(tmp_path / "sparse" / "0")
    np.testing.assert_allclose(ds.c2w, ds2.c2w)
    # every camera looks at TARGET, so the centre is TARGET: x_norm = s (x - TARGET)
    np.testing.assert_allclose(ds.normalization["translation"], -TARGET, atol=1e-6)
    s = ds.normalization["scale"]
    np.testing.assert_allclose(ds.c2w[:, :3, 3], s * (eyes - TARGET), atol=1e-5)
    np.testing.assert_allclose(ds.c2w[:, :3, :3], c2w_ref[:, :3, :3], atol=1e-6)
    inside = np.linalg.norm(s * (pts - TARGET), axis=-1) <= 1.0
    assert 0.9 <= inside.mean() < 1.0  # the 95th-percentile extent maps to radius 1
    np.testing.assert_allclose(ds.meta["points3d"], s * (pts - TARGET), atol=1e-5)


@pytest.mark.parametrize("model,params,expect", [
    ("SIMPLE_PINHOLE", (FX, CX, CY), (FX, FX, CX, CY)),
    ("SIMPLE_RADIAL", (FX, CX, CY, 0.0), (FX, FX, CX, CY)),
    ("RADIAL", (FX, CX, CY, 0.0, 0.0), (FX, FX, CX, CY)),
    ("OPENCV", (FX, FY, CX, CY, 0.0, 0.0, 0.0, 0.0), (FX, FY, CX, CY)),
])
def test_colmap_camera_models(tmp_path, model, params, expect):
    c2w_ref, _ = _look_at_poses(n=3)
    _write_colmap_scene(tmp_path, c2w_ref, ".txt", model=model, params=params)
    ds = formats.load_colmap(tmp_path, normalize=False)
    np.testing.assert_allclose(ds.intrinsics[0], expect, atol=1e-5)
    assert ds.meta["camera_models"] == [model] and not ds.meta["undistorted"]


def _distort(u_pin, v_pin, fx, fy, cx, cy, k1, k2, p1, p2):
    """Brown-Conrady distortion written out (COLMAP's OPENCV model)."""
    x, y = (u_pin - cx) / fx, (v_pin - cy) / fy
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return fx * xd + cx, fy * yd + cy


def test_colmap_opencv_undistorted_on_load(tmp_path):
    c2w_ref, _ = _look_at_poses(n=2)
    dist = (-0.6, 0.1, 0.01, -0.01)
    u, v = 9.0, 7.5  # pinhole pixel away from the centre; x is a point on its ray
    x = c2w_ref[0][:3, :3] @ (3.0 * np.array([(u - CX) / FX, -(v - CY) / FY, -1.0])) + c2w_ref[0][:3, 3]
    np.testing.assert_allclose(_project(x, c2w_ref[0], FX, FY, CX, CY), (u, v), atol=1e-9)
    ud, vd = _distort(u, v, FX, FY, CX, CY, *dist)
    assert np.hypot(ud - u, vd - v) > 0.6  # the distortion matters at this pixel
    imgs = [blob(ud, vd, W, H), blob(ud, vd, W, H)]
    _write_colmap_scene(tmp_path, c2w_ref, ".txt", model="OPENCV", params=(FX, FY, CX, CY, *dist),
                        images=imgs)
    ds = formats.load_colmap(tmp_path, normalize=False)
    # reference: each pinhole pixel centre samples the blob at its distorted position
    uu, vv = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    su, sv = _distort(uu, vv, FX, FY, CX, CY, *dist)
    ref = np.exp(-((su - ud) ** 2 + (sv - vd) ** 2) / (2 * 1.5**2))[..., None].repeat(3, -1)
    uc, vc = centroid(ds.images[0])
    ur, vr = centroid(ref)
    assert np.hypot(uc - ur, vc - vr) < 0.05, (uc, vc, ur, vr)
    assert np.hypot(uc - u, vc - v) < 0.5  # and near the pinhole projection of x
    np.testing.assert_allclose(ds.images[0][5:-5, 5:-5], ref[5:-5, 5:-5], atol=0.1)  # bilinear resampling error
    assert ds.meta["undistorted"] and ds.weights is not None
    assert ds.weights.min() == 1.0  # barrel: every pinhole pixel samples inside the source
    # pincushion: corners come from outside the source image and get loss weight 0
    pin = (0.3, 0.0, 0.0, 0.0)
    _write_colmap_scene(tmp_path, c2w_ref, ".bin", model="OPENCV", params=(FX, FY, CX, CY, *pin))
    ds = formats.load_colmap(tmp_path, normalize=False)
    su, sv = _distort(uu, vv, FX, FY, CX, CY, *pin)
    outside = (su < -1) | (su > W + 1) | (sv < -1) | (sv > H + 1)
    inside = (su > 1) & (su < W - 1) & (sv > 1) & (sv < H - 1)
    assert outside.sum() > 10 and np.all(ds.weights[0][outside] == 0) and np.all(ds.weights[0][inside] == 1)
    with pytest.raises(DataError, match="cameras.bin.*distortion"):
        formats.load_colmap(tmp_path, normalize=False, undistort=False)


def test_blender_transforms(tmp_path):
    c2w_ref, _ = _look_at_poses(n=4, target=np.zeros(3))
    angle = 0.69
    for name, idx in (("train", [0, 1, 2]), ("test", [3])):
        frames = []
        for i in idx:
            rgba = np.zeros((H, W, 4), np.float32)
            rgba[: H // 2] = [1.0, 0.0, 0.0, 0.5]  # top half: red at 50 % alpha
            io.write_png(tmp_path / name / f"r_{i}.png", rgba)
            frames.append({"file_path": f"./{name}/r_{i}", "rotation": 0.1,
                           "transform_matrix": c2w_ref[i].tolist()})
        (tmp_path / f"transforms_{name}.json").write_text(
            json.dumps({"camera_angle_x": angle, "frames": frames}))
    ds = formats.load_dataset(tmp_path, normalize=False)
    assert ds.meta["format"] == "blender"
    np.testing.assert_allclose(ds.c2w, c2w_ref, atol=1e-6)
    f = 0.5 * W / np.tan(0.5 * angle)
    np.testing.assert_allclose(ds.intrinsics[0], [f, f, W / 2, H / 2], rtol=1e-5)
    np.testing.assert_array_equal(ds.split["train"], [0, 1, 2])
    np.testing.assert_array_equal(ds.split["test"], [3])
    np.testing.assert_allclose(ds.images[0, 0, 0], [1.0, 0.5, 0.5], atol=1 / 255)  # over white
    np.testing.assert_allclose(ds.images[0, -1, -1], [1.0, 1.0, 1.0])  # transparent -> white
    assert (ds.near, ds.far) == (2.0, 6.0)
    # default: normalised; cameras at radius |eye| look at the origin
    ds_n = formats.load_blender(tmp_path)
    s = ds_n.normalization["scale"]
    np.testing.assert_allclose(ds_n.c2w[:, :3, 3], s * c2w_ref[:, :3, 3], atol=1e-5)
    assert ds_n.near == pytest.approx(2.0 * s) and ds_n.far == pytest.approx(6.0 * s)
    test_only = formats.load_dataset(tmp_path, "test", normalize=False)
    assert test_only.num_frames == 1


def _write_transforms(root, n=3, extras=True, scene_normalization=True):
    c2w_ref, _ = _look_at_poses(n=n, radius=2.0, height=0.5, target=np.zeros(3))
    frames = []
    rng = np.random.default_rng(2)
    for i in range(n):
        img = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
        io.write_png(root / "images" / f"f{i}.png", img)
        fr = {"file_path": f"images/f{i}.png", "transform_matrix": c2w_ref[i].tolist(),
              "split": "test" if i == 0 else "train"}
        if extras:
            io.write_png(root / "masks" / f"f{i}.png", (np.arange(W)[None].repeat(H, 0) < 10).astype(np.float32))
            io.write_exr(root / "depth" / f"f{i}.exr", np.full((H, W), 1.5 + i, np.float32))
            sem = np.zeros((H, W), np.float32)
            sem[:, 20:] = 3 / 255
            io.write_png(root / "semantic" / f"f{i}.png", sem)
            dmask = np.zeros((H, W), np.float32)
            dmask[5:8, 5:8] = 1.0
            io.write_png(root / "distractor" / f"f{i}.png", dmask)
            fr.update(mask_path=f"masks/f{i}.png", depth_file_path=f"depth/f{i}.exr",
                      semantic_file_path=f"semantic/f{i}.png", distractor_mask_path=f"distractor/f{i}.png")
            if i != 0:
                io.write_png(root / "clean" / f"f{i}.png", np.full((H, W, 3), 0.5, np.float32))
                fr["clean_file_path"] = f"clean/f{i}.png"
        frames.append(fr)
    top = {"fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H, "camera_model": "PINHOLE",
           "near": 0.3, "far": 9.0, "frames": frames, "generator": {"seed": 3}}
    if scene_normalization:
        top["scene_normalization"] = {"scale": 0.05, "translation": [0, 0, -0.75]}
    io.write_json(root / "transforms.json", top)
    return c2w_ref, top


def test_transforms_json_with_extras(tmp_path):
    c2w_ref, top = _write_transforms(tmp_path)
    ds = formats.load_dataset(tmp_path)
    assert ds.meta["format"] == "transforms.json" and ds.meta["generator"] == {"seed": 3}
    np.testing.assert_allclose(ds.c2w, c2w_ref, atol=1e-6)  # already normalised: untouched
    assert ds.normalization == {"scale": 0.05, "translation": [0.0, 0.0, -0.75]}
    assert (ds.near, ds.far) == (0.3, 9.0)
    np.testing.assert_array_equal(ds.split["test"], [0])
    np.testing.assert_array_equal(ds.split["train"], [1, 2])
    assert ds.masks.shape == (3, H, W) and ds.masks[0, 0, 5] == 1.0 and ds.masks[0, 0, 15] == 0.0
    np.testing.assert_array_equal(ds.weights, 1.0 - ds.masks)  # only mask_path given
    np.testing.assert_allclose(ds.depth[2], 3.5)
    assert ds.semantics.dtype == np.uint8 and ds.semantics[1, 0, 25] == 3 and ds.semantics[1, 0, 0] == 0
    assert ds.distractor_masks.dtype == bool and ds.distractor_masks[0, 6, 6] and ds.distractor_masks.sum() == 27
    np.testing.assert_array_equal(ds.clean_images[0], ds.images[0])  # no clean file: the image
    np.testing.assert_allclose(ds.clean_images[1], 0.5, atol=1 / 255)
    again = formats.load_dataset(tmp_path, normalize=True, load_extras=False)  # composed maps
    metric = np.array([[0.0, 0.0, 20.0], [1.0, -2.0, 3.0]])
    np.testing.assert_allclose(
        apply_normalization_to_points(metric, again.normalization),
        apply_normalization_to_points(apply_normalization_to_points(metric, ds.normalization),
                                      {"scale": again.normalization["scale"] / 0.05,
                                       "translation": -optical_axis_focus(c2w_ref)[0]}), atol=1e-9)
    keep = formats.load_dataset(tmp_path, mask_convention="keep")  # nerfstudio: 1 = keep the pixel
    np.testing.assert_array_equal(keep.masks, 1.0 - ds.masks)
    np.testing.assert_array_equal(keep.weights, ds.masks)
    bare = formats.load_transforms_json(tmp_path / "transforms.json", load_extras=False)
    assert bare.masks is None and bare.weights is None and bare.depth is None


def test_transforms_json_weights_exr_and_per_frame_intrinsics(tmp_path):
    c2w_ref, top = _write_transforms(tmp_path, n=2, extras=False)
    io.write_exr(tmp_path / "w0.exr", np.full((H, W), 0.25, np.float32))
    top["frames"][0]["weight_path"] = "w0.exr"
    top["frames"][1]["fl_x"] = 50.0
    io.write_json(tmp_path / "transforms.json", top)
    ds = formats.load_dataset(tmp_path)
    np.testing.assert_allclose(ds.weights[0], 0.25)
    np.testing.assert_allclose(ds.weights[1], 1.0)  # frame without weights: all ones
    np.testing.assert_allclose(ds.intrinsics[:, 0], [FX, 50.0])


def test_transforms_json_without_normalisation_gets_normalised(tmp_path):
    c2w_ref, _ = _write_transforms(tmp_path, n=4, extras=False, scene_normalization=False)
    ds = formats.load_dataset(tmp_path)
    s = ds.normalization["scale"]
    np.testing.assert_allclose(ds.normalization["translation"], 0.0, atol=1e-6)
    np.testing.assert_allclose(ds.c2w[:, :3, 3], s * c2w_ref[:, :3, 3], atol=1e-5)
    assert ds.near == pytest.approx(0.3 * s) and ds.far == pytest.approx(9.0 * s)


def test_downscale_keeps_projection(tmp_path):
    """A blob at a projected point lands at the same relative place after downscaling."""
    c2w_ref, _ = _look_at_poses(n=2, target=np.zeros(3))
    w, h, k = 64, 48, 4
    fx, fy, cx, cy = 60.0, 58.0, 30.3, 25.1
    x = np.array([0.2, -0.1, 0.15])
    frames = []
    for i in range(2):
        u, v = _project(x, c2w_ref[i], fx, fy, cx, cy)
        io.write_png(tmp_path / f"im{i}.png", blob(u, v, w, h, sigma=3.0), bits=16)
        frames.append({"file_path": f"im{i}.png", "transform_matrix": c2w_ref[i].tolist()})
    io.write_json(tmp_path / "transforms.json", {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": w, "h": h,
                                                  "scene_normalization": {"scale": 1, "translation": [0, 0, 0]},
                                                  "frames": frames})
    ds = formats.load_dataset(tmp_path, downscale=k)
    assert ds.images.shape[1:3] == (h // k, w // k)
    np.testing.assert_allclose(ds.intrinsics[0], [fx / k, fy / k, cx / k, cy / k], rtol=1e-6)
    for i in range(2):
        u, v = _project(x, c2w_ref[i], *ds.intrinsics[i])
        uc, vc = centroid(ds.images[i])
        assert np.hypot(uc - u, vc - v) < 0.03, (uc, vc, u, v)
        # and the loader's ray through that pixel hits x
        assert _ray_miss(ds.c2w[i], ds.intrinsics[i], u, v, x) < 1e-4


def test_llff_poses_bounds(tmp_path):
    c2w_ref, eyes = _look_at_poses(n=5, target=np.zeros(3))
    h_full, w_full, focal = 2 * H, 2 * W, 70.0
    rows = []
    for m in c2w_ref:
        # LLFF columns: down, right, backwards (= -y, x, z of OpenGL), centre, (H, W, f)
        pose = np.stack([-m[:3, 1], m[:3, 0], m[:3, 2], m[:3, 3], [h_full, w_full, focal]], axis=1)
        rows.append(np.concatenate([pose.ravel(), [2.5, 6.0]]))
    np.save(tmp_path / "poses_bounds.npy", np.array(rows))
    for i in range(5):  # images at half the resolution of the poses
        io.write_png(tmp_path / "images" / f"{i:03d}.png", np.full((H, W, 3), 0.3, np.float32))
    ds = formats.load_dataset(tmp_path, normalize=False)
    assert ds.meta["format"] == "llff"
    np.testing.assert_allclose(ds.c2w, c2w_ref, atol=1e-6)
    np.testing.assert_allclose(ds.intrinsics[0], [35.0, 35.0, W / 2, H / 2])
    cos = 1 / np.sqrt(1 + (W / 2 / 35) ** 2 + (H / 2 / 35) ** 2)
    assert ds.near == pytest.approx(0.9 * 2.5) and ds.far == pytest.approx(1.1 * 6.0 / cos)
    ds_n = formats.load_llff(tmp_path)
    np.testing.assert_allclose(ds_n.normalization["translation"], 0.0, atol=1e-6)


def test_normalize_poses_conventions():
    c2w, eyes = _look_at_poses(n=8, target=TARGET)
    focus, cond = optical_axis_focus(c2w)
    np.testing.assert_allclose(focus, TARGET, atol=1e-5)
    assert cond > 0.05
    out, norm = normalize_poses(c2w)
    dist = np.linalg.norm(eyes - TARGET, axis=-1)
    assert norm["scale"] == pytest.approx(1.0 / (0.5 * np.median(dist)))
    pts = np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]])
    np.testing.assert_allclose(apply_normalization_to_points(pts, norm), norm["scale"] * (pts - TARGET))
    back = apply_normalization_to_points(apply_normalization_to_points(pts, norm), invert_normalization(norm))
    np.testing.assert_allclose(back, pts, atol=1e-12)
    other = {"scale": 3.0, "translation": [1.0, -2.0, 0.5]}
    both = compose_normalization(norm, other)
    np.testing.assert_allclose(apply_normalization_to_points(pts, both),
                               apply_normalization_to_points(apply_normalization_to_points(pts, norm), other))
    # points method: median centre; background points far away do not inflate the sphere
    rng = np.random.default_rng(0)
    tower = TARGET + rng.normal(0, 0.3, (900, 3))
    background = TARGET + rng.normal(0, 50.0, (100, 3))
    _, norm_p = normalize_poses(c2w, np.concatenate([tower, background]), method="cameras")
    assert 1.0 / norm_p["scale"] <= dist.max() * (1 + 1e-6)
    # forward-facing cameras (parallel axes): centre falls back to focus_depth ahead
    ff = np.stack([np.asarray(rays.look_at([x, 0, 0], [x, 5.0, 0]), np.float64) for x in (-1, 0, 1)])
    _, norm_f = normalize_poses(ff, focus_depth=5.0)
    np.testing.assert_allclose(norm_f["translation"], [0, -5.0, 0], atol=1e-6)


def _random_record(seed):
    """A normalisation record with a random rotation, and its parts (s, R, t)."""
    rng = np.random.default_rng(seed)
    s, r, t = float(rng.uniform(0.05, 3.0)), Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 5, 3)
    return {"scale": s, "translation": t.tolist(), "rotation": r.tolist()}, s, r, t


def test_normalization_rotation_closed_form():
    """x_norm = s R (x + t): apply, invert and compose against the formula written out."""
    a, s1, r1, t1 = _random_record(1)
    b, s2, r2, t2 = _random_record(2)
    pts = np.random.default_rng(3).normal(0, 10, (20, 3))
    ref_a = np.stack([s1 * r1 @ (x + t1) for x in pts])
    np.testing.assert_allclose(apply_normalization_to_points(pts, a), ref_a, atol=1e-9)
    inv = invert_normalization(a)
    np.testing.assert_allclose(inv["rotation"], r1.T, atol=1e-12)
    np.testing.assert_allclose(apply_normalization_to_points(ref_a, inv), pts, atol=1e-9)
    ref_ab = np.stack([s2 * r2 @ (y + t2) for y in ref_a])
    np.testing.assert_allclose(apply_normalization_to_points(pts, compose_normalization(a, b)), ref_ab, atol=1e-9)
    # invert then compose: the identity, with and without a rotation on one side
    for first, second in ((a, inv), (inv, a), ({"scale": 2.0, "translation": [1.0, 2.0, 3.0]}, a)):
        both = compose_normalization(first, second)
        ref = apply_normalization_to_points(apply_normalization_to_points(pts, first), second)
        np.testing.assert_allclose(apply_normalization_to_points(pts, both), ref, atol=1e-9)
    # poses: centres move like points, rotations turn by R
    c2w, _ = _look_at_poses(n=4)
    out = formats_normalize.apply_normalization_to_poses(c2w, a)
    np.testing.assert_allclose(out[:, :3, :3], np.einsum("ij,njk->nik", r1, c2w[:, :3, :3]), atol=1e-12)
    np.testing.assert_allclose(out[:, :3, 3], [s1 * r1 @ (c + t1) for c in c2w[:, :3, 3]], atol=1e-9)


def test_normalization_without_rotation_unchanged():
    """A record without "rotation" maps exactly as the formula before rotations existed."""
    norm = {"scale": 0.37, "translation": [1.5, -2.25, 0.1]}
    other = {"scale": 3.0, "translation": [1.0, -2.0, 0.5]}
    pts = np.random.default_rng(5).normal(0, 10, (30, 3))
    s, t = norm["scale"], np.asarray(norm["translation"])
    np.testing.assert_array_equal(apply_normalization_to_points(pts, norm), s * (pts + t))
    inv = invert_normalization(norm)
    assert inv == {"scale": 1.0 / s, "translation": [float(-s * v) for v in t]}
    both = compose_normalization(norm, other)
    assert both == {"scale": s * 3.0, "translation": [float(v) for v in t + np.asarray(other["translation"]) / s]}
    c2w, _ = _look_at_poses(n=3)
    out = formats_normalize.apply_normalization_to_poses(c2w, norm)
    np.testing.assert_array_equal(out[:, :3, :3], c2w[:, :3, :3])
    np.testing.assert_array_equal(out[:, :3, 3], s * (c2w[:, :3, 3] + t))


def _tilt(c2w, pts, rot):
    """The whole scene turned by rot [3, 3] (x' = rot x), written out."""
    out = c2w.copy()
    out[:, :3, :3] = np.einsum("ij,njk->nik", rot, c2w[:, :3, :3])
    out[:, :3, 3] = c2w[:, :3, 3] @ rot.T
    return out, pts @ rot.T


def _angle_deg(a, b):
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


@pytest.mark.parametrize("ext", [".txt", ".bin"])
def test_colmap_tilted_world_loads_z_up(tmp_path, ext):
    """A COLMAP world turned 35 degrees off z-up loads with its up axis on +z again."""
    c2w_ref, eyes = _look_at_poses(n=8)  # level cameras, z up, 1.5 above TARGET
    pts = TARGET + np.random.default_rng(6).uniform(-0.6, 0.6, size=(200, 3))
    tilt = Rotation.from_rotvec(np.radians(35.0) * np.array([0.6, -0.8, 0.0])).as_matrix()
    c2w_t, pts_t = _tilt(c2w_ref, pts, tilt)
    _write_colmap_scene(tmp_path, c2w_t, ext, points=pts_t)
    ds = formats.load_colmap(tmp_path)
    r = np.asarray(ds.normalization["rotation"])
    assert _angle_deg(r @ tilt @ [0.0, 0.0, 1.0], np.array([0.0, 0.0, 1.0])) < 1.0  # the true up is +z
    for m in ds.c2w:
        assert abs(90.0 - _angle_deg(m[:3, 0], np.array([0.0, 0.0, 1.0]))) < 1.0  # level: right is horizontal
    # the cameras sit 1.5 above the centre, all at one height: s * 1.5
    s = ds.normalization["scale"]
    np.testing.assert_allclose(ds.c2w[:, 2, 3], s * 1.5, atol=2e-3)
    # the record maps the file's frame to the loaded scene: points and camera centres
    np.testing.assert_allclose(ds.meta["points3d"], apply_normalization_to_points(pts_t, ds.normalization), atol=1e-5)
    np.testing.assert_allclose(ds.c2w[:, :3, 3], apply_normalization_to_points(c2w_t[:, :3, 3], ds.normalization),
                               atol=1e-5)
    np.testing.assert_allclose(ds.normalization["translation"], -(tilt @ TARGET), atol=1e-5)
    # written as transforms.json and read back: the same record, the same cameras
    formats.save_transforms_json(ds, tmp_path / "out")
    again = formats.load_dataset(tmp_path / "out")
    np.testing.assert_allclose(again.normalization["rotation"], r, atol=1e-12)
    assert again.normalization["scale"] == s
    np.testing.assert_allclose(again.c2w, ds.c2w, atol=1e-6)


def test_llff_tilted_world_loads_z_up(tmp_path):
    c2w_ref, _ = _look_at_poses(n=6, target=np.zeros(3))
    tilt = Rotation.from_rotvec(np.radians(25.0) * np.array([1.0, 0.0, 0.0])).as_matrix()
    c2w_t, _ = _tilt(c2w_ref, np.zeros((0, 3)), tilt)
    rows = [np.concatenate([np.stack([-m[:3, 1], m[:3, 0], m[:3, 2], m[:3, 3], [H, W, 35.0]], 1).ravel(),
                            [2.5, 6.0]]) for m in c2w_t]
    np.save(tmp_path / "poses_bounds.npy", np.array(rows))
    for i in range(len(rows)):
        io.write_png(tmp_path / "images" / f"{i:03d}.png", np.full((H, W, 3), 0.3, np.float32))
    ds = formats.load_llff(tmp_path)
    r = np.asarray(ds.normalization["rotation"])
    assert _angle_deg(r @ tilt @ [0.0, 0.0, 1.0], np.array([0.0, 0.0, 1.0])) < 1.0
    np.testing.assert_allclose(ds.c2w[:, :3, 3], apply_normalization_to_points(c2w_t[:, :3, 3], ds.normalization),
                               atol=1e-5)


def test_transforms_json_rotation_checked(tmp_path):
    c2w_ref, _ = _look_at_poses(n=2, target=np.zeros(3))
    frames = [{"file_path": f"im{i}.png", "transform_matrix": m.tolist()} for i, m in enumerate(c2w_ref)]
    for i in range(2):
        io.write_png(tmp_path / f"im{i}.png", np.full((H, W, 3), 0.3, np.float32))
    top = {"fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H, "frames": frames}
    for bad in ([[1, 0, 0], [0, 1, 0]], [[2, 0, 0], [0, 1, 0], [0, 0, 1]], [[1, 0, 0], [0, 1, 0], [0, 0, -1]]):
        top["scene_normalization"] = {"scale": 0.5, "translation": [0, 0, 0], "rotation": bad}
        io.write_json(tmp_path / "transforms.json", top)
        with pytest.raises(DataError, match="transforms.json: scene_normalization 'rotation'"):
            formats.load_dataset(tmp_path)
    rot, _, r, _ = _random_record(7)
    top["scene_normalization"] = rot
    io.write_json(tmp_path / "transforms.json", top)
    ds = formats.load_dataset(tmp_path)
    np.testing.assert_allclose(ds.normalization["rotation"], r, atol=1e-12)
    np.testing.assert_allclose(ds.c2w, c2w_ref, atol=1e-6)  # a normalised file is taken as it is


def test_colmap_text_as_colmap_writes_it(tmp_path):
    """A hand-written model in COLMAP's documented text layout: comments, an image whose
    points line is empty, a name with a sub-folder, points3D with tracks."""
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        "# Number of cameras: 2\n"
        f"1 SIMPLE_PINHOLE {W} {H} 30 20 15\n"
        f"2 PINHOLE {W} {H} 31 32 19.5 14.5\n")
    (sparse / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
        "# Number of images: 2, mean observations per image: 1.5\n"
        "1 1 0 0 0 0 0 4 1 sub/a.png\n"
        "10.5 11.5 7 3.0 4.0 -1\n"
        "2 0 1 0 0 0.5 0 4 2 sub/b.png\n"
        "\n")
    (sparse / "points3D.txt").write_text(
        "# 3D point list with one line of data per point:\n"
        "7 0.1 0.2 0.3 255 128 0 0.75 1 0 2 5\n")
    cams, imgs, pts = colmap_io.read_model(sparse)
    assert cams[1].model == "SIMPLE_PINHOLE" and cams[2].params.tolist() == [31, 32, 19.5, 14.5]
    assert imgs[1].name == "sub/a.png" and imgs[1].point3D_ids.tolist() == [7, -1]
    np.testing.assert_array_equal(imgs[1].xys, [[10.5, 11.5], [3.0, 4.0]])
    assert imgs[2].name == "sub/b.png" and len(imgs[2].point3D_ids) == 0
    assert pts[7].rgb.tolist() == [255, 128, 0] and pts[7].track.tolist() == [[1, 0], [2, 5]]
    for name in ("a", "b"):
        io.write_png(tmp_path / "images" / "sub" / f"{name}.png", np.zeros((H, W, 3), np.float32))
    ds = formats.load_dataset(tmp_path, normalize=False, test_every=2)
    assert ds.frame_paths == ["images/sub/a.png", "images/sub/b.png"]
    np.testing.assert_allclose(ds.intrinsics, [[30, 30, 20, 15], [31, 32, 19.5, 14.5]])
    # image 1: identity rotation, camera centre -R^T t = (0, 0, -4); OpenGL axes flip y and z
    np.testing.assert_allclose(ds.c2w[0], [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, -4], [0, 0, 0, 1]], atol=1e-6)
    # image 2: 180 degrees about x (q = (0, 1, 0, 0)): R = diag(1, -1, -1); centre = -R^T t
    np.testing.assert_allclose(ds.c2w[1], [[1, 0, 0, -0.5], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]], atol=1e-6)
