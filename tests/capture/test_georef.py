"""Metric scale and georeference (docs/GEOREFERENCE.md): EXIF GPS and DJI XMP read from bytes
written here with piexif (another library than the reader, Pillow), the robust similarity against
a closed form with outliers, the CRS against pyproj's own projections, ground control and check
points against hand-computed residuals, and bad input as one-line errors with nothing written."""

import io
import re

import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.capture import georef, gps
from jaxnerf_grid.util.io import DataError

piexif = pytest.importorskip("piexif")
pyproj = pytest.importorskip("pyproj")


def jpeg_bytes(width=64, height=48) -> bytes:
    """A small grey JPEG, encoded by OpenCV (no EXIF)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.full((height, width, 3), 128, np.uint8))
    assert ok
    return buf.tobytes()


def write_gps_jpeg(path, lat_dms, lat_ref, lon_dms, lon_ref, alt=None, alt_ref=0, xmp: bytes | None = None):
    """A JPEG with a GPS IFD written by piexif (rationals as (num, den) pairs), and optionally an
    XMP APP1 segment spliced in after SOI by hand."""
    gps_ifd = {piexif.GPSIFD.GPSLatitudeRef: lat_ref, piexif.GPSIFD.GPSLatitude: lat_dms,
               piexif.GPSIFD.GPSLongitudeRef: lon_ref, piexif.GPSIFD.GPSLongitude: lon_dms}
    if alt is not None:
        gps_ifd[piexif.GPSIFD.GPSAltitude] = alt
        gps_ifd[piexif.GPSIFD.GPSAltitudeRef] = alt_ref
    out = io.BytesIO()
    piexif.insert(piexif.dump({"GPS": gps_ifd}), jpeg_bytes(), out)
    data = out.getvalue()
    if xmp is not None:
        payload = b"http://ns.adobe.com/xap/1.0/\x00" + xmp
        data = data[:2] + b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload + data[2:]
    path.write_bytes(data)
    return path


def test_gps_from_exif_dms_signs_and_altitude_ref(tmp_path):
    north_east = write_gps_jpeg(tmp_path / "a.jpg", ((47, 1), (22, 1), (365, 10)), "N", ((8, 1), (32, 1), (30, 1)),
                                "E", alt=(4105, 10), alt_ref=0)
    rec = gps.read_gps(north_east)
    assert rec["latitude"] == pytest.approx(47 + 22 / 60 + 36.5 / 3600, abs=1e-12)
    assert rec["longitude"] == pytest.approx(8 + 32 / 60 + 30 / 3600, abs=1e-12)
    assert rec["altitude"] == pytest.approx(410.5)
    assert rec["relative_altitude"] is None and rec["gimbal"] is None
    south_west = write_gps_jpeg(tmp_path / "b.jpg", ((33, 1), (51, 1), (0, 1)), "S", ((151, 1), (12, 1), (36, 1)),
                                "W", alt=(125, 10), alt_ref=1)
    rec = gps.read_gps(south_west)
    assert rec["latitude"] == pytest.approx(-(33 + 51 / 60), abs=1e-12)
    assert rec["longitude"] == pytest.approx(-(151 + 12 / 60 + 36 / 3600), abs=1e-12)
    assert rec["altitude"] == pytest.approx(-12.5)  # ref 1: below sea level


def test_dji_xmp_relative_altitude_and_gimbal(tmp_path):
    xmp = (b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF><rdf:Description drone-dji:AbsoluteAltitude="+452.17" '
           b'drone-dji:RelativeAltitude="+31.20" drone-dji:GimbalRollDegree="+0.00" '
           b'drone-dji:GimbalYawDegree="-12.50" drone-dji:GimbalPitchDegree="-45.10" '
           b'drone-dji:FlightRollDegree="+1.5" drone-dji:FlightYawDegree="-13.0" drone-dji:FlightPitchDegree="+2.25"/>'
           b"</rdf:RDF></x:xmpmeta>")
    path = write_gps_jpeg(tmp_path / "dji.jpg", ((1, 1), (0, 1), (0, 1)), "N", ((2, 1), (0, 1), (0, 1)), "E",
                          alt=(45217, 100), xmp=xmp)
    rec = gps.read_gps(path)
    assert rec["relative_altitude"] == pytest.approx(31.2)
    assert rec["gimbal"] == pytest.approx({"roll": 0.0, "pitch": -45.1, "yaw": -12.5})
    assert rec["flight"] == pytest.approx({"roll": 1.5, "pitch": 2.25, "yaw": -13.0})
    # the element form of the same tags
    element = gps.parse_dji_xmp(b"<drone-dji:RelativeAltitude>-3.5</drone-dji:RelativeAltitude>")
    assert element["relative_altitude"] == -3.5 and element["gimbal"] is None
    # heights: relative altitude lifted by the median offset to GPSAltitude
    heights, source = georef.gps_heights([{"altitude": 100.0, "relative_altitude": 10.0},
                                          {"altitude": 111.0, "relative_altitude": 20.0},
                                          {"altitude": 125.0, "relative_altitude": 30.0}])
    np.testing.assert_allclose(heights, [101.0, 111.0, 121.0])  # median(90, 91, 95) = 91
    assert "RelativeAltitude" in source


def test_photo_without_gps(tmp_path):
    (tmp_path / "plain.jpg").write_bytes(jpeg_bytes())
    assert gps.read_gps(tmp_path / "plain.jpg") is None
    import cv2

    cv2.imwrite(str(tmp_path / "plain.png"), np.zeros((8, 8, 3), np.uint8))
    assert gps.read_gps(tmp_path / "plain.png") is None
    (tmp_path / "bad.jpg").write_bytes(b"not a photo")
    with pytest.raises(DataError, match="bad.jpg"):
        gps.read_gps(tmp_path / "bad.jpg")


def rotation(axis, degrees) -> np.ndarray:
    """Rodrigues' closed form."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    a = np.radians(degrees)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx


