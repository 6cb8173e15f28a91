"""Ground control point layouts of `synth --gps-origin` (`capture.gps_photos`): the
spread layout's points against hand-computed world positions and pixels (a camera straight above
each point: closed-form projection), the depth map's visibility honoured, the ground layout as
the committed code wrote it, a layout written into an existing folder, and bad input refused."""

import re

import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.capture import gps_photos as gps_scene
from jaxnerf_grid.util import io as io_lib
from jaxnerf_grid.util.io import DataError

SCALE, SHIFT = 0.05, np.array([0.0, 0.0, -15.0])  # the synthetic normalisation
W, H, F, CX, CY = 64, 48, 100.0, 32.0, 24.0
# camera offsets (normalised, x / y from straight above the point, 2 units up) and, by hand,
# the pixel u = CX - F * dx / 2, v = CY + F * dy / 2; the last one's depth map shows an occluder
OFFSETS = ((0.1, 0.2), (-0.2, 0.1), (0.0, -0.15), (0.05, 0.05))
PIXELS = ((27.0, 34.0), (42.0, 29.0), (32.0, 16.5), (29.5, 26.5))
BASE = np.array([465000.0, 5247000.0, 400.0])


def tiny_scene(root, points_world):
    """A dataset in the synthetic layout: for each world point, four cameras looking straight down
    at it from 2 units up (OFFSETS); the depth map is 2 (the point) in a 3x3 window at its pixel in
    the first three and 1 (something in front) in the fourth, 0.1 elsewhere (nothing else seen)."""
    (root / "images").mkdir(parents=True)
    (root / "depth").mkdir()
    frames = []
    for k, world in enumerate(points_world):
        centre = SCALE * (np.asarray(world, np.float64) + SHIFT)
        for i, ((dx, dy), (u, v)) in enumerate(zip(OFFSETS, PIXELS)):
            name = f"train_{k}{i}"
            pose = np.eye(4)
            pose[:3, 3] = centre + [dx, dy, 2.0]
            depth = np.full((H, W), 0.1, np.float32)
            depth[int(v) - 1:int(v) + 2, int(u) - 1:int(u) + 2] = 1.0 if i == 3 else 2.0
            io_lib.write_exr(root / "depth" / f"{name}.exr", depth)
            io_lib.write_png(root / "images" / f"{name}.png", np.full((H, W, 3), 0.2 + 0.1 * i, np.float32))
            frames.append({"file_path": f"images/{name}.png", "depth_file_path": f"depth/{name}.exr",
                           "transform_matrix": pose.tolist()})
    meta = {"w": W, "h": H, "fl_x": F, "fl_y": F, "cx": CX, "cy": CY, "frames": frames,
            "scene_normalization": {"scale": SCALE, "translation": SHIFT.tolist()}}
    io_lib.write_json(root / "transforms.json", meta)
    return meta


def parse(lines):
    return [(r[0], float(r[1]), float(r[2]), *map(float, r[3:6]), r[6]) for r in (ln.split(",") for ln in lines[1:])]


def test_spread_points_are_the_towers_cross_arm_tip_and_peak_by_hand():
    """By hand from data/synthetic/scene.py: the middle arm (ARM_LEVELS[1] = 21.5 m) reaches
    half_width(21.5) = 1.1 m plus ARM_LENGTHS[1] = 7.5 m from the axis, its tip corners at y =
    +-0.35; the earth-wire peak's member ends at (+-2.6, 0, 30.4); and each lies on a member of
    the tower (within its radius of the member's axis)."""
    from jaxnerf_grid.data.synthetic.scene import tower_members

    points = gps_scene.GCP_LAYOUTS["spread"]
    assert points == ((15.0, 0.0, 0.0), (-(1.1 + 7.5), 0.35, 21.5), (2.6, 0.0, 30.4), (0.0, -15.0, 0.0))
    assert points[-1] == gps_scene.GCP_LAYOUTS["ground"][-1]  # the same check point
    caps = tower_members(np.random.default_rng(0))[0]
    for p in points[1:3]:
        p = np.asarray(p)
        near = [np.linalg.norm(p - (a + np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1) * (b - a))) - r
                for a, b, r in caps]
        assert min(near) <= 0.0


