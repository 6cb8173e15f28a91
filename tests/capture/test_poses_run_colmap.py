"""`capture.poses.run_colmap` and `_map`, the COLMAP options and the mapping choice, with
a stand-in for pycolmap's four running calls (no COLMAP run).

The stand-in has the signatures and defaults of pycolmap 4's `extract_features`,
`match_exhaustive`, `match_sequential`, `match_vocabtree` and `incremental_mapping` (an argument
left out is seen as pycolmap's default) and records the values it is handed; the option objects
are pycolmap's own. Its mapping runs hand back COLMAP models written by hand
(`test_poses_frames._write_model`) and read by pycolmap. Each expectation is written out here:
the options docs/POSES.md names (affine SIFT, Lowe's ratio 0.9, seed 0, the relaxed
thresholds), the relaxed run below 90 % of the photos, the model with the most photos, then
points, the seconds of each stage from a clock that gives known times.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxnerf_grid.capture import poses
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError
from tests.capture.test_poses_cameras_and_frame import FOCAL, _rings, _write_model

pycolmap = pytest.importorskip("pycolmap")


class _StructureLess:
    """Stand-in for `structure_less.register` (COLMAP's mapper on a real database:
    tests/capture/test_structure_less.py): records (the model it is handed, its options'
    abs_pose_min_num_inliers) and hands back the next of `results` ((model, names); none left:
    nothing placed)."""

    def __init__(self):
        self.calls: list = []
        self.results: list = []

    def __call__(self, module, database, model, options):
        self.calls.append((model, options.mapper.abs_pose_min_num_inliers))
        return self.results.pop(0) if self.results else (None, [])


@pytest.fixture(autouse=True)
def structure_less(monkeypatch):
    stand_in = _StructureLess()
    monkeypatch.setattr(poses.structure_less, "register", stand_in)
    return stand_in


class _StandIn:
    """pycolmap with its running calls replaced: records what they are handed; each mapping run
    hands back the next of `maps` ({id: model})."""

    def __init__(self, maps):
        self.maps, self.calls = list(maps), []
        for name in ("ImageReaderOptions", "CameraMode", "FeatureExtractionOptions", "FeatureMatchingOptions",
                     "TwoViewGeometryOptions",
                     "SequentialPairingOptions", "SpatialPairingOptions", "VocabTreePairingOptions",
                     "IncrementalPipelineOptions",
                     "Reconstruction", "ImportedPairingOptions"):
            setattr(self, name, getattr(pycolmap, name))

    def set_random_seed(self, seed):
        self.calls.append(("seed", seed))

    def extract_features(self, database_path, image_path, image_names=(), camera_mode=pycolmap.CameraMode.AUTO,
                         reader_options=None, extraction_options=None):
        reader = reader_options or pycolmap.ImageReaderOptions()
        extraction = extraction_options or pycolmap.FeatureExtractionOptions()
        self.calls.append(("features", database_path, image_path, list(image_names), camera_mode,
                           reader.camera_model, extraction.sift.estimate_affine_shape))

    def _matching(self, kind, database_path, matching_options, pairing, verification_options):
        matching = matching_options or pycolmap.FeatureMatchingOptions()
        self.calls.append((kind, database_path, matching.sift.max_ratio, pairing))
        self.guided = matching.guided_matching
        self.min_inliers = (verification_options or pycolmap.TwoViewGeometryOptions()).min_num_inliers

    def match_exhaustive(self, database_path, matching_options=None, verification_options=None):
        self._matching("exhaustive", database_path, matching_options, None, verification_options)

    def match_sequential(self, database_path, matching_options=None, pairing_options=None,
                         verification_options=None):
        pairing = pairing_options or pycolmap.SequentialPairingOptions()
        self._matching("sequential", database_path, matching_options,
                       (pairing.overlap, pairing.quadratic_overlap, pairing.loop_detection), verification_options)

    def match_spatial(self, database_path, matching_options=None, pairing_options=None,
                      verification_options=None):
        pairing = pairing_options or pycolmap.SpatialPairingOptions()
        self._matching("spatial", database_path, matching_options, (pairing.max_num_neighbors, pairing.max_distance),
                       verification_options)

    def match_image_pairs(self, database_path, matching_options=None, pairing_options=None,
                          verification_options=None):
        pairing = pairing_options or pycolmap.ImportedPairingOptions()
        self._matching("pairs", database_path, matching_options, Path(pairing.match_list_path).read_text(),
                       verification_options)

    def match_vocabtree(self, database_path, matching_options=None, pairing_options=None,
                        verification_options=None):
        pairing = pairing_options or pycolmap.VocabTreePairingOptions()
        self._matching("vocab", database_path, matching_options, str(pairing.vocab_tree_path), verification_options)

    def incremental_mapping(self, database_path, image_path, output_path, options=None, input_path="",
                            initial_image_pair_callback=None, next_image_callback=None):
        options = options or pycolmap.IncrementalPipelineOptions()
        if not Path(output_path).parent.is_dir():  # as COLMAP: it makes its output folder, not the parents
            raise RuntimeError(f"filesystem error: cannot create directory: {output_path}")
        self.prior_position = options.use_prior_position
        self.multiple_models = getattr(self, "multiple_models", []) + [options.multiple_models]
        self.calls.append(("mapping", database_path, image_path, output_path, options.random_seed,
                           options.mapper.filter_max_reproj_error, options.mapper.abs_pose_min_num_inliers,
                           options.mapper.init_min_num_inliers, options.mapper.init_min_tri_angle))
        if initial_image_pair_callback is not None:  # a first model of 2 photos
            initial_image_pair_callback()
        return self.maps.pop(0) if self.maps else {}


class _Undistorting(_StandIn):
    """With pycolmap's undistort_images replaced: reads the model it is handed and writes, as
    COLMAP does, output/images (each photo at its camera's size, pixels saying which photo) and
    output/sparse (the model, its cameras PINHOLE)."""

    def undistort_images(self, output_path, input_path, image_path, image_names=(), output_type="COLMAP",
                         jpeg_quality=-1):
        model = pycolmap.Reconstruction(input_path)
        self.calls.append(("undistort", output_path, input_path, image_path, output_type, jpeg_quality,
                           sorted(im.name for im in model.images.values())))
        (output_path / "images").mkdir(parents=True)
        (output_path / "sparse").mkdir()
        for k, im in enumerate(sorted(model.images.values(), key=lambda im: im.name)):
            cam = model.cameras[im.camera_id]
            io.write_png(output_path / "images" / im.name, np.full((cam.height, cam.width, 3), (k + 1) / 10.0))
        model.write(output_path / "sparse")


class _Clock:
    """time.monotonic giving the listed times in turn (no call past the list)."""

    def __init__(self, times):
        self.times = list(times)

    def monotonic(self):
        return self.times.pop(0)


def _model(folder, count, num_points=30, turned=(), moved=()):
    """A pycolmap.Reconstruction of the first `count` of 18 ring cameras (names v00..v17), each
    seeing `num_points` points where it projects them; the cameras in `turned` are written
    turned by 20 degrees about their own y axis, those in `moved` 10 units along x (their
    observations kept: they fail the vetting)."""
    centres, w2cs = _rings()
    points = np.array([1.0, -2.0, 3.0]) + np.random.default_rng(7).uniform(-2, 2, (num_points, 3))
    images = [(f"v{k:02d}.png", 1, r, -r @ c) for k, (c, r) in enumerate(zip(centres, w2cs))][:count]
    turn = Rotation.from_rotvec([0.0, np.radians(20.0), 0.0]).as_matrix()
    written = {k: (turn @ w2cs[k], -turn @ w2cs[k] @ centres[k]) for k in turned}
    written.update({k: (w2cs[k], -w2cs[k] @ (centres[k] + [10.0, 0.0, 0.0])) for k in moved})
    _write_model(folder, {1: (80, 60, FOCAL, FOCAL, 40, 30)}, images, points, written=written)
    return pycolmap.Reconstruction(folder)


NAMES = [f"v{k:02d}.png" for k in range(18)]
# 12 photos, each with its next 4, across the end too, and the quadratic overlap's step 8: every
# pair whose distance round the ring of 12 is 1-4 (8 apart is 4 the other way round)
RING_12_NEXT_4 = "".join(f"{NAMES[i]} {NAMES[j]}\n" for i in range(12) for j in range(i + 1, 12)
                         if min(j - i, 12 - (j - i)) <= 4)
DEFAULT_MAPPER = (0, 2.0, 30, 100, 16.0)                   # seed, filter px, then COLMAP's defaults
RELAXED_MAPPER = (0, 2.0, 15, 50, 8.0)


def test_run_colmap_exhaustive_single_camera_sets_its_options_and_keeps_the_largest_model(
        tmp_path, monkeypatch, capsys):
    """All 12 photos register in the first mapping: no second run; of its three models the one
    with the most photos, then the most points, is kept; the options handed to COLMAP are those
    docs/POSES.md names, and MATCHING's (empty in the package; one set here) reach the matching
    options; the seconds of features, matching and mapping come from the clock; nothing is
    said with show=False."""
    small, fewer_points, largest = (_model(tmp_path / n, c, p) for n, c, p in
                                    (("small", 5, 30), ("fewer", 12, 20), ("largest", 12, 30)))
    stand_in = _StandIn([{0: small, 1: largest, 2: fewer_points}])
    monkeypatch.setattr(poses, "time", _Clock([100.0, 101.26, 101.3, 101.8, 102.0, 109.34]))
    monkeypatch.setattr(poses, "MATCHING", {"guided_matching": True})
    timings = {"photos": 0.4}
    model, relaxed, extended, from_2d = poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work",
                                      matcher="exhaustive", camera_model="OPENCV", single_camera=True, show=False,
                                      timings=timings)
    assert model is largest and relaxed is False and extended is False
    db = tmp_path / "work" / "database.db"
    assert stand_in.calls == [
        ("seed", 0),
        ("features", db, tmp_path / "photos", NAMES[:12], pycolmap.CameraMode.SINGLE, "OPENCV", True),
        ("exhaustive", db, 0.9, None),
        ("mapping", db, tmp_path / "photos", tmp_path / "work" / "sparse0", *DEFAULT_MAPPER)]
    assert stand_in.guided is True
    assert timings == {"photos": 0.4, "features": 1.3, "matching": 0.5, "mapping": 7.3}
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("neighbours", [poses.SPATIAL_NEIGHBOURS, 37])
def test_run_colmap_spatial_pairs_each_photo_with_the_neighbours_asked_at_any_distance(tmp_path, neighbours):
    """Spatial matching hands COLMAP the neighbour count (20 unless asked; 37 here) and a distance
    bound that never binds (1e6 m): the count alone bounds the pairs."""
    stand_in = _StandIn([{0: _model(tmp_path / "m", 12)}])
    kwargs = {} if neighbours == poses.SPATIAL_NEIGHBOURS else {"neighbours": neighbours}
    poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work", matcher="spatial",
                     camera_model="SIMPLE_RADIAL", single_camera=True, show=False, **kwargs)
    assert ("spatial", tmp_path / "work" / "database.db", 0.9, (neighbours, 1e6)) in stand_in.calls
    assert poses.SPATIAL_NEIGHBOURS == 20


@pytest.mark.parametrize("small, guided, min_inliers", [(True, True, 10), (False, False, 15)])
def test_run_colmap_hands_small_photos_guided_matching_and_ten_inliers(tmp_path, small, guided, min_inliers):
    """Small photos (small_photos: every one at most SMALL_SIDE px) are matched with guided
    matching and verified from 10 inliers; larger ones with COLMAP's own (no guided matching,
    15 inliers)."""
    stand_in = _StandIn([{0: _model(tmp_path / "m", 12)}])
    poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work", matcher="exhaustive",
                     camera_model="SIMPLE_RADIAL", single_camera=True, show=False, small_photos=small)
    assert (stand_in.guided, stand_in.min_inliers) == (guided, min_inliers)


@pytest.mark.parametrize("small", [True, False])
def test_run_colmap_maps_with_the_gps_priors_for_small_photos_only(tmp_path, monkeypatch, small):
    """GPS fixes 60 m around the scene: written to the database either way (the spatial matcher
    pairs by them), in the mapping's bundle adjustment only for small photos."""
    written = []
    monkeypatch.setattr(poses, "write_gps_priors", lambda module, database, priors: written.append(len(priors)))
    fixes = {n: [60.0 * np.cos(k), 60.0 * np.sin(k), 0.0] for k, n in enumerate(NAMES[:12])}
    stand_in = _StandIn([{0: _model(tmp_path / "m", 12)}])
    poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work", matcher="spatial",
                     camera_model="SIMPLE_RADIAL", single_camera=True, show=False, priors=fixes, small_photos=small)
    assert written == [12]
    assert stand_in.prior_position is small


