"""The procedural power-grid scene: lattice tower, conductors, tree line, buildings, distractors.

World units are metres, +z up, the main tower's base centred at the origin, the line running
along +-y. A scene is a `Scene` (primitive tables per kind plus per-primitive attributes);
`static_scene(rng)` builds everything that is the same in every view, `distractor_*` build one
distractor each (a few primitives) for the per-view clutter.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxnerf_grid.data.synthetic import CLASSES
from jaxnerf_grid.data.synthetic.intersect import KINDS

SKY, TOWER, CONDUCTOR, GROUND, VEGETATION, BUILDING, PERSON, VEHICLE, BIRD = range(9)
assert CLASSES[TOWER] == "tower" and CLASSES[BIRD] == "bird"

# Materials select the procedural texture in shading.py.
PLAIN, FOLIAGE, FACADE, METAL = range(4)

SPAN = 320.0            # distance between towers along the line (m)
TOWER_HEIGHT = 30.0


class Scene(NamedTuple):
    """tables: {kind: geometry dict}; attrs: {kind: {"cls" [M] int, "albedo" [M, 3],
    "material" [M] int, "obj" [M] int (object id, e.g. one distractor or one building)}}."""

    tables: dict
    attrs: dict

    def count(self) -> int:
        return sum(len(a["cls"]) for a in self.attrs.values())


class Builder:
    """Accumulates primitives; `finish()` stacks them into a Scene."""

    def __init__(self):
        self.geom = {k: [] for k in KINDS}
        self.attr = {k: [] for k in KINDS}

    def _add(self, kind, geom, cls, albedo, material, obj):
        self.geom[kind].append(geom)
        self.attr[kind].append((cls, np.asarray(albedo, float), material, obj))

    def capsule(self, a, b, r, cls, albedo, material=PLAIN, obj=0):
        self._add("capsule", (np.asarray(a, float), np.asarray(b, float), float(r)), cls, albedo, material, obj)

    def cylinder(self, a, b, r, cls, albedo, material=PLAIN, obj=0):
        self._add("cylinder", (np.asarray(a, float), np.asarray(b, float), float(r)), cls, albedo, material, obj)

    def ellipsoid(self, c, radii, rotation, cls, albedo, material=PLAIN, obj=0):
        """radii: [3] semi-axes along the columns of rotation [3, 3]."""
        A = np.diag(1.0 / np.asarray(radii, float)) @ np.asarray(rotation, float).T
        self._add("ellipsoid", (np.asarray(c, float), A), cls, albedo, material, obj)

    def box(self, c, half, rotation, cls, albedo, material=PLAIN, obj=0):
        self._add("box", (np.asarray(c, float), np.asarray(rotation, float), np.asarray(half, float)),
                  cls, albedo, material, obj)

    def finish(self) -> Scene:
        names = {"capsule": ("a", "b", "r"), "cylinder": ("a", "b", "r"),
                 "ellipsoid": ("c", "A"), "box": ("c", "R", "h")}
        tables, attrs = {}, {}
        for kind in KINDS:
            items = self.geom[kind]
            if items:
                tables[kind] = {name: np.stack([np.asarray(it[i], float) for it in items])
                                for i, name in enumerate(names[kind])}
                cls, alb, mat, obj = zip(*self.attr[kind])
                attrs[kind] = {"cls": np.array(cls, np.int64), "albedo": np.stack(alb),
                               "material": np.array(mat, np.int64), "obj": np.array(obj, np.int64)}
            else:
                shapes = {"a": (0, 3), "b": (0, 3), "r": (0,), "c": (0, 3), "A": (0, 3, 3),
                          "R": (0, 3, 3), "h": (0, 3)}
                tables[kind] = {name: np.zeros(shapes[name]) for name in names[kind]}
                attrs[kind] = {"cls": np.zeros(0, np.int64), "albedo": np.zeros((0, 3)),
                               "material": np.zeros(0, np.int64), "obj": np.zeros(0, np.int64)}
        return Scene(tables, attrs)


def yaw(angle: float) -> np.ndarray:
    """Rotation [3, 3] about +z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# --- the lattice tower --------------------------------------------------------------------

