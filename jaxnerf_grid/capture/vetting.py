"""Camera vetting after structure from motion: each registered photo gets a score, and photos
that fail a rule are left out of the dataset (`jaxnerf-grid poses`, docs/POSES.md "Vetting").

The scores are pure functions of a reconstruction held in plain arrays (`Records`), so they
are tested on hand-made reconstructions; `records_from_pycolmap` fills one from a
pycolmap.Reconstruction. Per photo:

- observations: the number of its 2-D points that have a 3-D point;
- reprojection_px: the mean distance, in pixels, between where its pose projects those 3-D
  points and where the photo saw them (recomputed here from the pose, not read from COLMAP:
  a camera whose pose no longer fits what it saw, e.g. turned by 20 degrees, shows here);
- track_length: the mean number of photos that see each of its 3-D points;
- neighbour_ratio: the distance from its centre to the nearest of the NEIGHBOURS photos it
  shares the most 3-D points with, over the usual such distance: the same distance's median
  across all photos, or NEIGHBOUR_DEPTH_FLOOR x the photos' median viewing depth
  (`viewing_depths`) when that is larger. A photo registered in the wrong place (look-alike
  faces of a lattice tower) still shares points with the photos near its true place, which are
  then all far from where it was put. The nearest, not the median, of them: a photo at the edge
  of a gap in the flight has its best-shared photos on one side only, one beside it and the
  others further along (a 640x480 orbit's two gap-edge photos, 0.04-0.12 degrees from the
  truth, were 3.8-3.9 times the usual distance by the median, 1.5 by the nearest). The floor
  is for captures whose photos stand close together against the scene's depth: the frames of
  a video, a few centimetres apart where the camera pans, made the usual distance so small
  that 158 of a 302-frame capture were "hundreds of times" off it;
- covisible: the number of other photos it shares at least one 3-D point with. A photo tied
  to the model only through a small corner of it (few photos, few points) can sit in a local
  model that is itself wrong; on synthetic tower orbits the photos registered beside a gap of
  unregistered ones were kept 4-7 degrees off, sharing points with 8-11 photos where every good
  photo shared them with 17 or more (docs/POSES.md).

Rules (`vet`), each with its reason in the table:
- fewer observations than max(MIN_OBSERVATIONS, MIN_OBSERVATIONS_FRACTION x the median photo's);
- reprojection_px above MAX_REPROJECTION_PX (the mapper already drops every observation more
  than 2 px off, data.poses.MAPPER, so a mean above that means the pose does not fit);
- track_length below MIN_TRACK_FRACTION x the median photo's (points few others see: weakly tied);
- neighbour_ratio above MAX_NEIGHBOUR_RATIO (only with at least MIN_PHOTOS_FOR_LAYOUT photos);
- weakly tied: covisible below MIN_COVISIBLE_FRACTION x the median photo's *and* observations
  below WEAK_OBSERVATIONS_FRACTION x the median photo's (only with at least
  MIN_PHOTOS_FOR_LAYOUT photos). Both, so that the end photos of a straight flight line (half
  the neighbours of a middle photo, with the usual number of points) are kept.
"""

from __future__ import annotations

import dataclasses

import numpy as np

MIN_OBSERVATIONS = 15            # the relaxed mapper's inliers to register a photo (data.poses.RELAXED)
MIN_OBSERVATIONS_FRACTION = 0.1  # ... and a tenth of the median photo's observations
MAX_REPROJECTION_PX = 2.0        # the mapper's own per-observation filter (data.poses.MAPPER)
MIN_TRACK_FRACTION = 0.5
NEIGHBOURS = 3
MAX_NEIGHBOUR_RATIO = 3.0
NEIGHBOUR_DEPTH_FLOOR = 0.1  # the usual neighbour distance is at least this share of the viewing depth
MIN_PHOTOS_FOR_LAYOUT = 5
MIN_COVISIBLE_FRACTION = 2 / 3   # weakly tied: fewer covisible photos than 2/3 of the median photo's ...
WEAK_OBSERVATIONS_FRACTION = 0.25  # ... and fewer observations than a quarter of the median photo's
BEHIND_PX = 1e4  # the error given to a point behind the camera (it cannot be where the photo saw it)


@dataclasses.dataclass
class Records:
    """A reconstruction in plain arrays (N photos, P points).

    names: [N] photo names; cam_from_world: [N, 3, 4] world-to-camera (OpenCV axes: +z forward);
    focal: [N] focal length in pixels; point_index: per photo an int array [k_i] into xyz;
    observed: per photo [k_i, 2] its observations in normalised image coordinates (x / z, y / z;
    lens distortion removed); xyz: [P, 3]; track_length: [P] photos seeing each point.
    """

    names: list
    cam_from_world: np.ndarray
    focal: np.ndarray
    point_index: list
    observed: list
    xyz: np.ndarray
    track_length: np.ndarray


