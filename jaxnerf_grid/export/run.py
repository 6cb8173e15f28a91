"""`export_run`: the metric 3D model of a trained run's tower (`jaxnerf-grid export`, docs/EXPORT.md).

Steps, all in the normalised scene until the files are written:

1. render `views` training views (evenly spaced, `clouds.cloud_view_ids`), lift their depth
   (`clouds.lift_view`, inside the unit sphere) and keep the points confirmed by at least
   `min_views` other views (`export.fuse`): the dense cloud;
2. the ground plane: RANSAC on the lowest points of the dense cloud (`export.ground`);
3. the box: `auto` = the largest cluster standing more than the ground's clearance above the
   plane (`ground.tower_box`); or the given box (in the export's units);
4. the density of the main field on a grid over the box (`export.field.density_grid`,
   `export.mesh.grid_spec`: `resolution` voxels along the longest side), marching cubes at the
   density where one voxel is `opacity` opaque (`export.mesh.density_threshold`), components
   under `min_component_fraction` of the faces dropped, vertex colours from the field seen
   from the `colour_cameras` nearest training cameras;
5. the files, in the dataset's original units (`export.to_metric`): tower_mesh.ply,
   tower_points.ply (the dense cloud inside the box) and tower_points.las (the same points, in
   the projected CRS with its WKT when the dataset is georeferenced), tower_mesh_crs.ply (the
   mesh in the CRS, float64, when georeferenced; with `geoid`, the heights of these two and of
   the base centre's CRS coordinates are above the geoid: `export.geoid`), box.json,
   measurements.json (every figure with its uncertainty, the axis' tilt, the base centre, the
   conductors' clearance: `survey`), export_views.png; and the "Tower model" section of the
   run's report.md.

Every check (the output folder, the checkpoint, the box) runs before anything is written.
"""

from __future__ import annotations

import functools
import math
import os
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.export import (
    box_to_metric,
    box_to_scene,
    catenary,
    classes,
    field,
    fuse,
    ground,
    measure,
    plane_to_metric,
    survey,
    to_metric64,
)
from jaxnerf_grid.export import clearance as clearance_lib
from jaxnerf_grid.export import conductors as conductors_lib
from jaxnerf_grid.export import geoid as geoid_lib
from jaxnerf_grid.export import mesh as mesh_lib
from jaxnerf_grid.export import next_tower as next_tower_lib
from jaxnerf_grid.render import clouds
from jaxnerf_grid.render import views as views_lib
from jaxnerf_grid.report import html as report_html
from jaxnerf_grid.report import markdown as report
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import runs
from jaxnerf_grid.util import folders, io
from jaxnerf_grid.util import progress as progress_lib
from jaxnerf_grid.util.io import DataError

DEFAULT_RESOLUTION = mesh_lib.DEFAULT_RESOLUTION  # the defaults live where `jaxnerf-grid export --help` reads
DEFAULT_VIEWS = fuse.DEFAULT_VIEWS              # them without loading JAX (cli/export.py)
DEFAULT_COLOUR_CAMERAS = 3
GROUND_CELL = 0.02          # normalised units: columns of the ground fit, cells of the tower cluster
GROUND_INLIER = 0.025       # normalised units: RANSAC inlier distance
SCENE_LIMIT = 1.0           # the region of interest: the unit sphere's cube [-1, 1]^3 (normalised)
FILES = ("tower_mesh.ply", "tower_points.ply", "tower_points.las", "box.json", "measurements.json",
         "export_views.png", "classified_points.las", "conductors_views.png")
CRS_FILES = ("tower_mesh_crs.ply",)     # written only for a georeferenced dataset
# what overwrite=True may clear in a folder holding export's marker (folders.MARKERS["export"])
OUTPUTS = FILES + CRS_FILES + ("report.md", "report.html")
# bytes per grid node while the mesh is made: the float32 density, marching cubes' working
# copies and masks (a bound, not a measurement of the peak); the grid's node count is taken as
# the cube resolution^3, the largest box of that resolution
GRID_BYTES_PER_NODE = 32


def check_resolution(resolution, available: int | None = None) -> None:
    """ConfigError naming export.resolution when it is not an integer >= 8 or when a cube grid of
    that resolution would not fit in the host's RAM (`available` bytes; default the RAM), with the
    largest resolution that fits."""
    config_lib.check_value("export.resolution", resolution, int, config_lib.Range(8))
    if available is None:
        available = int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    need = (int(resolution) + 1) ** 3 * GRID_BYTES_PER_NODE
    if need > available:
        fits = int((available / GRID_BYTES_PER_NODE) ** (1 / 3)) - 1
        raise ConfigError(f"export.resolution = {resolution}: its grid needs about {need / 2**30:.1f} GiB, more than "
                          f"the {available / 2**30:.1f} GiB of memory here; use at most {fits}")


