"""A synthetic dataset's photos as a drone would write them: JPEGs with EXIF GPS from the true
camera centres plus a consumer receiver's error, and the truth to score against
(`jaxnerf-grid synth --gps-origin LAT,LON,ALT`, docs/GEOREFERENCE.md).

The synthetic world is metric, z up, the main tower's base at its origin
(`data.synthetic`); here that origin is placed at the WGS 84 point (LAT, LON, ALT) and the
world's x / y axes are the projected CRS's easting / northing (the GPS's UTM zone unless a CRS
is named), so a camera at world point p is at CRS point origin_crs + p. Each photo's GPS error
is drawn per photo from a seeded generator: horizontal 1-3 m (uniform length, uniform
direction), vertical 2-5 m (uniform length, random sign), as a consumer GNSS receiver gives.

Writes DATA_DIR/photos_gps/<frame>.jpg (every frame of transforms.json, its PNG re-encoded),
DATA_DIR/gps_truth.json and DATA_DIR/gcp.csv (`poses --gcp`): GCP_POINTS, marked ground points
around the tower (the last one a check point), each at its exact CRS position and seen in up to
GCP_PHOTOS photos where the depth map shows it unoccluded, its pixel the true projection plus a
seeded 0.5 px (standard deviation) click error. The generator's own files are not touched.

GCP_LAYOUTS names the sets of control points (`synth --gcp-layout`, `write_gcp` for an existing
folder): "ground" (GCP_POINTS, gcp.csv, the default) and "spread" (SPREAD_POINTS, gcp_spread.csv:
one ground point, a cross-arm tip and an earth-wire peak of the tower, so the control points span
its 30 m height; the check point is the ground layout's, docs/GEOREFERENCE.md) and "dense"
(`dense_points`, gcp_dense.csv: 37 control points over the ground and the whole tower, a
diagnostic of what is left once the alignment is nearly exact).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid.capture import georef
from jaxnerf_grid.capture.photo_exif import GPS_IFD
from jaxnerf_grid.data.normalize import apply_normalization_to_points, invert_normalization
from jaxnerf_grid.data.synthetic.scene import ARM_LENGTHS, ARM_LEVELS, half_width
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError

PHOTOS = "photos_gps"
TRUTH = "gps_truth.json"
HORIZONTAL_ERROR = (1.0, 3.0)  # metres
VERTICAL_ERROR = (2.0, 5.0)    # metres
JPEG_QUALITY = 95
SECONDS_DENOMINATOR = 10000    # EXIF seconds as n / 10000 (1e-4 arc second: 3 mm)
GCP_FILE = "gcp.csv"
# world metres (ground z = 0): three control points and, last, a check point, 15 m from the tower
GCP_POINTS = ((15.0, 0.0, 0.0), (-7.5, 13.0, 0.0), (-7.5, -13.0, 0.0), (0.0, -15.0, 0.0))
# world metres: control points spread in height (data/synthetic/scene.py's tower): a ground point
# 15 m east; the tip of the middle cross-arm on the west (its +y corner: half_width(21.5) = 1.1
# plus ARM_LENGTHS[1] = 7.5, at ARM_LEVELS[1]); the east earth-wire peak (its member's end, 30.4 m);
# last, the ground layout's check point. Each is seen unoccluded in 18-20 of the 31 photos of the
# seed-0 tower-small 320x240 scene (docs/GEOREFERENCE.md).
SPREAD_POINTS = ((15.0, 0.0, 0.0), (-8.6, 0.35, 21.5), (2.6, 0.0, 30.4), (0.0, -15.0, 0.0))


def dense_points() -> tuple:
    """A diagnostic layout, not a survey plan: the ground layout's 3 control points, the four
    footings' top outer corners, the four leg axes at 12, 17.5, 21.5 and 25.5 m, the twelve
    cross-arm tip corners and both earth-wire peaks (data/synthetic/scene.py's tower), then the
    ground layout's check point: 38 points whose fit leaves little of the alignment's error, so
    what a trained model's measurement still misses is the export's own. Returns [38] of (x, y, z)."""
    corners = ((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0))
    points = list(GCP_POINTS[:3]) + [(sx * 4.7, sy * 4.7, 0.45) for sx, sy in corners]
    for z in (12.0, *ARM_LEVELS):
        w = float(half_width(z))
        points += [(sx * w, sy * w, z) for sx, sy in corners]
    for z, length in zip(ARM_LEVELS, ARM_LENGTHS):
        points += [(s * (float(half_width(z)) + length), y, z) for s in (-1.0, 1.0) for y in (-0.35, 0.35)]
    return tuple(points + [(2.6, 0.0, 30.4), (-2.6, 0.0, 30.4), GCP_POINTS[-1]])


GCP_LAYOUTS = {"ground": GCP_POINTS, "spread": SPREAD_POINTS, "dense": dense_points()}
GCP_PHOTOS = 6                 # photos per point (evenly spread over those that see it)
CLICK_ERROR_PX = 0.5
EDGE_PX = 3.0                  # a point closer than this to a photo's border is not clicked there
VISIBLE_DEPTH = 0.02           # normalised units (0.4 m): the depth map's depth within this of the point's


def project(c2w: np.ndarray, intrinsics: dict, point: np.ndarray) -> tuple[float, float, float]:
    """A world point through a synthetic camera (OpenGL c2w [4, 4], pixel centres at +0.5):
    (u, v, z-depth along -z)."""
    cam = c2w[:3, :3].T @ (np.asarray(point, np.float64) - c2w[:3, 3])
    depth = -cam[2]
    return (intrinsics["fl_x"] * cam[0] / depth + intrinsics["cx"],
            -intrinsics["fl_y"] * cam[1] / depth + intrinsics["cy"], depth)


def layout_points(layout: str) -> tuple:
    """The world points (metres, [P] of (x, y, z), the last a check point) of a GCP layout;
    DataError naming synth.gcp_layout for an unknown name."""
    if layout not in GCP_LAYOUTS:
        raise DataError(f"synth.gcp_layout: unknown layout {layout!r} (known: {', '.join(GCP_LAYOUTS)})")
    return GCP_LAYOUTS[layout]


def gcp_file(layout: str) -> str:
    """The file name a layout's rows go to: gcp.csv (ground), gcp_<layout>.csv otherwise."""
    layout_points(layout)
    return GCP_FILE if layout == "ground" else f"gcp_{layout}.csv"


def visible_pixels(root: Path, meta: dict, points_norm: np.ndarray) -> list[list[tuple[str, float, float]]]:
    """For each point [P, 3] (normalised frame), the photos that see it: [(name.jpg, u, v)] per
    point, in frame order. Seen: in front of the camera, EDGE_PX inside the border, and the depth
    map's depth at its pixel within VISIBLE_DEPTH of its own (not hidden, not missed by a thin bar)."""
    seen: list[list] = [[] for _ in points_norm]
    for frame in meta["frames"]:
        if "depth_file_path" not in frame:
            continue
        depth_map = io.read_exr(root / frame["depth_file_path"])
        for k, point in enumerate(points_norm):
            u, v, depth = project(np.asarray(frame["transform_matrix"], np.float64), meta, point)
            if (depth > 0 and EDGE_PX <= u < meta["w"] - EDGE_PX and EDGE_PX <= v < meta["h"] - EDGE_PX
                    and abs(float(depth_map[int(v), int(u)]) - depth) <= VISIBLE_DEPTH):
                seen[k].append((Path(frame["file_path"]).stem + ".jpg", u, v))
    return seen


def gcp_rows(root: Path, meta: dict, base_crs: np.ndarray, seed: int,
             layout: str = "ground") -> tuple[list[str], list[dict]]:
    """gcp.csv's lines and the truth of each point (module docstring) for a layout of
    GCP_LAYOUTS. Points are placed in the normalised frame of transforms.json (its cameras),
    visibility read from each frame's depth map (`visible_pixels`)."""
    points = layout_points(layout)
    norm = meta["scene_normalization"]
    scale, shift = float(norm["scale"]), np.asarray(norm["translation"], np.float64)
    rng = np.random.default_rng([seed, 4141])
    seen = visible_pixels(root, meta, scale * (np.asarray(points, np.float64) + shift))
    lines, truth = ["image,x,y,X,Y,Z,check"], []
    for k, world in enumerate(points):
        count = min(GCP_PHOTOS, len(seen[k]))
        pick = [seen[k][i] for i in np.unique(np.linspace(0, len(seen[k]) - 1, count).round().astype(int))]
        crs = base_crs + np.asarray(world)
        check = k == len(points) - 1
        for name, u, v in pick:
            du, dv = rng.normal(0.0, CLICK_ERROR_PX, 2)
            lines.append(f"{name},{u + du:.2f},{v + dv:.2f},{crs[0]:.3f},{crs[1]:.3f},{crs[2]:.3f},"
                         f"{'check' if check else ''}")
        truth.append({"world": list(world), "crs": crs.round(4).tolist(), "check": check, "photos": len(pick)})
    return lines, truth


def parse_origin(text: str) -> tuple[float, float, float]:
    """'LAT,LON,ALT' (degrees, degrees, metres) -> a tuple; DataError naming synth.gps_origin."""
    try:
        lat, lon, alt = (float(v) for v in str(text).split(","))
    except ValueError:
        raise DataError(f"synth.gps_origin: expected LAT,LON,ALT (degrees, degrees, metres), got {text!r}") from None
    if not (-80.0 <= lat <= 84.0 and -180.0 <= lon <= 180.0 and np.isfinite(alt)):
        raise DataError(f"synth.gps_origin: latitude must lie in [-80, 84] (UTM) and longitude in [-180, 180], "
                        f"got {text!r}")
    return lat, lon, alt


def gps_errors(count: int, seed: int) -> np.ndarray:
    """Per-photo GPS errors [count, 3] (east, north, up; metres): module docstring's model."""
    rng = np.random.default_rng([seed, 41])
    length = rng.uniform(*HORIZONTAL_ERROR, count)
    angle = rng.uniform(0.0, 2.0 * np.pi, count)
    vertical = rng.uniform(*VERTICAL_ERROR, count) * rng.choice([-1.0, 1.0], count)
    return np.stack([length * np.cos(angle), length * np.sin(angle), vertical], -1)


def degrees_to_dms(value: float) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]]:
    """|value| degrees -> EXIF's three rationals ((d, 1), (m, 1), (s * 10000, 10000))."""
    value = abs(float(value))
    d = int(value)
    m = int((value - d) * 60.0)
    s = (value - d - m / 60.0) * 3600.0
    return (d, 1), (m, 1), (int(round(s * SECONDS_DENOMINATOR)), SECONDS_DENOMINATOR)


