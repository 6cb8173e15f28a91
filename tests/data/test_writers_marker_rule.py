"""The marker rule (`folders.prepare_output`, docs/RELIABILITY.md) for the two writers
of whole folders outside the commands: `data.formats.save_transforms_json` and
`data.preprocess.preprocess_images`. The expected trees are written out by hand (the user's own
files, the names a second run must leave), never read back from the code under test.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid.data import formats, preprocess
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError
from tests.train.test_loop import tiny_dataset


def hashes(root: Path) -> dict:
    """{relative path: sha256, "dir" or "link"} of everything under root."""
    return {p.relative_to(root).as_posix(): "link" if p.is_symlink() else "dir" if p.is_dir()
            else hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*"))}


def names(root: Path) -> set:
    return {p.relative_to(root).as_posix() for p in root.rglob("*")}


def photos(folder: Path, count: int) -> Path:
    rng = np.random.default_rng(count)
    for i in range(count):
        io.write_png(folder / f"p{i}.png", rng.random((12, 16, 3)))
    return folder


def test_save_transforms_json_never_clears_a_folder_it_did_not_write(tmp_path):
    """Before: overwrite=True wrote over a user's images/ and transforms.json in any folder."""
    out = tmp_path / "out"
    (out / "images").mkdir(parents=True)
    (out / "images" / "00000_a.png").write_bytes(b"the user's photo")
    (out / "transforms.json").write_text('{"mine": true}')
    before = hashes(tmp_path)
    with pytest.raises(DataError, match=r"out: exists, is not empty and was not written by jaxnerf-grid dataset "
                                        r"\(no \.jaxnerf-grid-dataset\)"):
        formats.save_transforms_json(tiny_dataset(frames=3), out, overwrite=True)
    with pytest.raises(DataError, match=r"out: dataset.out_dir exists and is not empty.*overwrite=True"):
        formats.save_transforms_json(tiny_dataset(frames=3), out)
    assert hashes(tmp_path) == before


def test_save_transforms_json_overwrite_replaces_only_its_outputs(tmp_path):
    """A second save with fewer frames: the old frames, and the mask outputs made from them,
    are gone; the user's notes stay; the dataset loads as the second one."""
    out = tmp_path / "out"
    formats.save_transforms_json(tiny_dataset(frames=5), out)
    (out / "notes.txt").write_text("surveyed 3 May")
    (out / "dpt_depth").mkdir()
    (out / "dpt_depth" / "00004_x.exr").write_bytes(b"stale")
    second = tiny_dataset(frames=3, seed=1)
    formats.save_transforms_json(second, out, overwrite=True)
    assert names(out) == {".jaxnerf-grid-dataset", "notes.txt", "transforms.json", "images", "weights",
                          *(f"images/{i:05d}.png" for i in range(3)), *(f"weights/{i:05d}.exr" for i in range(3))}
    assert (out / "notes.txt").read_text() == "surveyed 3 May"
    again = formats.load_dataset(out)
    np.testing.assert_allclose(again.images, second.images, atol=1 / 255)


def test_save_transforms_json_refuses_a_linked_output(tmp_path):
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    formats.save_transforms_json(tiny_dataset(frames=3), out)
    (elsewhere / "x").mkdir(parents=True)
    (out / "weights").rename(elsewhere / "weights")
    (out / "weights").symlink_to(elsewhere / "weights")
    before = hashes(tmp_path)
    with pytest.raises(DataError, match="weights: is a symbolic link"):
        formats.save_transforms_json(tiny_dataset(frames=3), out, overwrite=True)
    assert hashes(tmp_path) == before


def test_preprocess_never_clears_a_folder_it_did_not_write(tmp_path):
    src = photos(tmp_path / "src", 2)
    out = tmp_path / "out"
    (out / "images").mkdir(parents=True)
    (out / "images" / "p0.png").write_bytes(b"the user's own image")
    before = hashes(tmp_path)
    with pytest.raises(DataError, match=r"no \.jaxnerf-grid-preprocess"):
        preprocess.preprocess_images(src, out, overwrite=True)
    with pytest.raises(DataError, match=r"preprocess.out exists and is not empty.*overwrite=True"):
        preprocess.preprocess_images(src, out)
    assert hashes(tmp_path) == before


def test_preprocess_overwrite_replaces_only_its_outputs(tmp_path):
    """Three photos, then two: the third's image is gone, preprocess.json lists two, the user's
    file stays; a folder of an older preprocess (preprocess.json, no marker) may be replaced."""
    out = tmp_path / "out"
    preprocess.preprocess_images(photos(tmp_path / "three", 3), out)
    (out / "notes.txt").write_text("mine")
    preprocess.preprocess_images(photos(tmp_path / "two", 2), out, overwrite=True)
    assert names(out) == {".jaxnerf-grid-preprocess", "notes.txt", "preprocess.json", "images", "images/p0.png",
                          "images/p1.png"}
    assert [e["source"] for e in io.read_json(out / "preprocess.json")["images"]] == ["p0.png", "p1.png"]
    (out / ".jaxnerf-grid-preprocess").unlink()  # as an older version left it
    preprocess.preprocess_images(photos(tmp_path / "three", 3), out, overwrite=True)
    assert {p.name for p in (out / "images").iterdir()} == {"p0.png", "p1.png", "p2.png"}


def test_preprocess_refuses_a_source_inside_its_output(tmp_path):
    """overwrite=True on a folder holding the source would clear the source; the output inside
    the source would add files to it. Both are refused before anything is written."""
    out = tmp_path / "out"
    preprocess.preprocess_images(photos(tmp_path / "src", 2), out)
    before = hashes(tmp_path)
    with pytest.raises(DataError, match=r"out/images: the source lies inside preprocess.out"):
        preprocess.preprocess_images(out / "images", out, overwrite=True)
    with pytest.raises(DataError, match=r"preprocess.out is the dataset folder .*src or inside it"):
        preprocess.preprocess_images(tmp_path / "src", tmp_path / "src" / "pre")
    assert hashes(tmp_path) == before


def test_an_output_under_a_file_is_named_as_such(tmp_path):
    """`folders.check_folder` on a folder to be made below a file: the file is named, not a
    permission (a file is not "writable" as a folder is, even to root)."""
    from jaxnerf_grid.util import folders

    (tmp_path / "afile").write_text("x")
    with pytest.raises(DataError, match=r"afile/run: run.out cannot be made there: .*afile is a file"):
        folders.check_folder(tmp_path / "afile" / "run", "run.out")
    with pytest.raises(DataError, match=r"afile: run.out exists and is not a folder"):
        folders.check_folder(tmp_path / "afile", "run.out")
    folders.check_folder(tmp_path / "new" / "run", "run.out")  # to be made below a folder: fine
