"""Camera poses from a folder of photos: structure from motion with COLMAP's own Python
bindings (pycolmap, the optional extra `sfm`), written as a dataset in the transforms.json
layout (docs/DATASET.md). How to run it and its limits: docs/POSES.md.

`poses_from_images(images_dir, out_dir)` runs the stages in order:
  1. photos: the images of `images_dir` (not its subfolders), sorted by name; unreadable files
     are named and skipped; EXIF orientation is applied and, with `max_side`, the photos are
     scaled to a working size (working copies are written only for the photos that need it);
  2. features: SIFT (`pycolmap.extract_features`), one camera for all photos when they share
     one size and one EXIF camera, else one per photo (`camera_sharing`; `single_camera` True
     or False decides instead);
  3. matching (`match_photos`): exhaustive, spatial (each photo with its nearest by GPS),
     sequential (each photo with its next `overlap` in name order, as a flight records them,
     with loop closure: the pairs across the sequence's end that close an orbit and COLMAP's
     quadratic overlap, `pairing.sequential_pairs`; COLMAP's own loop detection needs a
     vocabulary tree, which is not shipped nor downloaded), a vocabulary tree (`vocab_tree`: a
     file), or `auto` (`choose_matcher`: exhaustive while the pairs are few, spatial when every
     photo has GPS, sequential when the names are numbered in sequence);
  4. mapping: incremental mapping (`pycolmap.incremental_mapping`), with the photos' GPS as
     position priors in its bundle adjustment where they hold (`priors_hold`: spread over
     PRIOR_MIN_SPREAD_M, photos of at most SMALL_SIDE px; `write_gps_priors`, `mapper_options`; GPS that
     disagrees with the growing model stops it, and the photos are mapped without it:
     `gps_watch`), once more with relaxed thresholds when under 90 % of the photos register
     (photos over 800 px: under half, `remap_relaxed`; `choose_model` keeps the relaxed model
     only when it is consistent with the first); the photos the kept model
     left out are then placed from their 2-D matches alone (`structure_less.register`, kept
     when it agrees), and those still out tried again, continuing that model with looser
     thresholds (`register_left_out`, likewise); the largest model is kept, the photos outside
     it are named with why (`unregistered_reasons`); a camera set too thin to train on is
     refused (`camera_set`, unless `accept_few_cameras`), its reconstruction and report kept in
     DATA_DIR.refused, which the same run with `accept_few_cameras` reuses (`refused`);
  5. undistortion to PINHOLE (`pycolmap.undistort_images`): DATA_DIR/images/ holds the
     undistorted photos under their input names, cropped to one size when each photo has its
     own camera (`crop_to_common_size`);
  6. orientation and normalisation: the model is rotated so the cameras' up axis is +z
     (`normalize.up_from_cameras`) and written to DATA_DIR/sparse/0; transforms.json carries
     OpenGL camera-to-world poses normalised for an orbit (`normalize.normalize_orbit`:
     the point the cameras look at in the unit sphere), `scene_normalization` mapping the
     sparse/0 frame to them, near / far from the points each photo sees (as the COLMAP
     loader computes them), and a `poses` record (the summary below);
  7. DATA_DIR/poses_topview.png: camera centres and sparse points seen from above.

Everything is built in a hidden folder next to DATA_DIR and moved into place at the end, so
a failed run leaves an existing DATA_DIR as it was, and the input photos are never written
to. `overwrite` replaces only a dataset this command wrote (MARKER), and in it only its own
outputs (OUTPUTS) and the outputs of `jaxnerf-grid mask` made from the photos it replaces
(STALE); other files stay (docs/RELIABILITY.md).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from jaxnerf_grid.capture import (
    camera_set,
    camera_sharing,
    georef,
    gps,
    pairing,
    photo_exif,
    refused,
    structure_less,
    vetting,
)
from jaxnerf_grid.capture.bounds import scene_bounds
from jaxnerf_grid.capture.gps_watch import GpsStopped, MappingWatch, gps_disagrees
from jaxnerf_grid.data.formats.colmap import collect_colmap, observation_depths
from jaxnerf_grid.data.formats.writing import MASK_OUTPUT_DIRS, transforms_top
from jaxnerf_grid.data.normalize import (
    apply_normalization_to_points,
    normalize_orbit,
    z_up_turn,
)
from jaxnerf_grid.util import folders, io, progress, staging
from jaxnerf_grid.util.io import DataError

MIN_PHOTOS = 3        # fewer readable photos: refused before any work
MIN_REGISTERED = 3    # fewer registered photos: no dataset is written ...
MIN_REGISTERED_FRACTION = 0.25  # ... nor below a quarter of the readable photos (`enough_registered`)
MATCHERS = ("auto", "exhaustive", "spatial", "sequential", "vocab")
# `auto` (`choose_matcher`): exhaustive matching while it is cheap, up to EXHAUSTIVE_MAX_PAIRS
# pairs (50 photos): about 0.03 s a pair at 320x240 (tower-small, 36 photos: 630 pairs in 17 s)
# and 0.2-0.5 s a pair at 3072x2048 (Herz-Jesus-P25, docs/POSES.md), so at most about 40 s to
# 10 min; every pair matched closes every loop. Above it: spatial matching by GPS
# (`pycolmap.match_spatial`, each photo with its SPATIAL_NEIGHBOURS nearest by GPS position) when
# every photo carries GPS; else sequential matching with loop closure when the names are
# numbered in sequence (`names_look_ordered`; `pairing.sequential_pairs`: each photo with its
# next SEQUENTIAL_OVERLAP, the wrap-around pairs that close an orbit and COLMAP's quadratic
# overlap); else every pair, however many (the capture order is unknown).
SEQUENTIAL_OVERLAP = 10
EXHAUSTIVE_MAX_PAIRS = 1225
SPATIAL_NEIGHBOURS = 20
SPATIAL_MAX_DISTANCE = 1e6  # metres: the neighbour count, not a distance, bounds the pairs
# GPS as pose priors (`write_gps_priors`): a consumer receiver's error as the prior's standard
# deviation, horizontal and vertical (data/gps_scene.py draws 1-3 m and 2-5 m)
PRIOR_SIGMA_M = (3.0, 5.0)
# ... and only when the GPS positions spread over PRIOR_MIN_SPREAD_M at least (their median
# horizontal distance from their mean, `gps_spread_m`): a phone's 3-5 m error around a tree
# photographed from 5 m would pull the cameras about, not hold them (monstree, 23 photos: with
# the priors the GPS alignment came out mirrored, docs/POSES.md); a drone orbit spreads 40-60 m.
PRIOR_MIN_SPREAD_M = 30.0
# ... and only for small photos (every working photo at most SMALL_SIDE px), whose few hundred
# features a photo leave an orbit weakly tied. Larger photos are mapped without them and the
# finished model aligned to the GPS: on 57 photos of a drone survey (3600x2700, SIFT at 1600 px)
# the priors' global bundle adjustments took the mapping from 121 s to 254 s, 51 photos kept
# against 52 without, the cameras' orientations 0.06 degrees apart (docs/POSES.md).
PRIORS_SMALL_ONLY = True
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")
INSTALL_HINT = "pip install -e '.[sfm]' (or: bash scripts/setup.sh)"
TOPVIEW = "poses_topview.png"
REPORT = "poses_report.md"
# `--overwrite` replaces only a dataset this command wrote (it holds MARKER), and in it only
# OUTPUTS; the user's other files stay (docs/RELIABILITY.md).
MARKER = ".jaxnerf-grid-poses"
OUTPUTS = ("images", "sparse", "transforms.json", TOPVIEW, REPORT, MARKER)
# `jaxnerf-grid mask` outputs in an old DATA_DIR describe the photos being replaced: --overwrite
# removes them with OUTPUTS (the new transforms.json names no masks), so `mask` runs again
# without --overwrite.
STALE = MASK_OUTPUT_DIRS
JPEG_QUALITY = 95
# Mapping runs again with RELAXED mapper thresholds when the first run registers fewer than
# RELAX_BELOW of the photos (small working sizes give a few hundred features per photo, below
# COLMAP's defaults of 30 inliers to register a photo); the run registering more is kept.
# Larger photos (over SMALL_SIDE) are mapped again only below RELAX_BELOW_LARGE: above it the
# photos left out go straight to `register_left_out` (the relaxed thresholds, continuing the
# model), which on the seneca flight kept as many photos in 60 % of the mapping time
# (`remap_relaxed`; docs/POSES.md).
RELAX_BELOW = 0.9
RELAX_BELOW_LARGE = 0.5
RELAXED = {"abs_pose_min_num_inliers": 15, "init_min_num_inliers": 50, "init_min_tri_angle": 8.0}
# ... and kept only when it agrees with the first run's model on the photos both register
# (median rotation difference and centre distance, `poses_agree`), or when the first failed.
AGREE_DEG, AGREE_CENTRE = 2.0, 0.05
# SIFT and matching options set on top of COLMAP's defaults. Affine-adapted features match
# across the strong foreshortening of ground seen from an oblique drone camera: on tower-small
# at 320x240 (30 photos, low clutter) they registered 19 photos against 16 without
# (benchmarks/poses_accuracy.py; docs/POSES.md). MATCHING_SIFT loosens Lowe's ratio test from
# COLMAP's 0.8 to 0.9: there 23 of 30 registered, 0.1-0.2 degrees median error; 0.93 and 0.95
# registered more (25, 29) but the first model was turned by 22 degrees and the second had
# photos 5 degrees and a quarter of the orbit radius off (look-alike tower faces matched).
SIFT: dict[str, Any] = {"estimate_affine_shape": True}
# SIFT_SMALL, for photos whose working size is at most SMALL_SIDE px on the long side: COLMAP's
# peak threshold 0.0067 lowered to 0.004 finds the fainter corners of small photos. On the
# 36-photo tower-small orbit (low clutter, seed 0, 320x240) the mapping then registered 28,
# relaxed 30 and after `register_left_out` 35 photos against 26, 29 and 31. Larger photos give
# thousands of features anyway, and there it cost time (fountain-P11 at 1024 px: features 126 s
# against 93 s, docs/POSES.md).
SIFT_SMALL: dict[str, Any] = {"peak_threshold": 0.004}
SMALL_SIDE = 800
# SIFT runs on the photos scaled to at most FEATURE_SIDE px on the long side (COLMAP's
# max_image_size; its own default 3200); the keypoints come back in the photos' pixels and the
# dataset keeps the photos' size. Feature extraction is most of a full-size run's time: at 1200
# against 1600 px the Strecha scenes keep their accuracy to the hundredth of a degree and a
# 57-photo 11 MP flight is posed in 405 s against 544 s; the measured trade-off is in
# docs/POSES.md ("Feature size"). 0: COLMAP's own size.
FEATURE_SIDE = 1200
MATCHING: dict[str, Any] = {}
MATCHING_SIFT: dict[str, Any] = {"max_ratio": 0.9}
# TWO_VIEW: COLMAP's geometric verification of each matched pair (`TwoViewGeometryOptions`) on
# top of its defaults.
TWO_VIEW: dict[str, Any] = {}
# For small photos (at most SMALL_SIDE px, as SIFT_SMALL), on top of MATCHING and TWO_VIEW.
# MATCHING_SMALL: guided matching matches each verified pair again along its epipolar geometry:
# the look-alike crosses of a lattice tower, which the ratio test drops, come back (a test
# lattice at 320x240: 159 verified matches without, 1717 with). TWO_VIEW_SMALL: a pair is
# verified from 10 inliers (COLMAP: 15): an orbit's low photos looking up at the tower share
# 10-37 with one to three others. Together, on the 12 generated orbits at 320x240 (one run
# each): 391 of 396 photos registered and 338 kept (85 %) against 354 and 306 (77 %), the worst
# kept camera 1.83 degrees against 2.06, 11 runs of 12 within 1 degree against 7; a 30-photo
# orbit took 71-73 s against 30-34 s, most of it mapping (docs/POSES.md, "Current figures").
# On one orbit either alone did
# worse: 10 inliers without guided matching built a partly wrong model, guided matching alone
# registered 26 of 30 against 29 (benchmarks/results/poses_orbits/levers_low-s0-30_gps.json).
# Larger photos give thousands of matches a pair anyway, and guided matching among 8192
# features a photo is slow on the CPU (fountain-P11 at 1024 px, docs/POSES.md).
MATCHING_SMALL: dict[str, Any] = {"guided_matching": True}
TWO_VIEW_SMALL: dict[str, Any] = {"min_num_inliers": 10}
# MAPPER: observations reprojecting more than 2 px off (COLMAP: 4) are dropped; with the looser
# ratio test the test scene's 95th-percentile reprojection error otherwise reached 1.3 px.
MAPPER = {"filter_max_reproj_error": 2.0}
MIN_COMPARED = 8  # a smaller first model is no judge: the relaxed one is kept
# Registering the photos a first model left out (`register_left_out`): the relaxed thresholds
# and fewer inliers still, more tries per photo; kept only when it agrees with the first model
# (`poses_agree`) and adds photos that pass the vetting.
# Two-view tracks are kept there: a photo seen only with one registered neighbour gets its 2-D -
# 3-D matches from them (on that orbit 35 of 36 against 33 without).
LEFT_OUT = {"abs_pose_min_num_inliers": 10, "max_reg_trials": 6}
# A grown model (the photos left out registered into it) is also judged against the photos' GPS:
# kept only when its cameras fit their fixes (RMS after a similarity fit) within GROWN_GPS_RATIO of
# the first model's fit, or within GROWN_GPS_FLOOR_M. The models are otherwise compared only on
# the photos both hold, so a strip of new photos registered turned passes that comparison (on a
# 57-photo survey at 3600x2700, 8 photos 63 degrees off and 46 of 57 over 9 m from their fixes).
GROWN_GPS_RATIO = 2.0
GROWN_GPS_FLOOR_M = 9.0
LEFT_OUT_TRIANGULATION = {"ignore_two_view_tracks": False}
# The first mapping and the continuation of a model stop after one model: only the largest model
# is kept, and the photos a model leaves out go on to the steps above, so further models started
# from them (COLMAP's multiple_models) are time for nothing: on a 57-photo survey at 3600x2700
# COLMAP was caught building one in a mapping of 739 s, against 100-300 s in the other runs of those
# matches. The relaxed mapping from scratch, the remedy when the first model is small, still tries several.
SINGLE_MODEL = True


def import_pycolmap():
    """The pycolmap module, or a one-line DataError saying how to install it."""
    try:
        import pycolmap
    except ImportError:
        raise DataError(f"pycolmap is not installed (jaxnerf-grid poses needs it): {INSTALL_HINT}") from None
    return pycolmap


# ----------------------------------------------------------------------------------------
# Stage 1: the photos


def list_photos(images_dir) -> list[Path]:
    """The photo files of a folder (PNG / JPEG, not recursive), sorted by name.

    DataError naming the folder when it is missing or holds fewer than MIN_PHOTOS photos.
    """
    folder = Path(images_dir)
    if not folder.is_dir():
        raise DataError(f"{folder}: photo folder not found")
    photos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
    if not photos:
        raise DataError(f"{folder}: no photos (PNG or JPEG) in this folder")
    if len(photos) < MIN_PHOTOS:
        raise DataError(f"{folder}: {len(photos)} photo(s); camera poses need at least {MIN_PHOTOS}")
    return photos


def working_size(width: int, height: int, max_side: int | None) -> tuple[int, int]:
    """(W', H'): the size scaled so the longer side is at most `max_side` (never enlarged)."""
    if max_side is None or max(width, height) <= max_side:
        return width, height
    s = max_side / max(width, height)
    return max(1, round(width * s)), max(1, round(height * s))


def prepare_photo(path: Path, work_dir: Path, max_side: int | None) -> tuple[Path, tuple[int, int]]:
    """The file COLMAP should read for one photo, and its size (W, H).

    The photo itself when it is upright (its EXIF orientation changes nothing) and within
    `max_side`; else an upright, scaled copy in `work_dir` under the same name. DataError
    naming the file when it cannot be decoded.
    """
    cv2 = io.opencv()
    upright, data = io.decode_raw(path, "photo", cv2.IMREAD_COLOR)
    stored = cv2.imdecode(data, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    height, width = upright.shape[:2]
    size = working_size(width, height, max_side)
    if size == (width, height) and stored is not None and np.array_equal(stored, upright):
        return path, size
    out = upright if size == (width, height) else io.resize(upright, size, "area")
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if path.suffix.lower() in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(path.suffix.lower(), out, params)
    if not ok:
        raise DataError(f"{path}: could not encode a working copy")
    io.atomic_write_bytes(work_dir / path.name, buf.tobytes())
    return work_dir / path.name, size


def prepare_photos(photos: list[Path], work_dir: Path, max_side: int | None, show: bool = True):
    """Stage 1 over all photos. Returns (folder COLMAP reads, names read, {name: why skipped},
    {name: (width, height) of its working copy}).

    Photos needing no copy are hard-linked (or copied) into `work_dir` too, so COLMAP reads one
    folder. DataError when fewer than MIN_PHOTOS are readable.
    """
    work_dir.mkdir(parents=True, exist_ok=True)
    names, skipped, sizes = [], {}, {}
    for path in progress.bar(photos, desc="poses: photos", unit="photo", enabled=show):
        try:
            used, sizes[path.name] = prepare_photo(path, work_dir, max_side)
        except DataError as err:
            skipped[path.name] = str(err)
            _say(f"poses: skipping {path}: not a readable image", show=True)
            continue
        if used == path:
            _link_or_copy(path, work_dir / path.name)
        names.append(path.name)
    if len(names) < MIN_PHOTOS:
        folder = photos[0].parent
        raise DataError(f"{folder}: only {len(names)} readable photo(s) of {len(photos)} "
                        f"(unreadable: {', '.join(skipped) or 'none'}); camera poses need at least {MIN_PHOTOS}")
    return work_dir, names, skipped, sizes


def check_one_size(sizes: dict, folder, single_camera: bool | None) -> None:
    """DataError naming the folder and the sizes when `single_camera` is asked for photos of more
    than one (working) size: COLMAP's one camera has one image size, so the photos of the other
    sizes would silently stay unregistered. sizes: {name: (width, height)}."""
    if not single_camera:
        return
    by_size: dict = {}
    for name, size in sorted(sizes.items()):
        by_size.setdefault(tuple(size), []).append(name)
    if len(by_size) > 1:
        shown = "; ".join(f"{w}x{h}: {len(names)} (e.g. {names[0]})" for (w, h), names in
                          sorted(by_size.items(), key=lambda kv: -len(kv[1])))
        raise DataError(f"{folder}: poses.single_camera needs photos of one size, these have {len(by_size)} "
                        f"({shown}); leave poses.single_camera off (each photo gets its own camera) or split "
                        "the folder")


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def _say(message: str, show: bool) -> None:
    """One progress or warning line on stderr (when `show`)."""
    if show:
        print(message, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------------------
# Stages 2-5: COLMAP


def check_options(matcher: str, camera_model: str, vocab_tree, overlap: int = SEQUENTIAL_OVERLAP,
                  neighbours: int = SPATIAL_NEIGHBOURS) -> None:
    """DataError for an unknown matcher / camera model, a sequential overlap or a spatial
    neighbour count that is not a positive integer, or `vocab` without a readable tree file."""
    if matcher not in MATCHERS:
        raise DataError(f"unknown poses.matcher {matcher!r}; choose one of {', '.join(MATCHERS)}")
    for key, count in (("poses.overlap", overlap), ("poses.neighbours", neighbours)):
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise DataError(f"{key} must be a whole number of photos, at least 1, got {count!r}")
    if camera_model not in CAMERA_MODELS:
        raise DataError(f"unknown camera model {camera_model!r}; choose one of {', '.join(CAMERA_MODELS)}")
    if matcher == "vocab":
        if vocab_tree is None:
            raise DataError("poses.matcher vocab needs a vocabulary tree file (poses.vocab_tree, e.g. COLMAP's "
                            "vocab_tree_flickr100K_words32K.bin); none is downloaded: use exhaustive or sequential")
        if not Path(vocab_tree).is_file():
            raise DataError(f"{vocab_tree}: vocabulary tree file not found")


def names_look_ordered(names: list[str]) -> bool:
    """Whether photo names are numbered in sequence, as a camera or a drone names a flight's
    photos (DJI_0001.JPG, IMG_0002.jpg, 0003.png): every name (less its extension) is one
    common prefix followed by a number, the numbers differ, and name order is number order
    (so 'p1, p10, p2' is not: its name order is not the capture order)."""
    parts = []
    for name in names:
        stem = Path(name).stem
        digits = len(stem) - len(stem.rstrip("0123456789"))
        if digits == 0:
            return False
        parts.append((stem[:-digits], int(stem[-digits:])))
    numbers = [number for _, number in parts]
    return (len({prefix for prefix, _ in parts}) == 1 and len(set(numbers)) == len(numbers)
            and [number for _, number in sorted(zip(names, numbers))] == sorted(numbers))


def choose_matcher(matcher: str, names: list[str], with_gps: int = 0,
                   max_pairs: int | None = None) -> tuple[str, str]:
    """The matcher to run for `matcher` (one of MATCHERS) on the readable photos `names`, and
    why, in words. with_gps: how many of them carry a GPS position. `auto`: exhaustive while
    the pairs (n (n - 1) / 2) are at most `max_pairs`; above it spatial when every photo
    carries GPS, sequential with loop closure when the names look ordered
    (`names_look_ordered`), else exhaustive (EXHAUSTIVE_MAX_PAIRS, the default `max_pairs`, has
    the figures)."""
    if matcher != "auto":
        return matcher, "asked for"
    max_pairs = EXHAUSTIVE_MAX_PAIRS if max_pairs is None else max_pairs
    n = len(names)
    pairs = pairing.pair_count(n)
    if pairs <= max_pairs:
        return "exhaustive", f"auto: {n} photos, {pairs} pairs, at most {max_pairs}"
    if with_gps == n:
        return "spatial", (f"auto: {n} photos, {pairs} pairs, more than {max_pairs}; every photo has GPS")
    if names_look_ordered(names):
        return "sequential", (f"auto: {n} photos, {pairs} pairs, more than {max_pairs}, named in sequence: with "
                              "loop closure")
    return "exhaustive", (f"auto: {n} photos, {pairs} pairs, more than {max_pairs}, but no GPS on every photo and "
                          "the names are not numbered in sequence")


def run_colmap(pycolmap, photo_dir: Path, names: list[str], work_dir: Path, *, matcher: str,
               camera_model: str, single_camera: bool, vocab_tree=None, show: bool = True, source=None,
               keep_all: bool = False, overlap: int = SEQUENTIAL_OVERLAP, timings: dict | None = None,
               priors: dict | None = None, small_photos: bool = False, feature_side: int = FEATURE_SIDE,
               watch: MappingWatch | None = None, neighbours: int = SPATIAL_NEIGHBOURS):
    """Features, matching and incremental mapping. Returns (the kept pycolmap.Reconstruction,
    whether it comes from the relaxed mapping, whether photos left out by the first model were
    registered afterwards (`register_left_out`), the photos placed from their 2-D matches alone
    (`structure_less.register`)). The relaxed model is judged by its photos that
    pass the vetting (`vetted_count`; all its photos with `keep_all`). `matcher`: exhaustive,
    spatial (each photo with its `neighbours` nearest by GPS), sequential (each photo with its
    next `overlap`, with loop closure) or vocab. `timings` ({stage: seconds}, when given) gets
    the seconds of features, matching and mapping.
    priors: {photo name: [3] GPS position in local metres of a projected CRS}: written to the
    database as pose priors (`write_gps_priors`), used by the spatial matcher and, when they hold
    (`priors_hold`: spread wide enough, small photos), by the mapper's bundle adjustment
    (`mapper_options`, use_prior_position). small_photos: SIFT_SMALL,
    MATCHING_SMALL and TWO_VIEW_SMALL on top of SIFT, MATCHING and TWO_VIEW, and the relaxed
    mapping below RELAX_BELOW rather than RELAX_BELOW_LARGE (`remap_relaxed`) (every working photo
    at most SMALL_SIDE px on its long side). feature_side: the
    long side SIFT sees at most (FEATURE_SIDE; 0: COLMAP's own). watch: judges the mapping with
    the priors as it grows (`gps_watch.MappingWatch`); when it stops it, the photos are mapped
    without the priors at once (under work_dir/without_gps, timings' "mapping_without_gps"), and
    `watch.stopped` says so.

    DataError (naming `source`, the input folder) when no model could be built.
    """
    database = work_dir / "database.db"
    pycolmap.set_random_seed(0)
    timings = {} if timings is None else timings
    with _stage(f"features (SIFT, {len(names)} photos)", show, timings, "features"):
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO
        extraction = pycolmap.FeatureExtractionOptions()  # SIFT on top of COLMAP's defaults
        extraction.max_image_size = feature_side if feature_side > 0 else -1
        set_options(extraction.sift, SIFT, SIFT_SMALL if small_photos else {})
        pycolmap.extract_features(database, photo_dir, image_names=names, camera_mode=mode, reader_options=reader,
                                  extraction_options=extraction)
        if priors:
            write_gps_priors(pycolmap, database, priors)
    with _stage(f"matching ({matcher})", show, timings, "matching"):
        match_photos(pycolmap, database, matcher, names, work_dir, overlap, vocab_tree, small_photos, neighbours)
    try:
        mapped = map_photos(pycolmap, database, photo_dir, len(names), work_dir,
                            priors=priors_hold(priors or {}, small_photos), keep_all=keep_all,
                            show=show, timings=timings, watch=watch, small_photos=small_photos, positions=priors)
    except GpsStopped as stop:
        _say(f"poses: {stop}: a receiver that lags or drifts; mapping without it", show)
        mapped = map_photos(pycolmap, database, photo_dir, len(names), work_dir / "without_gps",
                            priors=False, keep_all=keep_all, show=show, timings=timings,
                            key="mapping_without_gps", label="mapping without the GPS",
                            small_photos=small_photos)  # the GPS stopped it: no judge of the grown models
    if mapped[0] is None:
        raise DataError(f"{source or photo_dir}: no reconstruction: the photos share too few features (more overlap, "
                        f"more texture or more photos help; see docs/POSES.md)")
    return mapped


def remap_relaxed(registered: int | None, total: int, small_photos: bool) -> bool:
    """Whether the photos are mapped again from scratch with the relaxed thresholds after a first
    model of `registered` of `total` photos (None: no model): below RELAX_BELOW of them for
    small photos, below RELAX_BELOW_LARGE for larger ones."""
    if registered is None:
        return True
    return registered < (RELAX_BELOW if small_photos else RELAX_BELOW_LARGE) * total


def map_photos(pycolmap, database, photo_dir: Path, total: int, work_dir: Path, *, priors: bool, keep_all: bool,
               show: bool, timings: dict, key: str = "mapping", label: str = "mapping",
               watch: MappingWatch | None = None, small_photos: bool = False, positions: dict | None = None):
    """Incremental mapping of a matched database (`total` photos): the default run, the relaxed
    one when `remap_relaxed` says so (`choose_model`), then the photos left out placed from their
    2-D matches alone (`structure_less.register`, kept when the poses agree), then those still out
    tried again continuing the model (`register_left_out`, kept likewise). priors: the database's
    pose priors (GPS) enter the bundle adjustment. Its models go under `work_dir` (sparse0,
    sparse1, extend); `timings[key]` gets its seconds. watch: judges the default run as it grows
    (`watched_mapping`); its GpsStopped is raised on, `timings[key]` holding the seconds until then.
    positions: {photo name: [3] GPS position in local
    metres}: a grown or relaxed model is kept only when it fits them about as well as the model
    it would replace (`fits_gps_as_well`).
    Returns (the model or None, from the relaxed run, extended, [the photos placed structure-less])."""
    start = time.monotonic()
    work_dir.mkdir(parents=True, exist_ok=True)  # COLMAP makes its output folder, not the parents
    try:
        default = _map(pycolmap, database, photo_dir, work_dir / "sparse0", total, False, label, show, priors=priors,
                       watch=watch, single_model=SINGLE_MODEL)
    except GpsStopped:
        timings[key] = round(time.monotonic() - start, 1)
        raise
    best = default
    count = _registered_count if keep_all else vetted_count
    if remap_relaxed(None if default is None else default.num_reg_images(), total, small_photos):
        relaxed = _map(pycolmap, database, photo_dir, work_dir / "sparse1", total, True,
                       f"{label} again (relaxed thresholds)", show, priors=priors)
        best = choose_model(default, relaxed, show, count=count, positions=positions)
    relaxed_used, extended, placed = best is not default, False, []
    # structure-less first: seconds where continuing the model takes a minute, and what it places
    # is not offered to `register_left_out`, whose relaxed thresholds can fold a weakly tied strip
    if best is not None and best.num_reg_images() < total:
        more, names = structure_less.register(pycolmap, database, best, mapper_options(
            pycolmap, True, priors, LEFT_OUT, LEFT_OUT_TRIANGULATION))
        if _adds_photos(best, more, count, positions, show):
            _say(f"poses: placed {len(names)} more photo(s) from their 2-D matches alone (structure-less)", show)
            best, placed = more, names
    if best is not None and best.num_reg_images() < total:
        more = register_left_out(pycolmap, database, photo_dir, best, total, work_dir / "extend", show, priors)
        if _adds_photos(best, more, count, positions, show):
            _say(f"poses: registered {more.num_reg_images() - best.num_reg_images()} more photo(s) the first model "
                 "left out", show)
            best, extended = more, True
    timings[key] = round(time.monotonic() - start, 1)
    return best, relaxed_used, extended, placed


def _adds_photos(model, more, count, positions: dict | None = None, show: bool = False) -> bool:
    """Whether `more` (a model grown from `model`, or None) is worth more photos by `count`,
    agrees with `model` on the photos both hold (`poses_agree`) and, with `positions` (GPS),
    fits them within GROWN_GPS_RATIO of `model`'s fit or GROWN_GPS_FLOOR_M (`gps_fit_rms`)."""
    if more is None or count(more) <= count(model) or not poses_agree(model_poses(model), model_poses(more)):
        return False
    return fits_gps_as_well(model, more, positions, show)


def fits_gps_as_well(model, more, positions: dict | None, show: bool = False) -> bool:
    """Whether `more` (a model with more photos than `model`) fits the GPS `positions`
    ({name: [3]} local metres; None or too few: True) within GROWN_GPS_RATIO of `model`'s RMS
    or GROWN_GPS_FLOOR_M (`gps_fit_rms`); says so on stderr when it does not."""
    before, after = gps_fit_rms(model, positions or {}), gps_fit_rms(more, positions or {})
    if before is None or after is None or after <= max(GROWN_GPS_RATIO * before, GROWN_GPS_FLOOR_M):
        return True
    _say(f"poses: the model with {more.num_reg_images() - model.num_reg_images()} more photo(s) fits the GPS "
         f"{after:.1f} m RMS against {before:.1f} m without them; kept without them", show)
    return False


def gps_fit_rms(model, positions: dict) -> float | None:
    """RMS distance (m) of a model's registered cameras from their GPS positions ({name: [3]}
    local metres) after a least-squares similarity fit of the centres (`georef.umeyama`); None
    with fewer than 3 such photos."""
    centres = {name: c2w[:3, 3] for name, c2w in model_poses(model).items() if name in positions}
    if len(centres) < 3:
        return None
    names = sorted(centres)
    src = np.stack([centres[n] for n in names])
    dst = np.asarray([positions[n] for n in names], np.float64)
    error = georef.apply_similarity(georef.umeyama(src, dst), src) - dst
    return float(np.sqrt(np.mean(np.sum(error ** 2, axis=1))))


def priors_hold(priors: dict, small_photos: bool) -> bool:
    """Whether GPS positions ({name: [3]}) enter the mapping as priors: any, and no reason
    against them (`priors_skipped`)."""
    return bool(priors) and priors_skipped(priors, small_photos) is None


def priors_skipped(priors: dict, small_photos: bool) -> str | None:
    """Why GPS positions ({name: [3]}, some) stay out of the mapping, or None when they go in:
    spread under PRIOR_MIN_SPREAD_M, or photos over SMALL_SIDE px (not small_photos: PRIORS_SMALL_ONLY).
    None without positions."""
    if not priors:
        return None
    spread = gps_spread_m(priors)
    if spread < PRIOR_MIN_SPREAD_M:
        return (f"the GPS positions spread {spread:.0f} m, under {PRIOR_MIN_SPREAD_M:.0f} m: "
                "priors would pull the cameras about; the GPS aligns the finished model")
    if PRIORS_SMALL_ONLY and not small_photos:
        return (f"photos over {SMALL_SIDE} px: their features tie the model, and the priors' bundle adjustments "
                "would double the mapping's time; the GPS aligns the finished model")
    return None


def gps_spread_m(priors: dict) -> float:
    """The median horizontal distance (m) of GPS positions ({name: [3]}) from their mean."""
    xy = np.stack([np.asarray(p, np.float64)[:2] for p in priors.values()])
    return float(np.median(np.linalg.norm(xy - xy.mean(0), axis=1)))


def write_gps_priors(pycolmap, database, priors: dict) -> int:
    """Replaces the database's pose priors (COLMAP writes the EXIF GPS of the photos it reads
    in WGS 84, and none for a working copy) with `priors`: {photo name: [3] position in local
    metres of a projected CRS}, as CARTESIAN `pycolmap.PosePrior`s with a diagonal covariance
    of PRIOR_SIGMA_M (horizontal, vertical). Returns the priors written."""
    db = pycolmap.Database.open(database)
    try:
        db.clear_pose_priors()
        h, v = PRIOR_SIGMA_M
        cov = np.diag([h * h, h * h, v * v])
        written = 0
        for image in db.read_all_images():
            if image.name in priors:
                prior = pycolmap.PosePrior(corr_data_id=image.data_id,
                                           position=np.asarray(priors[image.name], np.float64),
                                           position_covariance=cov,
                                           coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN)
                db.write_pose_prior(prior)
                written += 1
    finally:
        db.close()
    return written


def set_options(options, *settings: dict) -> None:
    """Sets each {attribute: value} of settings on a pycolmap options object (in place), later
    dicts over earlier ones."""
    for one in settings:
        for key, value in one.items():
            setattr(options, key, value)


def matching_options(pycolmap, small_photos: bool = False):
    """COLMAP's feature matching options with MATCHING, MATCHING_SIFT (its SIFT part) and, for
    small photos, MATCHING_SMALL on top."""
    matching = pycolmap.FeatureMatchingOptions()
    set_options(matching, MATCHING, MATCHING_SMALL if small_photos else {})
    set_options(matching.sift, MATCHING_SIFT)
    return matching


def two_view_options(pycolmap, small_photos: bool = False):
    """COLMAP's geometric verification options (`TwoViewGeometryOptions`) with TWO_VIEW and, for
    small photos, TWO_VIEW_SMALL on top."""
    verify = pycolmap.TwoViewGeometryOptions()
    set_options(verify, TWO_VIEW, TWO_VIEW_SMALL if small_photos else {})
    return verify


def match_photos(pycolmap, database, matcher: str, names: list[str], work_dir: Path, overlap: int,
                 vocab_tree=None, small_photos: bool = False, neighbours: int = SPATIAL_NEIGHBOURS) -> None:
    """Stage 3: COLMAP's matcher for `matcher` (module docstring) on the database's photos.
    sequential: the pairs of `pairing.sequential_pairs` (next `overlap`, wrap-around, quadratic)
    through `pycolmap.match_image_pairs`; with a space in a name (COLMAP's pair list splits on
    spaces) COLMAP's own sequential matcher with its quadratic overlap instead (no wrap).
    spatial: each photo with its `neighbours` nearest by the database's pose priors (GPS).
    small_photos: MATCHING_SMALL and TWO_VIEW_SMALL on top (every photo at most SMALL_SIDE px)."""
    matching, verify = matching_options(pycolmap, small_photos), two_view_options(pycolmap, small_photos)
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verify)
    elif matcher == "spatial":
        options = pycolmap.SpatialPairingOptions()
        options.max_num_neighbors, options.max_distance = neighbours, SPATIAL_MAX_DISTANCE
        pycolmap.match_spatial(database, matching_options=matching, pairing_options=options,
                               verification_options=verify)
    elif matcher == "sequential" and not any(" " in name for name in names):
        pairs_file = Path(work_dir) / "pairs.txt"
        pairs_file.parent.mkdir(parents=True, exist_ok=True)
        pairs_file.write_text(pairing.pairs_file_text(pairing.sequential_pairs(sorted(names), overlap)))
        options = pycolmap.ImportedPairingOptions()
        options.match_list_path = str(pairs_file)
        pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=options,
                                   verification_options=verify)
    elif matcher == "sequential":
        options = pycolmap.SequentialPairingOptions()
        options.overlap, options.quadratic_overlap, options.loop_detection = overlap, True, False
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=options,
                                  verification_options=verify)
    else:
        options = pycolmap.VocabTreePairingOptions()
        options.vocab_tree_path = str(vocab_tree)
        pycolmap.match_vocabtree(database, matching_options=matching, pairing_options=options,
                                 verification_options=verify)