def gps_exif(latitude: float, longitude: float, altitude: float):
    """A Pillow Exif holding the GPS IFD of one position (refs N/S, E/W; altitude ref 1 below 0)."""
    from PIL import Image
    from PIL.TiffImagePlugin import IFDRational

    def rationals(value):
        return tuple(IFDRational(n, d) for n, d in degrees_to_dms(value))

    exif = Image.Exif()
    exif[GPS_IFD] = {0: b"\x02\x03\x00\x00", 1: "N" if latitude >= 0 else "S", 2: rationals(latitude),
                     3: "E" if longitude >= 0 else "W", 4: rationals(longitude),
                     5: b"\x01" if altitude < 0 else b"\x00", 6: IFDRational(int(round(abs(altitude) * 1000)), 1000)}
    return exif


def truth_key(layout: str) -> str:
    """gps_truth.json's key for a layout's points: "gcp" (ground), "gcp_<layout>" otherwise."""
    return "gcp" if layout == "ground" else f"gcp_{layout}"


def synthetic_meta(root: Path) -> dict:
    """transforms.json of a synthetic dataset folder; DataError naming it when it lacks
    scene_normalization or frames."""
    meta = io.read_json(root / "transforms.json")
    if "scene_normalization" not in meta or "frames" not in meta:
        raise DataError(f"{root / 'transforms.json'}: not a synthetic dataset (no scene_normalization or frames)")
    return meta