def test_similarity_closed_form_with_outliers():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(24, 3)) * [5.0, 5.0, 1.0]
    s, rot, t = 12.5, rotation([0.2, -0.4, 1.0], 73.0), np.array([1000.0, -250.0, 42.0])
    dst = s * src @ rot.T + t
    outliers = np.array([2, 7, 11, 19, 23])
    dst[outliers] += [[60.0, 0, 0], [0, -45.0, 0], [0, 0, 80.0], [30.0, 30.0, 0], [-70.0, 10.0, 5.0]]
    (s1, r1, t1), inliers = georef.ransac_similarity(src, dst, threshold=1.0)
    assert s1 == pytest.approx(s, rel=1e-9)
    np.testing.assert_allclose(r1, rot, atol=1e-9)
    np.testing.assert_allclose(t1, t, atol=1e-6)
    assert np.flatnonzero(~inliers).tolist() == outliers.tolist()
    # the plain least-squares fit is pulled off by the outliers
    s2, _, _ = georef.umeyama(src, dst)
    assert abs(s2 - s) > 0.05
    # weights: a point with weight 0 does not count
    w = np.ones(len(src))
    w[outliers] = 0.0
    s3, r3, _ = georef.umeyama(src, dst, w)
    assert s3 == pytest.approx(s, rel=1e-9) and np.allclose(r3, rot, atol=1e-9)


def test_yaw_only_similarity_closed_form():
    """Points turned 40 degrees about z, scaled by 3 and moved: the yaw-only fit finds them
    exactly; on points also tilted it stays a turn about z."""
    rng = np.random.default_rng(5)
    src = rng.normal(size=(10, 3)) * [10.0, 10.0, 2.0]
    rot = rotation([0.0, 0.0, 1.0], 40.0)
    dst = 3.0 * src @ rot.T + [5.0, 6.0, 7.0]
    (s, r, t), inliers = georef.ransac_similarity(src, dst, 0.5, yaw_only=True)
    assert s == pytest.approx(3.0, rel=1e-12) and inliers.all()
    np.testing.assert_allclose(r, rot, atol=1e-12)
    np.testing.assert_allclose(t, [5.0, 6.0, 7.0], atol=1e-9)
    _, r_tilted, _ = georef.umeyama(src, dst @ rotation([1.0, 0.0, 0.0], 2.0).T, yaw_only=True)
    np.testing.assert_allclose(r_tilted[2], [0.0, 0.0, 1.0], atol=1e-12)


def test_similarity_never_mirrors():
    """The mirror image (x -> -x) of points spread 2, 1, 0.5 m along x, y, z: the best proper
    rotation (Umeyama's sign correction) turns by 180 degrees about y, giving up the smallest
    spread: R = diag(-1, 1, -1), s = (8 + 2 - 0.5) / (8 + 2 + 0.5) (the axes' variances x 6)."""
    src = np.concatenate([np.eye(3), -np.eye(3)]) * [2.0, 1.0, 0.5]
    s, r, t = georef.umeyama(src, src * [-1.0, 1.0, 1.0])
    np.testing.assert_allclose(r, np.diag([-1.0, 1.0, -1.0]), atol=1e-12)
    assert s == pytest.approx(9.5 / 10.5, rel=1e-12)
    np.testing.assert_allclose(t, 0.0, atol=1e-12)


