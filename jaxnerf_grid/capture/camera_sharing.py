"""Whether the photos share one camera's intrinsics in the structure from motion.

A drone flies one camera at one zoom, and a video's frames come from one camera: one set of
intrinsics (focal length, principal point, distortion) fitted to every photo at once is better
determined than one per photo (on the tests' orbit one camera per photo gave focal lengths of 163
to 186 px for a true 180 px, docs/POSES.md), and a weakly textured orbit registers more photos
with it. Photos of several sizes, several camera bodies or several zoom settings need one camera
each. The photos tell which: `choose_sharing` shares one camera when every photo has the same
working size and the same EXIF camera (`exif_camera`: make, model, lens, focal length; photos
without EXIF, e.g. a video's frames, all count as the same unknown camera), and gives one camera
per photo otherwise, saying why in a line. The user's choice (`poses.single_camera` True or
False) wins over the photos' evidence.
"""

from __future__ import annotations

from jaxnerf_grid.capture.photo_exif import PhotoExif, read_exif


def exif_text(value) -> str | None:
    """An EXIF text field stripped of NULs and blanks; None when absent or empty."""
    return None if value is None else str(value).strip("\x00 ").strip() or None


def exif_number(value) -> float | None:
    """An EXIF number (a rational) rounded to 3 decimals; None when absent or not a number."""
    try:
        return None if value is None else round(float(value), 3)
    except (TypeError, ValueError, ZeroDivisionError):
        return None


def camera_of(record: PhotoExif) -> tuple:
    """The EXIF fields that name a photo's camera and zoom, from its header record (`read_exif`):
    (make, model, lens model, focal length in mm, focal length in 35 mm terms), each None when
    absent (all None without EXIF)."""
    return (exif_text(record.make), exif_text(record.model), exif_text(record.lens),
            exif_number(record.focal_mm), exif_number(record.focal_35mm))


def exif_camera(path) -> tuple:
    """`camera_of` one photo, read from its file. DataError naming the file when it cannot be
    read."""
    return camera_of(read_exif(path, gps=False))


def cameras_of(records: dict) -> dict:
    """{name: `camera_of`} of {name: `read_exif` record}."""
    return {name: camera_of(record) for name, record in records.items()}


def choose_sharing(asked: bool | None, sizes: dict, cameras: dict) -> tuple[bool, str]:
    """(one camera for every photo, why in a few words). asked: the user's poses.single_camera
    (None: from the photos); sizes: {name: (width, height)} of the working photos; cameras: {name:
    `exif_camera` tuple} of the same photos."""
    if asked is not None:
        return bool(asked), "as asked"
    n_sizes = len(set(map(tuple, sizes.values())))
    if n_sizes > 1:
        return False, f"{n_sizes} photo sizes"
    distinct = set(cameras.values())
    if len(distinct) > 1:
        return False, f"{len(distinct)} cameras or zoom settings in the EXIF"
    (camera,) = distinct if distinct else ((None,) * 5,)
    size = next(iter(sizes.values()), (0, 0))
    named = " ".join(str(v) for v in camera[:2] if v) or "no EXIF camera"
    return True, f"one size, {size[0]}x{size[1]}, and one camera: {named}"