def reprojection_errors(cam_from_world: np.ndarray, focal: float, xyz: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Pixel distance between the projection of xyz [k, 3] by the pose [3, 4] and the observed
    normalised coordinates [k, 2] (times `focal`). A point behind the camera gets BEHIND_PX. Returns [k]."""
    cam = np.asarray(xyz, np.float64) @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = cam[:, 2]
    safe = np.where(z > 1e-12, z, 1.0)
    err = focal * np.linalg.norm(cam[:, :2] / safe[:, None] - observed, axis=1)
    return np.where(z > 1e-12, np.minimum(err, BEHIND_PX), BEHIND_PX)


def camera_centres(cam_from_world: np.ndarray) -> np.ndarray:
    """Centres [N, 3] of world-to-camera poses [N, 3, 4]: c = -R^T t."""
    r, t = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    return -np.einsum("nji,nj->ni", r, t)


def shared_points(point_index: list, num_points: int) -> np.ndarray:
    """[N, N] number of 3-D points each pair of photos both see (diagonal: 0)."""
    seen = np.zeros((len(point_index), num_points), np.float64)
    for i, idx in enumerate(point_index):
        seen[i, np.unique(np.asarray(idx, np.int64))] = 1.0
    shared = seen @ seen.T
    np.fill_diagonal(shared, 0.0)
    return shared


def viewing_depths(cam_from_world: np.ndarray, point_index: list, xyz: np.ndarray) -> np.ndarray:
    """Per photo the median depth (camera z) of the 3-D points it sees; NaN for a photo that sees
    none. cam_from_world [N, 3, 4], point_index: per photo [k_i] into xyz [P, 3]. Returns [N]."""
    out = np.full(len(point_index), np.nan)
    for i, idx in enumerate(point_index):
        if len(idx):
            pts = xyz[np.asarray(idx, np.int64)]
            out[i] = float(np.median(pts @ cam_from_world[i, 2, :3] + cam_from_world[i, 2, 3]))
    return out


def neighbour_distances(centres: np.ndarray, shared: np.ndarray, k: int = NEIGHBOURS) -> np.ndarray:
    """Per photo the distance to the nearest of the k photos it shares the most points with (ties:
    the lower index; only photos sharing at least one point; NaN when none). centres [N, 3],
    shared [N, N]. Returns [N]."""
    out = np.full(len(centres), np.nan)
    for i in range(len(centres)):
        order = [j for j in np.argsort(-shared[i], kind="stable") if j != i and shared[i, j] > 0][:k]
        if order:
            out[i] = float(np.linalg.norm(centres[order] - centres[i], axis=1).min())
    return out


def photo_scores(rec: Records) -> dict:
    """The scores of every photo: {"observations" [N] int, "reprojection_px" [N],
    "track_length" [N], "neighbour_ratio" [N] (NaN when it cannot be computed), "covisible" [N]
    int}."""
    n = len(rec.names)
    obs = np.array([len(idx) for idx in rec.point_index], np.int64)
    reproj = np.full(n, np.nan)
    track = np.full(n, np.nan)
    for i, (idx, uv) in enumerate(zip(rec.point_index, rec.observed)):
        if len(idx):
            idx = np.asarray(idx, np.int64)
            reproj[i] = float(reprojection_errors(rec.cam_from_world[i], float(rec.focal[i]), rec.xyz[idx],
                                                  np.asarray(uv, np.float64)).mean())
            track[i] = float(np.asarray(rec.track_length, np.float64)[idx].mean())
    shared = shared_points(rec.point_index, len(rec.xyz))
    dist = neighbour_distances(camera_centres(rec.cam_from_world), shared)
    typical = np.nanmedian(dist) if np.any(np.isfinite(dist)) else np.nan
    depth = viewing_depths(rec.cam_from_world, rec.point_index, rec.xyz)
    if np.any(np.isfinite(depth)) and np.isfinite(typical):
        typical = max(typical, NEIGHBOUR_DEPTH_FLOOR * float(np.nanmedian(depth)))
    ratio = dist / typical if np.isfinite(typical) and typical > 0 else np.full(n, np.nan)
    return {"observations": obs, "reprojection_px": reproj, "track_length": track, "neighbour_ratio": ratio,
            "covisible": (shared > 0).sum(axis=1).astype(np.int64)}


def failures(scores: dict) -> list[list[str]]:
    """Per photo the rules it fails (module docstring), as short reasons; [] = kept."""
    obs, reproj = scores["observations"], scores["reprojection_px"]
    track, ratio, covisible = scores["track_length"], scores["neighbour_ratio"], scores["covisible"]
    n = len(obs)
    typical_obs = float(np.median(obs)) if n else 0.0
    min_obs = max(MIN_OBSERVATIONS, MIN_OBSERVATIONS_FRACTION * typical_obs)
    typical_track = np.nanmedian(track) if np.any(np.isfinite(track)) else np.nan
    typical_covisible = float(np.median(covisible)) if n else 0.0
    weak = ((covisible < MIN_COVISIBLE_FRACTION * typical_covisible)
            & (obs < WEAK_OBSERVATIONS_FRACTION * typical_obs)) if n >= MIN_PHOTOS_FOR_LAYOUT else np.zeros(n, bool)
    out = []
    for i in range(n):
        why = []
        if obs[i] < min_obs:
            why.append(f"{obs[i]} observations < {min_obs:.0f}")
        if not np.isfinite(reproj[i]) or reproj[i] > MAX_REPROJECTION_PX:
            why.append(f"reprojection {reproj[i]:.2f} px > {MAX_REPROJECTION_PX:g}")
        if np.isfinite(typical_track) and not track[i] >= MIN_TRACK_FRACTION * typical_track:
            why.append(f"track length {track[i]:.2f} < {MIN_TRACK_FRACTION:g} x median {typical_track:.2f}")
        if n >= MIN_PHOTOS_FOR_LAYOUT and np.isfinite(ratio[i]) and ratio[i] > MAX_NEIGHBOUR_RATIO:
            why.append(f"{ratio[i]:.1f}x the usual distance to the photos it shares points with")
        if weak[i]:
            why.append(f"weakly tied: shares points with {covisible[i]} photos (median {typical_covisible:g}) "
                       f"through {obs[i]} observations (median {typical_obs:g})")
        out.append(why)
    return out


def vet(rec: Records) -> list[dict]:
    """One row per photo, in rec.names order: {"name", "observations", "reprojection_px",
    "track_length", "neighbour_ratio" (None when not computed), "covisible", "kept", "reasons"}."""
    scores = photo_scores(rec)
    rows = []
    for i, why in enumerate(failures(scores)):
        rows.append({"name": rec.names[i], "observations": int(scores["observations"][i]),
                     **{key: (float(scores[key][i]) if np.isfinite(scores[key][i]) else None)
                        for key in ("reprojection_px", "track_length", "neighbour_ratio")},
                     "covisible": int(scores["covisible"][i]), "kept": not why, "reasons": why})
    return rows


def records_from_pycolmap(model) -> Records:
    """The registered photos of a pycolmap.Reconstruction as Records (sorted by name)."""
    ids = sorted(model.reg_image_ids(), key=lambda i: model.images[i].name)
    point_ids = sorted(model.points3D)
    where = {pid: k for k, pid in enumerate(point_ids)}
    xyz = np.array([model.points3D[p].xyz for p in point_ids], np.float64).reshape(-1, 3)
    track = np.array([model.points3D[p].track.length() for p in point_ids], np.float64)
    names, poses, focal, index, observed = [], [], [], [], []
    for i in ids:
        im = model.images[i]
        cam = model.cameras[im.camera_id]
        pts = [(p.xy, where[p.point3D_id]) for p in im.points2D if p.has_point3D() and p.point3D_id in where]
        xy = np.array([p[0] for p in pts], np.float64).reshape(-1, 2)
        names.append(im.name)
        poses.append(np.asarray(im.cam_from_world().matrix(), np.float64))
        focal.append(float(cam.mean_focal_length()))
        index.append(np.array([p[1] for p in pts], np.int64))
        observed.append(np.asarray(cam.cam_from_img(xy), np.float64).reshape(-1, 2) if len(xy) else xy)
    return Records(names, np.stack(poses) if poses else np.zeros((0, 3, 4)), np.array(focal), index, observed,
                   xyz, track)


def format_table(rows: list[dict]) -> list[str]:
    """The vetting table as Markdown lines (every photo, the left-out ones with their reasons)."""
    def num(v, digits):
        return "-" if v is None else f"{v:.{digits}f}"

    lines = ["| photo | observations | reprojection (px) | track length | neighbour ratio | covisible photos "
             "| kept | reason |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['name']} | {r['observations']} | {num(r['reprojection_px'], 2)} | "
                     f"{num(r['track_length'], 2)} | {num(r['neighbour_ratio'], 2)} | {r.get('covisible', '-')} | "
                     f"{'yes' if r['kept'] else 'no'} | {'; '.join(r['reasons'])} |")
    return lines