def register_left_out(pycolmap, database, photo_dir, model, total: int, work_dir: Path, show: bool,
                      priors: bool = False):
    """The photos a model left out, registered into it with the relaxed thresholds and LEFT_OUT
    (fewer inliers, more tries, two-view tracks kept), the model's cameras as the start
    (COLMAP's incremental mapper continuing an existing model, `input_path`). Returns the
    extended model, or None."""
    start, out = work_dir / "start", work_dir / "sparse"
    start.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    model.write(start)
    return _map(pycolmap, database, photo_dir, out, total, True, "registering the photos left out", show,
                priors=priors, start_from=start, extra=LEFT_OUT, triangulation=LEFT_OUT_TRIANGULATION,
                single_model=SINGLE_MODEL)


def _registered_count(model) -> int:
    return model.num_reg_images()


def vetted_count(model) -> int:
    """The number of a model's registered photos that pass the vetting (`data.vetting`)."""
    return sum(row["kept"] for row in vetting.vet(vetting.records_from_pycolmap(model)))


def choose_model(default, relaxed, show: bool = False, count=_registered_count, positions: dict | None = None):
    """The default mapping's model or the relaxed one's (either may be None).

    `count(model)`: the photos a model is worth (its registered photos, or those that pass the
    vetting: relaxed thresholds may add photos only when they pass it).
    The relaxed model is kept when it counts more photos and either the default model is
    too small to judge it (fewer than MIN_COMPARED photos) or it agrees with the default model
    on the photos both hold (`poses_agree`) and, with `positions` ({name: [3]} GPS, local metres),
    fits them about as well (`fits_gps_as_well`): relaxed thresholds can also register photos
    wrongly, e.g. across the look-alike faces of a lattice tower.
    """
    if relaxed is None or (default is not None and count(relaxed) <= count(default)):
        return default
    if default is None or default.num_reg_images() < MIN_COMPARED:
        return relaxed
    if poses_agree(model_poses(default), model_poses(relaxed)) and fits_gps_as_well(default, relaxed, positions,
                                                                                    show):
        _say(f"poses: kept the relaxed model ({relaxed.num_reg_images()} photos)", show)
        return relaxed
    _say(f"poses: the relaxed model ({relaxed.num_reg_images()} photos) disagrees with the default one; "
         f"kept the default ({default.num_reg_images()} photos)", show)
    return default