def test_run_colmap_sequential_maps_small_photos_again_relaxed_below_90_percent_and_keeps_an_agreeing_model(
        tmp_path, monkeypatch, capsys):
    """Small photos, 9 of 12 register (under 0.9 x 12): a second, relaxed mapping into sparse1; its 12
    photos, agreeing with the first model's 9, are kept. Sequential matching: each photo with
    its next `overlap`, no quadratic overlap, no loop detection; AUTO camera mode without
    --single-camera. Each stage is said on stderr by default, and each mapping run's progress
    line counts the photos COLMAP reported (2 here) of the 12."""
    first, second = _model(tmp_path / "first", 9), _model(tmp_path / "second", 12)
    stand_in = _StandIn([{0: first}, {0: second}])
    monkeypatch.setattr(poses, "time", _Clock([0.0, 1.0, 2.0, 3.0, 4.0, 5.0]))
    model, relaxed, extended, from_2d = poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work",
                                      matcher="sequential", camera_model="PINHOLE", single_camera=False, overlap=4,
                                      keep_all=True, small_photos=True)
    assert model is second and relaxed is True and extended is False
    db, photos = tmp_path / "work" / "database.db", tmp_path / "photos"
    assert stand_in.calls == [
        ("seed", 0),
        ("features", db, photos, NAMES[:12], pycolmap.CameraMode.AUTO, "PINHOLE", True),
        ("pairs", db, 0.9, RING_12_NEXT_4),
        ("mapping", db, photos, tmp_path / "work" / "sparse0", *DEFAULT_MAPPER),
        ("mapping", db, photos, tmp_path / "work" / "sparse1", *RELAXED_MAPPER)]
    err = capsys.readouterr().err
    for line in ("poses: features (SIFT, 12 photos) ...", "poses: matching (sequential) ...",
                 "poses: kept the relaxed model (12 photos)"):
        assert line in err.splitlines(), line
    for stage in ("features (SIFT, 12 photos)", "matching (sequential)"):
        assert any(line.startswith(f"poses: {stage} done in ") for line in err.splitlines()), stage
    for label in ("mapping", r"mapping again \(relaxed thresholds\)"):
        assert len([line for line in err.splitlines()
                    if re.fullmatch(rf"poses: {label}: 2/12 photos \(17%\), \d+\.\d s", line)]) == 1, label