LEVELS = np.array([0.0, 4.0, 8.0, 12.0, 15.0, 17.5, 19.0, 21.5, 23.0, 25.5, 27.0, 30.0])
ARM_LEVELS = (17.5, 21.5, 25.5)
ARM_LENGTHS = (6.5, 7.5, 6.5)
INSULATOR_LENGTH = 2.6


def half_width(z):
    """Tower body half-width (m) at height z: 4 m at the base tapering to 1.1 m at the waist."""
    return np.interp(z, [0.0, 17.5, 27.0, 30.0], [4.0, 1.1, 1.1, 0.35])


def _corner(z, i):
    """Leg corner i in {0,1,2,3} (counter-clockwise from (+,+)) at height z. Returns [3]."""
    sx, sy = [(1, 1), (-1, 1), (-1, -1), (1, -1)][i]
    w = half_width(z)
    return np.array([sx * w, sy * w, z])


def tower_members(rng: np.random.Generator, offset=(0.0, 0.0, 0.0)):
    """Lattice members of one tower.

    Returns (capsules: list of (a [3], b [3], r), cylinders: list of (a, b, r, insulator: bool),
    boxes: list of (centre, half), attachments: [K, 3] conductor attachment points (phase
    conductors first, then the two earth wires)).
    """
    off = np.asarray(offset, float)
    caps, cyls, boxes = [], [], []

    def member(a, b, r):
        caps.append((np.asarray(a) + off, np.asarray(b) + off, r))

    leg_r = lambda z: float(np.interp(z, [0, 30], [0.2, 0.1]))  # noqa: E731
    for k in range(len(LEVELS) - 1):
        z0, z1 = LEVELS[k], LEVELS[k + 1]
        zm = 0.5 * (z0 + z1)
        for i in range(4):
            j = (i + 1) % 4
            member(_corner(z0, i), _corner(z1, i), leg_r(zm))                 # leg
            member(_corner(z0, i), _corner(z1, j), 0.055)                    # X bracing
            member(_corner(z0, j), _corner(z1, i), 0.055)
            member(_corner(z1, i), _corner(z1, j), 0.065)                    # horizontal
            if z1 - z0 >= 3.5:                                               # secondary bracing
                centre = 0.5 * (_corner(zm, i) + _corner(zm, j))
                for zq, c in ((z0 + 0.25 * (z1 - z0), i), (z0 + 0.75 * (z1 - z0), j),
                              (z0 + 0.25 * (z1 - z0), j), (z0 + 0.75 * (z1 - z0), i)):
                    member(_corner(zq, c), centre, 0.04)
                member(_corner(zm, i), _corner(zm, j), 0.04)
        if z1 in ARM_LEVELS or z1 == 12.0:                                   # plan bracing
            member(_corner(z1, 0), _corner(z1, 2), 0.05)
            member(_corner(z1, 1), _corner(z1, 3), 0.05)
    attachments = []
    for z_a, length in zip(ARM_LEVELS, ARM_LENGTHS):
        w = half_width(z_a)
        for s in (-1.0, 1.0):
            tip_x = s * (w + length)
            top = z_a + 1.8
            root_b = [np.array([s * w, y, z_a]) for y in (-w, w)]
            root_t = [np.array([s * w, y * 0.6, top]) for y in (-w, w)]
            tips = [np.array([tip_x, y, z_a]) for y in (-0.35, 0.35)]
            for rb, rt, tp in zip(root_b, root_t, tips):
                member(rb, tp, 0.08)                                         # bottom chord
                member(rt, tp, 0.07)                                         # top chord
                member(rb, rt, 0.05)
            member(tips[0], tips[1], 0.05)
            stations = np.linspace(0, 1, 5)[1:-1]
            for q_i, q in enumerate(stations):
                b0 = [rb + q * (tp - rb) for rb, tp in zip(root_b, tips)]
                t0 = [rt + q * (tp - rt) for rt, tp in zip(root_t, tips)]
                member(b0[0], b0[1], 0.04)
                member(t0[0], t0[1], 0.04)
                for bb, tt in zip(b0, t0):
                    member(bb, tt, 0.04)
                prev_b = [rb + (stations[q_i - 1] if q_i else 0.0) * (tp - rb) for rb, tp in zip(root_b, tips)]
                for side in range(2):
                    member(prev_b[side], t0[side], 0.04)                     # side zig-zag
                member(prev_b[q_i % 2], b0[1 - q_i % 2], 0.04)               # bottom zig-zag
            # Suspension insulator string hanging from the tip.
            hang = np.array([tip_x - s * 0.15, 0.0, z_a])
            bottom = hang - np.array([0, 0, INSULATOR_LENGTH])
            caps.append((hang + off, bottom + off, 0.03))
            for zz in np.linspace(z_a - 0.45, z_a - INSULATOR_LENGTH + 0.35, 10):
                cyls.append((np.array([hang[0], 0, zz]) + off, np.array([hang[0], 0, zz + 0.05]) + off, 0.14, True))
            attachments.append(bottom + off)
    # Earth-wire peak.
    for s in (-1.0, 1.0):
        base = np.array([s * 0.35, 0.0, 29.6])
        tip = np.array([s * 2.6, 0.0, 30.4])
        member(base, tip, 0.07)
        member(np.array([s * 0.8, 0.0, 28.4]), tip, 0.05)
        attachments.append(tip + off - np.array([0, 0, 0.1]))
    for i in range(4):                                                       # concrete footings
        c = _corner(0.0, i)
        boxes.append((np.array([c[0], c[1], 0.225]) + off, np.array([0.7, 0.7, 0.225])))
    return caps, cyls, boxes, np.array(attachments)


