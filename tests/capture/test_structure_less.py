"""`capture.structure_less.register` with COLMAP's own mapper on a matching database and a model
written here from a known scene: ring cameras looking at two clouds of points, the model holding
the first cameras and the points of the first cloud; the photo left out sees the second cloud
with its two neighbours (hundreds of 2-D matches) and only 6 of the model's 3-D points, under
the 10 COLMAP's candidates need. Its pose is checked against the one the scene was made with.
"""

from __future__ import annotations

import numpy as np
import pytest

from jaxnerf_grid.capture import poses, structure_less
from tests.capture.test_poses_cameras_and_frame import _numbers, _pixels, _w2c_opencv

pycolmap = pytest.importorskip("pycolmap")

SIZE, FOCAL = (640, 480), 500.0
TARGET = np.array([0.0, 0.0, 0.0])


def _ring(count=12, radius=10.0, step_deg=12.0):
    """Camera centres [count, 3] on an arc round TARGET, `step_deg` apart, and their w2c rotations."""
    angles = np.radians(step_deg * np.arange(count))
    centres = np.column_stack([radius * np.cos(angles), radius * np.sin(angles), np.full(count, 2.0)])
    return centres, np.stack([_w2c_opencv(c, TARGET) for c in centres])


def _in_view(points, rot, centre):
    """Which points [P, 3] project inside the photo, in front of the camera."""
    cam = (points - centre) @ rot.T
    xy = _pixels(points, rot, -rot @ centre, FOCAL, FOCAL, SIZE[0] / 2, SIZE[1] / 2)
    return (cam[:, 2] > 0.1) & (xy >= 0).all(1) & (xy[:, 0] < SIZE[0]) & (xy[:, 1] < SIZE[1])


def _scene(tmp_path, seen_by_model=6, second_cloud=300, registered=8, third_cloud=0):
    """Database and model of 12 ring cameras (v00-v11). The model: v00..v{registered-1} and the
    first cloud (400 points) as its 3-D points. v{registered} (the photo left out) sees
    `seen_by_model` of those points and the second cloud (`second_cloud` points, seen by it and
    its two neighbours on one side only: no 3-D point). v{registered+1} sees the third cloud
    (`third_cloud` points) with v{registered-1} and v{registered} and nothing of the model; the
    photos after it nothing. Returns (database, model folder, true w2c (R, t) per name)."""
    rng = np.random.default_rng(4)
    centres, rots = _ring()
    first = rng.uniform(-2.0, 2.0, (400, 3))
    second = rng.uniform(-2.0, 2.0, (second_cloud, 3)) + [0.0, 0.0, 0.5]
    third = rng.uniform(-2.0, 2.0, (third_cloud, 3)) + [0.0, 0.0, -0.5]
    left = registered
    seen = {}   # name -> [(cloud, point index)] in keypoint order
    for k, (centre, rot) in enumerate(zip(centres, rots)):
        own = []
        if k < left:
            own += [("a", i) for i in np.flatnonzero(_in_view(first, rot, centre))]
        elif k == left:
            own += [("a", i) for i in np.flatnonzero(_in_view(first, rot, centre))[:seen_by_model]]
        if abs(k - left) <= 2 and k <= left:
            own += [("b", i) for i in np.flatnonzero(_in_view(second, rot, centre))]
        if left - 1 <= k <= left + 1:
            own += [("c", i) for i in np.flatnonzero(_in_view(third, rot, centre))]
        seen[f"v{k:02d}.png"] = own
    names, clouds = sorted(seen), {"a": first, "b": second, "c": third}
    database = tmp_path / "database.db"
    db = pycolmap.Database.open(str(database))
    camera = pycolmap.Camera(model="PINHOLE", width=SIZE[0], height=SIZE[1],
                             params=[FOCAL, FOCAL, SIZE[0] / 2, SIZE[1] / 2])
    camera.camera_id = db.write_camera(camera)
    rig = pycolmap.Rig()                    # one camera, one rig, a frame per photo
    rig.add_ref_sensor(camera.sensor_id)
    rig_id = db.write_rig(rig)
    ids, truth = {}, {}
    for k, name in enumerate(names):
        image = pycolmap.Image(name=name, camera_id=camera.camera_id)
        ids[name] = db.write_image(image)
        frame = pycolmap.Frame()
        frame.rig_id = rig_id
        frame.add_data_id(pycolmap.data_t(camera.sensor_id, ids[name]))
        db.write_frame(frame)
        rot, centre = rots[k], centres[k]
        truth[name] = (rot, -rot @ centre)
        xyz = np.array([clouds[c][i] for c, i in seen[name]]).reshape(-1, 3)
        db.write_keypoints(ids[name], _pixels(xyz, rot, -rot @ centre, FOCAL, FOCAL, SIZE[0] / 2,
                                              SIZE[1] / 2).astype(np.float32))
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            index_b = {key: j for j, key in enumerate(seen[names[b]])}
            pairs = [(i, index_b[key]) for i, key in enumerate(seen[names[a]]) if key in index_b]
            if len(pairs) < 5:
                continue
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            geometry.inlier_matches = np.array(pairs, np.uint32)
            db.write_matches(ids[names[a]], ids[names[b]], np.array(pairs, np.uint32))
            db.write_two_view_geometry(ids[names[a]], ids[names[b]], geometry)
    db.close()
    model = tmp_path / "model"
    model.mkdir()
    (model / "cameras.txt").write_text(f"{camera.camera_id} PINHOLE {SIZE[0]} {SIZE[1]} "
                                       f"{_numbers([FOCAL, FOCAL, SIZE[0] / 2, SIZE[1] / 2])}\n")
    lines, tracks = [], {}
    for name in names[:left]:
        rot, t = truth[name]
        q = pycolmap.Rotation3d(rot).quat   # x, y, z, w
        lines.append(f"{ids[name]} {_numbers([q[3], *q[:3]])} {_numbers(t)} {camera.camera_id} {name}")
        xyz = np.array([clouds[c][i] for c, i in seen[name]])
        xy = _pixels(xyz, rot, t, FOCAL, FOCAL, SIZE[0] / 2, SIZE[1] / 2)   # the keypoints, in their order
        lines.append(" ".join(f"{_numbers(p)} {i + 1 if c == 'a' else -1}" for p, (c, i) in zip(xy, seen[name])))
        for j, (c, i) in enumerate(seen[name]):
            if c == "a":                     # the first cloud alone has 3-D points
                tracks.setdefault(i, []).append(f"{ids[name]} {j}")
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    (model / "points3D.txt").write_text("".join(f"{i + 1} {_numbers(first[i])} 128 128 128 0.1 {' '.join(t)}\n"
                                                for i, t in sorted(tracks.items())))
    return database, model, truth


