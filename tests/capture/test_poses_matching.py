"""capture/poses.py's matching options for small photos (MATCHING_SMALL, TWO_VIEW_SMALL) on real
COLMAP runs of tiny inputs (a second or two).

The references are written here: a lattice of look-alike crosses and its view through a known
homography (the ratio test cannot tell one cross from its neighbour; the homography can), and
two known cameras seeing known points (every true correspondence is an inlier).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jaxnerf_grid.capture import poses

pycolmap = pytest.importorskip("pycolmap")

# the second photo's view of the first: a mild perspective turn and shift
LATTICE_HOMOGRAPHY = np.array([[0.9, 0.08, 20.0], [-0.05, 0.95, 10.0], [4e-4, 2e-4, 1.0]])


def _lattice_photos(folder, size=(320, 240), blobs=10):
    """Writes a.png (dark crosses every 24 px, like a lattice tower's bracing, and a few coloured
    blobs) and b.png (a.png through LATTICE_HOMOGRAPHY) into folder."""
    width, height = size
    photo = np.full((height, width, 3), 200, np.uint8)
    for x in range(20, width - 10, 24):
        for y in range(20, height - 10, 24):
            cv2.line(photo, (x - 6, y - 6), (x + 6, y + 6), (40, 40, 40), 2)
            cv2.line(photo, (x - 6, y + 6), (x + 6, y - 6), (40, 40, 40), 2)
    rng = np.random.default_rng(0)
    for _ in range(blobs):
        x, y, r = rng.integers(10, width - 10), rng.integers(10, height - 10), rng.integers(3, 8)
        cv2.circle(photo, (int(x), int(y)), int(r), tuple(int(v) for v in rng.integers(0, 256, 3)), -1)
    folder.mkdir(parents=True)
    cv2.imwrite(str(folder / "a.png"), photo)
    cv2.imwrite(str(folder / "b.png"), cv2.warpPerspective(photo, LATTICE_HOMOGRAPHY, (width, height),
                                                           borderValue=(200, 200, 200)))


def _verified_inliers(tmp_path, matching) -> int:
    """The verified inlier matches of the lattice pair with the package's SIFT and `matching`."""
    _lattice_photos(tmp_path / "photos")
    database = tmp_path / "database.db"
    extraction = pycolmap.FeatureExtractionOptions()
    for key, value in {**poses.SIFT, **poses.SIFT_SMALL}.items():
        setattr(extraction.sift, key, value)
    pycolmap.extract_features(database, tmp_path / "photos", camera_mode=pycolmap.CameraMode.SINGLE,
                              extraction_options=extraction)
    pycolmap.match_exhaustive(database, matching_options=matching)
    db = pycolmap.Database.open(database)
    try:
        _, inliers = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    return int(sum(inliers))


def test_guided_matching_recovers_the_lattice_matches_the_ratio_test_drops(tmp_path):
    """On small photos the package's matching finds over three times the verified matches of the same options
    without guided matching (159 against 1717 when measured): matches the ratio test drops
    between look-alike crosses come back once the pair's geometry is known."""
    plain = poses.matching_options(pycolmap, small_photos=True)
    plain.guided_matching = False
    without = _verified_inliers(tmp_path / "plain", plain)
    with_package = _verified_inliers(tmp_path / "package", poses.matching_options(pycolmap, small_photos=True))
    assert without > 50
    assert with_package > 3 * without


def _two_cameras_and_matches(true_matches: int, wrong_matches: int):
    """Two cameras (focal 300 px, 320x240) 1 m apart looking at points 4-6 m away: (camera,
    points1 [m, 2], points2 [m, 2]) where the first `true_matches` rows are true projections and
    the rest random pixel pairs."""
    rng = np.random.default_rng(3)
    camera = pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", 300.0, 320, 240)
    xyz = np.column_stack([rng.uniform(-1.5, 1.5, true_matches), rng.uniform(-1.0, 1.0, true_matches),
                           rng.uniform(4.0, 6.0, true_matches)])
    turn = np.array([[np.cos(0.15), 0.0, np.sin(0.15)], [0.0, 1.0, 0.0], [-np.sin(0.15), 0.0, np.cos(0.15)]])
    second = xyz @ turn.T + np.array([-1.0, 0.0, 0.2])

    def project(p):
        return 300.0 * p[:, :2] / p[:, 2:] + np.array([160.0, 120.0])

    wrong = rng.uniform([0, 0], [320, 240], (2, wrong_matches, 2))
    return camera, np.vstack([project(xyz), wrong[0]]), np.vstack([project(second), wrong[1]])


def test_a_pair_of_small_photos_with_twelve_true_matches_is_verified():
    """Twelve true correspondences among four wrong ones: the package's verification of small
    photos keeps the pair, the twelve among its inliers; COLMAP's own (15 inliers at least)
    drops it."""
    camera, points1, points2 = _two_cameras_and_matches(12, 4)
    matches = np.column_stack([np.arange(16), np.arange(16)]).astype(np.uint32)
    ours = pycolmap.estimate_two_view_geometry(camera, points1, camera, points2, matches,
                                               poses.two_view_options(pycolmap, small_photos=True))
    colmaps = pycolmap.estimate_two_view_geometry(camera, points1, camera, points2, matches,
                                                  pycolmap.TwoViewGeometryOptions())
    assert ours.config in (pycolmap.TwoViewGeometryConfiguration.CALIBRATED,
                           pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED)
    inliers = set(ours.inlier_matches[:, 0].tolist())
    assert set(range(12)) <= inliers and len(inliers) <= 14  # a wrong pair may lie within 4 px of its epipolar line
    assert len(colmaps.inlier_matches) == 0


def test_larger_photos_are_matched_with_colmaps_own_verification_and_no_guided_matching():
    """Photos over SMALL_SIDE px: no guided matching (slow among thousands of features a photo on
    the CPU) and COLMAP's own 15 inliers; small photos get both."""
    assert poses.matching_options(pycolmap).guided_matching is False
    assert poses.two_view_options(pycolmap).min_num_inliers == pycolmap.TwoViewGeometryOptions().min_num_inliers == 15
    assert poses.matching_options(pycolmap, small_photos=True).guided_matching is True
    assert poses.two_view_options(pycolmap, small_photos=True).min_num_inliers == 10
    assert poses.matching_options(pycolmap, small_photos=True).sift.max_ratio == 0.9
