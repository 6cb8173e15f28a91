"""Whether a dataset's cameras are enough to train on (`jaxnerf-grid poses`, `demo --data`;
docs/POSES.md, "Too few cameras").

A NeRF trained on a third of an orbit renders the far side as a ghost; the chain stops before
that, in one line, unless the user says to go on (`accept_few_cameras`). The rule
(`camera_set_verdict`):

- count: the photos kept (registered and passing the vetting) must be at least MIN_KEPT_SHARE
  of the readable photos;
- arc: the kept cameras must cover at least MIN_ARC_SHARE of the arc the flight covers around
  the scene centre (the point the cameras look at), arcs measured as azimuths about the
  vertical (`arc_covered_deg`: 360 degrees less the largest gap between neighbouring
  cameras). The flight's arc is that of the registered cameras (before the vetting) and, when
  the photos' GPS is close enough to place them (its residual RMS under a quarter of the
  cameras' distance from the centre: `data.poses.gps_places_cameras`), of the GPS positions of
  the photos that did not register; else the places of unregistered photos are unknown.

Why these shares: on tower-small orbits the runs that trained on 16 of 36 photos (44 %, under
half the orbit) rendered a ghost and `export --box auto` found no ground; real captures keep
90 % or more (docs/POSES.md, measured figures).
"""

from __future__ import annotations

import numpy as np

MIN_KEPT_SHARE = 0.75  # of the readable photos
MIN_ARC_SHARE = 0.75   # of the flight's arc around the scene centre


def azimuths_deg(centres: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Azimuths (degrees, [0, 360)) of camera centres about a vertical axis through `centre`.
    centres: [N, 3] (z up); centre: [3]. Returns [N]."""
    d = np.asarray(centres, np.float64)[:, :2] - np.asarray(centre, np.float64)[:2]
    return np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360.0


def arc_covered_deg(azimuths) -> float:
    """The arc (degrees) a set of azimuths covers: 360 less the largest gap between neighbours
    on the circle; 0 for fewer than 2 cameras. azimuths: [N] degrees."""
    a = np.sort(np.asarray(azimuths, np.float64) % 360.0)
    if len(a) < 2:
        return 0.0
    gaps = np.diff(np.concatenate([a, a[:1] + 360.0]))
    return float(360.0 - gaps.max())


def look_at_point(c2w: np.ndarray) -> np.ndarray:
    """The point nearest to every camera's optical axis (least squares). c2w: [N, 4, 4]
    OpenGL (the camera looks along -z). Returns [3]."""
    origins = c2w[:, :3, 3]
    dirs = -c2w[:, :3, 2]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    return np.linalg.solve(proj.sum(0), np.einsum("kij,kj->i", proj, origins))


def arc_around_deg(c2w: np.ndarray) -> float:
    """The arc (degrees) cameras cover about the vertical through the point they look at
    (`look_at_point`, `azimuths_deg`, `arc_covered_deg`). c2w: [N, 4, 4] OpenGL, z up."""
    c2w = np.asarray(c2w, np.float64)
    return arc_covered_deg(azimuths_deg(c2w[:, :3, 3], look_at_point(c2w)))


def camera_set_record(photos: int, kept: int, arc_kept_deg: float, arc_flight_deg: float, arc_from: str) -> dict:
    """The record transforms.json keeps (poses.camera_set) and `camera_set_verdict` judges."""
    return {"photos": int(photos), "kept": int(kept), "arc_kept_deg": round(float(arc_kept_deg), 1),
            "arc_flight_deg": round(float(arc_flight_deg), 1), "arc_from": arc_from,
            "min_kept_share": MIN_KEPT_SHARE, "min_arc_share": MIN_ARC_SHARE}


def camera_set_verdict(record: dict) -> str | None:
    """None when the camera set is enough to train on (module docstring), else the reason, one
    phrase naming the counts."""
    photos, kept = record["photos"], record["kept"]
    need = int(np.ceil(MIN_KEPT_SHARE * photos))
    if kept < need:
        return (f"only {kept} of {photos} photos kept ({100 * kept / max(photos, 1):.0f} %; training needs "
                f"{need}, {MIN_KEPT_SHARE:.0%})")
    arc, flight = record["arc_kept_deg"], record["arc_flight_deg"]
    if flight > 0 and arc < MIN_ARC_SHARE * flight:
        where = "the photos' GPS" if record.get("arc_from") == "gps" else "the registered cameras"
        return (f"the {kept} kept cameras cover {arc:.0f} of the {flight:.0f} degrees around the scene centre "
                f"that {where} cover (training needs {MIN_ARC_SHARE:.0%})")
    return None
