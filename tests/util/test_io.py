"""PNG / EXR / PLY round trips and the errors that name the file."""

import numpy as np
import pytest

from jaxnerf_grid.util import io


def test_png_round_trip_rgb_order(tmp_path):
    img = np.zeros((4, 5, 3), np.float32)
    img[..., 0] = 1.0  # pure red
    img[1, 2] = [0.2, 0.4, 0.6]
    io.write_png(tmp_path / "a.png", img)
    back = io.read_image(tmp_path / "a.png")
    np.testing.assert_allclose(back, np.round(img * 255) / 255, atol=1e-6)
    import cv2
    raw = cv2.imread(str(tmp_path / "a.png"))
    assert raw[0, 0, 2] == 255 and raw[0, 0, 0] == 0  # OpenCV sees BGR: red in the last channel


def test_exr_round_trip(tmp_path):
    depth = np.random.default_rng(0).uniform(0.1, 100.0, (6, 7)).astype(np.float32)
    depth[0, 0] = np.inf
    io.write_exr(tmp_path / "d.exr", depth)
    np.testing.assert_array_equal(io.read_exr(tmp_path / "d.exr"), depth)
    rgb = np.random.default_rng(1).uniform(size=(3, 4, 3)).astype(np.float32)
    io.write_exr(tmp_path / "c.exr", rgb)
    np.testing.assert_array_equal(io.read_exr(tmp_path / "c.exr"), rgb)


def test_ply_round_trip(tmp_path):
    pts = np.random.default_rng(2).normal(size=(10, 3)).astype(np.float32)
    io.write_ply(tmp_path / "p.ply", pts, colors=np.ones((10, 3)))
    np.testing.assert_array_equal(io.read_ply_points(tmp_path / "p.ply"), pts)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(io.DataError, match="missing.png"):
        io.read_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(io.DataError, match="bad.png.*not a readable image"):
        io.read_image(tmp_path / "bad.png")
    (tmp_path / "bad.exr").write_bytes(b"junk")
    with pytest.raises(io.DataError, match="bad.exr"):
        io.read_exr(tmp_path / "bad.exr")
    (tmp_path / "bad.json").write_text("{oops")
    with pytest.raises(io.DataError, match="bad.json.*line 1"):
        io.read_json(tmp_path / "bad.json")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(io.DataError, match="overwrite=True"):
        io.ensure_writable(out, overwrite=False)
    assert (out / "keep.txt").read_text() == "x"


def test_atomic_writes_give_the_mode_open_gives_and_keep_a_replaced_files_mode(tmp_path):
    """A written file is not left with mkstemp's 0600: a new one gets what a plain open() gives
    (0666 less the umask), a replaced one keeps its own mode."""
    import os
    import stat

    plain = tmp_path / "plain.json"
    plain.write_text("{}")  # open()'s mode under this process's umask: the reference
    io.write_json(tmp_path / "new.json", {"a": 1})
    io.write_png(tmp_path / "new.png", np.zeros((2, 2, 3), np.float32))
    want = stat.S_IMODE(plain.stat().st_mode)
    assert stat.S_IMODE((tmp_path / "new.json").stat().st_mode) == want
    assert stat.S_IMODE((tmp_path / "new.png").stat().st_mode) == want
    os.chmod(tmp_path / "new.json", 0o640)
    io.write_json(tmp_path / "new.json", {"a": 2})
    assert stat.S_IMODE((tmp_path / "new.json").stat().st_mode) == 0o640
    assert io.read_json(tmp_path / "new.json") == {"a": 2}


def test_distractor_mask_reads_the_generators_0_255_png(tmp_path):
    """The synthetic generator writes distractor masks as 0 / 255 PNGs (io.write_png of a bool
    image); reading one back gives the same pixels, in grey or in colour, and a missing file is
    a DataError naming it."""
    truth = np.zeros((5, 6), bool)
    truth[1:3, 2:5] = True
    truth[4, 0] = True
    io.write_png(tmp_path / "d.png", truth.astype(np.float32))
    np.testing.assert_array_equal(io.read_distractor_mask(tmp_path / "d.png"), truth)
    io.write_png(tmp_path / "c.png", np.repeat(truth[..., None], 3, -1).astype(np.float32))
    np.testing.assert_array_equal(io.read_distractor_mask(tmp_path / "c.png"), truth)
    assert io.distractor_bit(np.where(truth, 255, 0).astype(np.uint8)).tolist() == truth.tolist()
    with pytest.raises(io.DataError, match="gone.png: distractor mask file not found"):
        io.read_distractor_mask(tmp_path / "gone.png")