def check_views(views, min_views) -> None:
    """ConfigError naming the key unless export.views >= 1 and export.min_views >= 0 (integers)."""
    config_lib.check_value("export.views", views, int, config_lib.AT_LEAST_ONE)
    config_lib.check_value("export.min_views", min_views, int, config_lib.NONNEGATIVE)


def _is_legacy_export(out: Path) -> bool:
    """An export folder from before the marker: measurements.json, and only export's files."""
    return (out / "measurements.json").is_file() and all(p.name in OUTPUTS for p in out.iterdir())


def check_out(out: Path, data, overwrite: bool) -> None:
    """The output folder (export.out) may be written: not a file, not the dataset folder or
    inside it; when it holds files, only with `overwrite` and only a folder export wrote (its
    marker, or an older export's files alone), none of its outputs a link (`folders`)."""
    folders.check_folder(out, "export.out")
    folders.check_outside(out, data, "export.out")
    if folders.is_empty(out):
        return
    if not overwrite:
        raise DataError(f"{out}: already exists and is not empty; pass overwrite=True to replace the export there")
    folders.check_clearable(out, "export", OUTPUTS, "export.out", legacy=_is_legacy_export(out))


def parse_box(text) -> np.ndarray | None:
    """box: "auto" (None) or "xmin,ymin,zmin,xmax,ymax,zmax" -> [6] float64. ConfigError for
    a malformed or empty box (any max <= min)."""
    if text is None or (isinstance(text, str) and text.strip().lower() == "auto"):
        return None
    try:
        values = np.asarray([float(v) for v in (text.split(",") if isinstance(text, str) else text)], np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"export.box: expected 'auto' or six numbers xmin,ymin,zmin,xmax,ymax,zmax, "
                          f"got {text!r}") from None
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise ConfigError(f"export.box: expected six finite numbers xmin,ymin,zmin,xmax,ymax,zmax, got {text!r}")
    if np.any(values[3:] <= values[:3]):
        raise ConfigError(f"export.box: the box is empty (each max must exceed its min): {text!r}")
    return values


def units_of(ds) -> str:
    """'metres' or 'unknown': transforms.json's `georeference.units` where the record exists,
    else 'metres' for a stated metric normalisation (the synthetic scenes; `survey.units_of`)."""
    return survey.units_of(ds)


def units_comment(units: str) -> str:
    if units == "metres":
        return ("units: metres (the dataset's scene_normalization undone: x = R^T x_norm / scale - translation, "
                "R the identity without a rotation)")
    return ("units: unknown (the dataset has no metric scale; coordinates are in its original units, "
            "its loader's normalisation undone)")


def check_box_in_scene(lo: np.ndarray, hi: np.ndarray) -> None:
    """ConfigError when the box (normalised) does not meet the region of interest [-1, 1]^3."""
    if np.any(hi <= -SCENE_LIMIT) or np.any(lo >= SCENE_LIMIT):
        raise ConfigError("export.box lies outside the scene: it does not meet the region of interest (the unit "
                          "sphere of the normalised scene, i.e. the tower's surroundings); give it in the "
                          "dataset's original units (metres for the synthetic scenes)")


def _render_cloud(params, cfg, ds, ids, progress: bool):
    """The views' lifted points and cameras for `export.fuse`."""
    near, far = config_lib.near_far(cfg.model, ds)
    parts, cameras = [], []
    for i in progress_lib.bar(ids, desc="export: views", unit="view", enabled=progress):
        view = views_lib.render_view(params, cfg, ds, int(i))
        parts.append(clouds.lift_view(views_lib.camera_rays(ds, int(i), near, far), np.clip(view["rgb"], 0, 1),
                                      view["depth"], view["opacity"], radius=SCENE_LIMIT))
        cameras.append({"c2w": np.asarray(ds.c2w[i]), "intrinsics": np.asarray(ds.intrinsics[i]),
                        "depth": view["depth"], "opacity": view["opacity"]})
    return parts, cameras


def _ground(points: np.ndarray) -> dict | None:
    """The ground plane of the dense cloud (normalised): {"normal", "offset", "clearance",
    "inliers", "candidates", "settled_on", "settled_shift"}, or None when it cannot be fitted.
    The plane of the columns' lowest points (RANSAC), then moved to the median of every point
    within GROUND_INLIER of it (`ground.settle_on_cloud`: settled_on points; settled_shift > 0 up).
    clearance = max(GROUND_CELL, 3 x the robust spread (1.4826 MAD) of the lowest points' heights)."""
    low = ground.lowest_points(points, GROUND_CELL)
    try:
        n, d, inliers = ground.fit_plane_ransac(low, GROUND_INLIER, iterations=1000)
    except ValueError:
        return None
    res = ground.heights(low[inliers], n, d)
    spread = 1.4826 * float(np.median(np.abs(res - np.median(res)))) if len(res) else 0.0
    settled, near = ground.settle_on_cloud(points, n, d, GROUND_INLIER)
    return {"normal": n, "offset": settled, "clearance": max(GROUND_CELL, 3.0 * spread), "inliers": int(inliers.sum()),
            "candidates": int(len(low)), "settled_on": int(near.sum()), "settled_shift": float(d - settled)}


