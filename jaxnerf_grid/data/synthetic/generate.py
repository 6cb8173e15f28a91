"""Render the synthetic tower benchmark to a transforms.json dataset (docs/DATASET.md).

Per view, every pixel gets `supersample`^2 regular subpixel rays (averaged in linear radiance
for the colour images) plus one ray through the pixel centre, which alone decides the semantic
class and the z-depth. Train views carry per-view distractors; test views are clean
(their image *is* the clean image). The distractor mask marks pixels where any colour subsample
sees a distractor; the shadow mask marks the other pixels where any colour subsample lies in a
distractor's cast shadow. Outside these two masks the cluttered and clean images are identical
to the bit. Depth is z-depth along the camera's -z axis in normalised-scene units, +inf on sky.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import numpy as np

from jaxnerf_grid.util import io
from jaxnerf_grid.data.synthetic import CLASSES, DISTRACTOR_LEVELS, NORMALIZATION, PRESETS
from jaxnerf_grid.data.synthetic import cameras, scene as sc, shading
from jaxnerf_grid.data.synthetic.intersect import INTERSECT, KIND_CODE, KINDS, binned_trace, box_corners, box_local, intersect_ground, normal_box, normal_capsule, normal_cylinder, normal_ellipsoid, prim_bounds

SKY_CODE, GROUND_CODE = -1, -2
OUTPUT_DIRS = ("images", "clean", "depth", "clean_depth", "semantic", "distractor", "shadow")
# Written first into every dataset this generator makes: --overwrite clears only a folder that has
# it (or, from before the marker, a transforms.json with a "generator" record); docs/RELIABILITY.md.
SYNTH_MARKER = ".jaxnerf-grid-synth"


def is_synthetic_dataset(folder: Path) -> bool:
    """Whether `folder` was written by this generator (its marker, or an older dataset's
    transforms.json naming the generator)."""
    if (folder / SYNTH_MARKER).is_file():
        return True
    try:
        meta = io.read_json(folder / "transforms.json")
    except io.DataError:
        return False
    return isinstance(meta, dict) and isinstance(meta.get("generator"), dict)


@dataclasses.dataclass(frozen=True)
class SynthConfig:
    """Everything that decides a rendered dataset (a preset plus overrides)."""

    preset: str = "tower-small"
    seed: int = 0
    width: int = 160
    height: int = 120
    fov_deg: float = 60.0
    num_train: int = 40
    num_test: int = 8
    supersample: int = 2
    distractors: str = "medium"      # none | low | medium | high
    mode: str = "teleport"           # teleport | jitter
    shadows: bool = True
    trees: float = 1.0
    buildings: int = 26
    orbits: tuple = ()
    low_pass: tuple = ()
    conductors: bool = True          # the power lines (False: the towers alone, for the wire finder's test)


def make_config(preset: str, seed: int = 0, distractors: str | None = None, **overrides) -> SynthConfig:
    """A SynthConfig from a preset name and overrides (None values are ignored)."""
    if preset not in PRESETS:
        raise io.DataError(f"unknown synthetic preset {preset!r}; choose one of {sorted(PRESETS)}")
    values = dict(PRESETS[preset])
    values.update({k: v for k, v in overrides.items() if v is not None})
    if distractors is not None:
        values["distractors"] = distractors
    cfg = SynthConfig(preset=preset, seed=int(seed), **values)
    if cfg.distractors not in DISTRACTOR_LEVELS:
        raise io.DataError(f"unknown distractor level {cfg.distractors!r}; choose one of {list(DISTRACTOR_LEVELS)}")
    if cfg.mode not in ("teleport", "jitter"):
        raise io.DataError(f"unknown distractor mode {cfg.mode!r}; choose teleport or jitter")
    if cfg.width < 4 or cfg.height < 4 or cfg.supersample < 1 or cfg.num_train < 0 or cfg.num_test < 0:
        raise io.DataError(f"bad synthetic image size / view counts: {cfg}")
    if cfg.num_train + cfg.num_test < 1:
        raise io.DataError("synthetic scene needs at least one view")
    return cfg


# --- surfaces ------------------------------------------------------------------------------

def _surface(scene: sc.Scene, kind: np.ndarray, idx: np.ndarray, p: np.ndarray, d: np.ndarray,
             footprint: np.ndarray, seed: int):
    """Normals, albedo and class at hit points on a Scene's primitives.

    kind, idx: [N] (kind code into KINDS, local index); p, d: [N, 3]; footprint: [N] (m/pixel).
    Returns (normal [N, 3] facing the ray, albedo [N, 3], cls [N], obj [N]).
    """
    n = len(p)
    normal, albedo = np.zeros((n, 3)), np.zeros((n, 3))
    cls, obj = np.zeros(n, np.int64), np.zeros(n, np.int64)
    for name in KINDS:
        sel = np.nonzero(kind == KIND_CODE[name])[0]
        if not sel.size:
            continue
        g = {k: v[idx[sel]] for k, v in scene.tables[name].items()}
        a = {k: v[idx[sel]] for k, v in scene.attrs[name].items()}
        ps = p[sel]
        if name == "capsule":
            nn = normal_capsule(ps, g["a"], g["b"], g["r"])
        elif name == "cylinder":
            nn = normal_cylinder(ps, g["a"], g["b"], g["r"])
        elif name == "ellipsoid":
            nn = normal_ellipsoid(ps, g["c"], g["A"])
        else:
            nn = normal_box(ps, g["c"], g["R"], g["h"])
        col = shading.surface_albedo(a["material"], a["albedo"], ps, footprint[sel], seed)
        if name == "box":
            fac = a["material"] == sc.FACADE
            if fac.any():
                local, axis, _ = box_local(ps[fac], g["c"][fac], g["R"][fac], g["h"][fac])
                col[fac] = shading.facade_albedo(local, axis, g["h"][fac], a["albedo"][fac], footprint[sel][fac],
                                                 a["obj"][fac], seed)
        normal[sel], albedo[sel], cls[sel], obj[sel] = nn, col, a["cls"], a["obj"]
    flip = np.sum(normal * d, -1) > 0
    normal[flip] *= -1
    return normal, albedo, cls, obj


def _merge(scenes: list[sc.Scene]) -> tuple[sc.Scene, list[dict]]:
    """Concatenates scenes; returns (merged, per-scene {kind: index offset})."""
    offsets, tables, attrs = [], {}, {}
    for kind in KINDS:
        tables[kind] = {k: np.concatenate([s.tables[kind][k] for s in scenes]) for k in scenes[0].tables[kind]}
        attrs[kind] = {k: np.concatenate([s.attrs[kind][k] for s in scenes]) for k in scenes[0].attrs[kind]}
    running = {k: 0 for k in KINDS}
    for s in scenes:
        offsets.append(dict(running))
        for k in KINDS:
            running[k] += len(s.attrs[k]["cls"])
    return sc.Scene(tables, attrs), offsets


# --- distractors ---------------------------------------------------------------------------

_KIND_WEIGHTS = {"low": (0.5, 0.22, 0.0, 0.28), "medium": (0.4, 0.25, 0.08, 0.27),
                 "high": (0.25, 0.3, 0.15, 0.3)}            # person, car, truck, bird flock
_FOOTPRINT = {"person": 0.4, "car": 2.5, "truck": 4.8}     # ground radius (m) kept free of others
_GROUND_RANGE = {"low": (25.0, 110.0), "medium": (14.0, 110.0), "high": (11.0, 75.0)}


def _object_scene(kind: str, pos, heading, rng, obj, bird_scale=1.0) -> sc.Scene:
    b = sc.Builder()
    if kind == "person":
        sc.add_person(b, pos, heading, rng, obj)
    elif kind in ("car", "truck"):
        sc.add_vehicle(b, pos, heading, rng, obj, large=kind == "truck")
    else:
        sc.add_bird(b, pos, heading, rng, obj, bird_scale)
    return b.finish()


def _ground_ok(kind: str, xy: np.ndarray) -> bool:
    """Keeps distractors off the tower footings (vehicles off the gravel pad)."""
    if kind in ("car", "truck"):
        return max(abs(xy[0]), abs(xy[1])) > 8.0
    corners = np.array([[4, 4], [-4, 4], [-4, -4], [4, -4]], float)
    return bool(np.min(np.linalg.norm(corners - xy, axis=-1)) > 1.2)


class _ViewState:
    """Rays of one view and the per-ray distractor hits accumulated object by object."""

    def __init__(self, o, d, static_t, intr, c2w, shape):
        self.o, self.d, self.static_t = o, d, static_t
        self.intr, self.c2w, self.shape = intr, c2w, shape      # shape = (H, W, K)
        n = len(o)
        self.t = np.full(n, np.inf)
        self.obj = np.full(n, -1, np.int64)
        self.kind = np.full(n, -1, np.int64)
        self.idx = np.full(n, -1, np.int64)
        self.objects: list[sc.Scene] = []
        self.flat = np.arange(n).reshape(shape)
        self.pixel_hit = np.zeros(shape[:2], bool)

    def coverage(self) -> float:
        return float(self.pixel_hit.mean())

    def rays_near(self, lo, hi) -> np.ndarray:
        """Flat ray ids whose pixels may see the box [lo, hi] (bounding-sphere projection)."""
        h, w, _ = self.shape
        centre, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo) + 0.05
        rot, eye = self.c2w[:3, :3], self.c2w[:3, 3]
        pc = rot.T @ (centre - eye)
        depth = -pc[2]
        if depth - radius < 0.2:
            return self.flat.ravel()
        f = self.intr["fl_x"]
        u = f * pc[0] / depth + self.intr["cx"]
        v = -f * pc[1] / depth + self.intr["cy"]
        rad = f * radius / (depth - radius) + 2.0
        u0, u1 = int(max(0, math.floor(u - rad))), int(min(w, math.ceil(u + rad)))
        v0, v1 = int(max(0, math.floor(v - rad))), int(min(h, math.ceil(v + rad)))
        if u0 >= u1 or v0 >= v1:
            return np.zeros(0, np.int64)
        return self.flat[v0:v1, u0:u1].ravel()

    def try_add(self, obj_scene: sc.Scene, max_coverage: float = 1.0) -> float:
        """Adds an object if its visible coverage keeps the total <= max_coverage.

        Returns the number of pixels it newly covers (0 and not added when rejected/invisible).
        """
        los, his = [], []
        for kind in KINDS:
            if len(obj_scene.attrs[kind]["cls"]):
                lo, hi = prim_bounds(kind, obj_scene.tables[kind])
                los.append(lo.min(0))
                his.append(hi.max(0))
        ids = self.rays_near(np.min(los, 0), np.max(his, 0))
        if not ids.size:
            return 0
        best = np.minimum(self.static_t[ids], self.t[ids])
        t_new = np.full(len(ids), np.inf)
        k_new = np.full(len(ids), -1)
        i_new = np.full(len(ids), -1)
        for kind in KINDS:
            if not len(obj_scene.attrs[kind]["cls"]):
                continue
            t = INTERSECT[kind](self.o[ids], self.d[ids], obj_scene.tables[kind])
            j = np.argmin(t, axis=1)
            tm = t[np.arange(len(ids)), j]
            better = tm < t_new
            t_new[better], k_new[better], i_new[better] = tm[better], KIND_CODE[kind], j[better]
        wins = t_new < best
        if not wins.any():
            return 0
        h, w, k = self.shape
        colour = (ids % k) < k - 1
        pix = np.zeros((h, w), bool)
        pix.ravel()[ids[wins & colour] // k] = True
        new_pixels = int((pix & ~self.pixel_hit).sum())
        if new_pixels == 0:
            return 0
        if (self.pixel_hit.sum() + new_pixels) / (h * w) > max_coverage:
            return 0
        number = len(self.objects)
        self.objects.append(obj_scene)
        sel = ids[wins]
        self.t[sel], self.obj[sel], self.kind[sel], self.idx[sel] = t_new[wins], number, k_new[wins], i_new[wins]
        self.pixel_hit |= pix
        return new_pixels


def _place_teleport(state: _ViewState, level: str, rng: np.random.Generator, static_info) -> None:
    """Re-places distractors for this view until its coverage target is reached."""
    lo_cov, hi_cov = DISTRACTOR_LEVELS[level]
    target = rng.uniform(lo_cov, hi_cov)
    h, w, k = state.shape
    centre = state.flat[..., k - 1].ravel()
    src, t_static = static_info["source"][centre], state.static_t[centre]
    g_lo, g_hi = _GROUND_RANGE[level]
    ground_pool = centre[(src == GROUND_CODE) & (t_static > g_lo) & (t_static < g_hi)]
    kinds = ("person", "car", "truck", "bird")
    weights = np.array(_KIND_WEIGHTS[level])
    if not ground_pool.size:
        weights = np.array([0.0, 0.0, 0.0, 1.0])
    cap = hi_cov
    attempts = 0
    footprints = []
    while state.coverage() < target and attempts < 1500 and len(state.objects) < 700:
        attempts += 1
        kind = kinds[rng.choice(4, p=weights / weights.sum())]
        heading = rng.uniform(0, 2 * np.pi)
        seed = int(rng.integers(2**31))
        if kind == "bird":
            ray = int(rng.choice(centre))
            far = min(state.static_t[ray] - 2.0, 90.0)
            if far <= 16.0:
                continue
            pos = state.o[ray] + rng.uniform(16.0, far) * state.d[ray]     # >= ~11 m after flock spread
            flock = int(rng.integers(1, 6))
            scale = rng.uniform(1.0, 2.2)
            for b in range(flock):
                p = pos + (rng.normal(size=3) * [2.0, 2.0, 0.8] if b else 0.0)
                if p[2] < 2.5:
                    continue
                state.try_add(_object_scene("bird", p, heading + rng.normal() * 0.3,
                                            np.random.default_rng(seed + b), 0, scale), cap)
            continue
        ray = int(rng.choice(ground_pool))
        pos = state.o[ray] + state.static_t[ray] * state.d[ray]
        radius = _FOOTPRINT[kind]
        if not _ground_ok(kind, pos[:2]) or any(np.hypot(*(pos[:2] - xy)) < radius + r for xy, r in footprints):
            continue                                      # on a footing or overlapping another object
        if state.try_add(_object_scene(kind, pos, heading, np.random.default_rng(seed), 0), cap):
            footprints.append((pos[:2], radius))


def jitter_base(level: str, rng: np.random.Generator) -> list[tuple]:
    """Distractor layout shared by all views in jitter mode: [(kind, pos [3], heading, seed)]."""
    count = {"none": 0, "low": 12, "medium": 45, "high": 120}[level]
    out = []
    for _ in range(count):
        kind = ("person", "car", "truck", "bird")[rng.choice(4, p=[0.45, 0.25, 0.05, 0.25])]
        r, a = rng.uniform(6.0, 45.0), rng.uniform(0, 2 * np.pi)
        pos = np.array([r * np.cos(a), r * np.sin(a), 0.0])
        if kind == "bird":
            pos[2] = rng.uniform(5.0, 40.0)
        elif not _ground_ok(kind, pos[:2]):
            continue
        out.append((kind, pos, rng.uniform(0, 2 * np.pi), int(rng.integers(2**31))))
    return out


def _place_jitter(state: _ViewState, base: list, rng: np.random.Generator) -> None:
    for kind, pos, heading, seed in base:
        step = {"person": 1.0, "car": 2.0, "truck": 2.0, "bird": 3.0}[kind]
        p = pos + rng.normal(size=3) * [step, step, step if kind == "bird" else 0.0]
        state.try_add(_object_scene(kind, p, heading + rng.normal() * 0.2, np.random.default_rng(seed), 0, 1.6))


# --- one view ------------------------------------------------------------------------------

TILE = 8            # screen tile (pixels) for binning primary rays
SUN_CELL = 3.0      # cell (m) of the plane perpendicular to the sun for binning shadow rays


def scene_bounds(scene: sc.Scene) -> dict:
    """{kind: (lo [M, 3], hi [M, 3])} axis-aligned bounds of every primitive."""
    return {k: prim_bounds(k, scene.tables[k]) for k in KINDS}


def screen_rects(bounds: dict, c2w: np.ndarray, intr: dict, tile: int | None = None) -> tuple[dict, int]:
    """Inclusive tile rectangles covering each primitive's projected bounds in one camera.

    A primitive whose bounds reach behind (or within 0.1 m of) the camera plane gets the whole
    screen. Returns ({kind: [M, 4]}, tiles per row).
    """
    tile = tile or TILE
    gw, gh = -(-intr["w"] // tile), -(-intr["h"] // tile)
    rot, eye = c2w[:3, :3], c2w[:3, 3]
    rects = {}
    for kind, (lo, hi) in bounds.items():
        if len(lo) == 0:
            rects[kind] = np.zeros((0, 4), np.int64)
            continue
        cam = (box_corners(lo, hi) - eye) @ rot                      # [M, 8, 3] camera coords
        depth = -cam[..., 2]
        behind = depth.min(1) < 0.1                                    # straddles the camera plane
        hidden = depth.max(1) < 0.1                                    # entirely behind the camera
        safe = np.maximum(depth, 0.1)
        u = intr["fl_x"] * cam[..., 0] / safe + intr["cx"]
        v = -intr["fl_y"] * cam[..., 1] / safe + intr["cy"]
        r = np.stack([np.floor(u.min(1) / tile), np.floor(v.min(1) / tile),
                      np.floor(u.max(1) / tile), np.floor(v.max(1) / tile)], -1)
        r = np.where(behind[:, None], [0, 0, gw - 1, gh - 1], r)
        r = np.where(hidden[:, None], [0, 0, -1, -1], r)
        r[:, 0], r[:, 1] = np.maximum(r[:, 0], 0), np.maximum(r[:, 1], 0)
        r[:, 2], r[:, 3] = np.minimum(r[:, 2], gw - 1), np.minimum(r[:, 3], gh - 1)
        rects[kind] = r.astype(np.int64)                              # off-screen: x1 < x0 or y1 < y0
    return rects, gw


class SunGrid:
    """Cells of the plane perpendicular to the sun: a shadow ray p + t * sun meets only the
    primitives whose projected bounds cover the projection of p."""

    def __init__(self, sun: np.ndarray, bounds: dict, cell: float | None = None):
        cell = cell or SUN_CELL
        helper = np.array([0.0, 0.0, 1.0]) if abs(sun[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        e1 = np.cross(sun, helper)
        e1 /= np.linalg.norm(e1)
        self.basis = np.stack([e1, np.cross(sun, e1)], -1)           # [3, 2]
        corners = np.concatenate([box_corners(lo, hi).reshape(-1, 3) for lo, hi in bounds.values() if len(lo)])
        proj = corners @ self.basis
        self.origin = proj.min(0) - cell
        self.cell = cell
        self.gw, self.gh = (np.ceil((proj.max(0) - self.origin) / cell) + 2).astype(int)

    def rects(self, bounds: dict) -> dict:
        out = {}
        for kind, (lo, hi) in bounds.items():
            if len(lo) == 0:
                out[kind] = np.zeros((0, 4), np.int64)
                continue
            proj = (box_corners(lo, hi) @ self.basis - self.origin) / self.cell   # [M, 8, 2]
            r = np.concatenate([np.floor(proj.min(1)), np.floor(proj.max(1))], -1)
            r[:, :2] = np.maximum(r[:, :2], 0)
            r[:, 2] = np.minimum(r[:, 2], self.gw - 1)
            r[:, 3] = np.minimum(r[:, 3], self.gh - 1)
            out[kind] = r.astype(np.int64)
        return out

    def cells(self, points: np.ndarray) -> np.ndarray:
        """Cell id [N] of points [N, 3] (-1 outside the grid)."""
        c = np.floor((points @ self.basis - self.origin) / self.cell).astype(np.int64)
        ok = (c[:, 0] >= 0) & (c[:, 0] < self.gw) & (c[:, 1] >= 0) & (c[:, 1] < self.gh)
        return np.where(ok, c[:, 1] * self.gw + c[:, 0], -1)

    def occluded(self, tables: dict, rects: dict, origins: np.ndarray, sun: np.ndarray) -> np.ndarray:
        """bool [N]: the shadow ray from each origin [N, 3] hits a primitive."""
        t, _, _ = binned_trace(tables, rects, self.gw, self.cells(origins), origins,
                               np.broadcast_to(sun, origins.shape))
        return np.isfinite(t)


class StaticWorld:
    """The static scene, its bounds, lighting and shadow grid, shared by all views of a dataset."""

    def __init__(self, cfg: SynthConfig):
        rng = np.random.default_rng([cfg.seed, 0])
        self.scene, self.attachments = sc.static_scene(rng, trees=cfg.trees, buildings=cfg.buildings,
                                                       conductors=cfg.conductors)
        self.bounds = scene_bounds(self.scene)
        self.sun = shading.sun_direction(rng.uniform(35.0, 55.0), rng.uniform(0.0, 360.0))
        self.tex_seed = int(rng.integers(1 << 20))
        self.jitter = jitter_base(cfg.distractors, np.random.default_rng([cfg.seed, 3]))
        self.sun_grid = SunGrid(self.sun, self.bounds)
        self.sun_rects = self.sun_grid.rects(self.bounds)


def _shadow_offset(p, n, t):
    return p + n * (2e-3 + 2e-5 * t)[:, None]


def ray_trace_frame(world: StaticWorld, cfg: SynthConfig, c2w: np.ndarray, intr: dict, clutter: bool,
                    rng: np.random.Generator) -> dict:
    """Ray-traces one frame of the synthetic world (ground truth, not a NeRF render). c2w: [4, 4] metric.

    Returns {"clean" [H, W, 3], "image" [H, W, 3], "semantic" [H, W] uint8, "clean_semantic",
    "depth" [H, W] (metric z-depth, inf on sky), "clean_depth", "distractor" [H, W] bool,
    "shadow" [H, W] bool, "coverage" float}.
    """
    h, w, s = intr["h"], intr["w"], cfg.supersample
    o, d, cos = cameras.view_rays(c2w, intr, s)
    k = o.shape[2]
    o, d, cos = o.reshape(-1, 3), d.reshape(-1, 3), cos.reshape(-1)
    n = len(o)
    t_ground = intersect_ground(o, d)
    rects, gw = screen_rects(world.bounds, c2w, intr)
    flat = np.arange(n)
    ray_tile = (flat // (w * k) // TILE) * gw + (flat // k % w) // TILE
    t_obj, kind, idx = binned_trace(world.scene.tables, rects, gw, ray_tile, o, d, t_max=t_ground)
    source = np.where(np.isfinite(t_obj), kind, np.where(np.isfinite(t_ground), GROUND_CODE, SKY_CODE))
    t_static = np.where(np.isfinite(t_obj), t_obj, t_ground)
    pix_angle = 1.0 / intr["fl_x"]

    def surfaces(scene, src, kd, ix, t, rays):
        """Normal, albedo, class for rays `rays` hitting ground (src -2) or scene primitives."""
        p = o[rays] + t[:, None] * d[rays]
        foot = t * pix_angle
        normal = np.zeros((len(rays), 3))
        albedo = np.zeros((len(rays), 3))
        cls = np.zeros(len(rays), np.int64)
        gr = src == GROUND_CODE
        if gr.any():
            foot_g = foot[gr] / np.sqrt(np.maximum(np.abs(d[rays][gr, 2]), 0.05))
            normal[gr] = [0.0, 0.0, 1.0]
            albedo[gr] = shading.ground_albedo(p[gr], foot_g, world.tex_seed)
            cls[gr] = sc.GROUND
        ob = src >= 0
        if ob.any():
            nn, al, cl, _ = _surface(scene, kd[ob], ix[ob], p[ob], d[rays][ob], foot[ob], world.tex_seed)
            normal[ob], albedo[ob], cls[ob] = nn, al, cl
        return p, normal, albedo, cls

    hit = np.nonzero(source != SKY_CODE)[0]
    p_s, n_s, alb_s, cls_hit = surfaces(world.scene, source[hit], kind[hit], idx[hit], t_static[hit], hit)
    cls_static = np.zeros(n, np.int64)
    cls_static[hit] = cls_hit
    # Shadow rays only where the sun can light the surface at all (n . sun > 0).
    vis_s = (n_s @ world.sun > 0).astype(float)
    if cfg.shadows and len(hit):
        facing = np.nonzero(vis_s)[0]
        occ = world.sun_grid.occluded(world.scene.tables, world.sun_rects,
                                      _shadow_offset(p_s[facing], n_s[facing], t_static[hit][facing]), world.sun)
        vis_s[facing[occ]] = 0.0
    rad_static = np.zeros((n, 3))
    sky = np.nonzero(source == SKY_CODE)[0]
    rad_static[sky] = shading.sky_radiance(d[sky], world.sun, world.tex_seed)
    rad_static[hit] = shading.haze(shading.lambert(alb_s, n_s, world.sun, vis_s), t_static[hit])

    shape = (h, w, k)
    state = _ViewState(o, d, np.where(source == SKY_CODE, np.inf, t_static), intr, c2w, shape)
    if clutter and cfg.distractors != "none":
        if cfg.mode == "teleport":
            _place_teleport(state, cfg.distractors, rng, {"source": source})
        else:
            _place_jitter(state, world.jitter, rng)

    rad = rad_static.copy()
    cls_final = cls_static.copy()
    depth_t = t_static.copy()
    shadowed_by_d = np.zeros(n, bool)
    dhit = np.nonzero(state.obj >= 0)[0]
    if state.objects:
        dscene, offsets = _merge(state.objects)
        gidx = state.idx.copy()
        for number, off in enumerate(offsets):
            for kname, base in off.items():
                m = (state.obj == number) & (state.kind == KIND_CODE[kname])
                gidx[m] += base
        d_rects = world.sun_grid.rects(scene_bounds(dscene))
        p_d, n_d, alb_d, cls_d = surfaces(dscene, state.kind[dhit], state.kind[dhit], gidx[dhit], state.t[dhit], dhit)
        vis_d = (n_d @ world.sun > 0).astype(float)
        if cfg.shadows:
            facing = np.nonzero(vis_d)[0]
            origin = _shadow_offset(p_d[facing], n_d[facing], state.t[dhit][facing])
            occ_a = world.sun_grid.occluded(world.scene.tables, world.sun_rects, origin, world.sun)
            occ_b = world.sun_grid.occluded(dscene.tables, d_rects, origin, world.sun)
            vis_d[facing[occ_a | occ_b]] = 0.0
            # Static surfaces in a distractor's shadow (only where the sun reached them).
            lit = np.nonzero(vis_s > 0)[0]
            occ_c = world.sun_grid.occluded(dscene.tables, d_rects,
                                            _shadow_offset(p_s[lit], n_s[lit], t_static[hit][lit]), world.sun)
            dark = lit[occ_c]
            rays_dark = hit[dark]
            keep = state.obj[rays_dark] < 0            # not covered by a distractor themselves
            dark, rays_dark = dark[keep], rays_dark[keep]
            shadowed_by_d[rays_dark] = True
            rad[rays_dark] = shading.haze(shading.lambert(alb_s[dark], n_s[dark], world.sun, np.zeros(len(dark))),
                                          t_static[rays_dark])
        rad[dhit] = shading.haze(shading.lambert(alb_d, n_d, world.sun, vis_d), state.t[dhit])
        cls_final[dhit] = cls_d
        depth_t[dhit] = state.t[dhit]

    def image(radiance):
        return shading.to_srgb(radiance.reshape(h, w, k, 3)[:, :, : k - 1].mean(axis=2)).astype(np.float32)

    def centre(values):
        return values.reshape(h, w, k)[:, :, k - 1]

    covered = (state.obj >= 0).reshape(h, w, k)[:, :, : k - 1].any(axis=2)
    shadow = shadowed_by_d.reshape(h, w, k)[:, :, : k - 1].any(axis=2) & ~covered
    sky_static = centre(source == SKY_CODE)
    clean_depth = np.where(sky_static, np.inf, centre(t_static * cos))
    final_sky = sky_static & (centre(state.obj) < 0)
    depth = np.where(final_sky, np.inf, centre(depth_t * cos))
    clean = image(rad_static)
    return {"clean": clean, "image": image(rad) if state.objects else clean,
            "semantic": centre(cls_final).astype(np.uint8), "clean_semantic": centre(cls_static).astype(np.uint8),
            "depth": depth, "clean_depth": clean_depth, "distractor": covered, "shadow": shadow,
            "coverage": float(covered.mean()), "num_objects": len(state.objects)}


# --- the dataset ---------------------------------------------------------------------------

def _frame_record(name: str, split: str, c2w_norm: np.ndarray) -> dict:
    rec = {"file_path": f"images/{name}.png", "transform_matrix": c2w_norm.tolist(), "split": split,
           "clean_file_path": f"clean/{name}.png", "depth_file_path": f"depth/{name}.exr",
           "semantic_file_path": f"semantic/{name}.png", "distractor_mask_path": f"distractor/{name}.png",
           "shadow_mask_path": f"shadow/{name}.png"}
    if split == "train":
        rec["clean_depth_file_path"] = f"clean_depth/{name}.exr"
    return rec


def _write_view(out: Path, name: str, split: str, views: dict, scale: float) -> None:
    io.write_png(out / "images" / f"{name}.png", views["image"])
    io.write_png(out / "clean" / f"{name}.png", views["clean"])
    io.write_exr(out / "depth" / f"{name}.exr", (views["depth"] * scale).astype(np.float32))
    if split == "train":
        io.write_exr(out / "clean_depth" / f"{name}.exr", (views["clean_depth"] * scale).astype(np.float32))
    io.write_png(out / "semantic" / f"{name}.png", views["semantic"].astype(np.float32) / 255.0)
    io.write_png(out / "distractor" / f"{name}.png", views["distractor"].astype(np.float32))
    io.write_png(out / "shadow" / f"{name}.png", views["shadow"].astype(np.float32))


_WORKER: dict = {}


def _worker_init(cfg: SynthConfig, out: str) -> None:
    _WORKER["world"] = StaticWorld(cfg)
    _WORKER["cfg"] = cfg
    _WORKER["out"] = Path(out)


def _render_and_write(task) -> tuple[float, int]:
    """Renders and writes one view; task = (index, name, split, c2w [4, 4] metric)."""
    i, name, sp, c2w = task
    cfg, world, out = _WORKER["cfg"], _WORKER["world"], _WORKER["out"]
    intr = cameras.intrinsics(cfg.width, cfg.height, cfg.fov_deg)
    views = ray_trace_frame(world, cfg, c2w, intr, sp == "train", np.random.default_rng([cfg.seed, 2, i]))
    _write_view(out, name, sp, views, NORMALIZATION["scale"])
    return views["coverage"], views["num_objects"]


def generate_scene(preset: str, out_dir, seed: int = 0, distractors: str | None = None, overwrite: bool = False,
                   progress: bool = True, workers: int = 1, **overrides) -> Path:
    """Renders a synthetic dataset; returns the path of its transforms.json.

    overrides: any SynthConfig field (width, height, num_train, num_test, supersample, mode,
    shadows, fov_deg, trees, buildings, conductors). `workers` > 1 renders views in that many spawned
    processes (the output is identical for any worker count). Refuses a non-empty `out_dir`
    unless `overwrite` (then only this generator's own files and folders there are replaced).
    """
    from jaxnerf_grid.util import progress as progress_lib

    cfg = make_config(preset, seed, distractors, **overrides)
    out = io.ensure_writable(out_dir, overwrite)
    if overwrite and out.is_dir() and any(out.iterdir()):
        if not is_synthetic_dataset(out):
            raise io.DataError(f"{out}: not a dataset written by synth (no {SYNTH_MARKER} marker); "
                               "refusing to clear it, even with --overwrite")
        for sub in OUTPUT_DIRS:
            if (out / sub).is_dir():
                shutil.rmtree(out / sub)
        for f in ("transforms.json", "tower.ply", "preview.png"):
            if (out / f).is_file():
                (out / f).unlink()
    out.mkdir(parents=True, exist_ok=True)
    (out / SYNTH_MARKER).write_text("written by jaxnerf-grid synth; --overwrite may clear this folder\n")
    intr = cameras.intrinsics(cfg.width, cfg.height, cfg.fov_deg)
    c2w_all, split = cameras.camera_path(cfg.num_train, cfg.num_test, cfg.orbits, cfg.low_pass,
                                         np.random.default_rng([cfg.seed, 1]))
    scale, translation = NORMALIZATION["scale"], NORMALIZATION["translation"]
    counters = {"train": 0, "test": 0}
    tasks = []
    for i, sp in enumerate(split):
        tasks.append((i, f"{sp}_{counters[sp]:03d}", sp, c2w_all[i]))
        counters[sp] += 1
    bar = dict(total=len(tasks), desc=f"synth {cfg.preset}", unit="view", enabled=progress)
    workers = max(1, min(int(workers), len(tasks)))
    if workers == 1:
        _worker_init(cfg, str(out))
        results = [_render_and_write(t) for t in progress_lib.bar(tasks, **bar)]
        world = _WORKER["world"]
    else:
        import multiprocessing
        import sys
        from concurrent.futures import ProcessPoolExecutor, as_completed
        from concurrent.futures.process import BrokenProcessPool

        ctx = multiprocessing.get_context("spawn")
        done: dict = {}
        with progress_lib.bar(**bar) as pbar:
            try:
                with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init,
                                         initargs=(cfg, str(out))) as pool:
                    futures = {pool.submit(_render_and_write, t): t[0] for t in tasks}
                    for fut in as_completed(futures):
                        done[futures[fut]] = fut.result()
                        pbar.update(1)
            except BrokenProcessPool:
                # A worker was killed (e.g. by the OOM killer): finish the rest in this process.
                print(f"synth: a worker process died; rendering the remaining {len(tasks) - len(done)} views "
                      "in the main process", file=sys.stderr)
                _worker_init(cfg, str(out))
                for t in tasks:
                    if t[0] not in done:
                        done[t[0]] = _render_and_write(t)
                        pbar.update(1)
        results = [done[t[0]] for t in tasks]
        world = _WORKER.get("world") or StaticWorld(cfg)
    frames, coverages = [], []
    for (i, name, sp, c2w), (coverage, num_objects) in zip(tasks, results):
        rec = _frame_record(name, sp, cameras.normalise_pose(c2w, scale, translation))
        rec["distractor_coverage"] = round(coverage, 6)
        rec["num_distractors"] = num_objects
        frames.append(rec)
        if sp == "train":
            coverages.append(coverage)
    tower = sc.main_tower_scene(0)
    pts = sc.sample_tower_points(tower, 60000, np.random.default_rng([cfg.seed, 4]))
    io.write_ply(out / "tower.ply", scale * (pts + np.asarray(translation)))
    cov = np.asarray(coverages) if coverages else np.zeros(1)
    transforms = {
        **{k: v for k, v in intr.items()},
        "camera_model": "PINHOLE",
        "near": 0.5,
        "far": 40.0,
        "scene_normalization": {"scale": scale, "translation": list(translation)},
        "tower_ply": "tower.ply",
        "semantic_classes": list(CLASSES),
        "generator": {
            "name": "jaxnerf_grid.data.synthetic", "preset": cfg.preset, "seed": cfg.seed,
            "distractors": cfg.distractors, "distractor_mode": cfg.mode, "shadows": cfg.shadows,
            "conductors": cfg.conductors,
            "supersample": cfg.supersample, "fov_deg": cfg.fov_deg,
            "sun_direction": [round(float(x), 6) for x in world.sun],
            "depth": "z-depth along camera -z, normalised units, +inf on sky; semantic and depth from the pixel-centre ray",
            "distractor_coverage": {"mean": round(float(cov.mean()), 6), "min": round(float(cov.min()), 6),
                                    "max": round(float(cov.max()), 6)},
            "num_static_primitives": world.scene.count(),
        },
        "frames": frames,
    }
    io.write_json(out / "transforms.json", transforms)
    return out / "transforms.json"


def contact_sheet(dataset_dir, out_png, count: int = 4) -> Path:
    """A PNG grid of the first `count` train views: image, clean, semantic, depth, masks."""
    root = Path(dataset_dir)
    meta = io.read_json(root / "transforms.json")
    frames = [f for f in meta["frames"] if f["split"] == "train"][:count]
    palette = np.array([[0.55, 0.75, 0.95], [0.9, 0.1, 0.1], [1.0, 0.8, 0.0], [0.45, 0.35, 0.2], [0.1, 0.6, 0.1],
                        [0.6, 0.6, 0.65], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, 0.5, 0.0]])
    rows = []
    for f in frames:
        img = io.read_image(root / f["file_path"])
        clean = io.read_image(root / f["clean_file_path"])
        sem = palette[np.round(io.read_mask(root / f["semantic_file_path"]) * 255).astype(int)]
        depth = io.read_exr(root / f["depth_file_path"])
        disp = np.where(np.isfinite(depth), 1.0 / np.maximum(depth, 1e-3), 0.0)
        disp = np.repeat((disp / max(disp.max(), 1e-6))[..., None], 3, -1)
        dm = io.read_mask(root / f["distractor_mask_path"])
        sm = io.read_mask(root / f["shadow_mask_path"])
        masks = np.stack([dm, sm, np.zeros_like(dm)], -1)
        rows.append(np.concatenate([img, clean, sem, disp, masks], axis=1))
    io.write_png(out_png, np.concatenate(rows, axis=0))
    return Path(out_png)