def write_layout(root: Path, meta: dict, truth: dict, origin_crs: np.ndarray, seed: int, layout: str) -> Path:
    """A layout's GCP file (`gcp_file`, rows of `gcp_rows`) written into root, its points' truth
    added to `truth` under `truth_key` and gps_truth.json written. Returns the GCP file's path."""
    lines, truth[truth_key(layout)] = gcp_rows(root, meta, origin_crs, seed, layout)
    io.atomic_write_bytes(root / gcp_file(layout), ("\n".join(lines) + "\n").encode("utf-8"))
    io.write_json(root / TRUTH, truth)
    return root / gcp_file(layout)


def write_gcp(dataset_dir, layout: str = "ground") -> Path:
    """A layout's GCP file (`gcp_file`) written into a folder `synth --gps-origin` made, from its
    transforms.json, depth maps and gps_truth.json (the CRS, the tower's geodetic position, the seed), without
    regenerating the scene; the points' truth is added to gps_truth.json under `truth_key`.
    Returns the file's path. DataError (one line, nothing written) for an unknown layout or a
    folder without gps_truth.json."""
    root = Path(dataset_dir)
    layout_points(layout)
    if not (root / TRUTH).is_file():
        raise DataError(f"{root / TRUTH}: not found (write the photos first: synth.gps_origin)")
    truth = io.read_json(root / TRUTH)
    meta = synthetic_meta(root)
    lat0, lon0, alt0 = truth["origin_geodetic"]  # the base's CRS position unrounded, as synth had it
    origin_crs = georef.geodetic_to_projected(georef.projected_crs(truth["crs"]), lat0, lon0, alt0)[0]
    return write_layout(root, meta, truth, origin_crs, int(truth["seed"]), layout)