def test_nearest_rotation_beats_every_sampled_rotation_and_never_mirrors():
    """`nearest_rotation` against a brute search: for a matrix with a reflection in it and for
    a noisy rotation, its trace(R^T m) is at least that of 20000 random proper rotations (uniform
    quaternions), and it is a proper rotation (R^T R = I, det +1)."""
    rng = np.random.default_rng(7)
    q = rng.normal(size=(20000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    samples = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)
    for m in (np.diag([3.0, 2.0, -1.0]) @ samples[0], samples[1] * 2.0 + rng.normal(scale=0.3, size=(3, 3))):
        r = georef.nearest_rotation(m)
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
        assert np.trace(r.T @ m) >= np.einsum("nij,ij->n", samples, m).max() - 1e-12


@pytest.mark.parametrize("lat, lon, epsg, zone", [(47.3769, 8.5417, 32632, 32), (-33.8688, 151.2093, 32756, 56)])
def test_crs_round_trip_against_pyproj(lat, lon, epsg, zone):
    crs = georef.projected_crs(None, lat, lon)
    assert georef.crs_label(crs) == f"EPSG:{epsg}"
    east, north, h = georef.geodetic_to_projected(crs, lat, lon, 123.0)[0]
    # pyproj's own UTM projection, built from its parameters rather than the EPSG code
    proj = pyproj.Proj(proj="utm", zone=zone, ellps="WGS84", south=lat < 0)
    ref_e, ref_n = proj(lon, lat)
    assert (east, north) == pytest.approx((ref_e, ref_n), abs=1e-6)
    assert h == 123.0
    back_lat, back_lon = georef.projected_to_geodetic(crs, east, north)
    assert back_lat[0] == pytest.approx(lat, abs=1e-10) and back_lon[0] == pytest.approx(lon, abs=1e-10)
    named = georef.projected_crs("EPSG:2056")  # the Swiss grid, named by the user
    assert georef.crs_label(named) == "EPSG:2056"


class FakeCamera:
    """A pinhole camera: pixel (x, y) -> ((x - cx) / f, (y - cy) / f)."""

    def __init__(self, f, cx, cy):
        self.f, self.cx, self.cy = f, cx, cy

    def cam_from_img(self, xy):
        return np.array([(xy[0] - self.cx) / self.f, (xy[1] - self.cy) / self.f])


class FakeImage:
    def __init__(self, name, centre, look_at):
        self.name, self.camera_id, self.centre = name, 1, np.asarray(centre, np.float64)
        z = np.asarray(look_at, np.float64) - self.centre
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        self.rot = np.stack([x, np.cross(z, x), z])  # world -> camera (OpenCV axes)

    def projection_center(self):
        return self.centre

    def cam_from_world(self):
        rot = self.rot

        class Pose:
            class rotation:
                @staticmethod
                def matrix():
                    return rot
        return Pose()

    def project(self, point, cam):
        p = self.rot @ (np.asarray(point, np.float64) - self.centre)
        return cam.f * p[0] / p[2] + cam.cx, cam.f * p[1] / p[2] + cam.cy


class FakeModel:
    """What `georef.align_model` reads of a pycolmap.Reconstruction."""

    def __init__(self, centres):
        self.cameras = {1: FakeCamera(100.0, 320.0, 240.0)}
        self.images = {i: FakeImage(f"p{i}.jpg", c, [0.0, 0.0, 0.0]) for i, c in enumerate(centres)}

    def reg_image_ids(self):
        return list(self.images)


def ring(count=6, radius=20.0, height=8.0) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, count, endpoint=False)
    return np.stack([radius * np.cos(a), radius * np.sin(a), np.full(count, height)], -1)


def gcp_scene(tmp_path, check_offset=(0.3, -0.4, 0.0)):
    """A model whose frame is the local frame halved (model = local / 2, origin (500000,
    5000000, 0) of EPSG:32632), 3 control points and one check point whose surveyed position
    is off by `check_offset`, each seen in two photos."""
    origin = np.array([500000.0, 5000000.0, 0.0])
    model = FakeModel(ring() / 2.0)
    truth = {"gcp1": [3.0, 1.0, 0.0], "gcp2": [-2.0, 4.0, 0.5], "gcp3": [0.5, -3.5, 1.0], "chk": [1.0, 1.0, 2.0]}
    rows = ["image,x,y,X,Y,Z,check"]
    for k, (name, local) in enumerate(truth.items()):
        world = np.asarray(local) + origin + (check_offset if name == "chk" else 0.0)
        for i in (k, k + 2):
            x, y = model.images[i].project(np.asarray(local) / 2.0, model.cameras[1])
            rows.append(f"p{i}.jpg,{x:.9f},{y:.9f},{world[0]:.6f},{world[1]:.6f},{world[2]:.6f},"
                        f"{'check' if name == 'chk' else ''}")
    path = tmp_path / "gcp.csv"
    path.write_text("\n".join(rows) + "\n")
    sizes = {f"p{i}.jpg": (640, 480) for i in range(6)}
    ratios = {name: (1.0, 1.0) for name in sizes}
    return model, path, sizes, ratios


