"""capture/photo_exif.py: a photo's header read once (`read_exif`) and what the poses step takes
from it (`poses.photo_headers`): the same cameras, GPS records and upright sizes as the readers
that open the photo each on their own (`camera_sharing.exif_camera`, `gps.read_gps`,
`gps.upright_size`), from one Image.open per photo."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from jaxnerf_grid.capture import camera_sharing, gps, photo_exif, poses
from jaxnerf_grid.capture.gps_photos import gps_exif
from jaxnerf_grid.util.io import DataError


def _jpeg(path, size=(40, 30), orientation=None, position=None, make=None, focal=None):
    """A JPEG Pillow writes with the given EXIF: orientation, GPS position (lat, lon, alt), camera
    make and focal length (mm)."""
    exif = gps_exif(*position) if position is not None else Image.Exif()
    if orientation is not None:
        exif[photo_exif.ORIENTATION] = orientation
    if make is not None:
        exif[photo_exif.MAKE] = make
    if focal is not None:
        exif[photo_exif.EXIF_IFD] = {photo_exif.FOCAL_LENGTH: focal}
    Image.fromarray(np.full((size[1], size[0], 3), 90, np.uint8)).save(path, exif=exif)
    return path.name


def _folder(tmp_path) -> list[str]:
    """Four JPEGs: two from a drone with GPS (one turned, orientation 6), one without GPS, one
    without EXIF."""
    return [_jpeg(tmp_path / "a.jpg", position=(47.1, 8.2, 410.5), make="DJI", focal=8.8),
            _jpeg(tmp_path / "b.jpg", orientation=6, position=(-33.9, 151.2, 12.0), make="DJI", focal=8.8),
            _jpeg(tmp_path / "c.jpg", make="Other", focal=4.5),
            _jpeg(tmp_path / "d.jpg")]


def _count_opens(monkeypatch) -> Counter:
    """Counts PIL's Image.open calls by file name from here on."""
    opened: Counter = Counter()
    real_open = Image.open

    def counting_open(fp, *args, **kwargs):
        opened[Path(getattr(fp, "name", fp)).name] += 1
        return real_open(fp, *args, **kwargs)

    monkeypatch.setattr(Image, "open", counting_open)
    return opened


def test_photo_headers_open_each_photo_once_and_agree_with_each_reader(tmp_path, monkeypatch):
    names = _folder(tmp_path)
    expected = ({n: camera_sharing.exif_camera(tmp_path / n) for n in names},
                {n: r for n in names if (r := gps.read_gps(tmp_path / n)) is not None},
                {n: gps.upright_size(tmp_path / n) for n in names})
    opened = _count_opens(monkeypatch)
    got = poses.photo_headers(tmp_path, names)
    assert opened == {n: 1 for n in names}
    assert got == expected
    cameras, positions, sizes = got
    assert cameras["a.jpg"] == ("DJI", None, None, 8.8, None) and cameras["d.jpg"] == (None,) * 5
    assert sorted(positions) == ["a.jpg", "b.jpg"] and positions["b.jpg"]["latitude"] < 0
    assert sizes == {"a.jpg": (40, 30), "b.jpg": (30, 40), "c.jpg": (40, 30), "d.jpg": (40, 30)}


def test_photo_headers_without_gps_read_no_gps_and_still_open_each_photo_once(tmp_path, monkeypatch):
    names = _folder(tmp_path)
    opened = _count_opens(monkeypatch)
    cameras, positions, sizes = poses.photo_headers(tmp_path, names, ignore_gps=True)
    assert opened == {n: 1 for n in names}
    assert positions == {} and len(cameras) == len(sizes) == 4
    assert photo_exif.read_exif(tmp_path / "a.jpg", gps=False).gps == {}


def test_an_unreadable_photo_is_named_in_one_line(tmp_path):
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(DataError, match=r"broken\.jpg: cannot read the photo's EXIF") as err:
        poses.photo_headers(tmp_path, ["broken.jpg"])
    assert "\n" not in str(err.value)
    with pytest.raises(DataError, match=r"broken\.jpg: cannot read the photo: "):
        gps.upright_size(tmp_path / "broken.jpg")