def write_gps_photos(dataset_dir, origin: tuple[float, float, float], *, seed: int = 0, crs: str | None = None,
                     gcp_layout: str = "ground") -> Path:
    """The photos with GPS and the truth (module docstring) for a synthetic dataset.
    origin: (latitude, longitude, altitude) of the world's origin (the tower's base);
    gcp_layout: a name of GCP_LAYOUTS (its file `gcp_file`, its truth under `truth_key`).
    Returns the path of gps_truth.json."""
    from PIL import Image

    layout_points(gcp_layout)
    root = Path(dataset_dir)
    meta = synthetic_meta(root)
    norm = meta["scene_normalization"]
    inverse = invert_normalization({"scale": float(norm["scale"]),
                                    "translation": np.asarray(norm["translation"], np.float64)})
    lat0, lon0, alt0 = origin
    projected = georef.projected_crs(crs, lat0, lon0)
    origin_crs = georef.geodetic_to_projected(projected, lat0, lon0, alt0)[0]
    centres = np.stack([np.asarray(f["transform_matrix"], np.float64)[:3, 3] for f in meta["frames"]])
    true_crs = origin_crs + apply_normalization_to_points(centres, inverse)
    gps_crs = true_crs + gps_errors(len(centres), seed)
    lat, lon = georef.projected_to_geodetic(projected, gps_crs[:, 0], gps_crs[:, 1])
    out = root / PHOTOS
    out.mkdir(exist_ok=True)
    photos = {}
    for k, frame in enumerate(meta["frames"]):
        name = Path(frame["file_path"]).stem + ".jpg"
        pixels = np.asarray(io.read_image(root / frame["file_path"]) * 255.0 + 0.5, np.uint8)
        with io.atomic_path(out / name) as tmp:
            Image.fromarray(pixels[..., :3]).save(tmp, "JPEG", quality=JPEG_QUALITY,
                                                  exif=gps_exif(lat[k], lon[k], gps_crs[k, 2]).tobytes())
        photos[name] = {"true_crs": true_crs[k].round(4).tolist(), "gps_crs": gps_crs[k].round(4).tolist(),
                        "latitude": float(lat[k]), "longitude": float(lon[k]), "altitude": float(gps_crs[k, 2])}
    truth = {"crs": georef.crs_label(projected), "origin_geodetic": [lat0, lon0, alt0],
             "tower_base_crs": origin_crs.round(4).tolist(),
             "world_to_crs": "x_crs = x_world + tower_base_crs (world x, y, z = easting, northing, up; metres)",
             "scene_units_per_metre": float(norm["scale"]), "seed": seed,
             "gps_error": {"horizontal_m": list(HORIZONTAL_ERROR), "vertical_m": list(VERTICAL_ERROR)},
             "photos": photos}
    write_layout(root, meta, truth, origin_crs, seed, gcp_layout)
    return root / TRUTH
