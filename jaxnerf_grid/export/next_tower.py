"""The next tower along the line, found in the photos: a side's span length measured where the
photos look along the line, instead of read from the wires' curvature alone (`find_spans`).

The photos see a wire over 60-130 m of a 320 m span, so the curvature, and the span it gives,
are known to 1-3 % (docs/EXPORT.md). A photo looking along the line sees the next tower itself,
a lattice against the sky a span away. A plane across the line at a distance L from the tower's
axis, from the ground to above the tower's top, is sampled in every photo that sees it
(`plane_points`, `sampled`): at the next tower's distance the photos' samples show the same
lattice, elsewhere each photo's samples show a different part of the background. The score of
a distance is the mean over photo pairs of the normalised cross-correlation of their samples,
high-passed (`high_pass`: the sky's gradient and the horizon, alike at every distance, left
out); its peak over a window of distances (`length_scores`) is the span (`next_tower_length`),
its 1-sigma the jackknife over the photos (each photo left out in turn, `jackknife_sigma`).
A plane sweep (Collins' space-sweep stereo) along one line, in the export's frame and units.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from jaxnerf_grid.export import catenary
from jaxnerf_grid.export.conductors import project_all

HIGH_PASS_PX = 2.0        # px: the Gaussian whose blur is taken away (the lattice's members are 1-3 px there)
MIN_COMMON = 0.3          # share of the plane's samples both photos of a pair must see
MIN_PHOTOS = 3            # photos in the pairs: with two, one pair, no jackknife
MIN_SCORE = 0.2           # the peak's mean correlation (the background's away from it: about 0.0-0.05)
WINDOW_STEPS = 120        # distances tried across the window
TOP_MARGIN = 0.15         # tower heights: the plane reaches this far above the tower's top
DEPTH_SIGMA = 0.02        # tower heights: the span's 1-sigma floor (the plane stands for a lattice metres deep)


def high_pass(gray: np.ndarray, sigma: float = HIGH_PASS_PX) -> np.ndarray:
    """gray [H, W] less its Gaussian blur of sigma px, float32 [H, W]."""
    g = np.asarray(gray, np.float32)
    return g - cv2.GaussianBlur(g, (0, 0), sigma)


def grey_high_passed(images: np.ndarray) -> np.ndarray:
    """Photos [N, H, W, 3+] (RGB first) as the sweep reads them: grey, `high_pass`ed. Returns
    [N, H, W] float32."""
    return np.stack([high_pass(cv2.cvtColor(np.asarray(im[..., :3], np.float32), cv2.COLOR_RGB2GRAY))
                     for im in images])


def plane_points(centre, psi: float, up, distance: float, half_width: float, z_range: tuple,
                 spacing: float) -> np.ndarray:
    """Points [R, C, 3] of the plane across the line at `distance` along the line's direction at
    azimuth psi (`catenary.line_axes`) from centre [3]'s axis: across in [-half_width, half_width],
    heights along up in z_range (lo, hi) (the frame's zero, as `find_spans`' heights), a sample
    every `spacing`; rows from the top."""
    line, across, u = catenary.line_axes(psi, up)
    base = np.asarray(centre, np.float64)
    base = base - (base @ u) * u + distance * line
    xs = np.arange(-half_width, half_width + 0.5 * spacing, spacing)
    zs = np.arange(z_range[1], z_range[0] - 0.5 * spacing, -spacing)
    return base[None, None] + xs[None, :, None] * across[None, None] + zs[:, None, None] * u[None, None]


def sampled(images: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray, points: np.ndarray):
    """The photos' values at points [R, C, 3]: (values [N, R*C] float32, bilinear; seen [N, R*C]
    bool: in front and inside the photo). images [N, H, W] (high-passed), c2w [N, 4, 4],
    intrinsics [N, 4]."""
    shape = points.shape[:2]
    u, v, z = project_all(points.reshape(-1, 3), c2w, intrinsics)
    height, width = images.shape[1:3]
    seen = (z > 0) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    # pixel centres at +0.5 (`project_all`'s u, v are continuous image coordinates)
    values = np.stack([cv2.remap(images[i], (u[i] - 0.5).reshape(shape).astype(np.float32),
                                 (v[i] - 0.5).reshape(shape).astype(np.float32), cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE).ravel() for i in range(len(images))])
    return values, seen


def pair_correlations(values: np.ndarray, seen: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """The normalised cross-correlation of each pair (i, j) of pairs [P, 2] over the samples both
    see: values, seen [N, M]. Returns [P] (NaN where they share under MIN_COMMON of the samples or
    one is flat there)."""
    out = np.full(len(pairs), np.nan)
    for k, (i, j) in enumerate(pairs):
        both = seen[i] & seen[j]
        if both.mean() < MIN_COMMON:
            continue
        a = values[i][both] - values[i][both].mean()
        b = values[j][both] - values[j][both].mean()
        norm = math.sqrt(float(a @ a) * float(b @ b))
        if norm > 0:
            out[k] = float(a @ b) / norm
    return out


def length_scores(images: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray, centre, psi: float, up,
                  lengths: np.ndarray, half_width: float, z_range: tuple, spacing: float):
    """Each photo pair's correlation at each distance lengths [K]: (pairs [P, 2], scores [P, K]),
    the pairs that share MIN_COMMON of the plane at every distance (a fixed set: the mean of
    their curves is comparable along the window). images [N, H, W] high-passed."""
    n = len(images)
    pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)], np.int64).reshape(-1, 2)
    scores = np.full((len(pairs), len(lengths)), np.nan)
    for k, dist in enumerate(lengths):
        values, seen = sampled(images, c2w, intrinsics,
                               plane_points(centre, psi, up, float(dist), half_width, z_range, spacing))
        looking = seen.mean(axis=1) >= MIN_COMMON
        todo = looking[pairs[:, 0]] & looking[pairs[:, 1]]
        scores[todo, k] = pair_correlations(values, seen, pairs[todo])
    every = np.all(np.isfinite(scores), axis=1)
    return pairs[every], scores[every]


def peak(lengths: np.ndarray, curve: np.ndarray) -> float | None:
    """The distance [float] of curve [K]'s highest point over lengths [K] (evenly spaced), refined
    by the parabola through it and its neighbours; None at the window's ends (no peak inside)."""
    k = int(np.argmax(curve))
    if k == 0 or k == len(curve) - 1:
        return None
    y0, y1, y2 = (float(v) for v in curve[k - 1:k + 2])
    denom = y0 - 2 * y1 + y2
    shift = 0.0 if denom >= 0 else 0.5 * (y0 - y2) / denom
    return float(lengths[k] + shift * (lengths[1] - lengths[0]))