def test_run_colmap_counts_the_relaxed_model_by_the_vetting_unless_keep_all(tmp_path, monkeypatch):
    """Small photos: the relaxed model registers 12 photos to the first model's 9, but its 3 new
    ones are turned 20 degrees (they fail the vetting): by the vetted count (9 against 9) the
    first model stays; with keep_all, by the registered count, the relaxed model is kept. And 9
    of 10 photos (0.9 x 10, not under it) map once."""
    first = _model(tmp_path / "first", 9)
    second = _model(tmp_path / "second", 12, turned=(9, 10, 11))
    for keep_all, expected in ((False, first), (True, second)):
        stand_in = _StandIn([{0: first}, {0: second}])
        model, relaxed, extended, from_2d = poses.run_colmap(
            stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work", matcher="exhaustive",
            camera_model="OPENCV", single_camera=True, show=False, keep_all=keep_all, small_photos=True)
        assert model is expected and relaxed is (expected is second) and extended is False, keep_all
        assert [c[3].name for c in stand_in.calls if c[0] == "mapping"][:2] == ["sparse0", "sparse1"]
    stand_in = _StandIn([{0: first}, {0: second}])                    # keep_all left out: the vetted count
    assert poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work", matcher="exhaustive",
                            camera_model="OPENCV", single_camera=True, show=False,
                            small_photos=True) == (first, False, False, [])
    stand_in = _StandIn([{0: first}])
    assert poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:10], tmp_path / "work", matcher="exhaustive",
                            camera_model="OPENCV", single_camera=True, show=False,
                            small_photos=True) == (first, False, False, [])
    # one mapping, then the one photo it left out tried again continuing its model (no model back here)
    assert [c[3].name for c in stand_in.calls if c[0] == "mapping"] == ["sparse0", "sparse"]


