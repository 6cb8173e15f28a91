"""`jaxnerf-grid poses` (data/poses.py) and the orbit normalisation (data/normalize.py).

The end-to-end tests photograph a richly textured scene (a ground square and a box, random
multi-scale textures) from an orbit of known cameras with a small ray caster written here,
run the command, and compare the recovered poses with the true ones after a similarity
alignment (Umeyama, written here), so nothing of the code under test checks itself. The
normalisation tests compare with closed forms. Bad input goes through `jaxnerf_grid.cli.main`.
Only the tests that run COLMAP need pycolmap (the `sfm` extra; scripts/setup.sh --test
installs it).
"""

from __future__ import annotations

import shutil
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.capture import vetting
from jaxnerf_grid.capture.poses import (
    MARKER,
    REPORT,
    choose_matcher,
    choose_model,
    crop_offsets,
    enough_registered,
    names_look_ordered,
    poses_agree,
    prepare_photo,
    similarity_fit,
    working_size,
)
from jaxnerf_grid.data import formats
from jaxnerf_grid.data.formats import colmap_model as colmap_io
from jaxnerf_grid.data.normalize import normalize_orbit, rotate_scene, rotation_between, up_from_cameras
from jaxnerf_grid.util import io

W, H, FOCAL = 200, 150, 180.0
RADIUS, HEIGHT, TARGET = 5.0, 2.5, np.array([0.0, 0.0, 0.8])
NUM_VIEWS = 16
EXIF_VIEW = 3  # stored sideways as a JPEG with EXIF orientation 6


# ----------------------------------------------------------------------------------------
# The reference scene and the reference maths