def add_tower(builder: Builder, rng: np.random.Generator, offset=(0.0, 0.0, 0.0), obj: int = 1):
    """Adds one tower; returns its conductor attachment points [K, 3]."""
    caps, cyls, boxes, attach = tower_members(rng, offset)
    steel = np.array([0.40, 0.41, 0.42])
    for a, b, r in caps:
        builder.capsule(a, b, r, TOWER, steel * rng.uniform(0.9, 1.1), METAL, obj)
    glass = np.array([0.16, 0.32, 0.30])
    for a, b, r, _ in cyls:
        builder.cylinder(a, b, r, TOWER, glass * rng.uniform(0.9, 1.1), PLAIN, obj)
    for c, h in boxes:
        builder.box(c, h, np.eye(3), TOWER, [0.5, 0.49, 0.46], PLAIN, obj)
    return attach


def catenary(p0, p1, sag: float, segments: int) -> np.ndarray:
    """Points [segments + 1, 3] of a hanging cable from p0 to p1 (equal heights assumed
    approximately) whose lowest point is `sag` metres below the chord's midpoint."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    span = np.linalg.norm((p1 - p0)[:2])
    a = span ** 2 / (8.0 * max(sag, 1e-3))
    s = np.linspace(0.0, 1.0, segments + 1)
    pts = p0[None] + s[:, None] * (p1 - p0)[None]
    x = (s - 0.5) * span
    dip = a * (np.cosh(x / a) - np.cosh(0.5 * span / a))                  # 0 at the ends, <0 mid
    pts[:, 2] += dip
    return pts


PHASE_SAG, EARTH_SAG = 8.0, 6.0      # m: the `catenary` sag argument of each kind of cable


def conductor_spans(attach: np.ndarray, spans: int = 2) -> list[dict]:
    """Every cable span of `add_conductors`: [{"p0" [3], "p1" [3], "sag" (catenary's argument),
    "earth" (bool), "radius" (m), "wire" (index into attach), "k" (the span from y = k SPAN to
    (k + 1) SPAN)}] (phase conductors first, then the two earth wires, as attach)."""
    n_phase = len(attach) - 2
    out = []
    for i, p in enumerate(np.asarray(attach, float)):
        earth = i >= n_phase
        for k in range(-spans, spans):
            out.append({"p0": p + np.array([0.0, k * SPAN, 0.0]), "p1": p + np.array([0.0, (k + 1) * SPAN, 0.0]),
                        "sag": EARTH_SAG if earth else PHASE_SAG, "earth": earth, "radius": 0.03 if earth else 0.045,
                        "wire": i, "k": k})
    return out


def add_conductors(builder: Builder, attach: np.ndarray, spans: int = 2, segments: int = 32):
    """Cables along +-y through towers at y = k * SPAN, from y = -spans*SPAN to +spans*SPAN."""
    for span in conductor_spans(attach, spans):
        albedo = [0.30, 0.30, 0.31] if span["earth"] else [0.36, 0.36, 0.37]
        pts = catenary(span["p0"], span["p1"], span["sag"], segments)
        for a, b in zip(pts[:-1], pts[1:]):
            builder.capsule(a, b, span["radius"], CONDUCTOR, albedo, PLAIN, 2)


def add_trees(builder: Builder, rng: np.random.Generator, density: float = 1.0):
    """Forest patches and single trees at 100-500 m, kept out of the line corridor (|x| < 30 m)."""
    n_patches = int(round(16 * density))
    obj = 1000
    for _ in range(n_patches):
        az = rng.uniform(0, 2 * np.pi)
        width = rng.uniform(0.12, 0.5)
        dist = rng.uniform(105, 380)
        depth = rng.uniform(15, 70)
        n = int(rng.integers(10, 40) * density)
        conifer_frac = rng.uniform(0.0, 0.7)
        base_green = np.array([rng.uniform(0.07, 0.16), rng.uniform(0.17, 0.3), rng.uniform(0.04, 0.1)])
        for _ in range(n):
            a = az + rng.uniform(-width, width) * 0.5
            d = dist + rng.uniform(0, depth)
            x, y = d * np.cos(a), d * np.sin(a)
            if abs(x) < 30:
                continue
            obj += 1
            green = base_green * rng.uniform(0.75, 1.3, size=3)
            trunk = rng.uniform(1.5, 4.0)
            builder.capsule([x, y, 0.0], [x, y, trunk + 1.0], rng.uniform(0.2, 0.35), VEGETATION,
                            [0.22, 0.16, 0.1], PLAIN, obj)
            if rng.uniform() < conifer_frac:
                rv, rh = rng.uniform(5, 10), rng.uniform(1.8, 3.2)
                builder.ellipsoid([x, y, trunk + rv], [rh, rh, rv], np.eye(3), VEGETATION, green * 0.8, FOLIAGE, obj)
            else:
                for _ in range(int(rng.integers(1, 4))):
                    rh = rng.uniform(2.5, 5.5)
                    rv = rh * rng.uniform(0.7, 1.2)
                    c = [x + rng.uniform(-2, 2), y + rng.uniform(-2, 2), trunk + rv * rng.uniform(0.8, 1.1)]
                    builder.ellipsoid(c, [rh, rh * rng.uniform(0.8, 1.2), rv], yaw(rng.uniform(0, np.pi)),
                                      VEGETATION, green, FOLIAGE, obj)


def add_buildings(builder: Builder, rng: np.random.Generator, count: int = 26):
    """Boxes with window facades (see shading.FACADE) in 2-4 settlements at 150-500 m."""
    palette = np.array([[0.62, 0.58, 0.50], [0.70, 0.70, 0.68], [0.52, 0.30, 0.24],
                        [0.48, 0.49, 0.50], [0.66, 0.60, 0.42], [0.40, 0.42, 0.46]])
    centres = [(rng.uniform(0, 2 * np.pi), rng.uniform(160, 460)) for _ in range(int(rng.integers(2, 5)))]
    obj = 5000
    placed = 0
    while placed < count:
        az, dist = centres[placed % len(centres)]
        a = az + rng.uniform(-0.18, 0.18)
        d = dist + rng.uniform(-40, 40)
        x, y = d * np.cos(a), d * np.sin(a)
        if abs(x) < 35:
            continue
        tall = rng.uniform() < 0.25
        half = np.array([rng.uniform(4, 12), rng.uniform(4, 10), 0.0])
        half[2] = 0.5 * (rng.uniform(18, 40) if tall else rng.uniform(5, 13))
        rot = yaw(a + rng.choice([0.0, np.pi / 2]) + rng.uniform(-0.2, 0.2))
        obj += 1
        builder.box([x, y, half[2]], half, rot, BUILDING, palette[rng.integers(len(palette))], FACADE, obj)
        placed += 1


def static_scene(rng: np.random.Generator, neighbours: bool = True, trees: float = 1.0,
                 buildings: int = 26, conductors: bool = True) -> tuple[Scene, np.ndarray]:
    """The part of the world shared by all views (without the cables when not `conductors`).
    Returns (scene, main-tower attachments [K, 3])."""
    builder = Builder()
    attach = add_tower(builder, np.random.default_rng(rng.integers(2**31)), obj=1)
    if neighbours:
        for k in (-1, 1):
            add_tower(builder, np.random.default_rng(rng.integers(2**31)), offset=(0.0, k * SPAN, 0.0), obj=3)
    if conductors:
        add_conductors(builder, attach)
    add_trees(builder, rng, trees)
    add_buildings(builder, rng, buildings)
    return builder.finish(), attach


def main_tower_scene(seed: int = 0) -> Scene:
    """Only the main tower (for the geometry point sample)."""
    builder = Builder()
    add_tower(builder, np.random.default_rng(seed), obj=1)
    return builder.finish()


def sample_tower_points(scene: Scene, count: int, rng: np.random.Generator) -> np.ndarray:
    """Area-weighted random points on the surfaces of a tower's capsules/cylinders/boxes.

    Capsules are sampled on their cylindrical side (the end caps are hidden in joints).
    Returns [count, 3] metric points.
    """
    parts, areas = [], []
    for kind in ("capsule", "cylinder"):
        g = scene.tables[kind]
        length = np.linalg.norm(g["b"] - g["a"], axis=-1)
        parts += [(kind, i) for i in range(len(length))]
        areas += list(2 * np.pi * g["r"] * length)
    g = scene.tables["box"]
    parts += [("box", i) for i in range(len(g["c"]))]
    h = g["h"]
    areas += list(8 * (h[:, 0] * h[:, 1] + h[:, 1] * h[:, 2] + h[:, 0] * h[:, 2]))
    areas = np.asarray(areas)
    choice = rng.choice(len(parts), size=count, p=areas / areas.sum())
    pts = np.zeros((count, 3))
    for kind in ("capsule", "cylinder", "box"):
        sel = np.nonzero([parts[c][0] == kind for c in choice])[0]
        if not sel.size:
            continue
        idx = np.array([parts[choice[s]][1] for s in sel])
        g = scene.tables[kind]
        if kind == "box":
            c, R, hh = g["c"][idx], g["R"][idx], g["h"][idx]
            local = rng.uniform(-1, 1, size=(len(sel), 3)) * hh
            axis = rng.integers(0, 3, len(sel))
            local[np.arange(len(sel)), axis] = hh[np.arange(len(sel)), axis] * rng.choice([-1, 1], len(sel))
            pts[sel] = c + np.einsum("nij,nj->ni", R, local)
            continue
        a, b, r = g["a"][idx], g["b"][idx], g["r"][idx]
        u = (b - a) / np.linalg.norm(b - a, axis=-1, keepdims=True)
        helper = np.where(np.abs(u[:, 2:3]) < 0.9, [[0, 0, 1.0]], [[1.0, 0, 0]])
        e1 = np.cross(u, helper)
        e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = np.cross(u, e1)
        phi = rng.uniform(0, 2 * np.pi, len(sel))
        s = rng.uniform(0, 1, len(sel))
        pts[sel] = a + s[:, None] * (b - a) + r[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return pts


# --- distractors --------------------------------------------------------------------------

def add_person(builder: Builder, pos, heading: float, rng: np.random.Generator, obj: int):
    """A pedestrian standing at ground point pos [3] (about 1.75 m tall)."""
    x, y = float(pos[0]), float(pos[1])
    s = rng.uniform(0.9, 1.08)
    side = np.array([np.cos(heading + np.pi / 2), np.sin(heading + np.pi / 2), 0.0]) * 0.1 * s
    base = np.array([x, y, 0.0])
    trousers = rng.choice([[0.1, 0.1, 0.15], [0.25, 0.25, 0.3], [0.3, 0.22, 0.12], [0.05, 0.05, 0.05]])
    shirt = np.clip(rng.uniform(0.05, 0.9, size=3) * rng.choice([0.6, 1.0]), 0, 1)
    skin = rng.choice([[0.8, 0.6, 0.45], [0.55, 0.38, 0.25], [0.35, 0.22, 0.15]])
    for sgn in (-1, 1):
        builder.capsule(base + sgn * side + [0, 0, 0.09 * s], base + sgn * side * 0.8 + [0, 0, 0.85 * s], 0.085 * s,
                        PERSON, trousers, PLAIN, obj)
    builder.capsule(base + [0, 0, 0.95 * s], base + [0, 0, 1.38 * s], 0.2 * s, PERSON, shirt, PLAIN, obj)
    builder.ellipsoid(base + [0, 0, 1.64 * s], [0.1 * s, 0.1 * s, 0.125 * s], np.eye(3), PERSON, skin, PLAIN, obj)


def add_vehicle(builder: Builder, pos, heading: float, rng: np.random.Generator, obj: int, large: bool = False):
    """A car (or a van/truck when `large`) standing on the ground at pos [3]."""
    rot = yaw(heading)
    fwd = rot[:, 0]
    if large:
        length, width, body_h = rng.uniform(6, 9), rng.uniform(2.2, 2.5), rng.uniform(2.2, 3.0)
    else:
        length, width, body_h = rng.uniform(3.9, 4.8), rng.uniform(1.7, 1.9), rng.uniform(0.7, 0.9)
    paint = rng.choice([[0.8, 0.05, 0.05], [0.9, 0.9, 0.88], [0.08, 0.08, 0.1], [0.1, 0.2, 0.6],
                        [0.5, 0.52, 0.55], [0.85, 0.6, 0.05], [0.1, 0.4, 0.15]])
    base = np.array([pos[0], pos[1], 0.0])
    clear = 0.3
    builder.box(base + [0, 0, clear + body_h / 2], [length / 2, width / 2, body_h / 2], rot, VEHICLE, paint, PLAIN, obj)
    if large:
        cab_c = base + fwd * (length / 2 + 0.9) + [0, 0, clear + 1.1]
        builder.box(cab_c, [0.9, width / 2 - 0.05, 1.1], rot, VEHICLE, paint * 0.8, PLAIN, obj)
        builder.box(cab_c + fwd * 0.5 + [0, 0, 0.45], [0.42, width / 2 - 0.1, 0.4], rot, VEHICLE,
                    [0.05, 0.07, 0.1], PLAIN, obj)
    else:
        builder.box(base + fwd * -0.2 + [0, 0, clear + body_h + 0.3], [length * 0.28, width / 2 - 0.08, 0.3],
                    rot, VEHICLE, [0.06, 0.08, 0.1], PLAIN, obj)
    wheel_r = 0.5 if large else 0.33
    span = length / 2 - wheel_r - 0.2
    for sx in (-span, span + (1.3 if large else 0.0)):
        for sy in (-1, 1):
            c = base + fwd * sx + rot[:, 1] * sy * (width / 2 - 0.05) + [0, 0, wheel_r]
            builder.cylinder(c - rot[:, 1] * 0.12, c + rot[:, 1] * 0.12, wheel_r, VEHICLE, [0.03, 0.03, 0.03],
                             PLAIN, obj)


def add_bird(builder: Builder, pos, heading: float, rng: np.random.Generator, obj: int, scale: float = 1.0):
    """A bird in flight at pos [3]: body ellipsoid and two thin wing ellipsoids."""
    rot = yaw(heading)
    plumage = rng.choice([[0.05, 0.05, 0.06], [0.85, 0.85, 0.85], [0.35, 0.3, 0.25], [0.55, 0.56, 0.6]])
    s = scale * rng.uniform(0.8, 1.25)
    pos = np.asarray(pos, float)
    builder.ellipsoid(pos, [0.22 * s, 0.07 * s, 0.07 * s], rot, BIRD, plumage, PLAIN, obj)
    flap = rng.uniform(-0.5, 0.5)
    for sgn in (-1, 1):
        tilt = np.array([[1, 0, 0], [0, np.cos(flap), -sgn * np.sin(flap)], [0, sgn * np.sin(flap), np.cos(flap)]])
        wr = rot @ tilt
        builder.ellipsoid(pos + wr[:, 1] * sgn * 0.33 * s, [0.12 * s, 0.33 * s, 0.015 * s], wr, BIRD,
                          plumage * 0.85, PLAIN, obj)