def test_run_colmap_places_the_photos_still_out_from_their_2d_matches_when_that_agrees(tmp_path, structure_less):
    """Larger photos, 9 of 12 registered, continuing the model registers none: the structure-less
    step is handed the first model with LEFT_OUT's 10 inliers; its 12-photo model, agreeing, is
    kept with the names it placed. A grown model whose 3 new photos are turned 20 degrees (they
    fail the vetting: no more photos kept) or that disagrees is not; with every photo
    registered it is not called."""
    first, more = _model(tmp_path / "first", 9), _model(tmp_path / "more", 12)
    turned = _model(tmp_path / "turned", 12, turned=(9, 10, 11))
    placed = ["v09.png", "v10.png", "v11.png"]
    for grown, kept in ((more, more), (turned, first)):
        structure_less.results.append((grown, placed))
        stand_in = _StandIn([{0: first}, {}])
        result = poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work",
                                  matcher="exhaustive", camera_model="OPENCV", single_camera=True, show=False)
        assert result == (kept, False, False, placed if kept is more else [])
        assert structure_less.calls[-1] == (first, 10)
    shifted = _model(tmp_path / "shifted", 12)
    for k in range(9):               # the first 9 photos turned: the models disagree on them
        image = shifted.images[k + 1]
        image.frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d([0.0, 0.3, 0.0]), [0.0, 0.0, 0.0]) \
            * image.frame.rig_from_world
    structure_less.results.append((shifted, placed))
    result = poses.run_colmap(_StandIn([{0: first}, {}]), tmp_path / "photos", NAMES[:12], tmp_path / "work",
                              matcher="exhaustive", camera_model="OPENCV", single_camera=True, show=False,
                              keep_all=True)
    assert result == (first, False, False, [])
    calls = len(structure_less.calls)
    poses.run_colmap(_StandIn([{0: more}]), tmp_path / "photos", NAMES[:12], tmp_path / "work",
                     matcher="exhaustive", camera_model="OPENCV", single_camera=True, show=False)
    assert len(structure_less.calls) == calls