def model_poses(model) -> dict:
    """{photo name: camera-to-world [4, 4] OpenGL} of a pycolmap.Reconstruction's registered photos."""
    return {model.images[i].name: c2w_gl_from_cam_from_world(model.images[i].cam_from_world().matrix())
            for i in model.reg_image_ids()}


def similarity_fit(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity dst ~ s R src + t (Umeyama 1991): `georef.umeyama` with equal
    weights. src, dst: [N, 3], N >= 3. Returns (s, R [3, 3], t [3])."""
    return georef.umeyama(src, dst)


def poses_agree(a: dict, b: dict, *, max_deg: float = AGREE_DEG, max_centre: float = AGREE_CENTRE) -> bool:
    """Whether two sets of poses ({name: c2w [4, 4]}) describe the same cameras up to a
    similarity: on the names both hold (at least 3), after aligning b's centres to a's
    (`similarity_fit`), the median rotation difference is at most `max_deg` and the median
    centre distance at most `max_centre` times the spread of a's centres (their median
    distance to their mean)."""
    common = sorted(set(a) & set(b))
    if len(common) < 3:
        return False
    pa, pb = np.stack([a[k] for k in common]), np.stack([b[k] for k in common])
    scale, rot, t = similarity_fit(pb[:, :3, 3], pa[:, :3, 3])
    spread = float(np.median(np.linalg.norm(pa[:, :3, 3] - pa[:, :3, 3].mean(0), axis=1)))
    centre = np.linalg.norm(scale * pb[:, :3, 3] @ rot.T + t - pa[:, :3, 3], axis=1)
    cos = (np.einsum("nij,nij->n", rot @ pb[:, :3, :3], pa[:, :3, :3]) - 1.0) / 2.0
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return bool(np.median(angle) <= max_deg and np.median(centre) <= max_centre * max(spread, 1e-12))


def mapper_options(pycolmap, relaxed: bool, priors: bool = False, extra: dict | None = None,
                   triangulation: dict | None = None, single_model: bool = False):
    """COLMAP's incremental mapper options: its defaults, or with `relaxed` the thresholds for
    small or texture-poor photos (RELAXED: fewer inliers to start a model and to register a
    photo, a smaller starting triangulation angle); `extra` / `triangulation`: more mapper /
    triangulation options on top; with
    `priors` the database's pose priors (GPS) enter the bundle adjustment
    (`use_prior_position`, a robust loss: a GPS outlier does not bend the model); with
    `single_model` COLMAP stops after its first model (no further models started from the
    photos it left out: `SINGLE_MODEL`)."""
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = 0
    options.multiple_models = not single_model
    set_options(options.mapper, MAPPER, RELAXED if relaxed else {}, extra or {})
    set_options(options.triangulation, triangulation or {})
    if priors:
        options.use_prior_position = True
        options.use_robust_loss_on_prior_position = True
    return options


def _map(pycolmap, database, photo_dir, out_dir, total, relaxed, label, show, *, priors=False, start_from=None,
         extra=None, triangulation=None, watch: MappingWatch | None = None, single_model: bool = False):
    """One incremental mapping run (`pycolmap.incremental_mapping`), from scratch or continuing
    the model in the folder `start_from`. Returns its largest model or None. The progress line
    counts registered photos (`RegisteredCount`), at most `total`. With `watch`, the growing
    model is judged as it grows (`watched_mapping`; GpsStopped stops it)."""
    bar = progress.bar(total=total, desc=f"poses: {label}", unit="photo", enabled=show)
    count = RegisteredCount(bar, total, start=0 if start_from is None else _model_size(pycolmap, start_from))
    kwargs = {} if start_from is None else {"input_path": start_from}
    options = mapper_options(pycolmap, relaxed, priors, extra, triangulation, single_model)
    try:
        if watch is not None and start_from is None:
            models = watched_mapping(pycolmap, database, photo_dir, out_dir, options, count, watch)
        else:
            models = pycolmap.incremental_mapping(database, photo_dir, out_dir, options=options,
                                                  initial_image_pair_callback=count.new_model,
                                                  next_image_callback=count.next_image, **kwargs)
    finally:
        bar.close()
    if not models:
        return None
    return max(models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()))


def watched_mapping(pycolmap, database, photo_dir, out_dir: Path, options, count: RegisteredCount,
                    watch: MappingWatch) -> dict:
    """`pycolmap.incremental_mapping` as COLMAP's pipeline run here (`IncrementalPipeline`), so that
    the model can be read as it grows: after each photo registered (when `watch.due`), the
    placed cameras go to `watch.check`, whose GpsStopped ends the mapping. Each model is
    written to out_dir/<index>, as `incremental_mapping` writes them. Returns {index: model}."""
    options.image_path = str(photo_dir)
    manager = pycolmap.ReconstructionManager()
    db = pycolmap.Database.open(str(database))
    try:
        pipeline = pycolmap.IncrementalPipeline(options, db, manager)

        def next_image():
            count.next_image()
            model = manager.get(manager.size() - 1)
            if watch.due(model.num_reg_images()):
                watch.check(model_poses(model))

        pipeline.add_callback(pycolmap.IncrementalPipelineCallback.INITIAL_IMAGE_PAIR_REG_CALLBACK, count.new_model)
        pipeline.add_callback(pycolmap.IncrementalPipelineCallback.NEXT_IMAGE_REG_CALLBACK, next_image)
        pipeline.run()
    finally:
        db.close()
    models = {}
    for index in range(manager.size()):
        folder = Path(out_dir) / str(index)
        folder.mkdir(parents=True, exist_ok=True)
        models[index] = manager.get(index)
        models[index].write(folder)
    return models


def _model_size(pycolmap, folder) -> int:
    return pycolmap.Reconstruction(folder).num_reg_images()


class RegisteredCount:
    """The mapping's progress in registered photos. COLMAP calls back once for the first two
    photos of each model it starts (`new_model`) and once for each photo registered next
    (`next_image`), in every model it tries, so the calls add up past the photos ("80/57" on a
    57-photo capture); the bar shows the largest model's photos so far, at most `total`.
    `start`: the photos of a model the mapping continues."""

    def __init__(self, bar, total: int, start: int = 0):
        self.bar, self.total, self.current, self.shown = bar, total, start, 0
        self._show(start)

    def new_model(self):
        self.current = 2
        self._show(self.current)

    def next_image(self):
        self.current += 1
        self._show(self.current)

    def _show(self, count: int):
        count = min(count, self.total)
        if count > self.shown:
            self.bar.update(count - self.shown)
            self.shown = count


class _stage:
    """Prints `poses: NAME ...` and `poses: NAME done in 1.2 s` around a block; with `timings`
    (a dict), also stores the block's seconds under `key`."""

    def __init__(self, name: str, show: bool, timings: dict | None = None, key: str | None = None):
        self.name, self.show, self.timings, self.key = name, show, timings, key

    def __enter__(self):
        self.start = time.monotonic()
        _say(f"poses: {self.name} ...", self.show)

    def __exit__(self, kind, value, tb):
        if kind is None:
            seconds = time.monotonic() - self.start
            if self.timings is not None:
                self.timings[self.key] = round(seconds, 1)
            _say(f"poses: {self.name} done in {progress.format_seconds(seconds)}", self.show)
        return False


