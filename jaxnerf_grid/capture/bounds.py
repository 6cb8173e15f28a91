"""Scene bounds from the data: the region of interest, near, far and the contraction radius of
a capture, from its sparse points and its camera layout (docs/BOUNDS.md).

All distances are in the normalised scene, along unit rays. `scene_bounds` is the rule;
`jaxnerf-grid poses` records its result in transforms.json (`scene_bounds`), and `demo --data`
and `train --data` (contracted recipes) take near / far / contract_radius from there when a
dataset records them
(`recipe_with_bounds`; datasets without the key keep the recipe's constants, so the synthetic
demo is unchanged).

The rule:
- region of interest (ROI): a sphere centred on the point the cameras look at (the
  least-squares point nearest every optical axis, `normalize.scene_center`), of radius the
  ROI_PERCENTILE-th percentile of the points' distances to that centre, at most
  ROI_CAMERA_FRACTION of the median camera distance (`normalize.orbit_roi`, the rule
  `normalize.normalize_orbit` scales to the unit sphere, so in a dataset written by `poses`
  the ROI is the unit sphere: centre 0, radius 1);
- near: NEAR_FACTOR x the distance from the nearest camera to the ROI sphere (rays start just
  short of where the ROI can begin; nearer things are outside it: birds, the ground under a low
  pass), and never below `points_near` (the dataset's own near: 0.9 x the 0.5th percentile of
  the depths of the points the photos see, as the COLMAP loader computes it); except when more
  than NEAR_SHARE of one photo's observations of sparse points (`colmap.observation_depths`, photos
  with at least NEAR_MIN_OBSERVATIONS of them) lie nearer than that: static geometry fills part
  of that photo there (a wall at the end of an arc), which rays starting beyond it could only
  paint as fog, so near is then the smaller of the two; never below NEAR_FLOOR (the disparity
  warp's samples would crowd in front of the cameras);
- contract_radius: CONTRACT_RADIUS. Not a distance in the scene: `coords.contract` leaves the
  unit ball (the ROI, by the normalisation) as it is and maps everything outside it into the
  shell between 1 and this radius; 2 gives the background a shell as thick as the ROI's
  radius (mip-NeRF 360's choice). It holds for any capture normalised so the ROI is the unit ball;
- far: the distance whose contracted image lies within FAR_GAP of the contracted space's outer
  edge, far = (R - 1) / (R FAR_GAP) for R = contract_radius (1000 for R = 2): further out the
  contracted coordinates no longer change, so farther is the same as infinity for any capture.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid.data.formats import collect_scene
from jaxnerf_grid.data.normalize import orbit_roi
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError

ROI_PERCENTILE = 95.0
ROI_CAMERA_FRACTION = 1.0 / 3.0
NEAR_FACTOR = 0.9      # the same 10 % margin as the COLMAP loader's near (data/formats/colmap.py)
NEAR_SHARE = 0.1       # a photo with more of its observations nearer than the ROI's near: near from the points
NEAR_MIN_OBSERVATIONS = 100  # a photo with fewer observations says too little to move near
# near never below this (normalised units, the ROI's radius 1): the disparity warp spends half its
# samples between near and 2 x near, so a near of 0.001 (one point close to one camera) leaves the
# scene a few percent of them
NEAR_FLOOR = 0.05
CONTRACT_RADIUS = 2.0
FAR_GAP = 5e-4         # far's contracted image within 0.05 % of the outer radius
BOUND_KEYS = ("near", "far", "contract_radius")


def roi_sphere(c2w: np.ndarray, points: np.ndarray | None) -> tuple[np.ndarray, float]:
    """(centre [3], radius) of the region of interest: `normalize.orbit_roi` with ROI_PERCENTILE
    and ROI_CAMERA_FRACTION. c2w: [N, 3|4, 4] OpenGL; points: optional [P, 3]. Without points
    the radius is the camera cap alone."""
    return orbit_roi(c2w, points, percentile=ROI_PERCENTILE, camera_fraction=ROI_CAMERA_FRACTION)


def far_for_radius(contract_radius: float) -> float:
    """The far bound whose contracted image is within FAR_GAP of the outer radius R:
    (R - 1) / (R FAR_GAP)."""
    r = float(contract_radius)
    return (r - 1.0) / (r * FAR_GAP)


def scene_bounds(c2w: np.ndarray, points: np.ndarray | None, points_near: float | None = None,
                 depths: list[np.ndarray] | None = None) -> dict:
    """The bounds of a capture (module docstring). c2w: [N, 3|4, 4] OpenGL in the normalised
    scene; points: optional [P, 3] there; points_near: the dataset's near from its points (or None);
    depths: optional per photo the z-depths of its observations (`colmap.observation_depths`).

    Returns {"near", "far", "contract_radius", "roi_centre" [3], "roi_radius",
    "nearest_camera_to_roi" (distance from the nearest camera centre to the ROI sphere)[,
    "observations_nearer": the largest share of one photo's depths nearer than the ROI rule's near,
    among photos with NEAR_MIN_OBSERVATIONS or more]}.
    """
    c2w = np.asarray(c2w, np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((3, 4), (4, 4)) or len(c2w) == 0:
        raise DataError(f"scene_bounds: c2w must be [N, 3|4, 4] with N > 0, got {c2w.shape}")
    centre, radius = roi_sphere(c2w, points)
    gap = float(np.min(np.linalg.norm(c2w[:, :3, 3] - centre, axis=-1))) - radius
    near = NEAR_FACTOR * gap
    shares = [float(np.mean(np.asarray(d) < near)) for d in (depths or []) if len(d) >= NEAR_MIN_OBSERVATIONS]
    nearer = max(shares) if shares else None
    if points_near is not None:
        cut = nearer is not None and nearer > NEAR_SHARE
        near = min(near, float(points_near)) if cut else max(near, float(points_near))
    if not np.isfinite(near) or near <= 0:
        raise DataError(f"scene_bounds: no positive near (a camera inside the region of interest, "
                        f"{gap:.3g} from its sphere, and no points' near)")
    near = max(near, NEAR_FLOOR)
    out = {"near": float(near), "far": far_for_radius(CONTRACT_RADIUS), "contract_radius": CONTRACT_RADIUS,
           "roi_centre": [float(v) for v in centre], "roi_radius": float(radius), "nearest_camera_to_roi": gap}
    if nearer is not None:
        out["observations_nearer"] = nearer
    return out


def read_bounds(meta: dict, source) -> dict | None:
    """A transforms.json's recorded `scene_bounds` checked (None when it records none): finite
    numbers with 0 < near < far and contract_radius > 1. DataError naming `source` and the key."""
    bounds = meta.get("scene_bounds")
    if bounds is None:
        return None
    if not isinstance(bounds, dict):
        raise DataError(f"{source}: 'scene_bounds' must be an object with near, far, contract_radius")
    values = {}
    for key in BOUND_KEYS + ("roi_radius",):
        value = bounds.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise DataError(f"{source}: 'scene_bounds.{key}' must be a finite number, got {value!r}")
        values[key] = float(value)
    centre = bounds.get("roi_centre")
    if (not isinstance(centre, list) or len(centre) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in centre)):
        raise DataError(f"{source}: 'scene_bounds.roi_centre' must be 3 finite numbers, got {centre!r}")
    if not 0 < values["near"] < values["far"]:
        raise DataError(f"{source}: 'scene_bounds' needs 0 < near < far, got near={values['near']:g}, "
                        f"far={values['far']:g}")
    if not values["contract_radius"] > 1 or not values["roi_radius"] > 0:
        raise DataError(f"{source}: 'scene_bounds' needs contract_radius > 1 and roi_radius > 0")
    return {**bounds, **values, "roi_centre": [float(v) for v in centre]}


def folder_bounds(data) -> dict | None:
    """The checked `scene_bounds` of a dataset folder's transforms.json (`read_bounds`), near at
    least NEAR_FLOOR; None when the folder has no transforms.json (COLMAP, LLFF) or it records none."""
    path = Path(data) / "transforms.json"
    if not path.is_file():
        return None
    meta = io.read_json(path)
    bounds = read_bounds(meta, path) if isinstance(meta, dict) else None
    if bounds is not None and bounds["near"] < NEAR_FLOOR:  # a recorded near under the floor runs at the floor
        bounds = {**bounds, "near": NEAR_FLOOR}
    return bounds


def unrecorded_bounds(c2w: np.ndarray, points_near: float, recipe_near: float | None, far: float,
                      contract_radius: float) -> dict | None:
    """Bounds for a contracted recipe on a dataset that records none (not written by `poses`):
    None while the recipe's near holds, every camera at least recipe_near / NEAR_FACTOR outside
    the unit sphere (a normalised capture's region of interest; the synthetic orbits are); else
    the recipe's far and contraction radius with near lowered to NEAR_FACTOR x the nearest
    camera's distance to that sphere, never below points_near (the dataset's own near), which is
    near when a camera lies inside the sphere (a walk through a scene, not an orbit around one
    subject, where a near of 1 cuts off all that lies within a unit of that camera). c2w: [N, 3|4,
    4] in the normalised scene. Returns `scene_bounds`' keys (centre 0, radius 1) and "source":
    "cameras", or None."""
    if recipe_near is None:
        return None  # the dataset's own near is used
    gap = float(np.min(np.linalg.norm(np.asarray(c2w, np.float64)[:, :3, 3], axis=-1))) - 1.0
    near = max(NEAR_FACTOR * gap, float(points_near), NEAR_FLOOR)
    if near >= float(recipe_near):
        return None
    return {"near": near, "far": float(far), "contract_radius": float(contract_radius), "roi_centre": [0.0, 0.0, 0.0],
            "roi_radius": 1.0, "nearest_camera_to_roi": gap, "source": "cameras"}


def folder_camera_bounds(data, model) -> dict | None:
    """`unrecorded_bounds` of a dataset folder's cameras (read without the pixels) for a model
    config (its near, far, contract_radius); None when they cannot be read (the run's loading
    says why, in one line)."""
    try:
        scene = collect_scene(data, load_extras=False)
    except DataError:
        return None
    return unrecorded_bounds(scene.c2w, scene.near, model.near, model.far, model.contract_radius)


def recipe_with_bounds(recipe: dict, bounds: dict | None) -> dict:
    """The recipe (a config overrides dict) with model.near / far / contract_radius from a
    dataset's recorded `bounds` (None: the recipe unchanged; lay the user's --set flags on top
    afterwards). Returns a new dict."""
    if not bounds:
        return recipe
    model = dict(recipe.get("model", {}))
    for key in BOUND_KEYS:
        model[key] = float(bounds[key])
    return {**recipe, "model": model}


def bounds_warning(bounds: dict | None) -> str | None:
    """A one-line warning before training when a camera lies inside the region of interest (its
    recorded or camera-read "nearest_camera_to_roi" < 0): the photos look out from within the
    scene, not at one subject, and the contracted model, finest inside the unit sphere, comes out
    fogged on such a capture. None otherwise."""
    gap = (bounds or {}).get("nearest_camera_to_roi")
    if gap is None or gap >= 0:
        return None
    return (f"warning: a camera lies {-gap:.3g} inside the region of interest: the photos look out from within "
            "the scene rather than at one subject; the model resolves the region around one subject finest, "
            "so expect a fogged result (docs/BOUNDS.md)")


def bounds_line(bounds: dict | None) -> str:
    """One report line on where a run's bounds come from."""
    if not bounds:
        return ("Scene bounds: the recipe's constants (the dataset records no `scene_bounds`; "
                "docs/BOUNDS.md).")
    if bounds.get("source") == "cameras":
        where = (f"a camera lies {-bounds['nearest_camera_to_roi']:.3g} inside the region of interest (the "
                 "unit sphere): the photos walk through the scene rather than look at one subject, which the "
                 "model resolves finest inside that sphere" if bounds["nearest_camera_to_roi"] < 0 else
                 f"the nearest camera lies {bounds['nearest_camera_to_roi']:.3g} from the region of interest")
        return (f"Scene bounds: the recipe's, with near lowered to {bounds['near']:.3g}: {where} (the dataset "
                "records no `scene_bounds`; docs/BOUNDS.md).")
    return (f"Scene bounds from the data (docs/BOUNDS.md): near {bounds['near']:.3g}, far {bounds['far']:.4g}, "
            f"contraction radius {bounds['contract_radius']:g}, region of interest radius "
            f"{bounds['roi_radius']:.3g} around {', '.join(f'{v:.3g}' for v in bounds['roi_centre'])} "
            f"(normalised units).")