def test_the_photos_still_out_are_placed_from_their_2d_matches_before_the_model_is_continued(tmp_path,
                                                                                           structure_less):
    """Larger photos, 9 of 12 registered: the structure-less step is handed the first model and
    places 2 (11 photos); continuing the model (`register_left_out`) then starts from those 11
    and registers the last (12). When the structure-less step places all 3, the model is not
    continued at all."""
    first, eleven, twelve = _model(tmp_path / "first", 9), _model(tmp_path / "eleven", 11), _model(tmp_path / "all", 12)
    structure_less.results.append((eleven, ["v09.png", "v10.png"]))
    stand_in = _StandIn([{0: first}, {0: twelve}])
    result = poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work", matcher="exhaustive",
                              camera_model="OPENCV", single_camera=True, show=False)
    assert result == (twelve, False, True, ["v09.png", "v10.png"])
    assert structure_less.calls[-1][0] is first
    assert pycolmap.Reconstruction(tmp_path / "work" / "extend" / "start").num_reg_images() == 11
    structure_less.results.append((twelve, ["v09.png", "v10.png", "v11.png"]))
    stand_in = _StandIn([{0: first}, {0: twelve}])
    result = poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work2", matcher="exhaustive",
                              camera_model="OPENCV", single_camera=True, show=False)
    assert result == (twelve, False, False, ["v09.png", "v10.png", "v11.png"])
    assert [c[3].name for c in stand_in.calls if c[0] == "mapping"] == ["sparse0"]


def test_a_grown_model_is_kept_only_while_it_fits_the_gps_as_the_first_did(tmp_path, structure_less, capsys,
                                                                           monkeypatch):
    """GPS fixes at the ring cameras' true centres in metres (x 10: a ring of 90-120 m, plus 0-2 m
    of noise): continuing the 9-photo model gives 12, the 3 new photos in place (RMS about 1 m:
    kept) or moved 100 m (RMS tens of metres, over twice the first model's and over 9 m: the first
    kept, said on stderr). Without GPS the moved model is kept (keep_all: counted by its photos)."""
    centres, _ = _rings()
    noise = np.random.default_rng(1).uniform(-2.0, 2.0, (len(centres), 3))
    fixes = {NAMES[k]: 10.0 * centres[k] + noise[k] for k in range(12)}
    first, more = _model(tmp_path / "first", 9), _model(tmp_path / "more", 12)
    moved = _model(tmp_path / "moved", 12, moved=(9, 10, 11))
    assert poses.gps_fit_rms(more, fixes) < 2.0 * np.sqrt(3) and poses.gps_fit_rms(first, fixes) < 2.0 * np.sqrt(3)
    assert poses.gps_fit_rms(moved, fixes) > 30.0
    for grown, positions, kept in ((more, fixes, more), (moved, fixes, first), (moved, None, moved)):
        model, _, extended, _ = poses.map_photos(
            _StandIn([{0: first}, {0: grown}]), tmp_path / "db", tmp_path / "photos", 12, tmp_path / "work",
            priors=False, keep_all=True, show=True, timings={}, positions=positions)
        assert model is kept and extended is (kept is not first)
    assert "fits the GPS" in capsys.readouterr().err
    assert poses.gps_fit_rms(first, {NAMES[0]: fixes[NAMES[0]], NAMES[1]: fixes[NAMES[1]]}) is None
    monkeypatch.setattr(poses, "write_gps_priors", lambda module, database, priors: len(priors))
    result = poses.run_colmap(_StandIn([{0: first}, {0: moved}]), tmp_path / "photos", NAMES[:12], tmp_path / "w2",
                              matcher="spatial", camera_model="OPENCV", single_camera=True, show=False, keep_all=True,
                              priors=fixes)                  # run_colmap hands its GPS positions on as the judge
    assert result[0] is first