def test_gcp_and_check_point_residuals_hand_computed(tmp_path):
    model, path, sizes, ratios = gcp_scene(tmp_path)
    sim, record = georef.align_model(model, {}, crs_name="EPSG:32632", gcp_path=path, sizes=sizes, ratios=ratios)
    assert record["source"] == "gcp" and record["crs"] == "EPSG:32632" and record["units"] == "metres"
    assert record["metres_per_model_unit"] == pytest.approx(2.0, rel=1e-6)
    np.testing.assert_allclose(sim[1], np.eye(3), atol=1e-6)
    assert record["gcp"]["control"]["rms_m"] == pytest.approx(0.0, abs=1e-4)
    (row,) = record["gcp"]["check"]["residuals"]
    # predicted - surveyed = -(0.3, -0.4, 0): 0.5 m horizontally, 0.5 m in all
    assert (row["dx"], row["dy"], row["dz"]) == pytest.approx((-0.3, 0.4, 0.0), abs=1e-4)
    assert row["horizontal"] == pytest.approx(0.5, abs=1e-4) and row["error"] == pytest.approx(0.5, abs=1e-4)
    assert record["gcp"]["check"]["rms_m"] == pytest.approx(0.5, abs=1e-4)


def test_gps_alignment_recovers_scale_with_an_outlier(tmp_path):
    """GPS made from the true centres (local = 4 x model, shifted) through pyproj's inverse
    projection, one photo 40 m off: the scale comes back and that photo is the outlier."""
    crs = georef.projected_crs("EPSG:32632")
    local = ring(8, 30.0, 25.0)
    model = FakeModel(local / 4.0 + [1.0, -2.0, 0.5])
    world = local + [466000.0, 5247000.0, 400.0]
    world[5, 0] += 40.0
    lat, lon = georef.projected_to_geodetic(crs, world[:, 0], world[:, 1])
    records = {f"p{i}.jpg": {"latitude": lat[i], "longitude": lon[i], "altitude": world[i, 2],
                             "relative_altitude": None} for i in range(8)}
    sim, record = georef.align_model(model, records, crs_name="EPSG:32632")
    assert record["metres_per_model_unit"] == pytest.approx(4.0, rel=1e-6)
    assert record["gps"]["inliers"] == 7 and record["gps"]["rms_m"] == pytest.approx(0.0, abs=1e-3)
    assert [r["name"] for r in record["gps"]["residuals"] if not r["inlier"]] == ["p5.jpg"]
    np.testing.assert_allclose(georef.apply_similarity(sim, model.images[0].centre) + record["origin"], world[0],
                               atol=1e-4)


def test_gps_of_photos_closer_together_than_its_error_sets_no_scale():
    """A phone's photos on a 2 m ring round a tree trunk, each GPS fix 3 m off (the receivers'
    error) in a direction opposite its camera: a fit would mirror the scene (negative scale). The
    spread of the fixes (RMS about their mean, 2 + 3 = 5 m) is under 9 m: no scale, units unknown
    and why; with a CRS asked for, a one-line error."""
    local = ring(8, 2.0, 1.5)
    model = FakeModel(local)
    flipped = local * [-2.5, -2.5, 1.0] + [466000.0, 5247000.0, 400.0]
    sim, record = georef.align_model(model, gps_records(flipped))
    assert sim is None and record["units"] == "unknown" and "5.0 m" in record["gps_ignored"]
    with pytest.raises(DataError, match="poses.crs = EPSG:32632: the photos' GPS positions spread over 5.0 m"):
        georef.align_model(model, gps_records(flipped), crs_name="EPSG:32632")
    # spread wide enough (a 10 m ring) but heights swinging +-20 m upside down in the fixes: the yaw-only fit's
    # scale sum_i d_i.(R x_i) / sum_i |x_i|^2 = (800 - 1600) / (800 + 1600) < 0, refused too
    hilly = ring(8, 10.0, 0.0)
    hilly[:, 2] = 20.0 * np.sin(2 * np.linspace(0, 2 * np.pi, 8, endpoint=False) + 0.3)
    upside_down = hilly * [1.0, 1.0, -1.0] + [466000.0, 5247000.0, 400.0]
    assert "not positive" in georef.align_model(FakeModel(hilly), gps_records(upside_down))[1]["gps_ignored"]
    assert georef.gps_too_close(ring(8, 10.0), 1.0) is None