def jackknife_sigma(lengths: np.ndarray, pairs: np.ndarray, scores: np.ndarray) -> float:
    """The jackknife 1-sigma of the peak over the photos: the peak of the pairs' mean curve with
    each photo's pairs left out in turn, sqrt((n - 1) / n sum (L_i - mean)^2); inf when a
    left-out curve has no peak inside the window. pairs [P, 2], scores [P, K]."""
    photos = np.unique(pairs)
    peaks = []
    for p in photos:
        rest = ~np.any(pairs == p, axis=1)
        found = peak(lengths, scores[rest].mean(axis=0)) if rest.any() else None
        if found is None:
            return math.inf
        peaks.append(found)
    x = np.asarray(peaks)
    return math.sqrt((len(x) - 1) / len(x) * float(np.sum((x - x.mean()) ** 2)))


def next_tower_length(lengths: np.ndarray, pairs: np.ndarray, scores: np.ndarray) -> dict | None:
    """The span from the pairs' correlations (`length_scores`): {"length", "sigma" (the
    jackknife's, at least half a step), "score" (the mean correlation at the peak), "photos",
    "pairs"}; None when fewer than MIN_PHOTOS photos make the pairs, the peak is not inside the
    window, its score is under MIN_SCORE or its jackknife is undefined."""
    photos = len(np.unique(pairs))
    if photos < MIN_PHOTOS:
        return None
    curve = scores.mean(axis=0)
    length = peak(lengths, curve)
    if length is None or float(curve.max()) < MIN_SCORE:
        return None
    sigma = max(jackknife_sigma(lengths, pairs, scores), 0.5 * float(lengths[1] - lengths[0]))
    if not math.isfinite(sigma):
        return None
    return {"length": length, "sigma": sigma, "score": float(curve.max()), "photos": photos, "pairs": len(pairs)}


def next_tower(images: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray, centre, up, ground: float,
               tower_height: float, half_width: float, psi: float, window: tuple) -> dict | None:
    """The next tower's distance along azimuth psi within window (lo, hi) [export units]
    (`next_tower_length`; None: not seen well enough). images [N, H, W] high-passed (`high_pass`);
    ground: the ground's height at the axis (along up, the frame's zero); the plane from there to
    TOP_MARGIN above the tower's top, half_width across; a sample every half the pixel's
    footprint at the window's middle (the photos' median distance to it). The sigma is at least
    DEPTH_SIGMA tower heights: the photos see the lattice's near and far faces, a few metres
    either side of the plane, and the peak lies somewhere within (0.1-0.9 m off on three
    generated scenes, the jackknife 0.13-0.7 m)."""
    lo, hi = (float(v) for v in window)
    line, _, _ = catenary.line_axes(psi, up)
    target = np.asarray(centre, np.float64) + 0.5 * (lo + hi) * line
    footprint = float(np.median(np.linalg.norm(np.asarray(c2w)[:, :3, 3] - target, axis=1)
                                / np.asarray(intrinsics)[:, 0]))
    lengths = np.linspace(lo, hi, WINDOW_STEPS)
    z_range = (ground, ground + (1.0 + TOP_MARGIN) * tower_height)
    pairs, scores = length_scores(images, c2w, intrinsics, centre, psi, up, lengths, half_width, z_range,
                                  0.5 * footprint)
    found = next_tower_length(lengths, pairs, scores) if len(pairs) else None
    return None if found is None else {**found, "sigma": max(found["sigma"], DEPTH_SIGMA * float(tower_height))}