def c2w_gl_from_cam_from_world(matrix) -> np.ndarray:
    """COLMAP world-to-camera [3, 4] (OpenCV axes) -> camera-to-world [4, 4] (OpenGL axes)."""
    m = np.asarray(matrix, np.float64)
    c2w = np.eye(4)
    c2w[:3, :3] = m[:3, :3].T
    c2w[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return c2w @ np.diag([1.0, -1.0, -1.0, 1.0])


def orient_z_up(pycolmap, model) -> np.ndarray:
    """Rotates a pycolmap.Reconstruction in place so its cameras' up axis is +z. Returns R [3, 3]."""
    c2w = np.stack(list(model_poses(model).values()))
    rot = z_up_turn(c2w)
    model.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(rot), np.zeros(3)))
    return rot


def undistort(pycolmap, model, photo_dir: Path, stage_dir: Path) -> None:
    """Stage 5: undistorted photos in stage_dir/images, the PINHOLE model in stage_dir/sparse/0."""
    raw = stage_dir / "_work" / "model"
    raw.mkdir(parents=True, exist_ok=True)
    model.write(raw)
    out = stage_dir / "_work" / "undistorted"
    pycolmap.undistort_images(out, raw, photo_dir, output_type="COLMAP", jpeg_quality=JPEG_QUALITY)
    os.replace(out / "images", stage_dir / "images")
    (stage_dir / "sparse").mkdir()
    os.replace(out / "sparse", stage_dir / "sparse" / "0")
    crop_to_common_size(pycolmap, stage_dir / "sparse" / "0", stage_dir / "images")