def _look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world [4, 4]: -z towards the target, +y as close to `up` as possible."""
    f = np.asarray(target, float) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, np.cross(r, f), -f, eye
    return m


def _orbit(n=NUM_VIEWS) -> np.ndarray:
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([_look_at(np.array([RADIUS * np.cos(a), RADIUS * np.sin(a), HEIGHT + 0.3 * np.sin(3 * a)]),
                              TARGET) for a in angles])


def _texture(rng, size=256) -> np.ndarray:
    out = np.zeros((size, size, 3), np.float32)
    cv2 = io.opencv()
    for cells, weight in ((4, 0.5), (16, 0.8), (64, 1.0)):
        noise = rng.random((cells, cells, 3)).astype(np.float32)
        out += weight * cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC)
    out -= out.min()
    return out / out.max()


def _scene(seed=0) -> list:
    """Textured quads (origin, edge a, edge b, texture): the ground and a 1.6 x 1.6 x 2 box."""
    rng = np.random.default_rng(seed)
    quads = [(np.array([-4.0, -4.0, 0.0]), np.array([8.0, 0, 0]), np.array([0, 8.0, 0]))]
    r, h = 0.8, 2.0
    corners = [np.array([r, -r, 0.0]), np.array([r, r, 0.0]), np.array([-r, r, 0.0]), np.array([-r, -r, 0.0])]
    for i in range(4):
        quads.append((corners[i], corners[(i + 1) % 4] - corners[i], np.array([0, 0, h])))
    quads.append((np.array([-r, -r, h]), np.array([2 * r, 0, 0]), np.array([0, 2 * r, 0])))
    return [(o, a, b, _texture(rng)) for o, a, b in quads]


def _render(scene, c2w, ss=2) -> np.ndarray:
    """Ray casting, nearest texel, ss x ss samples per pixel; sky elsewhere. Returns [H, W, 3]."""
    uu, vv = np.meshgrid((np.arange(W * ss) + 0.5) / ss, (np.arange(H * ss) + 0.5) / ss)
    d = np.stack([(uu - W / 2) / FOCAL, -(vv - H / 2) / FOCAL, -np.ones_like(uu)], -1) @ c2w[:3, :3].T
    eye = c2w[:3, 3]
    best = np.full(uu.shape, np.inf)
    img = np.empty(uu.shape + (3,), np.float32)
    img[:] = (0.6, 0.75, 0.95)
    for o, a, b, tex in scene:
        n = np.cross(a, b)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((o - eye) @ n) / (d @ n)
        p = eye + t[..., None] * d
        s, q = (p - o) @ a / (a @ a), (p - o) @ b / (b @ b)
        hit = (t > 1e-6) & (t < best) & (s >= 0) & (s < 1) & (q >= 0) & (q < 1)
        th, tw = tex.shape[:2]
        iu, iv = np.clip((s * tw).astype(int), 0, tw - 1), np.clip((q * th).astype(int), 0, th - 1)
        img[hit] = tex[iv[hit], iu[hit]]
        best = np.where(hit, t, best)
    return img.reshape(H, ss, W, ss, 3).mean((1, 3))


def _exif_jpeg(image_bgr: np.ndarray, orientation: int) -> bytes:
    """JPEG bytes with an APP1 EXIF segment holding only the orientation tag (0x0112)."""
    ok, buf = io.opencv().imencode(".jpg", image_bgr, [io.opencv().IMWRITE_JPEG_QUALITY, 97])
    assert ok
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1)
    tiff += struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack("<I", 0)
    app1 = b"Exif\x00\x00" + tiff
    raw = buf.tobytes()
    return raw[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + raw[2:]


def _umeyama(src, dst):
    """Similarity (s, R, t) minimising |s R src + t - dst|^2. src, dst: [N, 3]."""
    ms, md = src.mean(0), dst.mean(0)
    xs, xd = src - ms, dst - md
    u, sig, vt = np.linalg.svd(xd.T @ xs / len(src))
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(u @ vt))
    rot = u @ d @ vt
    scale = float((sig * np.diag(d)).sum() / xs.var(0).sum())
    return scale, rot, md - scale * rot @ ms


def _angle_deg(r1, r2) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r1 @ r2.T) - 1) / 2, -1.0, 1.0))))


def _write_photos(folder, views) -> list[str]:
    cv2 = io.opencv()
    scene = _scene()
    names = []
    for i, c2w in enumerate(views):
        bgr = np.round(_render(scene, c2w)[..., ::-1] * 255).astype(np.uint8)
        if i == EXIF_VIEW:
            name = f"view_{i:02d}.jpg"
            io.atomic_write_bytes(folder / name, _exif_jpeg(cv2.rotate(bgr, cv2.ROTATE_90_COUNTERCLOCKWISE), 6))
        else:
            name = f"view_{i:02d}.png"
            cv2.imwrite(str(folder / name), bgr)
        names.append(name)
    return names


# ----------------------------------------------------------------------------------------
# One run of the command on the textured orbit (plus a blank photo and a broken file)


@pytest.fixture(scope="module")
def orbit_run(tmp_path_factory):
    pytest.importorskip("pycolmap")
    root = tmp_path_factory.mktemp("poses")
    photos = root / "photos"
    photos.mkdir()
    views = _orbit()
    names = _write_photos(photos, views)
    io.write_png(photos / "zz_blank.png", np.full((H, W, 3), 0.5, np.float32))  # no features: unregistered
    (photos / "broken.jpg").write_bytes(b"not a jpeg")                         # unreadable: skipped
    (photos / "notes.txt").write_text("not a photo")                           # ignored
    before = {p.name: p.read_bytes() for p in photos.iterdir()}
    out = root / "data"
    code = cli.main(["poses", "--images", str(photos), "--out", str(out), "--single-camera", "--quiet"])
    return dict(code=code, out=out, photos=photos, views=views, names=names, before=before)


@pytest.fixture(scope="module")
def per_photo_run(orbit_run):
    """The same photos with one camera per photo: each undistorts to its own size, and the
    dataset is cropped to one size."""
    out = orbit_run["out"].parent / "data_per_photo"
    code = cli.main(["poses", "--images", str(orbit_run["photos"]), "--out", str(out), "--quiet"])
    return dict(orbit_run, code=code, out=out)


def _orbit_errors(run) -> tuple:
    """(the run's cameras [N, 4, 4] in view order, the similarity (s, R, t) aligning them to the
    true orbit, rotation errors in degrees [N], centre errors in orbit radii [N]); every view
    must be in the dataset."""
    top = io.read_json(run["out"] / "transforms.json")
    by_name = {f["file_path"]: np.array(f["transform_matrix"]) for f in top["frames"]}
    assert sorted(by_name) == sorted(f"images/{n}" for n in run["names"])
    rec = np.stack([by_name[f"images/{n}"] for n in run["names"]])
    true = run["views"]
    s, rot, t = _umeyama(rec[:, :3, 3], true[:, :3, 3])
    centre_err = np.linalg.norm(s * rec[:, :3, 3] @ rot.T + t - true[:, :3, 3], axis=1) / RADIUS
    rot_err = np.array([_angle_deg(rot @ a[:3, :3], b[:3, :3]) for a, b in zip(rec, true)])
    return rec, (s, rot, t), rot_err, centre_err


def test_poses_recovers_the_orbit(orbit_run):
    """All 16 views register; after a similarity alignment the rotations are within 1 degree
    (median; 2 at most) and the centres within 1 % of the orbit radius (median; 3 % at most)."""
    assert orbit_run["code"] == 0
    rec, (s, rot, t), rot_err, centre_err = _orbit_errors(orbit_run)
    assert np.median(rot_err) < 1.0 and rot_err.max() < 2.0, rot_err
    assert np.median(centre_err) < 0.01 and centre_err.max() < 0.03, centre_err
    # z-up: the alignment is a rotation about z (the true world is z-up) ...
    assert np.degrees(np.arccos(np.clip(rot[2, 2], -1, 1))) < 2.0
    # ... and the looked-at point is the origin, the box (the "tower") inside the unit sphere
    assert np.linalg.norm(t - TARGET) < 0.03 * RADIUS
    corners = np.array([[x, y, z] for x in (-0.8, 0.8) for y in (-0.8, 0.8) for z in (0.0, 2.0)])
    in_norm = (corners - t) @ rot / s
    assert np.linalg.norm(in_norm, axis=1).max() < 1.0
    cam_dist = np.linalg.norm(rec[:, :3, 3], axis=1)
    assert np.all((cam_dist > 2.0) & (cam_dist < 4.0))  # about 3 radii away, as the synthetic scenes


@pytest.fixture(scope="module")
def sequential_run(orbit_run):
    """The same photos matched sequentially, each with its next 3 in name order (no pair closes
    the orbit: view_15 is never matched with view_00)."""
    out = orbit_run["out"].parent / "data_sequential"
    code = cli.main(["poses", "--images", str(orbit_run["photos"]), "--out", str(out), "--single-camera",
                     "--matcher", "sequential", "--overlap", "3", "--quiet"])
    return dict(orbit_run, code=code, out=out)


def test_poses_sequential_matcher_recovers_the_orbit_as_exhaustive(sequential_run):
    """Sequential matching registers all 16 views within the exhaustive run's bounds (1 degree
    median, 2 at most; 1 % / 3 % of the radius) and records what ran."""
    assert sequential_run["code"] == 0
    _, _, rot_err, centre_err = _orbit_errors(sequential_run)
    assert np.median(rot_err) < 1.0 and rot_err.max() < 2.0, rot_err
    assert np.median(centre_err) < 0.01 and centre_err.max() < 0.03, centre_err
    summary = io.read_json(sequential_run["out"] / "transforms.json")["poses"]
    assert (summary["matcher"], summary["matcher_asked"], summary["overlap"]) == ("sequential", "sequential", 3)
    assert "matcher: sequential (asked for, each photo with its next 3)" in (sequential_run["out"] / REPORT).read_text()


def test_poses_sequential_matches_the_next_photos_and_closes_the_orbit(orbit_run, tmp_path, monkeypatch):
    """The pairs COLMAP is handed for sequential matching (read back from the pair list given to
    `match_image_pairs`): 8 photos in name order, each with the next 2, the same across the end
    of the sequence (the last photos with the first: an orbit closes) and the quadratic
    overlap's step 4: every pair but those 3 apart either way round the ring of 8 (3 or 5 apart
    in name order)."""
    pycolmap = pytest.importorskip("pycolmap")
    seen = {}
    real = pycolmap.match_image_pairs

    def spy(database, matching_options=None, pairing_options=None, **kw):
        seen["pairs"] = Path(pairing_options.match_list_path).read_text().split("\n")
        return real(database, matching_options=matching_options, pairing_options=pairing_options, **kw)

    monkeypatch.setattr(pycolmap, "match_image_pairs", spy)
    photos = tmp_path / "p"
    photos.mkdir()
    names = sorted(orbit_run["names"][:8])
    for name in names:
        shutil.copyfile(orbit_run["photos"] / name, photos / name)
    cli.main(["poses", "--images", str(photos), "--out", str(tmp_path / "d"), "--single-camera",
              "--matcher", "sequential", "--overlap", "2", "--quiet"])
    got = {tuple(line.split()) for line in seen["pairs"] if line}
    expected = {(names[i], names[j]) for i in range(8) for j in range(i + 1, 8) if j - i not in (3, 5)}
    assert got == expected
    assert (names[0], names[7]) in got and (names[0], names[6]) in got   # across the end: the orbit closes


def _broken_orbit() -> np.ndarray:
    """16 views named in flight order round the test scene, in two legs of 8 at 22.5 degrees
    apart: the first from 0 to 157.5 degrees, then a jump of 120 degrees (nothing in common
    across it), the second from 277.5 round to 435 = 75 degrees, so the flight ends over the
    ground it began on: only pairs across the end of the sequence join the two legs."""
    angles = np.radians(np.concatenate([np.arange(8) * 22.5, 277.5 + np.arange(8) * 22.5]))
    return np.stack([_look_at(np.array([RADIUS * np.cos(a), RADIUS * np.sin(a), HEIGHT + 0.3 * np.sin(3 * a)]),
                              TARGET) for a in angles])


def test_auto_sequential_matching_closes_an_orbit_and_registers_its_ends(tmp_path, monkeypatch):
    """auto on a set above the exhaustive limit (lowered to 50 pairs here: 19 photos are 171),
    named in sequence: sequential matching with loop closure (next 3). The flight is
    `_broken_orbit` with 3 blank photos (the camera turned to the sky) flown between its legs,
    so the next 3 of the first leg's last photo see nothing: only pairs across the end of the
    sequence (or the quadratic overlap's longer steps) join the legs. Every view registers,
    the ends included, within 2 degrees of the truth; plain sequential matching (next 3 only)
    leaves a leg out."""
    pytest.importorskip("pycolmap")
    from jaxnerf_grid.capture import poses as poses_module

    monkeypatch.setattr(poses_module, "EXHAUSTIVE_MAX_PAIRS", 50)
    photos = tmp_path / "photos"
    photos.mkdir()
    views = _broken_orbit()
    cv2, scene = io.opencv(), _scene()
    names, k = [], 0
    for i, c2w in enumerate(views):
        if i == 8:                                   # the transit: three blank photos
            for _ in range(3):
                cv2.imwrite(str(photos / f"view_{k:02d}.png"), np.full((H, W, 3), 128, np.uint8))
                k += 1
        names.append(f"view_{k:02d}.png")
        cv2.imwrite(str(photos / names[-1]), np.round(_render(scene, c2w)[..., ::-1] * 255).astype(np.uint8))
        k += 1
    out = tmp_path / "data"
    code = cli.main(["poses", "--images", str(photos), "--out", str(out), "--single-camera", "--overlap", "3",
                     "--quiet"])
    assert code == 0
    summary = io.read_json(out / "transforms.json")["poses"]
    assert (summary["matcher"], summary["matcher_asked"]) == ("sequential", "auto")
    assert summary["unregistered"] == ["view_08.png", "view_09.png", "view_10.png"]   # the blank ones
    assert summary["registered"] == summary["in_dataset"] == 16
    _, _, rot_err, _ = _orbit_errors(dict(out=out, names=names, views=views))
    assert rot_err.max() < 2.0, rot_err


def test_names_look_ordered():
    assert names_look_ordered(["0000.jpg", "0001.jpg", "0002.jpg", "0010.jpg"])
    assert names_look_ordered(["DJI_0007.JPG", "DJI_0008.JPG", "DJI_0012.JPG"])  # gaps: deleted photos
    assert names_look_ordered(["IMG_1.jpg", "IMG_2.png", "IMG_3.jpg"])            # extensions do not count
    assert not names_look_ordered(["p1.jpg", "p10.jpg", "p2.jpg"])    # name order 1, 10, 2: not capture order
    assert not names_look_ordered(["a_01.jpg", "b_02.jpg", "a_03.jpg"])  # two prefixes
    assert not names_look_ordered(["x01.jpg", "x1.png", "x02.jpg"])      # number 1 twice
    assert not names_look_ordered(["front.jpg", "side1.jpg", "side2.jpg"])  # a name without a number


def test_choose_matcher_auto_rule():
    """auto: every pair up to 1225 pairs (50 photos); above, spatial when every photo has GPS,
    sequential (with loop closure) when the names are numbered in sequence, else every pair."""
    ordered = [f"DJI_{i:04d}.JPG" for i in range(1, 52)]      # 51 photos: 1275 pairs
    shuffled = [f"p{i}.jpg" for i in range(1, 52)]             # p1, p10, p11, ... in name order
    assert choose_matcher("auto", ordered[:50])[0] == "exhaustive"     # 50 * 49 / 2 = 1225 pairs: small
    assert choose_matcher("auto", ordered[:50], with_gps=50)[0] == "exhaustive"   # small: GPS changes nothing
    assert choose_matcher("auto", ordered)[0] == "sequential"
    assert choose_matcher("auto", ordered, with_gps=51)[0] == "spatial"
    assert choose_matcher("auto", shuffled, with_gps=51)[0] == "spatial"          # unnamed, GPS everywhere
    assert choose_matcher("auto", ordered, with_gps=50)[0] == "sequential"        # one photo without GPS
    assert choose_matcher("auto", shuffled)[0] == "exhaustive"                    # unnamed, no GPS: every pair
    assert choose_matcher("auto", ordered[:5], max_pairs=9)[0] == "sequential"    # 10 pairs > 9
    assert choose_matcher("auto", ordered[:5], max_pairs=10)[0] == "exhaustive"
    assert "1275 pairs" in choose_matcher("auto", ordered)[1]
    for matcher in ("exhaustive", "spatial", "sequential", "vocab"):   # an explicit choice is kept
        assert choose_matcher(matcher, ordered) == (matcher, "asked for")


def test_sequential_pairs_listed_by_hand():
    """`pairing.sequential_pairs` on 6 photos against pairs written out: next 1 only (no wrap, no
    quadratic: a line); with the wrap (5-0 too: a ring); with the quadratic overlap's steps
    2 and 4 as well (every pair but the 3 opposite ones)."""
    from jaxnerf_grid.capture.pairing import pair_count, sequential_pairs

    names = list("abcdef")
    line = [("a", "b"), ("b", "c"), ("c", "d"), ("d", "e"), ("e", "f")]
    assert sequential_pairs(names, 1, wrap=False, quadratic=False) == line
    assert sequential_pairs(names, 1, wrap=True, quadratic=False) == sorted(line + [("a", "f")])
    opposite = {("a", "d"), ("b", "e"), ("c", "f")}
    every = {(x, y) for i, x in enumerate(names) for y in names[i + 1:]}
    assert set(sequential_pairs(names, 1)) == every - opposite
    assert len(sequential_pairs(names, 1)) == 12
    assert set(sequential_pairs(names, 10)) == every and pair_count(6) == 15


def test_pair_count_against_enumerated_pairs():
    """benchmarks.poses_matchers.pair_count against the pairs listed one by one."""
    from benchmarks.poses_matchers import pair_count

    for n in (1, 2, 5, 11, 25):
        assert pair_count(n, "exhaustive", None) == len([(i, j) for i in range(n) for j in range(n) if i < j])
        for k in (1, 3, 10, 30):
            assert pair_count(n, "sequential", k) == len([(i, j) for i in range(n) for j in range(n) if 0 < j - i <= k])


def test_poses_summary_names_skipped_and_unregistered(orbit_run, capsys):
    top = io.read_json(orbit_run["out"] / "transforms.json")
    summary = top["poses"]
    assert summary["photos"] == NUM_VIEWS + 2
    assert summary["registered"] == NUM_VIEWS
    assert summary["unregistered"] == ["zz_blank.png"]
    assert summary["skipped"] == ["broken.jpg"]
    assert 0 < summary["mean_reprojection_error"] < 1.0 and summary["points3d"] > 100
    assert isinstance(summary["relaxed_mapping"], bool)
    # auto, 17 readable photos: every pair; the seconds of each stage add up to the run's
    assert (summary["matcher"], summary["matcher_asked"], summary["overlap"]) == ("exhaustive", "auto", None)
    timings = summary["timings_s"]
    assert list(timings) == ["photos", "features", "matching", "mapping", "writing"]
    assert all(v >= 0 for v in timings.values()) and sum(timings.values()) <= summary["seconds"] + 0.5
    report = (orbit_run["out"] / REPORT).read_text()
    assert "matcher: exhaustive (auto: 17 photos, 136 pairs, at most 1225)" in report and "matching " in report
    # the blank photo stayed out, and why; the camera set: all 16 views kept, the whole orbit
    assert "not registered (1): zz_blank.png (no verified match with a registered photo)" in report
    cameras = summary["camera_set"]
    assert (cameras["photos"], cameras["kept"], cameras["verdict"]) == (17, 16, None)
    assert cameras["arc_kept_deg"] == cameras["arc_flight_deg"] == pytest.approx(360 - 360 / 16, abs=2)
    assert (orbit_run["out"] / "poses_topview.png").is_file()
    # nothing of the input was touched
    assert {p.name: p.read_bytes() for p in orbit_run["photos"].iterdir()} == orbit_run["before"]
    # only the dataset is left in the parent folder (the hidden build folder is gone)
    assert not [p.name for p in orbit_run["out"].parent.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("run", ["orbit_run", "per_photo_run"])
def test_poses_dataset_loads_and_reprojects_within_a_pixel(run, request):
    """load_dataset reads DATA_DIR (the same names, the undistorted images, one size); its
    cameras project the sparse/0 points onto their observations within a pixel at the median
    and within 1.5 px at the 95th percentile: guided matching on small photos (MATCHING_SMALL)
    keeps more observations near the mapper's 2 px filter (0.30 / 1.40 px measured, 0.22 / 0.93
    without it)."""
    orbit_run = request.getfixturevalue(run)
    assert orbit_run["code"] == 0
    out = orbit_run["out"]
    ds = formats.load_dataset(out, progress=False)
    assert ds.num_frames == NUM_VIEWS
    assert sorted(ds.frame_paths) == sorted(f"images/{n}" for n in orbit_run["names"])
    assert ds.images.shape[1:3] == io.read_image(out / "images" / orbit_run["names"][0]).shape[:2]
    assert len(ds.split["train"]) and len(ds.split["test"])
    cams, imgs, pts = colmap_io.read_model(out / "sparse" / "0")
    assert {c.model for c in cams.values()} == {"PINHOLE"}
    assert {(c.width, c.height) for c in cams.values()} == {ds.images.shape[2:0:-1]}
    xyz = {pid: p.xyz for pid, p in pts.items()}
    s, tr = ds.normalization["scale"], np.asarray(ds.normalization["translation"])
    index = {p: i for i, p in enumerate(ds.frame_paths)}
    errors = []
    for im in imgs.values():
        i = index[f"images/{im.name}"]
        c2w, (fx, fy, cx, cy) = ds.c2w[i].astype(np.float64), ds.intrinsics[i]
        for uv, pid in zip(im.xys, im.point3D_ids):
            if pid < 0:
                continue
            x = s * (xyz[pid] + tr)
            cam = np.linalg.inv(c2w) @ np.append(x, 1.0)  # OpenGL: looking down -z, v grows down
            u, v = fx * cam[0] / -cam[2] + cx, fy * -cam[1] / -cam[2] + cy
            errors.append(np.hypot(u - uv[0], v - uv[1]))
    errors = np.array(errors)
    assert len(errors) > 300
    assert np.median(errors) < 0.5 and np.percentile(errors, 95) < 1.5, np.percentile(errors, [50, 95, 100])


def test_poses_refuses_existing_data_dir_and_keeps_it(orbit_run, capsys):
    out = orbit_run["out"]
    before = (out / "transforms.json").read_bytes()
    code = cli.main(["poses", "--images", str(orbit_run["photos"]), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and "\n" not in err and "--overwrite" in err and str(out) in err
    assert (out / "transforms.json").read_bytes() == before


def test_poses_overwrite_replaces_only_its_outputs(orbit_run, tmp_path, capsys):
    """--overwrite on a dataset poses wrote: images/, sparse/, transforms.json and the top view
    are new, the old photos' mask outputs are gone (so `mask` runs without --overwrite); the
    user's other files stay."""
    out = tmp_path / "again"
    shutil.copytree(orbit_run["out"], out)
    (out / "notes.txt").write_text("mine")
    (out / "images" / "stale.png").write_bytes(b"old")
    for name in ("masks", "weights", "dpt_depth", "overlays"):  # as `jaxnerf-grid mask` leaves them
        (out / name).mkdir()
        (out / name / "0000.png").write_bytes(b"old")
    code = cli.main(["poses", "--images", str(orbit_run["photos"]), "--out", str(out), "--single-camera",
                     "--overwrite", "--quiet"])
    assert code == 0, capsys.readouterr().err
    assert (out / "notes.txt").read_text() == "mine" and not (out / "images" / "stale.png").exists()
    # rewritten from every photo (how many of them COLMAP registers is tested by the orbit tests)
    top = io.read_json(out / "transforms.json")
    assert len(top["frames"]) == top["poses"]["in_dataset"] >= NUM_VIEWS - 2 and (out / MARKER).is_file()
    assert not any((out / name).exists() for name in ("masks", "weights", "dpt_depth", "overlays"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again"]


def test_poses_too_few_registered_keeps_old_data_dir(tmp_path, capsys):
    """Photos that share nothing: a one-line error, and --overwrite leaves the old DATA_DIR."""
    pytest.importorskip("pycolmap")
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        io.write_png(photos / f"grey_{i}.png", np.full((60, 80, 3), 0.2 + 0.2 * i, np.float32))
    out = tmp_path / "data"
    out.mkdir()
    (out / "keep.txt").write_text("old dataset")
    (out / MARKER).write_text("")  # as if poses wrote it, so --overwrite may replace it
    code = cli.main(["poses", "--images", str(photos), "--out", str(out), "--overwrite", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and "\n" not in err and str(photos) in err, err
    assert (out / "keep.txt").read_text() == "old dataset"
    assert sorted(p.name for p in out.iterdir()) == sorted(["keep.txt", MARKER])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "photos"]


# ----------------------------------------------------------------------------------------
# Vetting and scene bounds (data/vetting.py, data/bounds.py)


def _turned_20_degrees(cam_from_world: np.ndarray) -> np.ndarray:
    """A world-to-camera pose [3, 4] turned by 20 degrees about the camera's own y axis, the
    centre kept."""
    a = np.radians(20.0)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    centre = -cam_from_world[:, :3].T @ cam_from_world[:, 3]
    rot = ry @ cam_from_world[:, :3]
    return np.concatenate([rot, -(rot @ centre)[:, None]], 1)


def test_poses_vets_every_photo_and_records_bounds(orbit_run):
    """Every registered photo is scored and kept; scene_bounds follow the rule's closed form on
    the written cameras: the region of interest is the unit sphere about the origin (the orbit
    normalisation), near = max(0.9 x (nearest camera distance - 1), the dataset's near)."""
    out = orbit_run["out"]
    top = io.read_json(out / "transforms.json")
    vet = top["poses"]["vetting"]
    assert vet["left_out"] == [] and vet["keep_all"] is False
    assert sorted(r["name"] for r in vet["photos"]) == sorted(orbit_run["names"])
    assert all(r["kept"] and r["reprojection_px"] < 1.0 and r["observations"] > 30 for r in vet["photos"])
    centres = np.array([f["transform_matrix"] for f in top["frames"]])[:, :3, 3]
    b = top["scene_bounds"]
    assert np.linalg.norm(b["roi_centre"]) < 1e-6 and b["roi_radius"] == pytest.approx(1.0, rel=1e-6)
    nearest = float(np.linalg.norm(centres, axis=1).min())
    assert b["near"] == pytest.approx(max(0.9 * (nearest - 1.0), top["near"]), rel=1e-6)
    assert (b["far"], b["contract_radius"]) == (1000.0, 2.0)
    report = (out / REPORT).read_text()
    assert all(f"| {n} |" in report for n in orbit_run["names"]) and "## Scene bounds" in report


def test_vetting_catches_a_turned_camera_in_a_colmap_model(orbit_run):
    """The orbit's COLMAP model: all kept; the same with one camera turned by 20 degrees: that
    one is left out for its reprojection error, the others kept."""
    pycolmap = pytest.importorskip("pycolmap")
    rec = vetting.records_from_pycolmap(pycolmap.Reconstruction(orbit_run["out"] / "sparse" / "0"))
    assert all(r["kept"] for r in vetting.vet(rec))
    rec.cam_from_world[5] = _turned_20_degrees(rec.cam_from_world[5])
    rows = vetting.vet(rec)
    assert [r["name"] for r in rows if not r["kept"]] == [rec.names[5]]
    assert "reprojection" in rows[5]["reasons"][0] and rows[5]["reprojection_px"] > 20


def test_poses_leaves_out_a_wrong_camera_unless_keep_all(orbit_run, tmp_path, monkeypatch, capsys):
    """COLMAP's model with view_05 turned by 20 degrees (planted in what the vetting reads): the
    dataset leaves it out and the report says why; --keep-all keeps it."""
    original = vetting.records_from_pycolmap

    def planted(model):
        rec = original(model)
        i = rec.names.index("view_05.png")
        rec.cam_from_world[i] = _turned_20_degrees(rec.cam_from_world[i])
        return rec

    monkeypatch.setattr(vetting, "records_from_pycolmap", planted)
    out = tmp_path / "vetted"
    code = cli.main(["poses", "--images", str(orbit_run["photos"]), "--out", str(out), "--single-camera", "--quiet"])
    printed = capsys.readouterr().out
    assert code == 0
    top = io.read_json(out / "transforms.json")
    assert len(top["frames"]) == NUM_VIEWS - 1 and "images/view_05.png" not in [f["file_path"] for f in top["frames"]]
    assert not (out / "images" / "view_05.png").exists()
    assert top["poses"]["vetting"]["left_out"] == ["view_05.png"] and top["poses"]["in_dataset"] == NUM_VIEWS - 1
    row = next(line for line in (out / REPORT).read_text().splitlines() if line.startswith("| view_05.png |"))
    assert "| no | reprojection" in row
    assert "left out by the vetting (1; " in printed and "view_05.png (reprojection" in printed
    kept = tmp_path / "kept"
    code = cli.main(["poses", "--images", str(orbit_run["photos"]), "--out", str(kept), "--single-camera",
                     "--keep-all", "--quiet"])
    assert code == 0
    top = io.read_json(kept / "transforms.json")
    assert len(top["frames"]) == NUM_VIEWS and top["poses"]["vetting"]["left_out"] == []
    assert "--keep-all" in (kept / REPORT).read_text()


class _FakeModel:
    def __init__(self, n):
        self.n = n

    def num_reg_images(self):
        return self.n


def test_choose_model_counts_only_vetted_photos():
    """The relaxed model is taken only when it counts more photos; counted by the vetting, a
    relaxed model with more registered but fewer vetted photos loses."""
    default, relaxed = _FakeModel(5), _FakeModel(7)
    assert choose_model(default, relaxed) is relaxed
    vetted = {id(default): 5, id(relaxed): 4}
    assert choose_model(default, relaxed, count=lambda m: vetted[id(m)]) is default
    assert choose_model(None, relaxed, count=lambda m: vetted[id(m)]) is relaxed


# ----------------------------------------------------------------------------------------
# Bad input that is refused before COLMAP runs (no pycolmap needed)


def _one_line_error(capsys, argv) -> str:
    code = cli.main(["poses"] + argv + ["--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 1, err
    assert err.startswith("jaxnerf-grid poses: error: ") and "\n" not in err, err
    return err


def _few_photos(folder, n):
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        io.write_png(folder / f"p{i}.png", np.full((20, 30, 3), 0.5, np.float32))


def test_poses_missing_or_empty_folder(tmp_path, capsys):
    err = _one_line_error(capsys, ["--images", str(tmp_path / "nope"), "--out", str(tmp_path / "d")])
    assert str(tmp_path / "nope") in err and "not found" in err
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("x")
    err = _one_line_error(capsys, ["--images", str(tmp_path / "empty"), "--out", str(tmp_path / "d")])
    assert str(tmp_path / "empty") in err and "no photos" in err
    assert not (tmp_path / "d").exists()


def test_poses_too_few_photos_states_the_minimum(tmp_path, capsys):
    _few_photos(tmp_path / "two", 2)
    err = _one_line_error(capsys, ["--images", str(tmp_path / "two"), "--out", str(tmp_path / "d")])
    assert "2 photo(s)" in err and "at least 3" in err
    assert not (tmp_path / "d").exists()


def test_poses_vocab_needs_a_tree_file(tmp_path, capsys):
    _few_photos(tmp_path / "p", 3)
    err = _one_line_error(capsys, ["--images", str(tmp_path / "p"), "--out", str(tmp_path / "d"),
                                   "--matcher", "vocab"])
    assert "--vocab-tree" in err
    err = _one_line_error(capsys, ["--images", str(tmp_path / "p"), "--out", str(tmp_path / "d"),
                                   "--matcher", "vocab", "--vocab-tree", str(tmp_path / "tree.bin")])
    assert str(tmp_path / "tree.bin") in err and "not found" in err


@pytest.mark.parametrize("argv, flag, text", [(["--matcher", "nearest"], "--matcher", "'nearest'"),
                                               (["--overlap", "0"], "--overlap", "got 0"),
                                               (["--neighbours", "0"], "--neighbours", "got 0")])
def test_poses_bad_matcher_overlap_or_neighbours_says_which_flag(tmp_path, capsys, argv, flag, text):
    _few_photos(tmp_path / "p", 3)
    err = _one_line_error(capsys, ["--images", str(tmp_path / "p"), "--out", str(tmp_path / "d")] + argv)
    assert flag in err and text in err, err
    assert not (tmp_path / "d").exists()


def test_poses_overwrite_refuses_a_folder_it_did_not_write(tmp_path, capsys):
    _few_photos(tmp_path / "p", 3)
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "thesis.tex").write_text("years of work")
    err = _one_line_error(capsys, ["--images", str(tmp_path / "p"), "--out", str(tmp_path / "d"), "--overwrite"])
    assert str(tmp_path / "d") in err and MARKER in err
    assert [p.name for p in (tmp_path / "d").iterdir()] == ["thesis.tex"]
    (tmp_path / "f").write_text("a file")
    err = _one_line_error(capsys, ["--images", str(tmp_path / "p"), "--out", str(tmp_path / "f"), "--overwrite"])
    assert "is a file" in err and (tmp_path / "f").read_text() == "a file"


def test_poses_never_writes_over_its_input(tmp_path, capsys):
    _few_photos(tmp_path / "scene" / "images", 3)
    before = sorted(p.name for p in (tmp_path / "scene" / "images").iterdir())
    err = _one_line_error(capsys, ["--images", str(tmp_path / "scene" / "images"), "--out",
                                   str(tmp_path / "scene"), "--overwrite"])
    assert "input photos" in err
    assert sorted(p.name for p in (tmp_path / "scene" / "images").iterdir()) == before


def test_poses_without_pycolmap_says_how_to_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # `import pycolmap` now raises ImportError
    _few_photos(tmp_path / "p", 3)
    err = _one_line_error(capsys, ["--images", str(tmp_path / "p"), "--out", str(tmp_path / "d")])
    assert "pycolmap is not installed" in err and "[sfm]" in err
    assert not (tmp_path / "d").exists()


def test_package_and_cli_import_without_pycolmap():
    """Nothing imports pycolmap at module level (it is an optional extra)."""
    import subprocess

    code = ("import sys; sys.modules['pycolmap'] = None; import jaxnerf_grid.capture.poses, jaxnerf_grid.cli.poses, "
            "jaxnerf_grid.data.formats; from jaxnerf_grid.cli.poses import build_parser; build_parser()")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=600)


# ----------------------------------------------------------------------------------------
# EXIF orientation and the working size


def test_prepare_photo_honours_exif_orientation(tmp_path):
    cv2 = io.opencv()
    rng = np.random.default_rng(1)
    upright = np.round(cv2.resize(rng.random((6, 8, 3)).astype(np.float32), (80, 60),
                                  interpolation=cv2.INTER_CUBIC).clip(0, 1) * 255).astype(np.uint8)
    src = tmp_path / "in" / "side.jpg"
    src.parent.mkdir()
    src.write_bytes(_exif_jpeg(cv2.rotate(upright, cv2.ROTATE_90_COUNTERCLOCKWISE), 6))
    stored = cv2.imdecode(np.fromfile(str(src), np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    assert stored.shape[:2] == (80, 60)  # stored sideways
    used, size = prepare_photo(src, tmp_path / "work", None)
    assert used == tmp_path / "work" / "side.jpg" and size == (80, 60)
    copy = cv2.imdecode(np.fromfile(str(used), np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    assert copy.shape[:2] == (60, 80)  # upright without any tag
    assert np.abs(copy.astype(int) - upright.astype(int)).mean() < 6  # two JPEG encodings apart
    # an upright PNG within the working size is used as it is; a larger one is scaled down
    png = tmp_path / "in" / "flat.png"
    cv2.imwrite(str(png), upright)
    assert prepare_photo(png, tmp_path / "work", None) == (png, (80, 60))
    used, size = prepare_photo(png, tmp_path / "work", 40)
    assert size == (40, 30) and cv2.imread(str(used)).shape == (30, 40, 3) and used.name == "flat.png"


def test_working_size_and_crop_offsets():
    assert working_size(4000, 3000, None) == (4000, 3000)
    assert working_size(4000, 3000, 800) == (800, 600)
    assert working_size(3000, 4000, 800) == (600, 800)
    assert working_size(320, 240, 800) == (320, 240)  # never enlarged
    assert [enough_registered(n) for n in (3, 12, 13, 30, 120)] == [3, 3, 4, 8, 30]
    size, offsets = crop_offsets({1: (197, 147), 2: (193, 144), 3: (200, 150)})
    assert size == (193, 144) and offsets == {1: (2, 1), 2: (0, 0), 3: (3, 3)}


def test_similarity_fit_and_poses_agree():
    """Poses moved by a known similarity agree with the originals (and the fit recovers it);
    3 degrees of rotation noise on every camera, or a fifth of them swapped, do not."""
    views = _orbit(10)
    rot, scale, shift = _random_rotation(7), 0.37, np.array([1.0, -2.0, 0.5])
    moved = views.copy()
    moved[:, :3, :3] = rot @ views[:, :3, :3]
    moved[:, :3, 3] = scale * views[:, :3, 3] @ rot.T + shift
    s, r, t = similarity_fit(views[:, :3, 3], moved[:, :3, 3])
    assert s == pytest.approx(scale) and np.allclose(r, rot, atol=1e-9) and np.allclose(t, shift, atol=1e-9)
    a = {f"p{i}": m for i, m in enumerate(views)}
    b = {f"p{i}": m for i, m in enumerate(moved)}
    assert poses_agree(a, b) and poses_agree(b, a)
    assert poses_agree(a, dict(b, extra=np.eye(4)))  # names only one side holds are ignored
    assert not poses_agree(a, {k: b[k] for k in ("p0", "p1")})  # fewer than 3 in common
    noisy = {k: _roll(m, 3.0) for k, m in b.items()}
    assert not poses_agree(a, noisy)
    swapped = dict(b, p0=b["p5"], p5=b["p0"], p2=b["p7"], p7=b["p2"], p3=b["p8"], p8=b["p3"])
    assert not poses_agree(a, swapped)


# ----------------------------------------------------------------------------------------
# The up axis and the orbit normalisation, against closed forms


def _random_rotation(seed) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _roll(c2w, degrees):
    """The same camera turned about its viewing axis."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    out = c2w.copy()
    out[:3, 0], out[:3, 1] = c * c2w[:3, 0] + s * c2w[:3, 1], -s * c2w[:3, 0] + c * c2w[:3, 1]
    return out


@pytest.mark.parametrize("arc_deg", [360.0, 90.0])
def test_up_from_cameras_level_cameras(arc_deg):
    """Level cameras on arcs at two heights and radii, pitched down at the tower, in a rotated
    world: the up axis is the rotated +z exactly (the mean up vector is tilted on a 90-degree
    arc, and no plane holds both arcs)."""
    rot = _random_rotation(3)
    angles = np.radians(np.linspace(0, arc_deg, 12, endpoint=arc_deg < 360))
    views = [_look_at(np.array([r * np.cos(a), r * np.sin(a), z]), TARGET)
             for a in angles for r, z in ((5.0, 2.0), (4.0, 3.5))]
    views, _ = rotate_scene(np.stack(views), rot)
    np.testing.assert_allclose(up_from_cameras(views), rot[:, 2], atol=1e-9)
    if arc_deg < 360:
        mean_up = views[:, :3, 1].mean(0)
        assert _angle_deg(np.eye(3), rotation_between(mean_up, rot[:, 2])) > 5.0


def test_up_from_cameras_rolled_cameras_within_a_degree():
    """A full orbit with +-3 degrees of roll noise: within a degree."""
    rng = np.random.default_rng(2)
    views = np.stack([_roll(v, rng.uniform(-3, 3)) for v in _orbit(24)])
    assert _angle_deg(np.eye(3), rotation_between(up_from_cameras(views), [0, 0, 1.0])) < 1.0


def test_up_from_cameras_one_heading_uses_the_plane_of_centres():
    """A survey grid flown with one heading, cameras pitched 30 degrees down: the right
    vectors are all the same, the centres span the horizontal plane: its normal, +z."""
    rot = _random_rotation(4)
    pitch = np.radians(30.0)
    views = np.stack([_look_at(np.array([x, y, 10.0]), np.array([x, y + 10.0 / np.tan(pitch), 0.0]))
                      for x in np.linspace(-5, 5, 4) for y in np.linspace(-5, 5, 3)])
    views, _ = rotate_scene(views, rot)
    np.testing.assert_allclose(up_from_cameras(views), rot[:, 2], atol=1e-9)


def test_up_from_cameras_on_a_line_is_the_mean_up():
    views = np.stack([_look_at(np.array([x, -5.0, 2.0]), np.array([x, 0.0, 0.0])) for x in np.linspace(-2, 2, 5)])
    views = np.stack([_roll(v, d) for v, d in zip(views, (2.0, -1.0, 0.5, 3.0, -2.0))])
    mean_up = views[:, :3, 1].mean(0)
    np.testing.assert_allclose(up_from_cameras(views), mean_up / np.linalg.norm(mean_up), atol=1e-12)


@pytest.mark.parametrize("a, b", [([1.0, 2.0, 3.0], [0, 0, 1.0]), ([0, 0, -1.0], [0, 0, 1.0]),
                                  ([0, 0, 2.0], [0, 0, 1.0]), ([1.0, 0, 0], [-1.0, 0, 0])])
def test_rotation_between(a, b):
    r = rotation_between(a, b)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ (np.array(a) / np.linalg.norm(a)), np.array(b) / np.linalg.norm(b), atol=1e-12)


def test_rotate_scene_keeps_projections():
    views = _orbit(5)
    point = np.array([0.3, -0.2, 1.1])
    rot = _random_rotation(5)
    views_r, pts_r = rotate_scene(views, rot, point[None])
    for a, b in zip(views, views_r):
        np.testing.assert_allclose(np.linalg.inv(a) @ np.append(point, 1), np.linalg.inv(b) @ np.append(pts_r[0], 1),
                                   atol=1e-12)


def test_normalize_orbit_closed_forms():
    """Cameras at distance D from the looked-at point T: translation -T; scale 3 / D without
    points (cap D / 3), 1 / r for points on a sphere of radius r < D / 3 about T."""
    views = _orbit(8)
    dist = np.linalg.norm(views[:, :3, 3] - TARGET, axis=1)
    out, norm = normalize_orbit(views)
    np.testing.assert_allclose(norm["translation"], -TARGET, atol=1e-9)
    assert norm["scale"] == pytest.approx(3.0 / np.median(dist))
    np.testing.assert_allclose(out[:, :3, :3], views[:, :3, :3])
    np.testing.assert_allclose(out[:, :3, 3], norm["scale"] * (views[:, :3, 3] - TARGET), atol=1e-12)
    dirs = np.random.default_rng(0).normal(size=(500, 3))
    sphere = TARGET + 1.2 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    _, norm = normalize_orbit(views, sphere)
    assert norm["scale"] == pytest.approx(1 / 1.2)
    far_points = TARGET + 50.0 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)  # background only
    _, norm = normalize_orbit(views, far_points)
    assert norm["scale"] == pytest.approx(3.0 / np.median(dist))


def test_strecha_cameras_reads_the_surveyed_format(tmp_path):
    """benchmarks.poses_accuracy.strecha_cameras on a hand-written `.camera` file (K, distortion,
    R camera-to-world with OpenCV axes, centre, size): the centre is the camera's position and a
    point 5 m along R's third column (OpenCV's viewing axis) lies 5 m down the OpenGL -z axis."""
    from benchmarks.poses_accuracy import strecha_cameras

    a = np.radians(30.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]) @ \
        np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    centre = np.array([-7.25, -7.5, 0.2])
    rows = ["2759.48 0 1520.69", "0 2764.16 1006.81", "0 0 1", "0 0 0",
            *(" ".join(f"{v:.17g}" for v in row) for row in rot), " ".join(f"{v:g}" for v in centre), "3072 2048"]
    (tmp_path / "0000.jpg.camera").write_text("\n".join(rows) + "\n")
    c2w = strecha_cameras(tmp_path)["0000.jpg"]
    np.testing.assert_allclose(c2w[:3, 3], centre)
    ahead = np.linalg.inv(c2w) @ np.append(centre + 5.0 * rot[:, 2], 1.0)
    np.testing.assert_allclose(ahead[:3], [0.0, 0.0, -5.0], atol=1e-9)


def test_orientation_alignment_recovers_a_shared_rotation_and_keeps_a_lone_error():
    """benchmarks.poses_accuracy.compare on a ring of cameras whose found poses are the true ones
    turned by one rotation G (about a tilted axis) and scaled, with one camera turned 3 degrees
    more about its own axis: after aligning the orientations every camera's error is 0 but that
    one's, 3 degrees less the pull it has on the mean, whatever the centres' fit does."""
    from scipy.spatial.transform import Rotation

    from benchmarks.poses_accuracy import compare, orientation_alignment

    rng = np.random.default_rng(3)
    true, found = {}, {}
    g = Rotation.from_rotvec(np.radians(7.0) * np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3]))
    for k in range(12):
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.from_euler("zx", [30.0 * k, 80.0 + rng.normal()], degrees=True).as_matrix()
        c2w[:3, 3] = [4 * np.cos(np.radians(30 * k)), 4 * np.sin(np.radians(30 * k)), 1.0]
        true[f"p{k:02d}"] = c2w
        f = np.eye(4)
        f[:3, :3] = g.inv().as_matrix() @ c2w[:3, :3]
        f[:3, 3] = 0.5 * g.inv().as_matrix() @ c2w[:3, 3]
        if k == 5:
            f[:3, :3] = f[:3, :3] @ Rotation.from_rotvec(np.radians(3.0) * np.array([0, 0, 1.0])).as_matrix()
        found[f"p{k:02d}"] = f
    names = [n for n in sorted(found) if n != "p05"]
    exact = orientation_alignment(np.stack([found[n][:3, :3] for n in names]),
                                  np.stack([true[n][:3, :3] for n in names]))
    np.testing.assert_allclose(exact, g.as_matrix(), atol=1e-9)  # no lone error: G itself
    per = compare(true, found)["per_photo"]
    # the lone 3 degrees pull the chordal mean by about 3 / 12 degrees; the shared 7 are gone
    assert 2.6 < per["p05"]["rotation_deg_oriented"] < 3.0
    assert max(v["rotation_deg_oriented"] for n, v in per.items() if n != "p05") < 0.4


def test_compare_fitted_on_the_kept_cameras_scores_a_camera_put_far_off_by_its_own_error():
    """benchmarks.poses_accuracy.compare with align_on: found = true scaled by 2 and shifted,
    one camera moved 10 ring radii and turned 90 degrees. Fitted on the other 11, every one of
    them is exact and the moved one scores 10 radii and 90 degrees (closed form); fitted on all
    12 the moved camera drags the fit and the others score off."""
    from scipy.spatial.transform import Rotation

    from benchmarks.poses_accuracy import compare

    true, found = {}, {}
    for k in range(12):
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.from_euler("zx", [30.0 * k, 80.0], degrees=True).as_matrix()
        c2w[:3, 3] = [4 * np.cos(np.radians(30 * k)), 4 * np.sin(np.radians(30 * k)), 1.0]
        true[f"p{k:02d}"] = c2w
        f = c2w.copy()
        f[:3, 3] = 2.0 * c2w[:3, 3] + [1.0, -2.0, 0.5]
        found[f"p{k:02d}"] = f
    found["p05"] = found["p05"].copy()
    found["p05"][:3, 3] += 2.0 * 40.0 * np.array([0.0, 0.0, 1.0])  # 40 m up: 10 radii of 4
    found["p05"][:3, :3] = found["p05"][:3, :3] @ Rotation.from_euler("y", 90.0, degrees=True).as_matrix()
    kept = {n for n in found if n != "p05"}
    per = compare(true, found, align_on=kept)["per_photo"]
    assert per["p05"]["centre"] == pytest.approx(10.0, rel=1e-9)
    assert per["p05"]["rotation_deg"] == pytest.approx(90.0, abs=1e-4)
    assert max(per[n]["centre"] for n in kept) < 1e-9
    assert max(per[n]["rotation_deg"] for n in kept) < 1e-4  # arccos near 1
    dragged = compare(true, found)["per_photo"]
    assert max(dragged[n]["centre"] for n in kept) > 0.5


def test_poses_without_gps_says_units_unknown(orbit_run):
    """Photos without GPS and no scale bar: the dataset is written as before, its georeference
    says units unknown, and so do the summary and the report (docs/GEOREFERENCE.md)."""
    top = io.read_json(orbit_run["out"] / "transforms.json")
    assert top["georeference"] == {"units": "unknown", "source": None}
    assert "Units unknown" in (orbit_run["out"] / "poses_report.md").read_text()


def _stage_reached(parent: Path, name: str, stage: str) -> bool:
    """Whether a `poses` run writing `parent/name` has reached `stage` in its staging folder:
    "photos" (a working copy of a photo), "features" (keypoints in COLMAP's database),
    "matching" (matches in it), "mapping" (the first model's folder)."""
    import sqlite3

    for work in parent.glob(f".{name}.poses-*/_work"):
        if stage == "photos" and any((work / "photos").glob("*")):
            return True
        if stage == "mapping" and (work / "sparse0").exists():
            return True
        if stage in ("features", "matching") and (work / "database.db").is_file():
            table = "keypoints" if stage == "features" else "matches"
            try:
                with sqlite3.connect(f"file:{work / 'database.db'}?mode=ro", uri=True, timeout=0.1) as db:
                    if db.execute(f"SELECT count(*) FROM {table}").fetchone()[0] > 0:
                        return True
            except sqlite3.Error:  # not made yet, or locked by the writer: look again
                pass
    return False


@pytest.mark.parametrize("stage", ["photos", "features", "matching", "mapping"])
def test_poses_killed_in_a_colmap_stage_leaves_the_dataset_and_is_cleaned(orbit_run, tmp_path, stage):
    """kill -9 of `poses --overwrite` while COLMAP works (its working copy of the photos, SIFT
    features, matching, mapping): the dataset it was replacing is byte-identical, the killed
    run's staging folder is the only thing beside it, and `recover` (run first by the next
    `poses` or load) removes it, leaving the dataset as it was."""
    from jaxnerf_grid.capture.poses import recover
    from tests.support.killing import kill_when

    parent = tmp_path / "site"
    parent.mkdir()
    out = parent / "data"
    shutil.copytree(orbit_run["out"], out)
    before = {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    kill_when(["-m", "jaxnerf_grid", "poses", "--images", str(orbit_run["photos"]), "--out", str(out),
               "--overwrite", "--quiet"], ready=lambda: _stage_reached(parent, "data", stage), timeout=300, poll=0.05)
    after = {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    assert after == before
    assert [p.name for p in parent.iterdir() if p.name.startswith(".")] != []  # it died mid-run
    assert recover(out) == "cleaned"
    assert sorted(p.name for p in parent.iterdir()) == ["data"]
    assert {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before
