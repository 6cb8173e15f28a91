"""One camera for every photo when the photos say they come from one camera at one zoom."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from jaxnerf_grid.capture import camera_sharing, photo_exif
from jaxnerf_grid.capture.camera_sharing import choose_sharing, exif_camera
from jaxnerf_grid.util.io import DataError

NO_EXIF = (None, None, None, None, None)
DRONE = ("DJI", "FC6310", None, 8.8, 24.0)


def _jpeg(path, make=None, model=None, focal=None, focal35=None, lens=None, size=(40, 30)):
    """A JPEG whose EXIF holds exactly the given camera fields (Pillow writes them)."""
    exif = Image.Exif()
    if make is not None:
        exif[photo_exif.MAKE] = make
    if model is not None:
        exif[photo_exif.MODEL] = model
    sub = {}
    if focal is not None:
        sub[photo_exif.FOCAL_LENGTH] = focal
    if focal35 is not None:
        sub[photo_exif.FOCAL_35MM] = focal35
    if lens is not None:
        sub[photo_exif.LENS_MODEL] = lens
    if sub:
        exif[photo_exif.EXIF_IFD] = sub
    Image.fromarray(np.full((size[1], size[0], 3), 128, np.uint8)).save(path, exif=exif)
    return path


def test_exif_camera_reads_make_model_lens_and_both_focal_lengths(tmp_path):
    path = _jpeg(tmp_path / "a.jpg", make="DJI", model="FC6310", focal=8.8, focal35=24, lens="24mm F2.8")
    assert exif_camera(path) == ("DJI", "FC6310", "24mm F2.8", 8.8, 24.0)


def test_a_photo_without_exif_has_no_camera_fields(tmp_path):
    path = tmp_path / "frame.png"
    Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(path)
    assert exif_camera(path) == NO_EXIF


def test_an_unreadable_photo_is_named_in_one_line(tmp_path):
    path = tmp_path / "broken.jpg"
    path.write_bytes(b"not a jpeg")
    with pytest.raises(DataError, match=r"broken\.jpg: cannot read the photo's EXIF"):
        exif_camera(path)


def test_one_size_and_one_exif_camera_share_one_camera():
    sizes = {f"p{i}.jpg": (4000, 3000) for i in range(3)}
    assert choose_sharing(None, sizes, {n: DRONE for n in sizes}) == (
        True, "one size, 4000x3000, and one camera: DJI FC6310")


def test_a_video_without_exif_shares_one_camera():
    sizes = {f"f{i}.png": (480, 270) for i in range(4)}
    assert choose_sharing(None, sizes, {n: NO_EXIF for n in sizes}) == (
        True, "one size, 480x270, and one camera: no EXIF camera")


def test_two_sizes_or_two_zoom_settings_give_one_camera_per_photo():
    sizes = {"a": (400, 300), "b": (400, 300), "c": (300, 400)}
    assert choose_sharing(None, sizes, {n: DRONE for n in sizes}) == (False, "2 photo sizes")
    sizes = {"a": (400, 300), "b": (400, 300), "c": (400, 300)}
    zoomed = {"a": DRONE, "b": DRONE, "c": DRONE[:3] + (17.6, 48.0)}
    assert choose_sharing(None, sizes, zoomed) == (False, "2 cameras or zoom settings in the EXIF")
    mixed = {"a": DRONE, "b": NO_EXIF, "c": DRONE}
    assert choose_sharing(None, sizes, mixed) == (False, "2 cameras or zoom settings in the EXIF")


def test_the_users_choice_wins_over_the_photos():
    sizes = {"a": (400, 300), "b": (300, 400)}
    assert choose_sharing(True, sizes, {"a": DRONE, "b": NO_EXIF}) == (True, "as asked")
    same = {"a": (400, 300), "b": (400, 300)}
    assert choose_sharing(False, same, {"a": DRONE, "b": DRONE}) == (False, "as asked")


def test_the_cameras_of_each_named_photo_of_the_folder_are_read(tmp_path):
    _jpeg(tmp_path / "a.jpg", make="DJI", model="FC6310", focal=8.8)
    _jpeg(tmp_path / "b.jpg", make="DJI", model="FC6310", focal=4.5)
    _jpeg(tmp_path / "c.jpg", make="Other")
    records = photo_exif.read_all([tmp_path / "a.jpg", tmp_path / "b.jpg"], gps=False)
    assert camera_sharing.cameras_of(records) == {
        "a.jpg": ("DJI", "FC6310", None, 8.8, None), "b.jpg": ("DJI", "FC6310", None, 4.5, None)}


def test_the_cli_asks_for_one_camera_for_each_or_leaves_it_to_the_photos():
    from jaxnerf_grid.cli.poses import build_parser

    base = ["--images", "photos", "--out", "data"]
    assert build_parser().parse_args(base).single_camera is None
    assert build_parser().parse_args([*base, "--single-camera"]).single_camera is True
    assert build_parser().parse_args([*base, "--camera-per-photo"]).single_camera is False
    with pytest.raises(SystemExit):
        build_parser().parse_args([*base, "--single-camera", "--camera-per-photo"])