def crop_offsets(sizes: dict) -> tuple[tuple[int, int], dict]:
    """The common size of undistorted photos and each camera's crop.

    sizes: {camera id: (W, H)}. Returns ((W0, H0) = the smallest width and height,
    {camera id: (left, top)}: the columns and rows cut before the kept window, which is
    centred: (W - W0) // 2, (H - H0) // 2).
    """
    w0, h0 = min(w for w, _ in sizes.values()), min(h for _, h in sizes.values())
    return (w0, h0), {cid: ((w - w0) // 2, (h - h0) // 2) for cid, (w, h) in sizes.items()}


def crop_to_common_size(pycolmap, model_dir: Path, images_dir: Path) -> tuple[int, int]:
    """Crops undistorted photos to one size (a dataset has one image size, docs/DATASET.md).

    With one camera per photo, COLMAP's undistortion gives each photo its own size; every photo
    is cut to the smallest width and height, centred (`crop_offsets`), and the model follows:
    the cameras' size and principal point, the observations' pixel positions. Returns (W, H).
    """
    model = pycolmap.Reconstruction(model_dir)
    sizes = {cid: (int(cam.width), int(cam.height)) for cid, cam in model.cameras.items()}
    (w0, h0), offsets = crop_offsets(sizes)
    if all(size == (w0, h0) for size in sizes.values()):
        return w0, h0
    cv2 = io.opencv()
    for cid, cam in model.cameras.items():
        left, top = offsets[cid]
        params = np.array(cam.params, np.float64)
        params[2:4] -= (left, top)  # PINHOLE: fx, fy, cx, cy
        cam.width, cam.height, cam.params = w0, h0, params
    for im in model.images.values():
        left, top = offsets[im.camera_id]
        for point in im.points2D:
            point.xy = point.xy - np.array([left, top], np.float64)
        path = images_dir / im.name
        pixels, _ = io.decode_raw(path, "undistorted photo", cv2.IMREAD_UNCHANGED)
        jpeg = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if path.suffix.lower() in (".jpg", ".jpeg") else []
        ok, buf = cv2.imencode(path.suffix.lower(), pixels[top:top + h0, left:left + w0], jpeg)
        if not ok:
            raise DataError(f"{path}: could not encode the cropped photo")
        io.atomic_write_bytes(path, buf.tobytes())
    model.write(model_dir)
    return w0, h0


# ----------------------------------------------------------------------------------------
# Stages 6-7: the dataset


def write_dataset(stage_dir: Path, summary: dict) -> dict:
    """transforms.json from stage_dir/sparse/0 + images/ (orbit normalisation). Returns its dict."""
    scene = collect_colmap(stage_dir, normalize=False, test_every=8)
    points = np.asarray(scene.meta["points3d"], np.float64)
    c2w, norm = normalize_orbit(scene.c2w, points if len(points) else None)
    scale = norm["scale"]
    frames = []
    for frame, pose in zip(scene.frames, c2w):
        fx, fy, cx, cy = (float(v) for v in frame.intrinsics)
        frames.append({"file_path": f"images/{frame.image_path.name}", "transform_matrix": pose.tolist(),
                       "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
                       "w": int(frame.size[0]), "h": int(frame.size[1])})
    width, height = scene.frames[0].size
    top = transforms_top(width, height, scene.near * scale, scene.far * scale, norm, {}, stage_dir, stage_dir)
    points_norm = apply_normalization_to_points(points, norm)
    depths = observation_depths(c2w, points_norm, scene.meta["observed"]) if len(points) else None
    top["scene_bounds"] = scene_bounds(c2w, points_norm if len(points) else None, scene.near * scale, depths)
    top["poses"] = {key: value for key, value in summary.items() if key != "georeference"}
    top["georeference"] = scene_georeference(summary.get("georeference") or {"units": "unknown"}, norm)
    top["frames"] = frames
    io.write_json(stage_dir / "transforms.json", top)
    draw_topview(stage_dir / TOPVIEW, c2w, points_norm)
    lines = report_lines(summary, top["scene_bounds"]) + georef_report_lines(top["georeference"])
    io.atomic_write_bytes(stage_dir / REPORT, "\n".join(lines).encode("utf-8"))
    return top


def scene_georeference(record: dict, norm: dict) -> dict:
    """transforms.json's `georeference`: `georef.align_model`'s record plus, when in metres,
    `metres_per_scene_unit` (1 / scene_normalization.scale: sparse/0 and the normalisation's
    metric frame are the local frame, metres) and `scene_to_crs` [4, 4] (normalised scene ->
    projected CRS: x_crs = x_norm / scale - translation + origin)."""
    out = dict(record)
    if record.get("units") == "metres":
        scale, translation = float(norm["scale"]), np.asarray(norm["translation"], np.float64)
        matrix = np.eye(4)
        matrix[:3, :3] /= scale
        matrix[:3, 3] = np.asarray(record["origin"], np.float64) - translation
        out.update({"metres_per_scene_unit": 1.0 / scale, "scene_to_crs": matrix.tolist()})
    return out


def georef_report_lines(geo: dict) -> list[str]:
    """poses_report.md's section on metric scale and georeference (docs/GEOREFERENCE.md)."""
    lines = ["## Scale and georeference (docs/GEOREFERENCE.md)", ""]
    if geo.get("units") != "metres" and geo.get("gps_ignored"):
        return lines + [f"Units unknown: {geo['gps_ignored']}; the model is in arbitrary units.", ""]
    if geo.get("units") != "metres":
        return lines + ["Units unknown: no GPS read from the photos, no ground control points, no scale bar; "
                        "the model is in arbitrary units.", ""]
    lines += [f"- source: {geo['source']}; units: metres; CRS: {geo.get('crs') or 'none (scale only)'}"
              + (f" ({geo['crs_name']})" if geo.get("crs_name") else ""),
              f"- metres per normalised scene unit: {geo['metres_per_scene_unit']:.4g}; "
              f"local origin in the CRS: {', '.join(f'{v:.1f}' for v in geo['origin'])}"]
    if "gps" in geo:
        g = geo["gps"]
        lines.append(f"- GPS: {g['photos']} of {g['registered']} registered photos, {g['inliers']} inliers; "
                     f"residual RMS {g['rms_m']} m (horizontal {g['rms_horizontal_m']} m); "
                     f"heights from {geo.get('height_from')}")
    for label in ("control", "check"):
        group = (geo.get("gcp") or {}).get(label)
        if group:
            lines.append(f"- {label} points: RMS {group['rms_m']} m; "
                         + ", ".join(f"{r['name']} {r['error']:.3f} m (dz {r['dz']:+.3f})" for r in group["residuals"]))
    if "scale_bar" in geo:
        lines.append(f"- scale bar: {geo['scale_bar']['metres']} m over {geo['scale_bar']['model_length']:.4g} "
                     "model units")
    if georef.suspect(geo):
        lines.append("- **check the reconstruction**: the residuals exceed what GPS (about 3 m) or ground control "
                     "points (centimetres) explain; a photo registered in the wrong place bends the model "
                     "(docs/GEOREFERENCE.md)")
    return lines + [""]


def report_lines(summary: dict, bounds: dict | None) -> list[str]:
    """DATA_DIR/poses_report.md: the summary, the vetting table (every registered photo, the
    left-out ones with their reasons) and the scene bounds (docs/POSES.md, docs/BOUNDS.md; none
    when `bounds` is None)."""
    vet = summary.get("vetting") or {}
    lines = ["# Camera poses", "", *format_summary(summary).splitlines(), "",
             "## Vetting (docs/POSES.md)", ""]
    if vet.get("keep_all"):
        lines += ["`--keep-all`: every registered photo kept, whatever its scores.", ""]
    lines += vetting.format_table(vet.get("photos", []))
    if bounds is None:
        return lines + [""]
    lines += ["", "## Scene bounds (docs/BOUNDS.md)", "", "| bound | value (normalised units) |", "|---|---|"]
    for key in ("near", "far", "contract_radius", "roi_radius", "nearest_camera_to_roi"):
        lines.append(f"| {key} | {bounds[key]:.4g} |")
    lines.append(f"| roi_centre | {', '.join(f'{v:.3g}' for v in bounds['roi_centre'])} |")
    return lines + [""]


def draw_topview(path, c2w: np.ndarray, points: np.ndarray, size: int = 640) -> None:
    """A PNG of the scene seen from +z: the unit circle, sparse points (grey), camera centres
    (red) with their viewing directions. c2w: [N, 4, 4] normalised, z-up; points: [P, 3]."""
    cv2 = io.opencv()
    centres = c2w[:, :3, 3]
    extent = max(1.2, 1.1 * float(np.abs(centres[:, :2]).max()) if len(centres) else 1.2)
    img = np.full((size, size, 3), 255, np.uint8)

    def pix(xy):
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        pixels = np.stack([(xy[:, 0] / extent + 1) * size / 2, (1 - xy[:, 1] / extent) * size / 2], -1)
        return pixels.round().astype(int)

    cv2.circle(img, tuple(pix([0.0, 0.0])[0]), int(round(size / 2 / extent)), (200, 200, 200), 1, cv2.LINE_AA)
    inside = points[np.all(np.abs(points[:, :2]) < extent, axis=1)] if len(points) else points
    for u, v in pix(inside[:, :2]) if len(inside) else []:
        img[max(v, 0):v + 2, max(u, 0):u + 2] = (120, 120, 120)
    for m, (u, v) in zip(c2w, pix(centres[:, :2])):
        look = -m[:3, 2][:2]
        tip = pix(m[:2, 3] + 0.08 * extent * look / max(np.linalg.norm(look), 1e-9))[0]
        cv2.line(img, (int(u), int(v)), (int(tip[0]), int(tip[1])), (0, 0, 200), 1, cv2.LINE_AA)
        cv2.circle(img, (int(u), int(v)), 3, (0, 0, 220), -1, cv2.LINE_AA)
    cv2.putText(img, "top view (+z up): cameras red, points grey, unit circle", (8, 18),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    io.write_png(path, img[..., ::-1].astype(np.float32) / 255.0)


def format_summary(summary: dict) -> str:
    """The end-of-run summary as a few lines of text."""
    lines = [f"registered {summary['registered']}/{summary['photos']} photos, "
             f"{summary['points3d']} 3-D points, mean reprojection error {summary['mean_reprojection_error']:.3f} px"]
    if "matcher_reason" in summary:
        pairing = (f", each photo with its {summary['neighbours']} nearest by GPS" if summary.get("neighbours")
                   else f", each photo with its next {summary['overlap']}" if summary.get("overlap") else "")
        lines.append(f"matcher: {summary['matcher']} ({summary['matcher_reason']}{pairing})")
    if "camera_sharing" in summary:
        shared = "one shared by every photo" if summary["single_camera"] else "one per photo"
        lines.append(f"cameras: {shared} ({summary['camera_sharing']})")
    if summary.get("timings_s"):
        lines.append(f"time: {summary['seconds']:.0f} s in all; "
                     + ", ".join(f"{key} {value:.0f} s" for key, value in summary["timings_s"].items()))
    if summary["unregistered"]:
        why = summary.get("unregistered_why") or {}
        lines.append(f"not registered ({len(summary['unregistered'])}): "
                     + ", ".join(f"{name} ({why[name]})" if name in why else name for name in summary["unregistered"]))
    if summary.get("registered_left_out"):
        lines.append("the photos the first model left out were tried again (relaxed thresholds, continuing the model)")
    if summary.get("registered_structure_less"):
        lines.append(f"placed from their 2-D matches alone ({len(summary['registered_structure_less'])}; too few of "
                     "their features on the model's 3-D points to register, COLMAP's structure-less resectioning): "
                     + ", ".join(summary["registered_structure_less"]))
    cameras = summary.get("camera_set")
    if cameras:
        where = "the photos' GPS" if cameras["arc_from"] == "gps" else "the registered cameras"
        lines.append(f"cameras kept for training: {cameras['kept']} of {cameras['photos']} photos, covering "
                     f"{cameras['arc_kept_deg']:.0f} of the {cameras['arc_flight_deg']:.0f} degrees around the scene "
                     f"centre that {where} cover"
                     + (f"; {cameras['verdict']}" + (", written anyway as asked" if cameras.get("accepted") else "")
                        if cameras.get("verdict") else ""))
    if summary.get("reconstruction_reused"):
        lines.append("features, matching and mapping: taken from the refused run's reconstruction (the same photos "
                     "and options)")
    if summary.get("gps_priors"):
        lines.append(f"GPS as pose priors in the bundle adjustment: {summary['gps_priors']} photos")
    elif summary.get("gps_priors_skipped"):
        lines.append(f"GPS as pose priors: not in the mapping ({summary['gps_priors_skipped']})")
    judged = summary.get("gps_disagreed")
    if judged:
        early = judged.get("stopped_early")
        lines.append(f"the GPS disagreed with the reconstruction {'as it grew ' if early else ''}({judged['far']} of "
                     f"{judged['registered']} {'photos placed' if early else 'registered photos'} over "
                     f"{georef.INLIER_METRES:.0f} m from their fixes): "
                     + ("the mapping with the GPS priors stopped there, " if early else "")
                     + ("mapped again without the GPS priors, " if judged["remapped"] else "")
                     + (f"then {judged['far_after']} over; " if judged["remapped"] else "")
                     + ("scale and georeference without the GPS" if judged["georeference"] != "GPS"
                        else "scale and georeference from the GPS"))
    vet = summary.get("vetting") or {}
    if vet.get("left_out"):
        why = {row["name"]: "; ".join(row["reasons"]) for row in vet.get("photos", [])}
        lines.append(f"left out by the vetting ({len(vet['left_out'])}; table in {REPORT}, --keep-all keeps them): "
                     + ", ".join(f"{name} ({why.get(name, '?')})" for name in vet["left_out"]))
    if summary["skipped"]:
        lines.append(f"unreadable, skipped ({len(summary['skipped'])}): {', '.join(summary['skipped'])}")
    geo = summary.get("georeference") or {}
    if geo.get("units") == "metres":
        gps_line = f", GPS residual RMS {geo['gps']['rms_m']} m" if "gps" in geo else ""
        lines.append(f"scale and georeference from {geo['source']}: {geo.get('crs') or 'no CRS'}, "
                     f"{geo['metres_per_model_unit']:.4g} m per model unit{gps_line}"
                     + ("; residuals too large: check the reconstruction (poses_report.md)" if georef.suspect(geo)
                        else ""))
    elif geo.get("gps_ignored"):
        lines.append(f"units unknown: {geo['gps_ignored']}")
    elif "georeference" in summary:
        lines.append("units unknown (no GPS read from the photos, no ground control points, no scale bar)")
    if summary.get("relaxed_mapping"):
        lines.append("registered with relaxed mapper thresholds: check the cameras in "
                     f"{TOPVIEW} (a ring around the tower) before training (docs/POSES.md)")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------
# The whole step


def photo_headers(images_dir: Path, names: list[str], ignore_gps: bool = False) -> tuple[
        dict[str, tuple], dict[str, dict], dict[str, tuple[int, int]]]:
    """What the poses step reads from the photos `names` in `images_dir` beyond their pixels, each
    photo opened once (`photo_exif.read_exif`): ({name: `camera_sharing.camera_of`}, {name:
    `gps.gps_of`} of those with a GPS position ({} when `ignore_gps`: the GPS is not read), {name:
    upright (width, height) of the photo itself, `photo_exif.upright_of`}). DataError naming the
    first photo that cannot be read."""
    records = photo_exif.read_all([Path(images_dir) / name for name in names], gps=not ignore_gps)
    positions = {} if ignore_gps else gps.positions_of(records.items())
    sizes = {name: photo_exif.upright_of(record) for name, record in records.items()}
    return camera_sharing.cameras_of(records), positions, sizes


def poses_from_images(images_dir, out_dir, *, matcher: str = "auto", camera_model: str = "SIMPLE_RADIAL",
                      single_camera: bool | None = None, max_side: int | None = None, vocab_tree=None,
                      overlap: int = SEQUENTIAL_OVERLAP,
                      overwrite: bool = False, progress: bool = True, keep_all: bool = False, crs: str | None = None,
                      gcp=None, scale_bar: str | None = None, ignore_gps: bool = False,
                      accept_few_cameras: bool = False, feature_side: int = FEATURE_SIDE,
                      neighbours: int = SPATIAL_NEIGHBOURS) -> dict:
    """Camera poses for a folder of photos, written as a dataset in `out_dir` (module docstring).

    Returns the summary: photos, registered, in_dataset (registered less those left out),
    unregistered (names),
    vetting ({"keep_all", "left_out": names, "photos": a row per registered photo, `data.vetting.vet`;
    photos that fail are left out of the dataset unless `keep_all`}), skipped (names of unreadable
    files), mean_reprojection_error (px), points3d, matcher (the one that ran: `matcher`, or
    `choose_matcher`'s pick for auto), matcher_asked, matcher_reason, overlap (sequential:
    each photo matched with its next `overlap`; else None), neighbours (spatial: each photo
    matched with its `neighbours` nearest by GPS; else None), camera_model, relaxed_mapping
    (the model came from the relaxed second mapping), seconds, timings_s ({stage: seconds}:
    photos, features, matching, mapping, writing), up_rotation ([3, 3] applied to
    COLMAP's frame), georeference (`georef.align_model`'s record: the photos' GPS, `gcp` (a
    ground control point file) and `crs` (EPSG:XXXX, else the GPS's UTM zone) align the model to
    metres in a projected CRS; without GPS, `scale_bar` scales it; else units stay unknown,
    docs/GEOREFERENCE.md; `ignore_gps`: the photos' GPS is not read), feature_side (SIFT's
    largest side, FEATURE_SIDE; 0: COLMAP's own), reconstruction_reused (COLMAP's model taken from
    a refused run of the same photos and options, `refused.load`), transforms (path).
    DataError (one line, naming the path) for bad input; nothing is written then.
    """
    start = time.monotonic()
    check_options(matcher, camera_model, vocab_tree, overlap, neighbours)
    if max_side is not None and max_side < 16:
        raise DataError(f"poses.max_side must be at least 16 pixels, got {max_side}")
    if feature_side != 0 and feature_side < 16:
        raise DataError(f"poses.feature_side must be 0 (COLMAP's own) or at least 16 pixels, got {feature_side}")
    images_dir, out = Path(images_dir), Path(out_dir)
    photos = list_photos(images_dir)
    if scale_bar is not None:
        georef.parse_scale_bar(scale_bar)
    if crs is not None:
        georef.projected_crs(crs)
    if gcp is not None and not Path(gcp).is_file():
        raise DataError(f"{gcp}: ground control point file not found")
    if _inside(images_dir, out):
        raise DataError(f"{out}: the output folder holds the input photos ({images_dir}); choose another poses.out")
    recover(out)  # a swap a kill interrupted is finished first; a killed run's staging copy removed
    check_out(out, overwrite)
    pycolmap = import_pycolmap()
    pycolmap.logging.minloglevel = 3  # COLMAP's own log: fatal only; progress and errors are ours
    out.parent.mkdir(parents=True, exist_ok=True)
    stage_dir = make_stage(out)
    try:
        timings: dict[str, float] = {}
        with _stage("photos", False, timings, "photos"):
            photo_dir, names, skipped, working_sizes = prepare_photos(photos, stage_dir / "_work" / "photos",
                                                                      max_side, progress)
        used_sizes = {n: working_sizes[n] for n in names}
        check_one_size(used_sizes, images_dir, single_camera)
        cameras, positions, sizes = photo_headers(images_dir, names, ignore_gps)
        single_camera, camera_reason = camera_sharing.choose_sharing(single_camera, used_sizes, cameras)
        used, reason = choose_matcher(matcher, names, with_gps=len(positions))
        if used == "spatial" and len(positions) < len(names):
            raise DataError(f"{images_dir}: poses.matcher spatial pairs photos by their GPS, and only "
                            f"{len(positions)} of {len(names)} photos carry GPS; use exhaustive or sequential")
        ratios = {name: tuple(w1 / w0 for w1, w0 in zip(working_size(*size, max_side), size))
                  for name, size in sizes.items()}
        if gcp is not None:
            georef.read_gcp_csv(gcp, sizes)
        if positions:
            georef.precheck_gps(positions, crs, len(names), images_dir)
        priors, priors_origin = gps_local_positions(positions, crs)
        key = refused.run_key([images_dir / n for n in names], {
            "matcher": used, "camera_model": camera_model, "single_camera": single_camera, "max_side": max_side,
            "vocab_tree": str(vocab_tree), "overlap": overlap, "neighbours": neighbours, "keep_all": keep_all,
            "priors": priors,
            "feature_side": feature_side, "pycolmap": str(getattr(pycolmap, "__version__", "")),
            "code": colmap_settings()})
        database, raw_model = stage_dir / "_work" / "database.db", stage_dir / "_work" / "model"
        reused = refused.load(pycolmap, out, key)
        # GPS that disagrees stops the mapping with the priors as the model grows (not with keep_all,
        # which keeps every photo whatever its GPS)
        small_photos = max(max(working_sizes[n]) for n in names) <= SMALL_SIDE
        priors_in_mapping = priors_hold(priors, small_photos)
        watch = MappingWatch(priors) if priors_in_mapping and not keep_all else None
        if reused is None:
            model, relaxed, extended, from_2d = run_colmap(
                pycolmap, photo_dir, names, stage_dir / "_work", matcher=used, camera_model=camera_model,
                single_camera=single_camera, vocab_tree=vocab_tree, show=progress, source=images_dir,
                keep_all=keep_all, overlap=overlap, timings=timings, priors=priors,
                small_photos=small_photos, feature_side=feature_side,
                watch=watch, neighbours=neighbours)
        else:
            model, record, database = reused
            relaxed, extended = bool(record["relaxed"]), bool(record["extended"])
            from_2d = list(record.get("structure_less", []))
            _say(f"poses: features, matching and mapping taken from the refused run in {refused.folder_of(out)} "
                 "(the same photos and options)", progress)
        stopped = None if watch is None else watch.stopped   # None too for a reused run: nothing was mapped
        without_gps = stopped is not None or (reused is not None and bool(reused[1].get("without_gps")))
        raw_model.mkdir(parents=True, exist_ok=True)
        model.write(raw_model)  # as COLMAP returned it: what a refused run keeps
        align_options = {"crs_name": crs, "gcp_path": gcp, "scale_bar": scale_bar, "sizes": sizes, "ratios": ratios,
                         "source": images_dir}
        placed = vet_and_place(pycolmap, raw_model, names, keep_all, positions, align_options, priors)
        disagreed = None if keep_all else gps_disagrees(placed["off"], len(placed["registered"]))
        gps_judged: dict[str, Any] | None = None
        if stopped is not None:  # judged on the growing model: far of the photos placed when it stopped
            gps_judged = {"far": stopped["far"], "registered": stopped["placed"], "stopped_early": True,
                          "remapped": True, "far_after": placed["off"], "georeference": "GPS"}
        if disagreed is not None:
            gps_judged = gps_judged or {"far": placed["off"], "registered": len(placed["registered"]),
                                        "stopped_early": False, "remapped": False, "georeference": "GPS"}
            if priors_in_mapping and not without_gps:
                _say(f"poses: {disagreed}; mapping again without it", progress)
                again = map_photos(pycolmap, database, photo_dir, len(names), stage_dir / "_work" / "without_gps",
                                   priors=False, keep_all=keep_all, show=progress, timings=timings,
                                   key="mapping_without_gps", label="mapping without the GPS",
                                   small_photos=small_photos)
                if again[0] is not None:
                    (model, relaxed, extended, from_2d), without_gps = again, True
                    shutil.rmtree(raw_model)
                    raw_model.mkdir()
                    model.write(raw_model)
                    placed = vet_and_place(pycolmap, raw_model, names, keep_all, positions, align_options, priors)
            still = gps_disagrees(placed["off"], len(placed["registered"]))
            gps_judged.update(remapped=without_gps, far_after=placed["off"])
            if still is not None and crs is not None and gcp is None:
                raise DataError(f"{images_dir}: poses.crs = {crs}: {still}; ground control points (poses.gcp) place "
                                "the model in the CRS without it")
            if still is not None:  # the receiver is wrong: the model keeps its photos, not the GPS's frame
                placed = vet_and_place(pycolmap, raw_model, names, keep_all, {}, align_options)
                placed["georeference"]["gps_ignored"] = still
                gps_judged["georeference"] = "without the GPS"
        model, registered, rows, left_out = placed["model"], placed["registered"], placed["rows"], placed["left_out"]
        unregistered, registered_centres, far = placed["unregistered"], placed["centres"], placed["far"]
        georeference, kept = placed["georeference"], len(registered) - len(left_out)
        writing = time.monotonic()
        with _stage("undistortion to PINHOLE, orientation, transforms.json", progress):
            if far:  # a camera far from its GPS fix was registered in the wrong place: vetted out too
                leave_out(model, [name for name, _ in far])
                mark_left_out(rows, far)
                left_out += [name for name, _ in far]
                kept -= len(far)
            cameras = camera_set_of(model, len(names), registered_centres, priors, priors_origin, georeference)
            verdict = camera_set.camera_set_verdict(cameras)
            summary = {"photos": len(photos), "registered": len(registered), "in_dataset": kept,
                       "unregistered": unregistered,
                       "vetting": {"keep_all": bool(keep_all), "left_out": left_out, "photos": rows},
                       "skipped": sorted(skipped), "points3d": int(model.num_points3D()),
                       "mean_reprojection_error": float(model.compute_mean_reprojection_error()),
                       "matcher": used, "matcher_asked": matcher, "matcher_reason": reason,
                       "overlap": overlap if used == "sequential" else None,
                       "neighbours": neighbours if used == "spatial" else None,
                       "camera_model": camera_model, "single_camera": bool(single_camera),
                       "camera_sharing": camera_reason,
                       "max_side": max_side, "feature_side": feature_side, "relaxed_mapping": bool(relaxed),
                       "up_rotation": placed["up_rotation"].tolist(),
                       "registered_left_out": bool(extended),
                       "registered_structure_less": [name for name in from_2d if name in registered],
                       "unregistered_why": unregistered_reasons(pycolmap, database, unregistered, registered),
                       "gps_disagreed": gps_judged,
                       "gps_priors": len(priors) if priors_in_mapping and not without_gps else 0,
                       "gps_priors_skipped": priors_skipped(priors, small_photos),
                       "camera_set": dict(cameras, verdict=verdict, accepted=bool(accept_few_cameras)),
                       "pycolmap": str(getattr(pycolmap, "__version__", "unknown")),
                       "reconstruction_reused": reused is not None,
                       "georeference": georeference}
            if verdict is not None and not accept_few_cameras:
                summary.update(seconds=round(time.monotonic() - start, 1), timings_s=dict(timings))
                kept_in = keep_refused(out, key, raw_model, database, summary, model, relaxed, extended, from_2d,
                                       timings if reused is None else reused[1]["timings_s"], without_gps)
                raise DataError(f"{images_dir}: {verdict}; not written (a NeRF trained on them renders the rest as "
                                f"a ghost); which photos and why: {kept_in / REPORT}; "
                                "accept_few_cameras=True writes it anyway, reusing this run's reconstruction "
                                "(docs/POSES.md)")
            undistort(pycolmap, model, photo_dir, stage_dir)
            shutil.rmtree(stage_dir / "_work")
            summary["seconds"] = round(time.monotonic() - start, 1)
            timings["writing"] = round(time.monotonic() - writing, 1)  # less the transforms.json write
            summary["timings_s"] = timings
            write_dataset(stage_dir, summary)
            (stage_dir / MARKER).write_text("written by jaxnerf-grid poses; --overwrite replaces its outputs\n")
        move_into_place(stage_dir, out)
        refused.discard(out)
    except BaseException:
        if not (stage_dir / COMPLETE).is_file():  # committed: `recover` finishes the swap, never undoes it
            shutil.rmtree(stage_dir, ignore_errors=True)
        raise
    summary["transforms"] = str(out / "transforms.json")
    return summary


def colmap_settings() -> dict:
    """The settings this module hands COLMAP on top of its defaults (part of a run's key,
    `refused.run_key`: a reconstruction kept under other settings is not reused)."""
    return {"sift": SIFT, "sift_small": SIFT_SMALL, "small_side": SMALL_SIDE, "matching": MATCHING,
            "matching_sift": MATCHING_SIFT, "two_view": TWO_VIEW, "matching_small": MATCHING_SMALL,
            "two_view_small": TWO_VIEW_SMALL, "mapper": MAPPER, "relax_below": RELAX_BELOW,
            "relax_below_large": RELAX_BELOW_LARGE, "relaxed": RELAXED,
            "left_out": LEFT_OUT, "left_out_triangulation": LEFT_OUT_TRIANGULATION, "prior_sigma_m": PRIOR_SIGMA_M,
            "prior_min_spread_m": PRIOR_MIN_SPREAD_M, "priors_small_only": PRIORS_SMALL_ONLY,
            "structure_less_min_correspondences": structure_less.MIN_CORRESPONDENCES,
            "grown_gps": (GROWN_GPS_RATIO, GROWN_GPS_FLOOR_M), "single_model": SINGLE_MODEL,
            "left_out_steps": ("structure_less", "continued")}


def keep_refused(out: Path, key: str, raw_model: Path, database: Path, summary: dict, model, relaxed: bool,
                 extended: bool, from_2d: list[str], colmap_timings: dict, without_gps: bool = False) -> Path:
    """`refused.keep` of a run whose camera set was refused: the model as COLMAP returned it
    (raw_model), the database, poses_report.md (the summary and vetting table, no scene bounds)
    and the top view of the kept cameras. extended: whether photos were registered after the first
    model; from_2d: the photos placed structure-less. colmap_timings: the seconds of COLMAP's stages, kept
    for the run that reuses them; without_gps: the model was mapped again without the GPS priors
    (`gps_disagrees`), so the run that reuses it does not do so again. Returns the folder."""
    c2w = np.stack(list(model_poses(model).values()))
    points = np.array([p.xyz for p in model.points3D.values()], np.float64).reshape(-1, 3)
    c2w_norm, norm = normalize_orbit(c2w, points if len(points) else None)
    points_norm = apply_normalization_to_points(points, norm) if len(points) else points
    verdict = (summary.get("camera_set") or {}).get("verdict")
    report = "\n".join([f"**Refused: {verdict}.** Not written; `poses` with accept_few_cameras=True on the same photos "
                        "and options writes it from this reconstruction (docs/POSES.md).", "",
                        *report_lines(summary, None)])
    return refused.keep(out, key, raw_model, database,
                        {"relaxed": relaxed, "extended": extended, "structure_less": list(from_2d),
                         "timings_s": colmap_timings,
                         "without_gps": bool(without_gps)}, report,
                        lambda path: draw_topview(path, c2w_norm, points_norm))


def gps_local_positions(positions: dict, crs_name: str | None) -> tuple[dict, np.ndarray | None]:
    """The photos' GPS as positions in local metres of a projected CRS (`crs_name`, else the
    GPS's UTM zone; heights as `georef.gps_heights` reads them), for the pose priors. Returns
    ({name: [3]}, the local origin in the CRS [3]); ({}, None) without GPS."""
    if not positions:
        return {}, None
    names = sorted(positions)
    records = [positions[n] for n in names]
    lat = np.asarray([r["latitude"] for r in records])
    lon = np.asarray([r["longitude"] for r in records])
    heights, _ = georef.gps_heights(records)
    crs = georef.projected_crs(crs_name, float(np.median(lat)), float(np.median(lon)))
    xyz = georef.geodetic_to_projected(crs, lat, lon, heights)
    origin = georef.local_origin(xyz)
    return {n: (p - origin) for n, p in zip(names, xyz)}, origin


def vet_and_place(pycolmap, model_dir: Path, names: list[str], keep_all: bool, positions: dict,
                  align_options: dict, fixes: dict | None = None) -> dict:
    """The model COLMAP returned (read from `model_dir`, pycolmap's model folder) vetted
    (`vetting.vet`; the photos that fail left out unless `keep_all`), turned z-up (`orient_z_up`)
    and aligned (`georef.align_model` with the photos' GPS `positions` and `align_options`);
    fixes: {name: [3]} the GPS positions in local metres, for `gps_outliers`.
    DataError (naming align_options["source"]) when fewer than `enough_registered` photos pass.
    Returns {"model", "registered" (names, before the vetting), "unregistered", "rows" (the
    vetting's), "left_out", "centres" [R, 3] (the registered cameras, in the aligned frame),
    "up_rotation" [3, 3], "georeference", "far" (`gps_outliers`, [] with keep_all), "off"
    (`gps_off_count`)}."""
    model = pycolmap.Reconstruction(str(model_dir))
    registered = sorted(model.images[i].name for i in model.reg_image_ids())
    unregistered = sorted(set(names) - set(registered))
    rows = vetting.vet(vetting.records_from_pycolmap(model))
    left_out = [] if keep_all else [row["name"] for row in rows if not row["kept"]]
    centres = np.stack([c2w[:3, 3] for c2w in model_poses(model).values()])
    leave_out(model, left_out)
    kept = len(registered) - len(left_out)
    if kept < enough_registered(len(names)):
        missing = unregistered + left_out
        shown = ", ".join(missing[:5]) + (", ..." if len(missing) > 5 else "")
        raise DataError(f"{align_options['source']}: only {kept} of {len(names)} photos registered and passed the "
                        f"vetting (a dataset needs {enough_registered(len(names))}; not registered or left out: "
                        f"{shown}); more overlap and texture between photos help (docs/POSES.md)")
    rot = orient_z_up(pycolmap, model)
    sim, georeference = georef.align_model(model, positions, **align_options)
    centres = centres @ rot.T
    if sim is not None:
        model.transform(pycolmap.Sim3d(sim[0], pycolmap.Rotation3d(sim[1]), sim[2]))
        centres = georef.apply_similarity(sim, centres)
    return {"model": model, "registered": registered, "unregistered": unregistered, "rows": rows,
            "left_out": left_out, "centres": centres, "up_rotation": rot, "georeference": georeference,
            "far": [] if keep_all else gps_outliers(georeference, fixes), "off": gps_off_count(georeference)}


def camera_set_of(model, readable: int, registered_centres: np.ndarray, priors: dict, priors_origin,
                  georeference: dict) -> dict:
    """`camera_set.camera_set_record` of a z-up model (its registered photos less those left
    out): the kept cameras' arc about the point they look at, against the flight's: the
    registered cameras (`registered_centres` [R, 3], in the model's frame, before the vetting)
    and, when the model is in metres from the GPS and the GPS is close enough to tell the
    cameras' places apart (`gps_places_cameras`), the GPS positions of the photos that did not
    register (`priors`, local metres from `priors_origin`)."""
    poses_now = model_poses(model)
    c2w = np.stack(list(poses_now.values()))
    centre = camera_set.look_at_point(c2w)
    arc_kept = camera_set.arc_covered_deg(camera_set.azimuths_deg(c2w[:, :3, 3], centre))
    flight, arc_from = registered_centres, "registered"
    registered = set(poses_now) | {row["name"] for row in (georeference.get("gps") or {}).get("residuals") or []}
    missing = [name for name in priors if name not in registered]
    if missing and gps_places_cameras(georeference, c2w[:, :3, 3], centre):
        shift = np.asarray(priors_origin, np.float64) - np.asarray(georeference["origin"], np.float64)
        flight = np.concatenate([flight, np.stack([np.asarray(priors[n]) + shift for n in missing])])
        arc_from = "gps"
    arc_flight = camera_set.arc_covered_deg(camera_set.azimuths_deg(flight, centre))
    return camera_set.camera_set_record(readable, len(c2w), arc_kept, arc_flight, arc_from)


def gps_places_cameras(georeference: dict, centres: np.ndarray, centre: np.ndarray) -> bool:
    """Whether the photos' GPS tells where around the scene a camera is: the model is in metres
    from the GPS and its GPS residual RMS is under a quarter of the cameras' median horizontal
    distance from the scene centre (a phone's 3-5 m error around a 5 m tree says nothing of
    the side a photo was taken from). centres: [N, 3] local metres; centre: [3]."""
    rms_m = (georeference.get("gps") or {}).get("rms_m")
    if georeference.get("units") != "metres" or rms_m is None:
        return False
    radius = float(np.median(np.linalg.norm(np.asarray(centres)[:, :2] - np.asarray(centre)[:2], axis=1)))
    return rms_m < 0.25 * radius


def unregistered_reasons(pycolmap, database, unregistered: list[str], registered: list[str]) -> dict:
    """Why each unregistered photo stayed out, from the matching database: {name: phrase}
    naming its verified pairs with registered photos and the most inliers of one (a photo
    needs LEFT_OUT's inliers at least to register)."""
    if not unregistered or not Path(database).is_file():
        return {}
    db = pycolmap.Database.open(database)
    try:
        ids = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, geometries = db.read_two_view_geometries()
        links: dict[str, list] = {name: [] for name in unregistered}
        for pair_id, geometry in zip(pair_ids, geometries):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            names = ids.get(a), ids.get(b)
            inliers = int(np.asarray(geometry.inlier_matches).shape[0])
            for one, other in (names, names[::-1]):
                if one in links and other in registered and inliers > 0:
                    links[one].append(inliers)
    finally:
        db.close()
    need = LEFT_OUT["abs_pose_min_num_inliers"]
    out = {}
    for name, found in links.items():
        if not found:
            out[name] = "no verified match with a registered photo"
        else:
            out[name] = (f"{len(found)} verified pair(s) with registered photos, at most {max(found)} inliers "
                         f"(registering needs {need} that fit one pose)")
    return out


GPS_OUTLIER_MEDIANS = 2.5   # a camera further from its fix than this many median residuals (and 9 m) is off


def gps_outlier_metres(errors) -> float:
    """The distance from its GPS fix beyond which a camera was put in the wrong place:
    `georef.INLIER_METRES` (three times a consumer receiver's error), or GPS_OUTLIER_MEDIANS times
    the median of the photos' residuals [N] when that is larger: a receiver noisier than a drone's
    (5 m RMS) spreads right cameras 9-11 m from their fixes, while a misplaced camera lies tens of
    metres off (2.5 medians is about 3.9 sigma of a Gaussian receiver's error)."""
    errors = np.asarray(errors, np.float64)
    if not len(errors):
        return georef.INLIER_METRES
    return max(georef.INLIER_METRES, GPS_OUTLIER_MEDIANS * float(np.median(errors)))


GPS_NEIGHBOURS = 4   # the photos taken next (or nearest by GPS) whose residuals say where the receiver stood


def gps_outliers(georeference: dict, positions: dict | None = None) -> list[tuple[str, str]]:
    """The registered photos whose camera lies further from its GPS position after the alignment
    than `gps_outlier_metres` of the residuals, with the reason in words: [(name, reason)]. A
    consumer receiver errs by 1-5 m; a camera 9 m or more off (more on a noisier receiver) was put
    in the wrong place by the mapping (on a 30-photo orbit one such camera was kept by the vetting
    105 degrees off, and tilted the rest by 10 degrees in the alignment).
    A camera is off only when its residual also differs by more than the limit from the median
    residual of its GPS_NEIGHBOURS neighbours (`local_residuals`; positions: {name: [3]} the fixes
    in local metres, for photos not named in sequence): a receiver that drifts or lags moves the
    fixes of photos taken one after the other alike (seneca: the altitudes of consecutive photos
    7, 9 and 12 m off), a misplaced camera alone."""
    rows = (georeference.get("gps") or {}).get("residuals") or []
    limit = gps_outlier_metres([r["error"] for r in rows])
    local = local_residuals(rows, positions or {})
    return [(r["name"], f"{r['error']:.1f} m from its GPS position (more than {limit:.0f} m)")
            for r in rows if r["error"] > limit and local.get(r["name"], r["error"]) > limit]


def local_residuals(rows: list[dict], positions: dict, neighbours: int = GPS_NEIGHBOURS) -> dict:
    """{name: metres}: each GPS residual (rows of `georef.align_model`'s residuals: name, dx, dy,
    dz) less the component-wise median residual of its `neighbours` neighbours: the photos taken
    just before and after it when the names are numbered in sequence (`names_look_ordered`: the
    capture order), else those whose fixes (`positions`, {name: [3]} local metres) are nearest
    its own. Empty with `neighbours` photos or fewer (or without the fixes it needs)."""
    rows = sorted((r for r in rows if "dx" in r), key=lambda r: r["name"])
    names = [r["name"] for r in rows]
    if names_look_ordered(names):
        rank = np.arange(len(rows), dtype=np.float64)[:, None]
        gap = np.abs(rank - rank.T)
    elif all(name in positions for name in names):
        fixes = np.asarray([positions[name] for name in names], np.float64).reshape(-1, 3)
        gap = np.linalg.norm(fixes[:, None] - fixes[None], axis=-1)
    else:
        return {}
    if len(rows) <= neighbours:
        return {}
    np.fill_diagonal(gap, np.inf)
    nearest = np.argsort(gap, axis=1, kind="stable")[:, :neighbours]
    residual = np.asarray([[r["dx"], r["dy"], r["dz"]] for r in rows], np.float64)
    local = residual - np.median(residual[nearest], axis=1)
    return {name: float(np.linalg.norm(d)) for name, d in zip(names, local)}


def gps_off_count(georeference: dict) -> int:
    """The registered photos over `georef.INLIER_METRES` from their GPS fixes after the alignment
    (the alignment's outliers): half of them or more and the GPS disagrees (`gps_disagrees`)."""
    return sum(not r["inlier"] for r in (georeference.get("gps") or {}).get("residuals") or [])


def mark_left_out(rows: list[dict], far: list[tuple[str, str]]) -> None:
    """Marks the vetting rows of `far` ([(name, reason)]) left out, with the reason (in place)."""
    why = dict(far)
    for row in rows:
        if row["name"] in why:
            row["kept"] = False
            row["reasons"] = list(row["reasons"]) + [why[row["name"]]]


def leave_out(model, names: list[str]) -> None:
    """Deregisters the named photos from a pycolmap.Reconstruction (in place): they are then not
    undistorted nor written, and their observations leave the 3-D points' tracks."""
    for i in list(model.reg_image_ids()):
        if model.images[i].name in names:
            model.deregister_frame(model.images[i].frame_id)


def enough_registered(num_photos: int) -> int:
    """The fewest registered photos that make a dataset: MIN_REGISTERED, and a quarter of the
    photos (MIN_REGISTERED_FRACTION): a small partial model is rarely useful and often wrong
    (on the ttpla-like scene 5 of 30 registered, turned over, docs/POSES.md)."""
    return max(MIN_REGISTERED, int(np.ceil(MIN_REGISTERED_FRACTION * num_photos)))


def _inside(path: Path, folder: Path) -> bool:
    """Whether `path` is `folder` or lies inside it (after resolving links)."""
    return folders.inside(path, folder)


def check_out(out: Path, overwrite: bool) -> None:
    """DataError unless `out` may receive the dataset: absent, an empty folder, or with
    `overwrite` a dataset this command wrote (it holds MARKER; the marker rule of `folders`,
    a symbolic link among its outputs refused)."""
    if out.is_file():
        raise DataError(f"{out}: is a file; poses.out must be a folder")
    folders.check_folder(out, "poses.out")  # this user may write it (or make it), before COLMAP runs
    folders.check_folder(out.parent, "poses.out")  # and the staging folder beside it
    if folders.is_empty(out):
        return
    if not overwrite:
        raise DataError(f"{out}: already exists and is not empty; pass overwrite=True to replace it")
    folders.check_clearable(out, "poses", OUTPUTS + STALE, "poses.out")


# The swap of a finished dataset into an existing DATA_DIR (`move_into_place`) and its recovery
# (`recover`): the staging folder `.NAME.poses-XXXX` beside DATA_DIR gets OWNER (the process
# building it) when made and COMPLETE (the staged names, the commit point) when done; the old
# outputs move to `.NAME.old-XXXX` (same XXXX) while the new ones move in (`staging.swap_in`).
STAGE_TAG, RETIRED_TAG = ".poses-", ".old-"
OWNER, COMPLETE = staging.OWNER, "COMPLETE"


def make_stage(out: Path) -> Path:
    """A new staging folder beside `out`, holding OWNER (this process's host and id)."""
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}{STAGE_TAG}", dir=out.parent))
    staging.write_owner(stage)
    return stage


def _siblings(out: Path, tag: str) -> list[Path]:
    """The hidden folders `.NAME<tag>XXXX` beside `out`."""
    prefix = f".{out.name}{tag}"
    try:
        return sorted(p for p in out.parent.iterdir() if p.name.startswith(prefix) and p.is_dir())
    except OSError:  # no parent folder, or one this user may not list: nothing to recover there
        return []


def _staged_names(stage: Path) -> list[str] | None:
    """The names a staging folder holds for the swap: COMPLETE's list; for a staging folder of an
    older version without COMPLETE, one holding MARKER (written last) counts as complete with
    all of OUTPUTS; None for an incomplete one."""
    names = staging.read_complete(stage, COMPLETE)
    if names is None and not (stage / OWNER).exists() and (stage / MARKER).is_file():
        names = list(OUTPUTS)
    return names


def recover(out) -> str | None:
    """Finishes what a killed `poses` left beside the dataset folder `out`: a complete staging
    folder is swapped in ("rolled forward"), an incomplete one whose process is gone (a kill
    during COLMAP) and retired old outputs are removed ("cleaned"); None when there was nothing.
    A staging folder of a process still running is left alone."""
    out = Path(out)
    result = None
    for stage in _siblings(out, STAGE_TAG):
        staged = _staged_names(stage)
        if staged is None:
            if staging.owner_alive(stage):
                continue
            shutil.rmtree(stage, ignore_errors=True)
            result = result or "cleaned"
            continue
        retired = out.parent / (f".{out.name}{RETIRED_TAG}" + stage.name[len(f".{out.name}{STAGE_TAG}"):])
        _finish_swap(stage, out, retired, staged)
        result = "rolled forward"
    for retired in _siblings(out, RETIRED_TAG):
        shutil.rmtree(retired, ignore_errors=True)
        result = result or "cleaned"
    return result


def _finish_swap(stage: Path, out: Path, retired: Path, staged: list[str]) -> None:
    names = [n for n in OUTPUTS if n != "transforms.json"] + list(STALE)
    out.mkdir(parents=True, exist_ok=True)
    staging.swap_in(out, stage, retired, names, staged, last="transforms.json")


def move_into_place(stage: Path, out: Path) -> None:
    """Moves the finished dataset from `stage` to `out`: the whole folder when `out` does not
    exist (one rename), else entry by entry (OUTPUTS; transforms.json last), the old entries of
    that name and the stale mask outputs (STALE) retired and every other file of `out` kept.
    COMPLETE is written first, so a kill during the swap is finished by `recover`."""
    (stage / OWNER).unlink(missing_ok=True)
    if not out.exists():
        os.replace(stage, out)
        return
    staged = [name for name in OUTPUTS if (stage / name).exists()]
    staging.write_complete(stage, COMPLETE, staged)
    retired = out.parent / (f".{out.name}{RETIRED_TAG}" + stage.name[len(f".{out.name}{STAGE_TAG}"):])
    _finish_swap(stage, out, retired, staged)