def test_scale_bar_points_and_parse_errors():
    model = FakeModel(ring())
    sim, record = georef.align_model(model, {}, scale_bar="0,0,0,3,4,0,10")
    assert record["source"] == "scale_bar" and record["metres_per_model_unit"] == pytest.approx(2.0)
    assert sim[0] == pytest.approx(2.0)
    assert georef.align_model(model, {})[1] == {"units": "unknown", "source": None}
    for bad in ("1,2,3", "0,0,0,1,1,1,-2", "a:1,2;b:3,4;2"):
        with pytest.raises(DataError, match="poses.scale_bar"):
            georef.parse_scale_bar(bad)


def gps_records(positions_crs, crs="EPSG:32632"):
    lat, lon = georef.projected_to_geodetic(georef.projected_crs(crs), positions_crs[:, 0], positions_crs[:, 1])
    return {f"p{i}.jpg": {"latitude": lat[i], "longitude": lon[i], "altitude": positions_crs[i, 2],
                          "relative_altitude": None} for i in range(len(positions_crs))}


def test_bad_gps_and_gcp_input_in_the_library(tmp_path):
    model = FakeModel(ring())
    two = gps_records(ring()[:2] + [466000.0, 5247000.0, 400.0])
    with pytest.raises(DataError, match="only 2 of the 6 registered photos have GPS"):
        georef.align_model(model, two, source="photos")
    one_spot = gps_records(np.zeros((6, 3)) + [466000.0, 5247000.0, 400.0] + np.linspace(0, 0.1, 6)[:, None])
    with pytest.raises(DataError, match=r"all 6 photos lie within 0\.\d+ m of one spot"):
        georef.align_model(model, one_spot, source="photos")
    with pytest.raises(DataError, match="poses.crs: unknown coordinate system 'EPSG:99999'"):
        georef.projected_crs("EPSG:99999")
    with pytest.raises(DataError, match="not a projected coordinate system in metres"):
        georef.projected_crs("EPSG:4326")
    sizes = {"p0.jpg": (640, 480)}
    (tmp_path / "unknown.csv").write_text("image,x,y,X,Y,Z\nnope.jpg,1,2,3,4,5\n")
    with pytest.raises(DataError, match=r"unknown.csv: row 2: image 'nope.jpg' is not one of the photos"):
        georef.read_gcp_csv(tmp_path / "unknown.csv", sizes)
    (tmp_path / "outside.csv").write_text("p0.jpg,700,2,3,4,5\n")
    with pytest.raises(DataError, match=r"outside.csv: row 1: pixel \(700, 2\) lies outside p0.jpg \(640 x 480\)"):
        georef.read_gcp_csv(tmp_path / "outside.csv", sizes)


def write_photos(folder, positions_crs, crs="EPSG:32632"):
    folder.mkdir()
    for name, rec in gps_records(positions_crs, crs).items():
        lat, lon = rec["latitude"], rec["longitude"]

        def dms(v):
            v = abs(v)
            d, m = int(v), int((v - int(v)) * 60)
            return (d, 1), (m, 1), (int(round((v - d - m / 60) * 3600 * 10000)), 10000)
        write_gps_jpeg(folder / name, dms(lat), "N", dms(lon), "E", alt=(int(rec["altitude"] * 100), 100))
    return folder


@pytest.mark.parametrize("case, expected", [
    ("one_spot", r"the GPS positions of all 4 photos lie within 0\.\d+ m of one spot"),
    ("two_gps", "only 2 of the 4 readable photos have GPS.*--ignore-gps leaves the GPS unread"),
    ("ignored", "^(?!.*GPS).*no reconstruction"),  # one_spot's photos with --ignore-gps: COLMAP's turn
    ("bad_crs", "--crs: unknown coordinate system 'EPSG:99999'"),
    ("gcp_unknown", "row 1: image 'nope.jpg' is not one of the photos"),
    ("gcp_outside", r"row 1: pixel \(64, 60\) lies outside p0.jpg \(64 x 48\)"),
])
def test_poses_refuses_bad_georeference_input_writing_nothing(tmp_path, capsys, case, expected):
    base = np.array([466000.0, 5247000.0, 400.0])
    spot = np.zeros((4, 3)) + base
    photos = write_photos(tmp_path / "photos", spot if case in ("one_spot", "ignored") else ring(4) + base)
    if case == "two_gps":
        for name in ("p2.jpg", "p3.jpg"):
            (photos / name).write_bytes(jpeg_bytes())
    argv = ["poses", "--images", str(photos), "--out", str(tmp_path / "out"), "--quiet"]
    if case == "ignored":
        argv += ["--ignore-gps"]
    if case == "bad_crs":
        argv += ["--crs", "EPSG:99999"]
    if case.startswith("gcp"):
        row = "nope.jpg,1,2,3,4,5" if case == "gcp_unknown" else "p0.jpg,64,60,3,4,5"
        (tmp_path / "gcp.csv").write_text(row + "\n")
        argv += ["--gcp", str(tmp_path / "gcp.csv")]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert re.search(expected, err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["photos"] + (["gcp.csv"] if "gcp" in case else []))


