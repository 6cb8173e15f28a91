"""benchmarks.depth_rays_truth: each depth ray's point against the true depth and class at its pixel."""

import numpy as np
from PIL import Image

from benchmarks import depth_rays_truth
from jaxnerf_grid.util import io


def test_a_ray_whose_point_lies_behind_a_tower_pixel_counts_as_behind(tmp_path):
    width, height, f = 8, 6, 4.0
    truth = {"fl_x": f, "fl_y": f, "cx": 4.0, "cy": 3.0, "w": width, "h": height,
             "semantic_classes": ["sky", "tower", "ground"]}
    depth = np.full((height, width), 10.0, np.float32)
    sem = np.full((height, width), 2, np.uint8)
    sem[:, 4:6] = 1  # a tower column two pixels wide, at 10 like the ground
    (tmp_path / "depth").mkdir()
    (tmp_path / "semantic").mkdir()
    io.write_exr(tmp_path / "depth" / "train_000.exr", depth)
    Image.fromarray(sem).save(tmp_path / "semantic" / "train_000.png")
    frames = [{"file_path": "images/train_000.png", "depth_file_path": "depth/train_000.exr"}]
    c2w = np.eye(4)[None]  # at the origin, looking down -z
    # pixel centres (u, v) -> the direction through them; z-depth 10 on the ground (u=1.5), 11 (10 %
    # behind) through the tower (u=4.5) and 10.1 (1 % behind, on its surface) at u=5.5
    pixels, zs = [(1.5, 2.5), (4.5, 2.5), (5.5, 2.5)], [10.0, 11.0, 10.1]
    points = np.array([[(u - 4.0) / f * z, -(v - 3.0) / f * z, -z] for (u, v), z in zip(pixels, zs)])
    dist = np.linalg.norm(points, axis=1)
    rays = {"origins": np.zeros((3, 3)), "directions": points / dist[:, None], "t": dist, "camera": np.zeros(3, int)}
    got = depth_rays_truth.classify(tmp_path, truth, frames, c2w, rays)
    assert got["ground"] == {"rays": 1, "on_surface": 1.0, "behind": 0.0}
    assert got["tower"]["rays"] == 2 and got["tower"]["behind"] == 0.5 and got["tower"]["on_surface"] == 0.5
    assert got["tower"]["edge_px_of_rays_behind"][1] == 1.0  # the column's edge pixel