def test_the_relaxed_model_is_kept_only_while_it_fits_the_gps_as_the_first_did(tmp_path, capsys):
    """Small photos, 9 of 12 registered: the relaxed mapping from scratch registers 12, agreeing
    with the first on their 9; its 3 new photos moved 100 m from their fixes (RMS tens of metres):
    with the GPS the first model is kept, said on stderr; without it the relaxed one."""
    centres, _ = _rings()
    fixes = {NAMES[k]: 10.0 * centres[k] for k in range(12)}
    first, moved = _model(tmp_path / "first", 9), _model(tmp_path / "moved", 12, moved=(9, 10, 11))
    for positions, kept in ((fixes, first), (None, moved)):
        model, relaxed, _, _ = poses.map_photos(
            _StandIn([{0: first}, {0: moved}]), tmp_path / "db", tmp_path / "photos", 12, tmp_path / "work",
            priors=False, keep_all=True, show=True, timings={}, small_photos=True, positions=positions)
        assert model is kept and relaxed is (kept is moved)
    assert "poses: the model with 3 more photo(s) fits the GPS" in capsys.readouterr().err


def test_the_first_mapping_and_its_continuation_build_one_model_the_relaxed_mapping_several(tmp_path):
    """Small photos, 9 of 12 registered: the first mapping (sparse0) asks COLMAP for one model,
    the relaxed mapping from scratch (sparse1) for several, the continuation of the kept model
    (extend/sparse) for one."""
    first = _model(tmp_path / "first", 9)
    stand_in = _StandIn([{0: first}, {}, {}])
    poses.map_photos(stand_in, tmp_path / "db", tmp_path / "photos", 12, tmp_path / "work", priors=False,
                     keep_all=True, show=False, timings={}, small_photos=True)
    assert [c[3].relative_to(tmp_path / "work").as_posix() for c in stand_in.calls if c[0] == "mapping"] == [
        "sparse0", "sparse1", "extend/sparse"]
    assert stand_in.multiple_models == [False, True, False]


def test_remap_relaxed_below_90_percent_for_small_photos_and_below_half_for_larger_ones():
    """The relaxed mapping from scratch: always without a first model; for small photos when the
    first registers under 0.9 of them, for larger ones under 0.5 (RELAX_BELOW, RELAX_BELOW_LARGE)."""
    assert poses.remap_relaxed(None, 20, False) and poses.remap_relaxed(None, 20, True)
    assert poses.remap_relaxed(17, 20, True) and not poses.remap_relaxed(18, 20, True)
    assert poses.remap_relaxed(9, 20, False) and not poses.remap_relaxed(10, 20, False)
    assert not poses.remap_relaxed(17, 20, False)


def test_run_colmap_takes_larger_photos_a_first_model_left_out_straight_to_registering_them(tmp_path):
    """Larger photos, 9 of 12 registered (over half): no relaxed mapping from scratch; the photos
    left out are registered continuing the first model (extend/sparse), kept when that model
    registers more and agrees. 5 of 12 (under half): the relaxed mapping into sparse1 first."""
    first, more = _model(tmp_path / "first", 9), _model(tmp_path / "more", 12)
    stand_in = _StandIn([{0: first}, {0: more}])
    model, relaxed, extended, from_2d = poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work",
                                                matcher="exhaustive", camera_model="OPENCV", single_camera=True,
                                                show=False, keep_all=True)
    assert (model, relaxed, extended) == (more, False, True)
    mappings = [c for c in stand_in.calls if c[0] == "mapping"]
    assert [c[3].relative_to(tmp_path / "work").as_posix() for c in mappings] == ["sparse0", "extend/sparse"]
    assert mappings[1][6:] == (10, 50, 8.0)                  # LEFT_OUT's inliers on the relaxed thresholds
    few = _model(tmp_path / "few", 5)
    stand_in = _StandIn([{0: few}, {0: more}])
    model, relaxed, extended, from_2d = poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work2",
                                                matcher="exhaustive", camera_model="OPENCV", single_camera=True,
                                                show=False, keep_all=True)
    assert (model, relaxed) == (more, True)
    assert [c[3].name for c in stand_in.calls if c[0] == "mapping"][:2] == ["sparse0", "sparse1"]