def test_synthetic_photos_carry_noisy_gps_of_the_true_centres(tmp_path):
    """`data.gps_scene` on a small dataset in the synthetic layout: the JPEGs' EXIF, read back
    with exifread (not the package's reader), lies 1-3 m horizontally and 2-5 m vertically
    from origin + the metric camera centre (x_metric = x_norm / 0.05 - translation)."""
    import cv2
    import exifread

    from jaxnerf_grid.capture.gps_photos import write_gps_photos
    from jaxnerf_grid.util import io as io_lib

    (tmp_path / "images").mkdir()
    centres_norm = np.array([[1.0, 0.0, 0.5], [0.0, 1.2, 0.6], [-0.9, 0.0, 0.4], [0.0, -1.1, 0.7]])
    frames = []
    for k, c in enumerate(centres_norm):
        cv2.imwrite(str(tmp_path / "images" / f"train_{k:03d}.png"), np.full((12, 16, 3), 40 * k, np.uint8))
        pose = np.eye(4)
        pose[:3, 3] = c
        frames.append({"file_path": f"images/train_{k:03d}.png", "transform_matrix": pose.tolist()})
    io_lib.write_json(tmp_path / "transforms.json", {"scene_normalization": {"scale": 0.05,
                                                                             "translation": [0.0, 0.0, -15.0]},
                                                     "frames": frames})
    truth = io_lib.read_json(write_gps_photos(tmp_path, (47.3769, 8.5417, 410.0), seed=3))
    crs = georef.projected_crs(truth["crs"])
    base = georef.geodetic_to_projected(crs, 47.3769, 8.5417, 410.0)[0]
    assert truth["crs"] == "EPSG:32632" and np.allclose(truth["tower_base_crs"], base, atol=1e-3)

    def degrees(tag, ref):
        d, m, s = (float(v.num) / float(v.den) for v in tag.values)
        return (d + m / 60 + s / 3600) * (-1 if str(ref) in "SW" else 1)

    for k, c in enumerate(centres_norm):
        true = base + c / 0.05 - [0.0, 0.0, -15.0]
        with open(tmp_path / "photos_gps" / f"train_{k:03d}.jpg", "rb") as f:
            tags = exifread.process_file(f, details=False)
        lat = degrees(tags["GPS GPSLatitude"], tags["GPS GPSLatitudeRef"])
        lon = degrees(tags["GPS GPSLongitude"], tags["GPS GPSLongitudeRef"])
        alt = tags["GPS GPSAltitude"].values[0]
        alt = float(alt.num) / float(alt.den) * (-1 if tags["GPS GPSAltitudeRef"].values[0] == 1 else 1)
        seen = georef.geodetic_to_projected(crs, lat, lon, alt)[0]
        np.testing.assert_allclose(truth["photos"][f"train_{k:03d}.jpg"]["true_crs"], true, atol=1e-3)
        horizontal, vertical = np.hypot(*(seen - true)[:2]), abs(seen[2] - true[2])
        assert 1.0 - 0.01 <= horizontal <= 3.0 + 0.01 and 2.0 - 0.01 <= vertical <= 5.0 + 0.01


def test_synthetic_gcp_projection_meets_the_renderers_ray():
    """`gps_scene.project` against `rays.rays_for_pixels` (the rays the synthetic frames are
    rendered with): the ray through the projected pixel passes through the point."""
    from jaxnerf_grid.capture.gps_photos import project
    from jaxnerf_grid.nerf import rays

    c2w = np.eye(4)
    c2w[:3, :3] = rotation([1.0, 0.3, 0.0], 70.0)
    c2w[:3, 3] = [0.5, -2.0, 1.0]
    intr = {"fl_x": 250.0, "fl_y": 260.0, "cx": 160.0, "cy": 120.0}
    point = c2w[:3, :3] @ np.array([0.4, -0.3, -3.0]) + c2w[:3, 3]
    u, v, depth = project(c2w, intr, point)
    assert depth == pytest.approx(3.0)
    origin, direction = (np.asarray(a, np.float64).reshape(-1, 3)[0] for a in rays.rays_for_pixels(
        c2w[:3, :4].astype(np.float32), 250.0, 260.0, 160.0, 120.0, np.float32(u), np.float32(v), 0.1, 10.0)[:2])
    off = np.cross(point - origin, direction / np.linalg.norm(direction))
    assert np.linalg.norm(off) < 1e-4


