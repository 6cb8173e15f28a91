"""Procedural textures, sky and Lambertian sun + sky shading (NumPy).

Radiance is linear; `to_srgb` applies a plain 1/2.2 gamma. Textures are band-limited by the
pixel footprint (octaves finer than about two pixels fade out) so the far field is detailed
but not aliased. All functions are elementwise over a leading batch [N].
"""

from __future__ import annotations

import numpy as np

from jaxnerf_grid.data.synthetic.scene import FOLIAGE, METAL

SUN_COLOR = np.array([1.0, 0.95, 0.86]) * 1.05
ZENITH = np.array([0.10, 0.24, 0.55])
HORIZON = np.array([0.55, 0.66, 0.78])


def _hash(ix, iy, iz, seed: int) -> np.ndarray:
    """Integer lattice hash to [0, 1). ix, iy, iz: int64 arrays [...]."""
    h = (ix.astype(np.uint64) * np.uint64(0x9E3779B1) ^ iy.astype(np.uint64) * np.uint64(0x85EBCA77)
         ^ iz.astype(np.uint64) * np.uint64(0xC2B2AE3D) ^ np.uint64(seed * 0x27D4EB2F + 0x165667B1))
    h &= np.uint64(0xFFFFFFFF)
    h ^= h >> np.uint64(15)
    h = (h * np.uint64(0x2C1B3C6D)) & np.uint64(0xFFFFFFFF)
    h ^= h >> np.uint64(12)
    h = (h * np.uint64(0x297A2D39)) & np.uint64(0xFFFFFFFF)
    h ^= h >> np.uint64(15)
    return h.astype(np.float64) / 4294967296.0