def test_dense_points_by_hand_lie_on_the_tower():
    """The diagnostic layout: 3 + 4 + 16 + 12 + 2 control points and the check point. By hand:
    half_width(12) = 4 - 2.9 * 12 / 17.5 = 2.01143 m; the low arm's tip 1.1 + 6.5 = 7.6 m out;
    every point off the ground within its member's radius of a member's axis, or on a footing
    (centre (+-4, +-4, 0.225), half 0.7, 0.7, 0.225)."""
    from jaxnerf_grid.data.synthetic.scene import tower_members

    points = gps_scene.GCP_LAYOUTS["dense"]
    assert len(points) == 38 and points[:3] == gps_scene.GCP_POINTS[:3] and points[-1] == (0.0, -15.0, 0.0)
    assert (4.7, -4.7, 0.45) in points and (-7.6, 0.35, 17.5) in points and (8.6, -0.35, 21.5) in points
    assert any(np.allclose(p, (-2.0114286, 2.0114286, 12.0)) for p in points)
    caps, _, boxes, _ = tower_members(np.random.default_rng(0))
    for p in map(np.asarray, points[3:-1]):
        near = min(np.linalg.norm(p - (a + np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1) * (b - a))) - r
                   for a, b, r in caps)
        on_box = any(np.all(np.abs(p - c) <= h + 1e-9) for c, h in boxes)
        assert near <= 0.0 or on_box, p


def test_spread_rows_match_hand_projections_and_honour_visibility(tmp_path):
    points = gps_scene.GCP_LAYOUTS["spread"]
    meta = tiny_scene(tmp_path, points)
    lines, truth = gps_scene.gcp_rows(tmp_path, meta, BASE, 0, "spread")
    rows = parse(lines)
    assert lines[0] == "image,x,y,X,Y,Z,check" and len(rows) == 3 * len(points)
    hand_crs = [(465015.0, 5247000.0, 400.0), (464991.4, 5247000.35, 421.5), (465002.6, 5247000.0, 430.4),
                (465000.0, 5246985.0, 400.0)]
    for k, crs in enumerate(hand_crs):
        mine = rows[3 * k:3 * k + 3]
        # the occluded fourth photo (depth map 1 in front of the point's 2) is never used
        assert [r[0] for r in mine] == [f"train_{k}{i}.jpg" for i in range(3)]
        for r, (u, v) in zip(mine, PIXELS):
            assert abs(r[1] - u) <= 2.5 and abs(r[2] - v) <= 2.5  # 0.5 px click error: 5 sigma
            assert r[3:6] == pytest.approx(crs, abs=1e-3)
            assert r[6] == ("check" if k == 3 else "")
        assert truth[k]["photos"] == 3 and truth[k]["check"] == (k == 3)


# gcp.csv as the ground layout (the only layout before the spread one) wrote it for tiny_scene(GCP_POINTS),
# base BASE, seed 0: `gcp_rows(root, meta, BASE, 0)`
COMMITTED_GROUND = """\
image,x,y,X,Y,Z,check
train_00.jpg,27.03,33.82,465015.000,5247000.000,400.000,
train_01.jpg,41.33,29.59,465015.000,5247000.000,400.000,
train_02.jpg,31.99,16.80,465015.000,5247000.000,400.000,
train_10.jpg,26.46,34.15,464992.500,5247013.000,400.000,
train_11.jpg,43.17,28.70,464992.500,5247013.000,400.000,
train_12.jpg,32.38,16.08,464992.500,5247013.000,400.000,
train_20.jpg,27.38,33.56,464992.500,5246987.000,400.000,
train_21.jpg,41.76,29.34,464992.500,5246987.000,400.000,
train_22.jpg,32.69,16.46,464992.500,5246987.000,400.000,
train_30.jpg,28.29,34.96,465000.000,5246985.000,400.000,check
train_31.jpg,41.75,28.73,465000.000,5246985.000,400.000,check
train_32.jpg,31.95,16.34,465000.000,5246985.000,400.000,check
"""