def test_gcp_seen_in_unregistered_photos_is_placed_from_the_others(tmp_path):
    model, path, sizes, ratios = gcp_scene(tmp_path)
    text = path.read_text().splitlines()
    row = text[1].split(",")
    path.write_text("\n".join(text + [",".join(["p6.jpg", "10", "10"] + row[3:])]) + "\n")
    sizes["p6.jpg"] = (640, 480)  # a photo that did not register: its observation is passed over
    ratios["p6.jpg"] = (1.0, 1.0)
    _, record = georef.align_model(model, {}, crs_name="EPSG:32632", gcp_path=path, sizes=sizes, ratios=ratios)
    assert record["gcp"]["control"]["rms_m"] == pytest.approx(0.0, abs=1e-4)
    del model.images[0]  # gcp1 now has one registered photo left
    with pytest.raises(DataError, match=r"gcp1 is seen in 1 registered photo\(s\) of the 3 it names"):
        georef.align_model(model, {}, crs_name="EPSG:32632", gcp_path=path, sizes=sizes, ratios=ratios)


def test_poses_aligns_photos_with_gps_to_metres(tmp_path):
    """The whole step on test_poses' textured orbit (16 JPEGs) with exact GPS: the orbit's units
    are taken as 10 m, its origin at (466000, 5247000, 400) of EPSG:32632; the cameras of the
    written dataset, through `georeference.scene_to_crs`, lie within 2 % of the orbit radius of
    the truth, and sparse/0 / scene_normalization are in local metres."""
    pytest.importorskip("pycolmap")
    import cv2

    from jaxnerf_grid.capture.poses import poses_from_images
    from jaxnerf_grid.util import io as io_lib
    from tests.capture.test_poses import RADIUS, _orbit, _render, _scene

    photos = tmp_path / "photos"
    photos.mkdir()
    views, scene = _orbit(), _scene()
    base = np.array([466000.0, 5247000.0, 400.0])
    true = 10.0 * views[:, :3, 3] + base
    records = gps_records(true)
    for i, c2w in enumerate(views):
        ok, buf = cv2.imencode(".jpg", np.round(_render(scene, c2w)[..., ::-1] * 255).astype(np.uint8),
                               [cv2.IMWRITE_JPEG_QUALITY, 95])
        rec = records[f"p{i}.jpg"]

        def dms(v):
            v = abs(v)
            d, m = int(v), int((v - int(v)) * 60)
            return (d, 1), (m, 1), (int(round((v - d - m / 60) * 3600 * 100000)), 100000)
        gps_ifd = {1: "N", 2: dms(rec["latitude"]), 3: "E", 4: dms(rec["longitude"]), 5: 0,
                   6: (int(round(rec["altitude"] * 1000)), 1000)}
        out = io.BytesIO()
        piexif.insert(piexif.dump({"GPS": gps_ifd}), buf.tobytes(), out)
        (photos / f"view_{i:02d}.jpg").write_bytes(out.getvalue())
    summary = poses_from_images(photos, tmp_path / "data", single_camera=True, progress=False)
    geo = summary["georeference"]
    assert geo["units"] == "metres" and geo["source"] == "gps" and geo["crs"] == "EPSG:32632"
    top = io_lib.read_json(tmp_path / "data" / "transforms.json")
    to_crs = np.asarray(top["georeference"]["scene_to_crs"])
    found = {f["file_path"]: to_crs[:3, :3] @ np.asarray(f["transform_matrix"])[:3, 3] + to_crs[:3, 3]
             for f in top["frames"]}
    assert len(found) >= 12
    errors = [np.linalg.norm(found[f"images/view_{i:02d}.jpg"] - true[i]) for i in range(16)
              if f"images/view_{i:02d}.jpg" in found]
    assert max(errors) < 0.02 * 10.0 * RADIUS, errors
    assert top["georeference"]["metres_per_scene_unit"] == pytest.approx(1.0 / top["scene_normalization"]["scale"])
    assert "## Scale and georeference" in (tmp_path / "data" / "poses_report.md").read_text()


