"""The pasted-transient benchmark's data (benchmarks/pasted_transients.py) on hand-made images
and cameras: the pasted masks are exact (inside them the sprite's colours, outside them the
photo untouched), test photos stay clean, the Strecha cameras become poses that project a world
point where the Strecha convention (x = K R^T (X - C)) does, and the share of pasted pixels
that training used is a plain weighted count."""

import json

import numpy as np
import pytest

from benchmarks import pasted_transients as pt
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError

RED = np.array([1.0, 0.0, 0.0], np.float32)


def _sprites():
    """Two hand-made sprites in pure red (no photo pixel here is pure red): an L and a bar."""
    ell = np.zeros((6, 4), bool)
    ell[:, 0] = True
    ell[-1, :] = True
    bar = np.ones((2, 5), bool)
    return [(np.where(m[..., None], RED, 0.3).astype(np.float32), m) for m in (ell, bar)]


def _photo(h, w, seed=0):
    return np.random.default_rng(seed).uniform(0.1, 0.9, size=(h, w, 3)).astype(np.float32)


@pytest.mark.parametrize("coverage", [0.05, 0.2, 0.4])
def test_pasted_mask_is_exactly_where_the_sprites_are(coverage):
    photo = _photo(40, 60)
    out, mask = pt.paste_sprites(photo, _sprites(), np.random.default_rng(3), coverage, scale=1.0)
    assert mask.mean() >= coverage
    np.testing.assert_array_equal(out[~mask], photo[~mask])  # outside: the photo, bit for bit
    red = np.all(out == RED, axis=-1)
    np.testing.assert_array_equal(red, mask)  # inside: the sprites' own colour, nowhere else
    assert pt.paste_sprites(photo, _sprites(), np.random.default_rng(3), 0.0)[1].sum() == 0


def test_sprite_bank_keeps_whole_components_only():
    img = _photo(20, 30)
    m = np.zeros((20, 30), bool)
    m[5:9, 10:13] = True          # a 12-pixel blob inside
    m[0:3, 0:3] = True            # touches the border: cut off by the frame, dropped
    m[15, 25] = True              # too small
    bank = pt.sprite_bank([img], [m], min_pixels=5)
    assert len(bank) == 1
    rgb, sm = bank[0]
    np.testing.assert_array_equal(sm, np.ones((4, 3), bool))
    np.testing.assert_array_equal(rgb, img[5:9, 10:13])


def _strecha_scene(root, n=4, w=90, h=60):
    """A Strecha-layout scene: photos (PNG bytes under .jpg names) and .camera files of cameras on
    a circle looking at the origin (OpenCV axes: x right, y down, z forward)."""
    (root / "images").mkdir(parents=True)
    (root / "gt_dense_cameras").mkdir()
    k = np.array([[80.0, 0, 44.0], [0, 82.0, 31.0], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        c = np.array([6 * np.cos(a), 6 * np.sin(a), 1.0])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        r = np.stack([x, y, z], 1)  # camera-to-world: columns are the camera axes in the world
        name = f"{i:04d}.jpg"
        io.write_png(root / "images" / f"{i:04d}.png", _photo(h, w, seed=i))
        (root / "images" / f"{i:04d}.png").rename(root / "images" / name)
        rows = [k[0], k[1], k[2], [0, 0, 0], r[0], r[1], r[2], c, [w, h]]
        (root / "gt_dense_cameras" / f"{name}.camera").write_text(
            "\n".join(" ".join(f"{v:.9g}" for v in row) for row in rows) + "\n")
        cams.append((k, r, c))
    return cams


def test_build_scene_pastes_train_photos_keeps_test_photos_and_poses(tmp_path):
    cams = _strecha_scene(tmp_path / "scene")
    out = pt.build_scene(tmp_path / "scene", tmp_path / "data", _sprites(), long_side=45, test_every=2,
                         coverage=0.1, sprite_scale=1.0)
    meta = io.read_json(out / "transforms.json")
    assert [f["split"] for f in meta["frames"]] == ["train", "test", "train", "test"]
    norm = meta["scene_normalization"]
    point = np.array([0.3, -0.2, 0.5])  # a world point every camera sees
    for f, (k, r, c) in zip(meta["frames"], cams):
        img = io.read_image(out / f["file_path"])
        clean = io.read_image(out / f["clean_file_path"])
        mask = io.read_distractor_mask(out / f["distractor_mask_path"])
        assert img.shape == (30, 45, 3) and (f["w"], f["h"]) == (45, 30)
        if f["split"] == "test":
            assert not mask.any()
            np.testing.assert_array_equal(img, clean)
        else:
            assert mask.mean() >= 0.1 and f["pasted_share"] == pytest.approx(mask.mean(), abs=1e-4)
            np.testing.assert_array_equal(img[~mask], clean[~mask])
            np.testing.assert_array_equal(np.all(img == RED, -1), mask)
        # Strecha's projection at full size, scaled to the small photo ...
        x = k @ (r.T @ (point - c))
        ref = x[:2] / x[2] * 0.5
        # ... against the dataset's OpenGL pose in the normalised scene
        c2w = np.asarray(f["transform_matrix"])
        p = norm["scale"] * (point + np.asarray(norm["translation"]))
        cam = c2w[:3, :3].T @ (p - c2w[:3, 3])
        uv = np.array([f["fl_x"] * cam[0] / -cam[2] + f["cx"], f["fl_y"] * -cam[1] / -cam[2] + f["cy"]])
        np.testing.assert_allclose(uv, ref, atol=1e-6)


def test_read_strecha_camera_refuses_a_short_file(tmp_path):
    bad = tmp_path / "x.camera"
    bad.write_text("1 2 3\n")
    with pytest.raises(DataError, match="x.camera"):
        pt.strecha.read_camera(bad)


def test_pasted_share_used_is_the_weighted_count(tmp_path):
    m = np.zeros((4, 5), bool)
    m[1:3, 1:4] = True  # 6 pixels
    io.write_png(tmp_path / "d0.png", m.astype(np.float32))
    io.write_png(tmp_path / "d1.png", np.ones((4, 5), np.float32))  # a test frame: never counted
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": [
        {"file_path": "images/a.png", "distractor_mask_path": "d0.png", "split": "train"},
        {"file_path": "images/b.png", "distractor_mask_path": "d1.png", "split": "test"}]}))
    w = np.ones((4, 5))
    w[1, 1:4] = 0.0  # 3 of the 6 pasted pixels ignored
    w[2, 1] = 0.5
    share = pt.pasted_share_used(tmp_path, {"a": w, "b": np.zeros((4, 5))})
    assert share == pytest.approx((0 + 0 + 0 + 0.5 + 1 + 1) / 6)
    assert pt.pasted_share_used(tmp_path, None) == 1.0


