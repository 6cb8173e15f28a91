"""poses.FEATURE_SIDE: SIFT sees the photos scaled to at most that many pixels on the long side,
and COLMAP hands the keypoints back in the photos' own pixels (checked on a real extraction)."""

from __future__ import annotations

import types

import cv2
import numpy as np
import pytest

from jaxnerf_grid.capture import poses
from jaxnerf_grid.cli import poses as poses_cli
from jaxnerf_grid.util.io import DataError

pycolmap = pytest.importorskip("pycolmap")


class _Stop(Exception):
    pass


def _extraction_size(tmp_path, **kwargs) -> int:
    """max_image_size of the options run_colmap hands to pycolmap.extract_features."""
    seen = {}

    def extract(database, photo_dir, **kw):
        seen["options"] = kw["extraction_options"]
        raise _Stop

    fake = types.SimpleNamespace(**{k: getattr(pycolmap, k) for k in dir(pycolmap) if not k.startswith("_")})
    fake.extract_features = extract
    with pytest.raises(_Stop):
        poses.run_colmap(fake, tmp_path, ["a.png"], tmp_path / "work", matcher="exhaustive",
                         camera_model="SIMPLE_RADIAL", single_camera=False, show=False, **kwargs)
    return seen["options"].max_image_size


def test_sift_sees_at_most_the_feature_side_and_zero_leaves_colmaps_own(tmp_path):
    assert poses.FEATURE_SIDE == 1200
    assert _extraction_size(tmp_path) == 1200
    assert _extraction_size(tmp_path, feature_side=800) == 800
    assert _extraction_size(tmp_path, feature_side=0) == -1      # COLMAP's own: 3200 for SIFT
    assert pycolmap.FeatureExtractionOptions().eff_max_image_size() == 3200


def test_the_cli_passes_the_feature_side_and_a_tiny_one_is_refused(tmp_path, monkeypatch):
    args = poses_cli.build_parser().parse_args(["--images", "a", "--out", "b"])
    assert args.feature_side == poses.FEATURE_SIDE
    asked = {}

    def stand_in(images, out, **kwargs):
        asked.update(kwargs)
        raise _Stop

    monkeypatch.setattr(poses, "poses_from_images", stand_in)
    with pytest.raises(_Stop):
        poses_cli.main(["--images", "a", "--out", "b", "--feature-side", "800"])
    assert asked["feature_side"] == 800
    monkeypatch.undo()
    (tmp_path / "photos").mkdir()
    with pytest.raises(DataError, match="poses.feature_side must be 0 .COLMAP's own. or at least 16 pixels, got 8"):
        poses.poses_from_images(tmp_path / "photos", tmp_path / "out", feature_side=8, progress=False)


def test_keypoints_of_a_scaled_extraction_come_back_in_the_photos_pixels(tmp_path):
    """A 640x480 photo of random blobs, extracted at 160 px: fewer keypoints, spread over the whole
    photo's pixels (not the 160x120 it was scaled to), at the blobs' corners found at full size."""
    rng = np.random.default_rng(0)
    photo = np.full((480, 640, 3), 128, np.uint8)
    for _ in range(60):
        x, y, r = rng.integers(20, 620), rng.integers(20, 460), rng.integers(6, 20)
        cv2.circle(photo, (int(x), int(y)), int(r), tuple(int(v) for v in rng.integers(0, 256, 3)), -1)
    (tmp_path / "photos").mkdir()
    cv2.imwrite(str(tmp_path / "photos" / "a.png"), photo)
    counts, extents = [], []
    for side in (0, 160):
        db = tmp_path / f"db{side}.db"
        options = pycolmap.FeatureExtractionOptions()
        options.max_image_size = side if side else -1
        pycolmap.extract_features(db, tmp_path / "photos", extraction_options=options)
        with pycolmap.Database.open(db) as database:
            keypoints = database.read_keypoints(database.read_all_images()[0].image_id)
        counts.append(len(keypoints))
        extents.append(keypoints[:, :2].max(axis=0))
    assert counts[1] < counts[0]
    assert extents[1][0] > 400 and extents[1][1] > 300      # photo pixels, not the 160x120 SIFT saw