def test_ground_layout_is_the_committed_one(tmp_path):
    """The default (no layout named) and "ground" give the committed file, byte for byte."""
    meta = tiny_scene(tmp_path, gps_scene.GCP_POINTS)
    assert gps_scene.GCP_POINTS == ((15.0, 0.0, 0.0), (-7.5, 13.0, 0.0), (-7.5, -13.0, 0.0), (0.0, -15.0, 0.0))
    for args in ((), ("ground",)):
        lines, _ = gps_scene.gcp_rows(tmp_path, meta, BASE, 0, *args)
        assert "\n".join(lines) + "\n" == COMMITTED_GROUND


def test_a_layout_written_into_an_existing_folder_is_what_synth_writes(tmp_path):
    """`write_gcp` (benchmarks.gps_alignment --write-gcp) into a folder made with the default
    layout: gcp.csv rewritten byte-identical, gcp_spread.csv as `write_gps_photos(gcp_layout=
    "spread")` writes it into a fresh copy, the truth of both in gps_truth.json."""
    origin = (47.3769, 8.5417, 410.0)
    points = gps_scene.GCP_POINTS + gps_scene.GCP_LAYOUTS["spread"][1:3]
    tiny_scene(tmp_path / "a", points)
    tiny_scene(tmp_path / "b", points)
    gps_scene.write_gps_photos(tmp_path / "a", origin, seed=2)
    ground = (tmp_path / "a" / "gcp.csv").read_bytes()
    assert not (tmp_path / "a" / "gcp_spread.csv").exists()
    assert gps_scene.write_gcp(tmp_path / "a", "ground") == tmp_path / "a" / "gcp.csv"
    assert (tmp_path / "a" / "gcp.csv").read_bytes() == ground
    assert gps_scene.write_gcp(tmp_path / "a", "spread") == tmp_path / "a" / "gcp_spread.csv"
    gps_scene.write_gps_photos(tmp_path / "b", origin, seed=2, gcp_layout="spread")
    assert not (tmp_path / "b" / "gcp.csv").exists()
    assert (tmp_path / "a" / "gcp_spread.csv").read_bytes() == (tmp_path / "b" / "gcp_spread.csv").read_bytes()
    truth = io_lib.read_json(tmp_path / "a" / "gps_truth.json")
    assert [p["world"] for p in truth["gcp_spread"]] == [list(p) for p in gps_scene.GCP_LAYOUTS["spread"]]
    assert [p["world"] for p in truth["gcp"]] == [list(p) for p in gps_scene.GCP_POINTS]


def test_unknown_layout_is_refused_naming_the_key_writing_nothing(tmp_path, capsys):
    tiny_scene(tmp_path / "d", gps_scene.GCP_POINTS)
    before = sorted(p.name for p in (tmp_path / "d").iterdir())
    with pytest.raises(DataError, match=r"^synth\.gcp_layout: unknown layout 'tall' \(known: ground, spread, dense\)$"):
        gps_scene.write_gps_photos(tmp_path / "d", (47.0, 8.0, 400.0), gcp_layout="tall")
    with pytest.raises(DataError, match=r"^synth\.gcp_layout: unknown layout 'tall'"):
        gps_scene.write_gcp(tmp_path / "d", "tall")
    with pytest.raises(DataError, match=r"gps_truth\.json: not found"):
        gps_scene.write_gcp(tmp_path / "d", "spread")
    assert sorted(p.name for p in (tmp_path / "d").iterdir()) == before
    assert cli.main(["synth", "--out", str(tmp_path / "s"), "--gps-origin", "47,8,400", "--gcp-layout", "tall"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.search(r"--gcp-layout: unknown layout 'tall'", err), err
    assert not (tmp_path / "s").exists()