@pytest.mark.parametrize("value", ["47.3,8.5", "north,8.5,400", "95,8.5,400"])
def test_synth_refuses_a_bad_gps_origin_writing_nothing(tmp_path, capsys, value):
    assert cli.main(["synth", "--out", str(tmp_path / "syn"), "--gps-origin", value, "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.count("--gps-origin") == 1, err
    assert not (tmp_path / "syn").exists()


def test_scale_bar_from_pixels_in_two_photos_each():
    """Each end of the bar clicked in two photos (exact projections): the scale is the given
    metres over the ends' distance in the model, 10 / |(3, 1, 0) - (-2, 4, 0.5)| here."""
    model = FakeModel(ring())
    cam = model.cameras[1]
    ends = [np.array([3.0, 1.0, 0.0]), np.array([-2.0, 4.0, 0.5])]
    clicks = [(f"p{i}.jpg", *model.images[i].project(end, cam)) for end, pair in zip(ends, [(0, 2), (1, 4)])
              for i in pair]
    spec = ";".join(f"{name}:{x:.9f},{y:.9f}" for name, x, y in clicks) + ";10"
    ratios = {f"p{i}.jpg": (1.0, 1.0) for i in range(6)}
    sim, record = georef.align_model(model, {}, scale_bar=spec, ratios=ratios)
    assert record["source"] == "scale_bar" and record["crs"] is None
    assert sim[0] == pytest.approx(10.0 / np.linalg.norm(ends[1] - ends[0]), rel=1e-6)


def test_scale_bar_uncertainty_against_a_monte_carlo_of_the_clicks():
    """Each of the bar's 4 clicks moved by N(0, 1 px) in x and y (800 draws): the spread of the
    triangulated length over its value matches `scale_bar_relative_sigma` within 15 %, and the
    record carries it."""
    model = FakeModel(ring())
    cam = model.cameras[1]
    ends = [np.array([3.0, 1.0, 0.0]), np.array([-2.0, 4.0, 0.5])]
    clicks = [(f"p{i}.jpg", *model.images[i].project(end, cam)) for end, pair in zip(ends, [(0, 2), (1, 4)])
              for i in pair]
    ratios = {f"p{i}.jpg": (1.0, 1.0) for i in range(6)}
    rng = np.random.default_rng(7)
    lengths = []
    for _ in range(800):
        noisy = [(name, x + rng.normal(), y + rng.normal()) for name, x, y in clicks]
        lengths.append(georef.scale_bar_length(model, noisy, ratios))
    true_length = np.linalg.norm(ends[1] - ends[0])
    got = georef.scale_bar_relative_sigma(model, clicks, ratios)
    assert got == pytest.approx(np.std(lengths) / true_length, rel=0.15)
    spec = ";".join(f"{name}:{x:.9f},{y:.9f}" for name, x, y in clicks) + ";10"
    _, record = georef.align_model(model, {}, scale_bar=spec, ratios=ratios)
    assert record["scale_bar"]["relative_sigma"] == pytest.approx(got)
    _, by_points = georef.align_model(model, {}, scale_bar="0,0,0,3,4,0,10")
    assert "relative_sigma" not in by_points["scale_bar"]


def test_report_flags_residuals_beyond_the_sources_accuracy():
    from jaxnerf_grid.capture.poses import georef_report_lines

    base = {"units": "metres", "source": "gps", "crs": "EPSG:32632", "crs_name": "x", "origin": [0.0, 0.0, 0.0],
            "metres_per_scene_unit": 20.0, "height_from": "EXIF GPSAltitude"}
    gps_ok = {"photos": 9, "registered": 9, "inliers": 9, "rms_m": 5.9, "rms_horizontal_m": 2.0, "residuals": []}
    assert not any("check the reconstruction" in line for line in georef_report_lines({**base, "gps": gps_ok}))
    bent = {**base, "gps": {**gps_ok, "rms_m": 6.1}}
    assert any("check the reconstruction" in line for line in georef_report_lines(bent))
    control = {**base, "gps": gps_ok, "gcp": {"control": {"rms_m": 0.6, "residuals": []}}}
    assert any("check the reconstruction" in line for line in georef_report_lines(control))
    assert georef_report_lines({"units": "unknown"})[2].startswith("Units unknown")


def test_upright_size_follows_exif_orientation(tmp_path):
    """GCP pixels are in the upright photo: orientation 6 (turned 90 degrees) swaps the sides."""
    for orientation, expected in ((1, (64, 48)), (6, (48, 64))):
        out = io.BytesIO()
        piexif.insert(piexif.dump({"0th": {piexif.ImageIFD.Orientation: orientation}}), jpeg_bytes(), out)
        (tmp_path / f"o{orientation}.jpg").write_bytes(out.getvalue())
        assert gps.upright_size(tmp_path / f"o{orientation}.jpg") == expected
