"""What the poses step reads from a photo's header, read once: its size, EXIF orientation, GPS IFD
and the EXIF fields that name its camera (`PhotoExif`).

`read_exif(path)` opens the photo once with Pillow (the header only, no pixels are decoded) and
returns a plain record; `gps.gps_of`, `gps.upright_of` and `camera_sharing.camera_of` read that
record, so a capture of a thousand photos is opened a thousand times, not once per reader.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from PIL import Image, UnidentifiedImageError

from jaxnerf_grid.util.io import DataError

ORIENTATION = 0x0112  # IFD0
MAKE, MODEL = 0x010F, 0x0110  # IFD0
EXIF_IFD = 0x8769  # the pointer to the Exif sub-IFD (EXIF 2.32, section 4.6.3)
GPS_IFD = 0x8825  # the EXIF pointer to the GPS IFD
FOCAL_LENGTH, FOCAL_35MM, LENS_MODEL = 0x920A, 0xA405, 0xA434  # Exif sub-IFD
EXIF_WHAT = "the photo's EXIF"  # what `read_exif` says it could not read, by default


class PhotoExif(NamedTuple):
    """One photo's header as `read_exif` read it. path: the file; size: (width, height) as stored,
    before the orientation; orientation: EXIF 0x0112 (1 when absent); gps: the GPS IFD {tag number:
    value} ({} when absent or not read); make, model, lens, focal_mm, focal_35mm: the raw EXIF
    values (None when absent)."""

    path: Path
    size: tuple[int, int]
    orientation: int
    gps: dict
    make: object = None
    model: object = None
    lens: object = None
    focal_mm: object = None
    focal_35mm: object = None


def read_exif(path, gps: bool = True, what: str = EXIF_WHAT) -> PhotoExif:
    """The header record of one photo (`PhotoExif`), the file opened once. gps False: the GPS IFD
    is not read (left {}). DataError naming the file ("cannot read <what>") when it cannot be
    opened or its EXIF read."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            width, height = im.size
            exif = im.getexif()
            sub = exif.get_ifd(EXIF_IFD)
            gps_ifd = dict(exif.get_ifd(GPS_IFD)) if gps else {}
            return PhotoExif(path, (width, height), exif.get(ORIENTATION, 1), gps_ifd, exif.get(MAKE),
                             exif.get(MODEL), sub.get(LENS_MODEL), sub.get(FOCAL_LENGTH), sub.get(FOCAL_35MM))
    except (OSError, UnidentifiedImageError, SyntaxError) as err:
        raise DataError(f"{path}: cannot read {what}: {err}") from None


def read_all(paths, gps: bool = True) -> dict:
    """{file name: `read_exif` record} of the photos `paths`, each opened once."""
    return {Path(path).name: read_exif(path, gps) for path in paths}


def upright_of(record: PhotoExif) -> tuple[int, int]:
    """(W, H) of a photo as viewers show it: EXIF orientations 5-8 swap the sides."""
    width, height = record.size
    return (height, width) if record.orientation in (5, 6, 7, 8) else (width, height)