def test_results_name_no_folder_of_this_machine():
    argv = ["/data/x/Benchmarking_Camera_Calibration_2008", "--work", "/scratch/w", "--out",
            str(pt.ROOT / "benchmarks/results/p"), "--steps", "10"]
    assert pt.shown_argv(argv, argv[0]) == ["STRECHA_DIR", "--work", "w", "--out", "benchmarks/results/p",
                                            "--steps", "10"]


def test_the_weights_a_robust_run_wrote_are_read_back_by_frame_stem(tmp_path):
    """run_weights reads what train.write_robust_record writes (8-bit PNGs named by the frame's
    file stem), so pasted_share_used looks the training photos' stems up in it."""

    from jaxnerf_grid.data.dataset import Dataset
    from jaxnerf_grid.train import loop as train

    record = np.random.default_rng(0).random((2, 5, 7)).astype(np.float32)
    ds = Dataset(root=tmp_path, images=np.zeros((3, 5, 7, 3), np.float32), c2w=np.tile(np.eye(4), (3, 1, 1)),
                 intrinsics=np.ones((3, 4), np.float32), split={"train": np.array([0, 2]), "test": np.array([1])},
                 near=0.1, far=10.0, frame_paths=["images/0000.jpg", "images/0001.jpg", "images/0002.jpg"])
    train.write_robust_record(tmp_path / "run", ds, record)
    got = pt.run_weights(tmp_path / "run")
    assert sorted(got) == ["0000", "0002"]
    np.testing.assert_allclose(got["0002"], record[1], atol=0.5 / 255 + 1e-6)


def test_set_changes_the_robust_rows_only():
    from jaxnerf_grid.config import run_config
    from jaxnerf_grid.config import schema as config
    from jaxnerf_grid.train import loop as train

    sets = config.parse_sets(["train.robust.confirm=0.02", "train.robust.spread=2"], run_config.RunConfig)
    robust = train.make_config("ours", pt.row_overrides("robust", 0, 10, sets)).train
    assert (robust.robust.mode, robust.robust.confirm, robust.robust.spread) == ("robust", 0.02, 2.0)
    gt = train.make_config("ours", pt.row_overrides("gt", 0, 10, sets)).train
    default = train.make_config("ours").train
    assert gt.robust.mode == "off" and (gt.robust.confirm, gt.robust.spread) == (default.robust.confirm,
                                                                           default.robust.spread)
    with pytest.raises(SystemExit, match="--set"):
        pt.main(["somewhere", "--set", "train.no_such_key=1"])


def test_prior_picks_the_masked_rows_masks_only(tmp_path):
    """--prior: the dpt and dpt+robust rows train on the pasted masks ("gt") or on a named masked copy
    ({scene} filled in); every other row keeps its own data; a folder without masks is a
    one-line DataError naming it."""
    from jaxnerf_grid.util.io import DataError

    _strecha_scene(tmp_path / "scene")
    base = pt.build_scene(tmp_path / "scene", tmp_path / "data" / "fount", _sprites(), long_side=45, test_every=2,
                          coverage=0.1, sprite_scale=1.0)
    assert pt.prior_data(base, "dpt+robust", "gt") == tmp_path / "data" / "fount-gt"
    assert io.read_json(tmp_path / "data" / "fount-gt" / "transforms.json")["mask_source"] == "ground-truth"
    assert pt.prior_data(base, "robust", "gt") == base           # not a masked row: its own data
    assert pt.prior_data(base, "dpt", "gt") == tmp_path / "data" / "fount-gt"
    assert pt.prior_data(base, "gt", "elsewhere") == tmp_path / "data" / "fount-gt"
    other = tmp_path / "sweep" / "fount-masked"
    other.mkdir(parents=True)
    io.write_json(other / "transforms.json", {"mask_source": "sweep (offline)", "frames": []})
    assert pt.prior_data(base, "dpt+robust", str(tmp_path / "sweep" / "{scene}-masked")) == other
    with pytest.raises(DataError, match="no masked dataset"):
        pt.prior_data(base, "dpt+robust", str(tmp_path / "nowhere"))
    with pytest.raises(DataError, match="the only name"):
        pt.prior_data(base, "dpt+robust", str(tmp_path / "{place}-masked"))