def _options():
    return poses.mapper_options(pycolmap, True, False, poses.LEFT_OUT, poses.LEFT_OUT_TRIANGULATION)


def _angle_deg(a, b):
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1.0) / 2.0, -1.0, 1.0))))


def test_a_photo_tied_by_two_view_matches_alone_is_placed_where_it_was_taken(tmp_path):
    """v08 sees 6 of the model's 3-D points (under LEFT_OUT's 10: COLMAP's pipeline never tries
    it) and a second cloud with v06 and v07: placed within 0.05 degrees and 0.2 % of the ring's
    radius of its true pose, its matches triangulated; the model handed in keeps its 8 photos."""
    database, folder, truth = _scene(tmp_path)
    model = pycolmap.Reconstruction(folder)
    grown, names = structure_less.register(pycolmap, database, model, _options())
    assert names == ["v08.png"] and model.num_reg_images() == 8
    assert grown.num_reg_images() == grown.num_images() == 9      # the photos still out are not in it
    image = grown.find_image_with_name("v08.png")
    pose = image.cam_from_world().matrix()
    rot, t = truth["v08.png"]
    assert _angle_deg(pose[:, :3], rot) < 0.05
    centre, true_centre = -pose[:, :3].T @ pose[:, 3], -rot.T @ t
    assert np.linalg.norm(centre - true_centre) < 0.002 * 10.0
    assert image.num_points3D > 100                               # the second cloud, triangulated


class _Tried:
    """pycolmap with its IncrementalMapper recording the photos handed to structure-less
    resectioning (the real mapper does the work)."""

    def __init__(self):
        self.tried: list[str] = []
        tried = self.tried

        class Mapper(pycolmap.IncrementalMapper):
            def register_next_structure_less_image(self, options, image_id):
                tried.append(self.reconstruction.images[image_id].name)
                return super().register_next_structure_less_image(options, image_id)

        self.IncrementalMapper = Mapper

    def __getattr__(self, name):
        return getattr(pycolmap, name)


@pytest.mark.parametrize("second_cloud, tried", [(9, []), (10, ["v08.png"])])
def test_a_photo_is_tried_from_twenty_matches_with_registered_photos(tmp_path, second_cloud, tried):
    """v08 sees no 3-D point and a second cloud of 9 or 10 points with v06 and v07: 18 matches
    with registered photos (under MIN_CORRESPONDENCES, 20) are not tried, 20 are; the photos
    matched with no registered photo (v09-v11) never."""
    assert structure_less.MIN_CORRESPONDENCES == 20
    database, folder, _ = _scene(tmp_path, seen_by_model=0, second_cloud=second_cloud)
    module = _Tried()
    structure_less.register(module, database, pycolmap.Reconstruction(folder), _options())
    assert module.tried == tried


class _FailsAfterRegistering(_Tried):
    """As COLMAP's structure-less resectioning when its pose refinement fails: `failing` is given
    a pose and registered (the observation manager's register_frame), and False is returned."""

    def __init__(self, failing: str, truth: dict):
        super().__init__()
        base, tried = self.IncrementalMapper, self.tried

        class Mapper(base):
            def register_next_structure_less_image(self, options, image_id):
                image = self.reconstruction.images[image_id]
                if image.name != failing:
                    return super().register_next_structure_less_image(options, image_id)
                tried.append(failing)
                rot, t = truth[failing]
                self.reconstruction.frames[image.frame_id].rig_from_world = pycolmap.Rigid3d(
                    pycolmap.Rotation3d(rot), t)
                self.observation_manager.register_frame(image.frame_id)
                return False

        self.IncrementalMapper = Mapper


def test_a_photo_whose_placement_fails_after_colmap_registered_it_is_left_out(tmp_path):
    """v09 sees a third cloud with v07 and v08; its structure-less resectioning registers it and
    then fails (COLMAP does so when the pose refinement that follows fails): it is deregistered,
    so the model holds v00-v08 alone."""
    database, folder, truth = _scene(tmp_path, third_cloud=300)
    module = _FailsAfterRegistering("v09.png", truth)
    grown, names = structure_less.register(module, database, pycolmap.Reconstruction(folder), _options())
    assert "v09.png" in module.tried and names == ["v08.png"]
    assert sorted(grown.images[i].name for i in grown.reg_image_ids()) == [f"v{k:02d}.png" for k in range(9)]
    assert grown.num_images() == 9