def test_run_colmap_vocab_hands_on_the_tree_and_names_the_folder_when_no_model_is_built(tmp_path):
    tree = tmp_path / "tree.bin"
    stand_in = _StandIn([{}, {}])
    with pytest.raises(DataError) as err:
        poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:6], tmp_path / "work", matcher="vocab",
                         camera_model="SIMPLE_RADIAL", single_camera=True, vocab_tree=tree, show=False,
                         source=tmp_path / "input")
    assert str(err.value) == (f"{tmp_path / 'input'}: no reconstruction: the photos share too few features (more "
                              "overlap, more texture or more photos help; see docs/POSES.md)")
    assert stand_in.calls[2] == ("vocab", tmp_path / "work" / "database.db", 0.9, str(tree))
    assert [c[3].name for c in stand_in.calls if c[0] == "mapping"] == ["sparse0", "sparse1"]
    with pytest.raises(DataError, match="^" + re.escape(f"{tmp_path / 'photos'}: no reconstruction: ")):
        poses.run_colmap(_StandIn([{}, {}]), tmp_path / "photos", NAMES[:6], tmp_path / "work",
                         matcher="exhaustive", camera_model="SIMPLE_RADIAL", single_camera=True, show=False)


def test_run_colmap_lets_a_failing_stage_raise_and_does_not_say_it_is_done(tmp_path, capsys):
    """COLMAP failing in feature extraction: its error comes out of run_colmap, nothing runs
    after it, and no `done in` line is said for the stage."""
    class _Failing(_StandIn):
        def extract_features(self, *args, **kwargs):
            raise RuntimeError("feature extraction failed")

    stand_in = _Failing([{}, {}])
    with pytest.raises(RuntimeError, match="feature extraction failed"):
        poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:6], tmp_path / "work", matcher="exhaustive",
                         camera_model="OPENCV", single_camera=True)
    assert stand_in.calls == [("seed", 0)]
    assert capsys.readouterr().err.splitlines() == ["poses: features (SIFT, 6 photos) ..."]


def test_undistort_hands_colmap_the_model_and_lays_out_images_and_sparse_cut_to_one_size(tmp_path):
    """Stage 5: the model written to _work/model is what COLMAP's undistortion reads (with the
    photo folder, COLMAP output, JPEG_QUALITY); its images/ and sparse/ become the stage's
    images/ and sparse/0, cut to the smallest size (70 x 50 and 64 x 48 -> 64 x 48)."""
    centres, w2cs = _rings()
    images = [("a.png", 1, w2cs[0], -w2cs[0] @ centres[0]), ("b.png", 2, w2cs[1], -w2cs[1] @ centres[1])]
    _write_model(tmp_path / "text", {1: (70, 50, FOCAL, FOCAL, 35, 25), 2: (64, 48, FOCAL, FOCAL, 32, 24)}, images,
                 np.array([[1.0, -2.0, 3.0]]))
    model = pycolmap.Reconstruction(tmp_path / "text")
    stage = tmp_path / "stage"
    stage.mkdir()
    stand_in = _Undistorting([])
    poses.undistort(stand_in, model, tmp_path / "photos", stage)
    assert stand_in.calls == [("undistort", stage / "_work" / "undistorted", stage / "_work" / "model",
                               tmp_path / "photos", "COLMAP", 95, ["a.png", "b.png"])]
    assert sorted(p.name for p in (stage / "images").iterdir()) == ["a.png", "b.png"]
    for k, name in enumerate(["a.png", "b.png"]):
        pixels = io.opencv().imread(str(stage / "images" / name))
        assert pixels.shape == (48, 64, 3) and np.all(np.abs(pixels.astype(int) - round(25.5 * (k + 1))) <= 1)
    out = pycolmap.Reconstruction(stage / "sparse" / "0")
    assert {(c.width, c.height) for c in out.cameras.values()} == {(64, 48)}
    np.testing.assert_allclose(out.cameras[1].params, [FOCAL, FOCAL, 32, 24])
    assert sorted(p.name for p in stage.iterdir()) == ["_work", "images", "sparse"]
    assert sorted(p.name for p in (stage / "sparse").iterdir()) == ["0"]


