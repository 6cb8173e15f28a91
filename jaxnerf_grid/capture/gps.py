"""A photo's GPS position from its EXIF GPS tags and, where a DJI drone wrote them, its XMP
relative altitude and gimbal / flight angles (docs/GEOREFERENCE.md lists the tags).

The EXIF reader is Pillow's (`Image.getexif().get_ifd(GPSInfo)`): Pillow is kept up to date,
is already installed with matplotlib, reads the tags without decoding the pixels, and reads
JPEG, PNG (eXIf) and TIFF alike. DJI's XMP packet is plain text in the file's first segments;
its `drone-dji:` attributes are read with a regular expression (no XML library is needed
for flat attributes, and none is installed).

`read_gps(path)` (or `gps_of` on a photo's `photo_exif.read_exif` record, the photo opened once for
all its readers) -> a `GpsRecord` dict or None (no GPS in the photo):
  {"latitude": deg (+N), "longitude": deg (+E), "altitude": m or None (EXIF GPSAltitude, negative
   below the reference when GPSAltitudeRef = 1), "relative_altitude": m or None (DJI XMP),
   "gimbal": {"roll", "pitch", "yaw"} deg or None, "flight": {...} or None}
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from jaxnerf_grid.capture.photo_exif import PhotoExif, read_exif, upright_of
from jaxnerf_grid.util.io import DataError

# GPS IFD tag numbers (EXIF 2.32, section 4.6.6)
LATITUDE_REF, LATITUDE, LONGITUDE_REF, LONGITUDE, ALTITUDE_REF, ALTITUDE = 1, 2, 3, 4, 5, 6
XMP_BYTES = 1 << 20  # the XMP packet sits in the first APP segments: only this much of a file is read
DJI_ANGLES = {"gimbal": ("GimbalRollDegree", "GimbalPitchDegree", "GimbalYawDegree"),
              "flight": ("FlightRollDegree", "FlightPitchDegree", "FlightYawDegree")}
_DJI_ATTRIBUTE = re.compile(rb'drone-dji:(\w+)\s*=\s*"([^"]*)"')
_DJI_ELEMENT = re.compile(rb"<drone-dji:(\w+)>([^<]*)</drone-dji:\1>")


def dms_to_degrees(dms, ref: str, path=None) -> float:
    """Degrees, minutes, seconds (three numbers, e.g. EXIF rationals) and a hemisphere
    reference ('N', 'S', 'E', 'W') -> signed decimal degrees (S and W negative).
    DataError naming `path` for a malformed value."""
    try:
        d, m, s = (float(v) for v in dms)
    except (TypeError, ValueError, ZeroDivisionError):
        raise DataError(f"{path}: EXIF GPS coordinate is not three numbers (degrees, minutes, seconds): "
                        f"{dms!r}") from None
    ref = (ref.decode("ascii", "replace") if isinstance(ref, bytes) else str(ref or "")).strip().upper()[:1]
    if ref not in ("N", "S", "E", "W"):
        raise DataError(f"{path}: EXIF GPS reference {ref!r} is not N, S, E or W")
    value = d + m / 60.0 + s / 3600.0
    return -value if ref in ("S", "W") else value


def altitude_metres(value, ref) -> float | None:
    """EXIF GPSAltitude (a rational, metres) with GPSAltitudeRef (0 or missing: above the
    reference, 1: below) -> signed metres; None when absent."""
    if value is None:
        return None
    if isinstance(ref, bytes):
        ref = ref[0] if ref else 0
    below = int(ref or 0) == 1
    return -float(value) if below else float(value)


def parse_gps_ifd(gps: dict, path=None) -> dict | None:
    """A GPS IFD ({tag number: value}) -> (latitude, longitude, altitude) as in `read_gps`, or
    None when it holds no latitude / longitude."""
    if not gps or LATITUDE not in gps or LONGITUDE not in gps:
        return None
    lat = dms_to_degrees(gps[LATITUDE], gps.get(LATITUDE_REF, "N"), path)
    lon = dms_to_degrees(gps[LONGITUDE], gps.get(LONGITUDE_REF, "E"), path)
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise DataError(f"{path}: EXIF GPS position out of range: latitude {lat}, longitude {lon}")
    return {"latitude": lat, "longitude": lon, "altitude": altitude_metres(gps.get(ALTITUDE), gps.get(ALTITUDE_REF))}


def parse_dji_xmp(data: bytes) -> dict:
    """DJI's `drone-dji:` XMP values (attribute or element form) in a file's bytes ->
    {"relative_altitude": m or None, "absolute_altitude": m or None, "gimbal": {roll, pitch, yaw}
    or None, "flight": ... or None}; numbers such as "+31.20" are read as floats."""
    values = {}
    for pattern in (_DJI_ATTRIBUTE, _DJI_ELEMENT):
        for key, text in pattern.findall(data):
            try:
                values[key.decode("ascii")] = float(text.decode("ascii", "replace").strip())
            except ValueError:
                continue
    out: dict[str, Any] = {"relative_altitude": values.get("RelativeAltitude"),
                           "absolute_altitude": values.get("AbsoluteAltitude")}
    for name, keys in DJI_ANGLES.items():
        out[name] = ({axis: values[k] for axis, k in zip(("roll", "pitch", "yaw"), keys)}
                     if all(k in values for k in keys) else None)
    return out


def read_head(path) -> bytes:
    """The first XMP_BYTES of a file (where DJI's XMP packet sits). DataError naming the file when
    it cannot be read."""
    try:
        with open(path, "rb") as f:
            return f.read(XMP_BYTES)
    except OSError as err:
        raise DataError(f"{path}: cannot read the photo's EXIF: {err}") from None


def gps_of(record: PhotoExif) -> dict | None:
    """The GPS record (module docstring) of a photo from its header record (`read_exif`), or None
    when it has no EXIF GPS position; DJI's XMP values are read from the file's head when it has
    one. DataError naming the file when its GPS tags are malformed or its head cannot be read."""
    position = parse_gps_ifd(record.gps, record.path)
    if position is None:
        return None
    dji = parse_dji_xmp(read_head(record.path))
    return {**position, "relative_altitude": dji["relative_altitude"], "gimbal": dji["gimbal"],
            "flight": dji["flight"]}


def positions_of(records) -> dict:
    """{file name: GPS record} (`gps_of`) of the photos that have one, from (file name, `read_exif`
    record) pairs (e.g. a dict's items), taken in turn."""
    out = {}
    for name, record in records:
        position = gps_of(record)
        if position is not None:
            out[name] = position
    return out


def read_gps(path) -> dict | None:
    """The GPS record of one photo (module docstring), or None when it has no EXIF GPS position.
    DataError naming the file when it cannot be read or its GPS tags are malformed."""
    return gps_of(read_exif(path))


def read_all(paths) -> dict:
    """{file name: GPS record} of the photos that have one (`read_gps`)."""
    return positions_of((Path(path).name, read_exif(path)) for path in paths)


def upright_size(path) -> tuple[int, int]:
    """(W, H) of a photo as viewers show it (EXIF orientations 5-8 swap the sides), read from
    its header (`photo_exif.upright_of`). DataError naming the file when it cannot be read."""
    return upright_of(read_exif(path, gps=False, what="the photo"))