def value_noise(p: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth value noise in [0, 1]. p: [N, 3]. Returns [N]."""
    fl = np.floor(p)
    f = p - fl
    i = fl.astype(np.int64)
    w = f * f * (3 - 2 * f)
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1 - w[:, 2]
                out += wx * wy * wz * _hash(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
    return out


def fbm(p: np.ndarray, octaves: int, seed: int = 0, footprint: np.ndarray | None = None) -> np.ndarray:
    """Fractal noise in about [0, 1]. p: [N, 3] in noise units (feature size 1);
    footprint: optional [N] pixel size in the same units, fading octaves finer than ~2 pixels
    towards their mean 0.5 (faded-out octaves are not evaluated). Returns [N]."""
    out = np.zeros(len(p))
    amp, total = 0.5, 0.0
    for k in range(octaves):
        freq = 2.0 ** k
        if footprint is None:
            out += amp * value_noise(p * freq, seed + 17 * k)
        else:
            fade = np.clip(1.5 - 2.0 * footprint * freq, 0.0, 1.0)
            act = np.nonzero(fade > 0)[0]
            out += amp * 0.5
            if act.size:
                out[act] += amp * fade[act] * (value_noise(p[act] * freq, seed + 17 * k) - 0.5)
        total += amp
        amp *= 0.5
    return out / total


def sun_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector [3] towards the sun."""
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def sky_radiance(d: np.ndarray, sun: np.ndarray, seed: int) -> np.ndarray:
    """Sky gradient, sun glow and fBm clouds on a plane 1.2 km up. d: [N, 3] unit. Returns [N, 3]."""
    up = np.clip(d[:, 2], 0.0, 1.0)
    g = np.sqrt(up)[:, None]
    col = HORIZON * (1 - g) + ZENITH * g
    cos_sun = np.clip(d @ sun, 0.0, 1.0)
    col = col + np.array([1.0, 0.9, 0.7])[None] * (0.25 * cos_sun ** 8 + 2.0 * cos_sun ** 800)[:, None]
    z = np.maximum(d[:, 2], 0.02)
    plane = np.stack([d[:, 0] / z * 1200.0, d[:, 1] / z * 1200.0, np.zeros(len(d))], -1) / 900.0
    density = fbm(plane, 6, seed + 101)
    cover = np.clip((density - 0.48) * 4.0, 0.0, 1.0) * np.clip(d[:, 2] * 8.0, 0.0, 1.0)
    shade = 0.75 + 0.35 * fbm(plane * 2.0 + 3.1, 3, seed + 202)
    cloud = np.array([0.93, 0.93, 0.95])[None] * shade[:, None] + 0.2 * cos_sun[:, None] ** 4
    return col * (1 - cover[:, None]) + cloud * cover[:, None]


SHRUB = np.array([0.035, 0.06, 0.02])
ROCK = np.array([0.45, 0.43, 0.38])
SCATTER_CELL = 2.0  # m: one shrub or stone at most per cell


def ground_scatter(p: np.ndarray, footprint: np.ndarray, seed: int, cell: float = SCATTER_CELL):
    """Shrubs and stones scattered over the field: round patches of 0.36-0.8 m radius (for the
    2 m cell), dark or light, at most one per `cell`-metre square (75 % of squares hold one),
    each inside its square. They give the ground the distinct, repeatable spots that real drone photos of grass
    and gravel have and that SIFT needs to match photos (docs/POSES.md); fBm alone is too smooth.
    A patch's edge is smoothed over a pixel and a patch smaller than about a pixel fades out.

    p: [N, 3] points on z = 0; footprint: [N] metres per pixel.
    Returns (cover [N] in [0, 1], albedo [N, 3]).
    """
    ij = np.floor(p[:, :2] / cell).astype(np.int64)
    h = [_hash(ij[:, 0], ij[:, 1], np.full(len(p), k, np.int64), seed + 31) for k in range(5)]
    radius = cell * (0.18 + 0.22 * h[4])
    margin = radius / cell
    centre = (ij + margin[:, None] + (1 - 2 * margin[:, None]) * np.stack([h[2], h[3]], -1)) * cell
    dist = np.linalg.norm(p[:, :2] - centre, axis=1)
    fp = np.maximum(footprint, 1e-4)
    edge = np.clip((radius - dist) / fp + 0.5, 0.0, 1.0)
    cover = np.where(h[0] < 0.75, edge, 0.0) * np.clip(1.5 - fp / radius, 0.0, 1.0)
    albedo = np.where((h[1] < 0.6)[:, None], SHRUB[None], ROCK[None]) * (0.8 + 0.4 * h[4])[:, None]
    return cover, albedo


def ground_albedo(p: np.ndarray, footprint: np.ndarray, seed: int) -> np.ndarray:
    """Grass/dry patches, fine detail, scattered shrubs and stones, a gravel pad under the tower
    and a dirt track.

    p: [N, 3] points on z = 0; footprint: [N] metres per pixel. Returns [N, 3].
    """
    grass = np.array([0.13, 0.20, 0.06])
    dry = np.array([0.30, 0.27, 0.14])
    soil = np.array([0.33, 0.28, 0.21])
    large = fbm(p / 30.0, 4, seed + 1, footprint / 30.0)
    mix = np.clip((large - 0.42) * 3.0, 0.0, 1.0)[:, None]
    col = grass * (1 - mix) + dry * mix
    fine = fbm(p / 0.9, 5, seed + 2, footprint / 0.9)
    tufts = fbm(p / 5.0, 3, seed + 4, footprint / 5.0)
    col = col * ((0.35 + 1.3 * fine) * (0.55 + 0.9 * tufts))[:, None]
    cover, scatter = ground_scatter(p, footprint, seed)
    col = col * (1 - cover[:, None]) + scatter * cover[:, None]
    pad = np.nonzero(np.maximum(np.abs(p[:, 0]), np.abs(p[:, 1])) < 7.0)[0]
    col[pad] = soil * (0.75 + 0.5 * fbm(p[pad] / 0.25, 3, seed + 3, footprint[pad] / 0.25))[:, None]
    track_x = 22.0 + 6.0 * np.sin(p[:, 1] / 45.0)
    track = np.abs(p[:, 0] - track_x) < 1.8
    col = np.where(track[:, None], soil * 1.25 * (0.8 + 0.4 * fine)[:, None], col)
    return col


def facade_albedo(local: np.ndarray, axis: np.ndarray, half: np.ndarray, wall: np.ndarray,
                  footprint: np.ndarray, obj: np.ndarray, seed: int) -> np.ndarray:
    """Windows on the walls of a box building, a darker roof.

    local: [N, 3] hit point in box coordinates; axis: [N] face axis (2 = roof);
    half: [N, 3] half extents; wall: [N, 3] wall albedo; footprint: [N] m per pixel;
    obj: [N] building id. Returns [N, 3].
    """
    u = np.where(axis == 0, local[:, 1] + half[:, 1], local[:, 0] + half[:, 0])
    v = local[:, 2] + half[:, 2]
    fu, fv = np.mod(u, 2.8) / 2.8, np.mod(v, 3.2) / 3.2
    window = (fu > 0.22) & (fu < 0.78) & (fv > 0.3) & (fv < 0.82) & (v > 1.2) & (v < 2 * half[:, 2] - 0.8)
    lit = _hash(np.floor(u / 2.8).astype(np.int64), np.floor(v / 3.2).astype(np.int64), obj, seed + 5)
    glass = np.array([0.08, 0.10, 0.14])[None] * (0.6 + 0.9 * lit[:, None])
    # Fade the window pattern into its average where a window is below about a pixel.
    visible = np.clip(1.5 - footprint / 1.2, 0.0, 1.0)[:, None]
    avg = 0.7 * wall + 0.3 * glass
    col = np.where(window[:, None], glass, wall)
    col = visible * col + (1 - visible) * avg
    roof = np.array([0.22, 0.21, 0.2])
    return np.where((axis == 2)[:, None], roof, col)


def surface_albedo(material: np.ndarray, albedo: np.ndarray, p: np.ndarray, footprint: np.ndarray,
                   seed: int) -> np.ndarray:
    """Base albedo modulated per material. material: [N]; albedo, p: [N, 3]; footprint: [N].

    FACADE is handled by `facade_albedo` (needs box coordinates); here it is plain.
    """
    col = albedo.copy()
    fol = material == FOLIAGE
    if fol.any():
        n = fbm(p[fol] / 0.7, 4, seed + 7, footprint[fol] / 0.7)
        big = fbm(p[fol] / 3.0, 2, seed + 8)
        col[fol] = albedo[fol] * ((0.35 + 1.3 * n) * (0.7 + 0.6 * big))[:, None]
    met = material == METAL
    if met.any():
        col[met] = albedo[met] * (0.85 + 0.3 * value_noise(p[met] / 0.5, seed + 9))[:, None]
    return col


def lambert(albedo: np.ndarray, normal: np.ndarray, sun: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Sun (with shadow visibility) + hemispherical sky ambient.

    albedo, normal: [N, 3]; sun: [3] unit; visible: [N] float in {0, 1}. Returns [N, 3] radiance.
    """
    ndl = np.clip(normal @ sun, 0.0, 1.0)
    sky_amb = ZENITH * 0.9 + HORIZON * 0.5
    ambient = sky_amb[None] * (0.55 + 0.45 * normal[:, 2:3]) + np.array([0.06, 0.07, 0.04]) * (0.5 - 0.5 * normal[:, 2:3])
    return albedo * (SUN_COLOR[None] * (ndl * visible)[:, None] + ambient)


def haze(radiance: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Aerial perspective: blends towards the horizon colour with distance t [N] (m)."""
    f = (1.0 - np.exp(-t / 2500.0))[:, None]
    return radiance * (1 - f) + HORIZON[None] * f


def to_srgb(radiance: np.ndarray) -> np.ndarray:
    """Linear radiance -> display values in [0, 1] (clip, gamma 1/2.2)."""
    return np.clip(radiance, 0.0, 1.0) ** (1.0 / 2.2)