def test_undistort_into_a_stage_already_holding_a_work_model_writes_over_it(tmp_path):
    """A stage whose _work/model exists already (with a stale file): the model is written into it
    and handed to COLMAP's undistortion, and the stage is laid out as from a fresh one."""
    centres, w2cs = _rings()
    images = [("a.png", 1, w2cs[0], -w2cs[0] @ centres[0]), ("b.png", 1, w2cs[1], -w2cs[1] @ centres[1])]
    _write_model(tmp_path / "text", {1: (64, 48, FOCAL, FOCAL, 32, 24)}, images, np.array([[1.0, -2.0, 3.0]]))
    model = pycolmap.Reconstruction(tmp_path / "text")
    stage = tmp_path / "stage"
    (stage / "_work" / "model").mkdir(parents=True)
    (stage / "_work" / "model" / "stale.txt").write_text("from an earlier attempt")
    stand_in = _Undistorting([])
    poses.undistort(stand_in, model, tmp_path / "photos", stage)
    assert stand_in.calls == [("undistort", stage / "_work" / "undistorted", stage / "_work" / "model",
                               tmp_path / "photos", "COLMAP", 95, ["a.png", "b.png"])]
    assert sorted(p.name for p in (stage / "images").iterdir()) == ["a.png", "b.png"]
    assert {(c.width, c.height) for c in pycolmap.Reconstruction(stage / "sparse" / "0").cameras.values()} == {(64, 48)}


def test_mapping_progress_counts_registered_photos_never_more_than_the_photos(tmp_path, monkeypatch, capsys):
    """A stand-in mapper that registers each of the 12 photos twice (a first model of all 12, then
    a second one of all 12 again: 24 registrations, as COLMAP reports each model it tries): the
    progress line counts 12/12 at most, and says 12/12 at the end."""
    class _Twice(_StandIn):
        def incremental_mapping(self, database_path, image_path, output_path, options=None, input_path="",
                                initial_image_pair_callback=None, next_image_callback=None):
            for _ in range(2):                      # two models, each registering every photo
                initial_image_pair_callback()       # its first two photos
                for _ in range(10):
                    next_image_callback()           # the other ten, one by one
            return self.maps.pop(0)

    real_bar = poses.progress.bar
    monkeypatch.setattr(poses.progress, "_is_tty", lambda stream: False)   # plain lines, every update written
    monkeypatch.setattr(poses.progress, "bar", lambda *a, **k: real_bar(*a, **k, interval=0.0))
    stand_in = _Twice([{0: _model(tmp_path / "all", 12)}])
    poses.run_colmap(stand_in, tmp_path / "photos", NAMES[:12], tmp_path / "work", matcher="exhaustive",
                     camera_model="OPENCV", single_camera=True)
    counts = [tuple(map(int, m.groups())) for m in
              re.finditer(r"poses: mapping: (\d+)/(\d+) photos", capsys.readouterr().err)]
    assert len(counts) > 10 and all(total == 12 and done <= 12 for done, total in counts), counts
    assert counts[-1] == (12, 12)


def test_map_photos_maps_into_a_work_folder_not_made_yet(tmp_path):
    """The mapping without the GPS priors runs into a new folder under the work folder: its
    models go to that folder's sparse0, the priors off, the seconds under its own key."""
    stand_in = _StandIn([{0: _model(tmp_path / "m", 12, 30)}])
    timings: dict = {}
    model, relaxed, extended, from_2d = poses.map_photos(stand_in, tmp_path / "db", tmp_path / "photos", 12,
                                                tmp_path / "work" / "without_gps", priors=False, keep_all=False,
                                                show=False, timings=timings, key="mapping_without_gps")
    assert model.num_reg_images() == 12 and (relaxed, extended, from_2d) == (False, False, [])
    assert [c[3] for c in stand_in.calls] == [tmp_path / "work" / "without_gps" / "sparse0"]
    assert list(timings) == ["mapping_without_gps"]