def _inside(points: np.ndarray, lo, hi) -> np.ndarray:
    return np.all((points >= lo) & (points <= hi), axis=-1)


def export_run(run_dir, out=None, resolution: int = DEFAULT_RESOLUTION, box="auto",
               opacity: float = mesh_lib.DEFAULT_OPACITY, views: int = DEFAULT_VIEWS, min_views: int = 2,
               colour_cameras: int = DEFAULT_COLOUR_CAMERAS,
               min_component_fraction: float = mesh_lib.DEFAULT_MIN_COMPONENT_FRACTION,
               overwrite: bool = False, progress: bool = True, dataset=None, allow_other_data: bool = False,
               geoid=None, vertical_crs: str | None = None, min_clearance: float | None = None,
               span_length: float | None = None) -> dict:
    """Exports the tower of a trained run (module docstring). Returns measurements.json's dict.
    A dataset other than the run's (its fingerprint) is refused unless `allow_other_data`.

    out: the folder (default RUN/export; refused when it holds files, unless `overwrite`);
    box: "auto" or "xmin,ymin,zmin,xmax,ymax,zmax" (or 6 numbers) in the export's units.
    geoid: a local geoid grid file PROJ reads (GTX, GeoTIFF): the CRS outputs' heights become
    H = h - N (`export.geoid`); the local-frame files and every relative measurement are unchanged.
    vertical_crs: with geoid, the vertical datum the grid realises ('EPSG:5773'): the LAS header's
    CRS becomes the compound of the horizontal one and it (`export.vertical_crs`).
    min_clearance: spans whose conductor clearance over the ground or the objects beneath is
    below this (export units) are flagged (`export.clearance`); None flags nothing.
    span_length: the distance between the towers (export units): each span's catenary a level span
    of that length (`export.conductors.fit_profile`); None: each side's span measured at the next
    tower where the photos see it (`export.next_tower`), else from the wires' curvature.
    DataError / ConfigError for a run without a checkpoint, an empty box or one outside the
    scene, an occupied folder, a box without a surface, a geoid grid that is missing, unreadable,
    not covering the site or given for a dataset without a CRS; nothing is written then.
    """
    start = time.perf_counter()
    run_dir = Path(run_dir)
    check_span_length(span_length)         # a value alone: refused before the run folder is read
    cfg, data = runs.load_run(run_dir)  # the config first: a bad run folder fails before the dataset loads
    given = parse_box(box)
    check_resolution(resolution)
    check_views(views, min_views)
    if not 0 < float(opacity) < 1:
        raise ConfigError(f"export.opacity (of one voxel) must be in (0, 1), got {opacity}")
    if min_clearance is not None and not (isinstance(min_clearance, (int, float)) and math.isfinite(min_clearance)
                                          and min_clearance > 0):
        raise ConfigError(f"export.min_clearance must be a positive number (export units), got {min_clearance!r}")
    out = Path(out) if out is not None else run_dir / "export"
    check_out(out, data, overwrite)
    grid = geoid_lib.open_grid(geoid) if geoid is not None else None   # a missing file fails before the dataset loads
    datum = geoid_lib.vertical_crs(vertical_crs, geoid)
    ds = runs.dataset_of_run(run_dir, data, dataset, progress, allow_other_data, max_side=cfg.train.max_side)
    norm = ds.normalization
    if given is not None:
        lo_given, hi_given = box_to_scene(given[:3], given[3:], norm)   # all 8 corners (a rotated record)
        check_box_in_scene(lo_given, hi_given)
    units = units_of(ds)
    geo = survey.georeference_of(ds)
    crs_name, crs_origin = survey.crs_of(geo)
    if crs_name is not None:
        survey.pyproj_crs(crs_name)       # a CRS pyproj does not know fails before anything is written
    if grid is not None:
        _check_geoid_site(geoid, grid, crs_name, geo, ds, norm, units)
    params, step = train.load_params(run_dir, cfg, ds)
    scale = float(norm.get("scale", 1.0))

    # 1-2. the dense cloud and the ground
    timings = {"load": time.perf_counter() - start}
    ids = clouds.cloud_view_ids(ds, views)
    parts, cameras = _render_cloud(params, cfg, ds, ids, progress)
    timings["views"] = time.perf_counter() - start - sum(timings.values())
    points, colours, fuse_stats = fuse.fuse(parts, cameras, min_views=min_views)
    plane = _ground(points)

    # 3. the box
    if given is not None:
        lo, hi = lo_given, hi_given
        box_stats: dict = {}
    else:
        if plane is None:
            raise DataError(f"{run_dir}: export.box auto found no ground in the rendered views ({len(points)} "
                            "points inside the unit sphere); give export.box")
        try:
            lo, hi, box_stats = ground.tower_box(points, plane["normal"], plane["offset"], plane["clearance"],
                                                 GROUND_CELL)
        except ValueError as err:
            raise DataError(f"{run_dir}: export.box auto: {err}; give export.box") from None

    # 4. the mesh
    origin, h, shape = mesh_lib.grid_spec(lo, hi, int(resolution))
    level = mesh_lib.density_threshold(h, float(opacity))
    with progress_lib.bar(total=int(np.prod(shape)), desc="export: density", unit="point", enabled=progress) as pbar:
        density = field.density_grid(params, cfg.model, origin, h, shape, progress=pbar)
    timings["density"] = time.perf_counter() - start - sum(timings.values())
    verts, faces, normals = mesh_lib.extract_mesh(density, level, origin, h)
    del density
    if len(faces) == 0:
        raise DataError(f"{run_dir}: no surface in the box: the density never reaches {level:.4g} (one voxel "
                        f"{opacity:g} opaque); lower export.opacity or check export.box")
    verts, faces, (normals,), comp = mesh_lib.remove_small_components(verts, faces, min_component_fraction, (normals,))
    train_ids = np.asarray(ds.split["train"]) if len(ds.split["train"]) else np.arange(ds.num_frames)
    centres = np.asarray(ds.c2w)[train_ids, :3, 3]
    timings["mesh"] = time.perf_counter() - start - sum(timings.values())
    vcolours = field.colours_from_cameras(params, cfg.model, verts, centres, k=colour_cameras)
    timings["colours"] = time.perf_counter() - start - sum(timings.values())

    # 5. measurements and files, in the export's units
    verts_m = to_metric64(verts, norm)
    inside = _inside(points, lo, hi)
    tower_pts, tower_cols = to_metric64(points[inside], norm), colours[inside]
    lo_m, hi_m = box_to_metric(lo, hi, norm)
    box_m = {"min": [float(v) for v in lo_m], "max": [float(v) for v in hi_m]}
    meas: dict[str, Any] = {"units": units, "run": str(run_dir), "step": int(step),
            "box": {**box_m, "source": "given" if given is not None else "auto"},
            "resolution": int(resolution), "grid": list(shape), "voxel_size": h / scale,
            "threshold": {"opacity_per_voxel": float(opacity), "density": level,
                          "density_per_unit": level * scale,
                          "definition": "sigma = -ln(1 - opacity) / voxel_size (docs/EXPORT.md); 'density' per "
                                        "normalised scene unit, 'density_per_unit' per export unit"},
            "mesh": {"vertices": int(len(verts)), "faces": int(len(faces)), "closed": mesh_lib.is_closed(faces),
                     **comp, "min_component_fraction": float(min_component_fraction)},
            "points": {"count": int(len(tower_pts)), "views": [int(i) for i in ids], "min_views": int(min_views),
                       **fuse_stats},
            "ground": None, "height": None, "footprint": None, "cross_arms": None, "tilt": None,
            "conductors": None, "conductor_spans": None}
    alignment = survey.alignment_uncertainty(geo, units, to_metric64(centres, norm))
    cloud_m = to_metric64(points, norm)   # the cloud in metres, once: the ground's and the wires' checks read it
    if plane is not None:
        n_m, d_m = plane_to_metric(plane["normal"], plane["offset"], norm)
        meas["ground"] = {"normal": [float(v) for v in n_m], "offset": d_m, "equation": "normal . x + offset = 0",
                          "tilt_degrees": math.degrees(math.acos(min(1.0, abs(float(n_m[2]))))),
                          "clearance": plane["clearance"] / scale, "inliers": plane["inliers"],
                          "candidates": plane["candidates"], "settled_on": plane["settled_on"],
                          "settled_shift": plane["settled_shift"] / scale}
        heights = verts_m @ n_m + d_m
        height = float(heights.max())
        meas["height"] = height
        fp = measure.footprint(verts_m, n_m, d_m, max(0.05 * (height - float(heights.min())), 2 * h / scale))
        meas["footprint"] = fp
        arms = measure.cross_arms(verts_m, n_m, d_m, *measure.arm_axes(verts_m, n_m, d_m),
                                  max(0.01 * height, 2 * h / scale))
        meas["cross_arms"] = measure.arm_levels(arms, height)
        meas["tilt"] = measure.axis_tilt(verts_m, n_m, d_m, fp["axis_a"], fp["axis_b"],
                                         max(0.01 * height, 2 * h / scale))
        levels = meas["cross_arms"]["levels"]
        meas["conductors"] = measure.conductor_clearance(
            cloud_m, n_m, d_m, lo_m, hi_m,
            0.5 * min(level["height"] for level in levels) if levels else 0.5 * height, GROUND_CELL / scale)
        meas["conductors"]["ground_seen"] = clearance_lib.lowest_point_ground_seen(
            meas["conductors"], cloud_m, n_m, d_m, meas["ground"]["clearance"], GROUND_CELL / scale,
            (0.0, 0.0, 1.0) if units == "metres" else n_m)
    meas["box"].update(box_stats)
    # 6. the conductors from the photos, their clearance; the classified cloud
    meas["conductor_spans"] = _conductors(ds, train_ids, meas, cloud_m, lo_m, hi_m, units, min_clearance, progress,
                                          span_length)
    timings["conductors"] = time.perf_counter() - start - sum(timings.values())
    meas["survey"] = _survey(meas, geo, alignment, h / scale)
    # the CRS outputs (heights above the geoid with `geoid`), all converted before anything is written
    points_crs, mesh_crs = survey.to_crs(tower_pts, geo), None
    if crs_name is not None and geo:  # a CRS name comes from a georeference record
        points_crs, mesh_crs = _vertical(meas["survey"], geo, crs_name, grid, geoid, points_crs,
                                         survey.to_crs(verts_m, geo), datum)
    comments = (units_comment(units), f"jaxnerf-grid export of {run_dir} at step {step}")
    if not folders.is_empty(out):  # checked by check_out: empty, or export's own (overwrite=True)
        folders.clear_outputs(out, "export", OUTPUTS, "export.out", legacy=_is_legacy_export(out))
    folders.write_marker(out, "export")
    io.write_ply(out / "tower_mesh.ply", verts_m, vcolours, faces,
                 comments=comments + (f"marching cubes at density {level:.6g} per normalised unit "
                                      f"(one voxel {opacity:g} opaque), voxel {h / scale:.4g}",))
    clouds.write_point_cloud(out / "tower_points.ply", [(tower_pts, tower_cols)],
                      comments=comments + (f"depth of {len(ids)} views fused, each point confirmed by >= "
                                           f"{min_views} other views",))
    survey.write_las(out / "tower_points.las", points_crs, tower_cols, crs_name, datum)
    cls_points, cls_colours, cls_classes = _classified_cloud(meas, cloud_m, colours, lo_m, hi_m)
    cls_crs = survey.to_crs(cls_points, geo)
    if grid is not None and crs_name is not None:  # a geoid grid needs a CRS (checked above)
        cls_crs, _ = geoid_lib.orthometric(cls_crs, crs_name, grid, Path(geoid))
    survey.write_las(out / "classified_points.las", cls_crs, cls_colours, crs_name, datum, classification=cls_classes)
    io.write_png(out / "conductors_views.png", meas["conductor_spans"].pop("_picture"))
    if crs_name is not None and geo and mesh_crs is not None:  # all three, or none
        survey.write_ply_double(out / "tower_mesh_crs.ply", mesh_crs, vcolours, faces,
                                comments=(f"crs: {crs_name} ({geo.get('crs_name')}); x = tower_mesh.ply's x + "
                                          f"origin {[float(v) for v in crs_origin]}",
                                          f"heights: {meas['survey']['vertical']['reference']}",
                                          f"jaxnerf-grid export of {run_dir} at step {step}"))
    io.write_json(out / "box.json", {**meas["box"], "units": units, "frame": BOX_FRAME, "normalised": {
        "min": [float(v) for v in lo], "max": [float(v) for v in hi]}})
    picture = measure.orthographic_views(verts_m, vcolours, normals, splat=1)
    io.write_png(out / "export_views.png", picture)
    meas["seconds"] = time.perf_counter() - start
    meas["timings"] = {**timings, "write": meas["seconds"] - sum(timings.values())}
    meas["peak_memory_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    io.write_json(out / "measurements.json", meas)
    _update_report(run_dir, out, meas, ds)
    return meas


CORRIDOR = 0.5            # tower heights: the objects this far across a span's wire count for its clearance
CONDUCTOR_SPACING = 0.5   # export units between the classified cloud's points along each fitted span


def _line_azimuth(meas: dict, up: np.ndarray) -> float | None:
    """The line's azimuth (`catenary.line_axes`) across the cross-arms: the arms' axis (of the
    cross-arms' two axes, the one most levels lie along) turned a quarter about up; None without
    cross-arms."""
    arms = meas.get("cross_arms") or {}
    levels = arms.get("levels") or []
    if not levels or "axis_a" not in arms:
        return None
    names = [lv["axis"] for lv in levels]
    arm = np.asarray(arms["axis_a"] if names.count("a") >= names.count("b") else arms["axis_b"], np.float64)
    line = np.cross(up, arm)
    e1, e2, _ = catenary.line_axes(0.0, up)
    return math.atan2(float(line @ e2), float(line @ e1))


def check_span_length(span_length) -> None:
    """ConfigError naming export.span_length unless it is None or a positive finite number."""
    if span_length is None:
        return
    if isinstance(span_length, bool) or not isinstance(span_length, (int, float)) or not math.isfinite(span_length) \
            or span_length <= 0:
        raise ConfigError(f"export.span_length must be a positive number (export units), got {span_length!r}")


SEED_WINDOW = (0.05, 0.25, 0.05)   # tower heights: each cross-arm tip's window (across, below, above)


def arm_seeds(levels: list[dict], centre, psi: float, up) -> list[tuple[float, float]]:
    """The cross-arms' tips as `find_spans` seeds [(across offset, height)]: each level's two ends
    (`measure.cross_arms`, the export's frame) as the offset across the line (along
    `catenary.line_axes(psi)`'s e_across, from the axis point centre) and the height along up."""
    _, across, u = catenary.line_axes(psi, up)
    centre = np.asarray(centre, np.float64)
    out = []
    for level in levels:
        for end in level.get("ends") or []:
            e = np.asarray(end, np.float64)
            out.append((float((e - centre) @ across), float(e @ u)))
    return out


def _conductors(ds, train_ids, meas: dict, cloud_m: np.ndarray, lo_m, hi_m, units: str, min_clearance,
                progress: bool, span_length: float | None = None) -> dict:
    """measurements.json's `conductor_spans` (`export.conductors`, `export.clearance`): the spans
    found in the training photos, each with its figures, its clearance, whether the ground beneath
    its lowest point is seen (`clearance.ground_seen`) and its flag; "_picture"
    (conductors_views.png's image, taken out before writing). Seeds: the cross-arms' direction,
    heights and span (the module's find_spans, searched again along the azimuth its wires measured:
    `turned_search`, the turns in "azimuth_turns"), the cross-arms' tips (`arm_seeds`, each searched
    in a window below it: SEED_WINDOW), the tower's axis and box; span_length: the towers'
    spacing given (a level span of that length), None: the curvature from the photos."""
    n_m = np.asarray((meas.get("ground") or {}).get("normal", [0.0, 0.0, 1.0]), np.float64)
    d_m = float((meas.get("ground") or {}).get("offset", 0.0))
    # the frame's z is up where it is metric (georeferenced: east, north, up; the generator's
    # world); else the ground's normal is the best vertical there is
    up = np.array([0.0, 0.0, 1.0]) if units == "metres" else n_m
    images = np.asarray(ds.images)[train_ids]
    out = {"found": 0, "spans": [], "why": None, "up": [float(v) for v in up],
           "min_clearance": min_clearance, "flagged": 0, "photos": int(len(train_ids)),
           "span_length": None if span_length is None else float(span_length), "seeds": [], "azimuth_turns": [0.0, 0.0],
           "_picture": np.ones((8, 8, 3), np.float32)}
    height = meas.get("height")
    psi = _line_azimuth(meas, up)
    if meas.get("ground") is None or height is None or psi is None:
        out["why"] = "no ground, height or cross-arms measured: the line's direction and heights are unknown"
        return out
    tilt = meas.get("tilt") or {}
    centre = np.asarray(tilt.get("base", 0.5 * (np.asarray(lo_m) + np.asarray(hi_m))), np.float64)
    line, across_axis, _ = catenary.line_axes(psi, up)
    box = measure_box_corners(lo_m, hi_m)
    half_length = float(np.max(np.abs((box - centre) @ line)))
    levels = meas["cross_arms"]["levels"]
    ground_at_centre = float(centre @ up - (centre @ n_m + d_m) / max(float(n_m @ up), 1e-6))
    lowest_arm = min(lv["height"] for lv in levels)
    heights = (ground_at_centre + lowest_arm - 0.35 * height, ground_at_centre + 1.1 * height)
    across = 0.5 * max(lv["span"] for lv in levels) + 0.3 * height
    c2w = conductors_lib.metric_cameras(np.asarray(ds.c2w)[train_ids], ds.normalization)
    intr = np.asarray(ds.intrinsics, np.float64)[train_ids]
    station = centre + (half_length + 0.3 * height) * line
    step = float(np.median(np.linalg.norm(c2w[:, :3, 3] - station, axis=1) / intr[:, 0]))
    responses = [conductors_lib.ridge_map(im) for im in progress_lib.bar(images, desc="export: wires", unit="photo",
                                                                        enabled=progress)]
    masks = np.stack([conductors_lib.detections(r) for r in responses])
    if not masks.any():
        out["why"] = "no wire detected in any photo"
        return out
    views = conductors_lib.Views(c2w, intr, masks, responses)
    del responses
    seeds = arm_seeds(levels, centre, psi, up)
    out["seeds"] = [[c, z] for c, z in seeds]
    # the next towers, where the photos look along the line: the spans without the curvature's doubt
    # (searched only without a span length)
    next_tower = None if span_length is not None else functools.partial(
        next_tower_lib.next_tower, next_tower_lib.grey_high_passed(images), c2w, intr, centre, up, ground_at_centre,
        float(height), 0.5 * max(lv["span"] for lv in levels))
    fits, turns = conductors_lib.turned_search(views, centre, psi, half_length, heights, across, step, float(height),
                                               up, seeds=seeds, span_length=span_length,
                                               seed_window=tuple(v * float(height) for v in SEED_WINDOW),
                                               next_tower=next_tower)
    out["azimuth_turns"] = [float(t) for t in turns]
    del next_tower
    plane_band = float(meas["ground"]["clearance"])
    for fit in fits:
        rec = conductors_lib.span_record(fit, centre, up)
        curve = conductors_lib.sample_span(fit["theta"], centre, CONDUCTOR_SPACING, up)
        low = rec["lowest_point"]["value"]
        ground_clear = None if low is None else float(np.asarray(low) @ n_m + d_m)
        objects = clearance_lib.objects_beneath(curve, cloud_m, n_m, d_m, plane_band, CORRIDOR * float(height), up,
                                                (lo_m, hi_m)) if len(curve) > 1 else None
        span = rec["span"]["value"]
        seen = None if low is None or span is None else clearance_lib.ground_seen(
            low, cloud_m, n_m, d_m, plane_band, clearance_lib.GROUND_RADIUS_SHARE * float(span), up)
        rec["clearance"] = {"ground": ground_clear,
                            "ground_sigma": None if low is None else rec["lowest_point"]["sigma"][2],
                            "ground_seen": seen,
                            "objects": objects,
                            "flag": clearance_lib.flag(ground_clear, (objects or {}).get("clearance"), min_clearance)}
        out["spans"].append(rec)
    out["found"] = len(out["spans"])
    out["flagged"] = sum(1 for r in out["spans"] if r["clearance"]["flag"])
    if not fits:
        out["why"] = (f"no wire crossing the line's cross-section beyond the tower was seen by enough photos "
                      f"({int(masks.reshape(len(masks), -1).sum(1).mean())} wire pixels a photo on average)")
    out["_picture"] = conductors_lib.views_picture(images, views, fits, centre, up)
    return out


def measure_box_corners(lo, hi) -> np.ndarray:
    """The 4 horizontal corners [4, 3] of the box lo [3] - hi [3] at its bottom."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return np.array([[x, y, lo[2]] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])])


def _classified_cloud(meas: dict, cloud_m: np.ndarray, colours: np.ndarray, lo_m, hi_m):
    """classified_points.las's points [M, 3], colours [M, 3] and ASPRS classes [M] (`export.classes`):
    the whole fused cloud, and the fitted spans sampled every CONDUCTOR_SPACING (class 14, orange)."""
    g = meas.get("ground")
    pts, cols = np.asarray(cloud_m, np.float64), np.asarray(colours, np.float32)
    if g is None:
        return pts, cols, np.ones(len(pts), np.uint8)          # 1: unclassified (no ground to stand on)
    cls = classes.classify(pts, g["normal"], g["offset"], g["clearance"], (lo_m, hi_m))
    spans = (meas.get("conductor_spans") or {}).get("spans") or []
    wires = [conductors_lib.sample_span(r["theta"], r["centre"], CONDUCTOR_SPACING, r["up"]) for r in spans]
    wires = [w for w in wires if len(w) > 1]
    if wires:
        w = np.concatenate(wires)
        pts = np.concatenate([pts, w])
        cols = np.concatenate([cols, np.tile(np.array([[1.0, 0.5, 0.0]], np.float32), (len(w), 1))])
        cls = np.concatenate([cls, np.full(len(w), classes.CONDUCTOR, np.uint8)])
    return pts, cols, cls


BOX_FRAME = ("min / max: axis-aligned in the export's units (the dataset's frame); the mesh grid is "
             "axis-aligned in the normalised scene: 'normalised', the box around the 8 corners of a given box, "
             "and min / max the box around the 8 corners of 'normalised' mapped back")


def _check_geoid_site(path, grid, crs_name, geo, ds, norm, units) -> None:
    """export.geoid needs a dataset in a CRS; the grid must cover the cameras' positions (the
    site; checked again on every written point). DataError naming the grid file otherwise."""
    if crs_name is None:
        why = "metres but no CRS" if units == "metres" else "no metric scale"
        raise DataError(f"{Path(path)}: export.geoid needs a dataset georeferenced in a projected CRS (poses with "
                        f"GPS or control points, docs/GEOREFERENCE.md); this one has {why}")
    centres = to_metric64(np.asarray(ds.c2w)[:, :3, 3], norm)
    geoid_lib.orthometric(survey.to_crs(centres, geo), crs_name, grid, Path(path))


def _vertical(sv: dict, geo: dict, crs_name: str, grid, path, points_crs: np.ndarray, mesh_crs: np.ndarray,
              datum=None):
    """With a geoid grid: (the points' and the mesh's CRS coordinates with H = h - N), the base
    centre's CRS coordinates likewise; `sv["vertical"]` records the reference (and N at the base)
    either way. DataError naming the grid when it does not cover a point."""
    if grid is None:
        sv["vertical"] = geoid_lib.vertical_record(geo=geo)
        return points_crs, mesh_crs
    points_crs, n_points = geoid_lib.orthometric(points_crs, crs_name, grid, Path(path))
    mesh_crs, n_mesh = geoid_lib.orthometric(mesh_crs, crs_name, grid, Path(path))
    n_base = None
    base = sv.get("base_centre")
    if base and base.get("crs") is not None:
        moved, n = geoid_lib.orthometric(base["crs"], crs_name, grid, Path(path))
        base["crs"], n_base = [float(v) for v in moved[0]], float(n[0])
    n_all = np.concatenate([n_points, n_mesh])
    sv["vertical"] = geoid_lib.vertical_record(Path(path), n_base, (n_all.min(), n_all.max()) if len(n_all) else None,
                                               datum=datum)
    return points_crs, mesh_crs


def _survey(meas: dict, geo: dict | None, alignment: dict, voxel: float) -> dict:
    """measurements.json's `survey`: each figure {"value", "sigma", "fit_sigma"} in metres
    (docs/EXPORT.md "Survey outputs and uncertainty"), the tower's base centre (local and CRS), the alignment's
    terms. fit terms: ground = the ground inliers' robust spread (its clearance / 3), a vertex's
    height = voxel / sqrt(12), a cross-arm's = its slice height / sqrt(12); a width or span (two
    ends) = voxel sqrt(2 / 12); the tilt's = its fit's scatter and its thickness spread in
    quadrature (`measure.axis_tilt`), the top offset's the same angle at the height; the base
    centre's adds the tilt's error over the height the axis is extended below the model's lowest
    point (`extrapolated`, export units)."""
    g = meas.get("ground") or {}
    ground_sigma = float(g.get("clearance", 0.0)) / 3.0
    vertex = voxel / math.sqrt(12.0)
    out: dict[str, Any] = {"alignment": alignment, "height": None, "cross_arm_heights": [], "cross_arm_spans": [],
           "footprint": None, "tilt_degrees": None, "top_offset": None, "conductor_clearance": None,
           "base_centre": None, "vertical": None}
    ends = voxel * math.sqrt(2.0 / 12.0)
    fp = meas.get("footprint") or {}
    if fp:
        out["footprint"] = [survey.with_sigma(fp["width_a"], ends, alignment),
                            survey.with_sigma(fp["width_b"], ends, alignment)]
    if meas.get("height") is not None:
        out["height"] = survey.with_sigma(meas["height"], math.hypot(ground_sigma, vertex), alignment)
    arms = meas.get("cross_arms") or {}
    for level in arms.get("levels") or []:
        out["cross_arm_heights"].append(survey.with_sigma(
            level["height"], math.hypot(ground_sigma, arms["slice_height"] / math.sqrt(12.0)), alignment))
        out["cross_arm_spans"].append(survey.with_sigma(level["span"], ends, alignment))
    tilt = meas.get("tilt")
    if tilt:
        # the angle does not scale: the fit's scatter and its spread over slice thicknesses (the
        # frame's own vertical error is not in it)
        spread = float(tilt.get("thickness_spread_degrees", 0.0))
        angle = math.hypot(tilt["tilt_sigma_degrees"], spread)
        out["tilt_degrees"] = {"value": tilt["tilt_degrees"], "sigma": angle, "fit_sigma": angle}
        out["top_offset"] = survey.with_sigma(tilt["top_offset"], math.hypot(
            tilt["top_offset_sigma"], math.radians(spread) * float(meas.get("height") or 0.0)), alignment)
        base = np.asarray(tilt["base"], np.float64)
        lever = float(np.linalg.norm(base - np.asarray(alignment.get("centroid", base), np.float64)))
        # the base is the axis extended down from the model's lowest point: its angle's error there
        extrapolated = max(float(tilt.get("lowest_height", 0.0)), 0.0)
        reach = extrapolated * math.tan(math.radians(angle))
        crs_name, _ = survey.crs_of(geo)
        out["base_centre"] = {"local": [float(v) for v in base],
                              "crs": [float(v) for v in survey.to_crs(base, geo)] if crs_name else None,
                              "crs_name": crs_name, "extrapolated": extrapolated,
                              **(survey.with_sigma(0.0, math.sqrt(vertex ** 2 + ground_sigma ** 2 + reach ** 2),
                                                     alignment, lever=lever, position=True) or {})}
        out["base_centre"].pop("value", None)
    cond = meas.get("conductors") or {}
    if cond.get("reconstructed"):
        out["conductor_clearance"] = survey.with_sigma(cond["lowest_height"], math.hypot(ground_sigma, voxel),
                                                       alignment)
    return out


def _update_report(run_dir: Path, out: Path, meas: dict, ds) -> None:
    """Writes the "Tower model" section into RUN/report.md and rewrites RUN/report.html
    (`report_html`) when the export is RUN/export (the default), else OUT/report.md and
    OUT/report.html."""
    if out.resolve() == (run_dir / "export").resolve():
        path, image, wires = run_dir / "report.md", "export/export_views.png", "export/conductors_views.png"
    else:
        path, image, wires = out / "report.md", "export_views.png", "conductors_views.png"
    report.set_section(path, report.EXPORT_HEADING, report.export_lines({"measurements": meas, "image": image,
                                                                         "conductors_image": wires}))
    report_html.write_report_html(path.with_suffix(".html"), run_dir, ds, export_dir=out)
