"""The next tower's distance along the line from the photos (export.next_tower) and the spans it
sets (export.conductors.side_lengths), against photos ray-traced here and closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jaxnerf_grid.export import conductors as cond
from jaxnerf_grid.export import next_tower as nt

W, H, F = 320, 240, 400.0
TOWER_AT = 300.0                  # m along +y: the next tower's face
HALF_WIDTH, TOP = 6.0, 30.0       # m: its lattice, x in [-6, 6], z in [0, 30]


def look_at(eye, target) -> np.ndarray:
    """OpenGL camera-to-world [4, 4]: -z towards the target, +y as near +z as possible."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    f = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(right, f), -f, eye
    return m


def cameras_along_line(count: int = 8) -> np.ndarray:
    """[count, 4, 4]: views from around the near tower (x in [-80, 80], y in [-60, 60], 10-40 m
    high), each looking at the next tower's middle."""
    out = []
    for k in range(count):
        x = -80.0 + 160.0 * k / (count - 1)
        out.append(look_at([x, 60.0 * math.sin(1.7 * k), 10.0 + 30.0 * (k % 3) / 2], [0.0, TOWER_AT, 15.0]))
    return np.stack(out)


def traced_photos(c2w: np.ndarray, tower: bool = True, seed: int = 0) -> np.ndarray:
    """Grey photos [N, H, W] ray-traced: each pixel's ray (through its centre) meets the plane
    y = TOWER_AT; inside the tower's face (where there is a tower) it takes the lattice's value (a
    fixed random value per 1 m cell), elsewhere a sky brightening upwards with each photo's own
    noise."""
    rng = np.random.default_rng(seed)
    cells = rng.uniform(40.0, 200.0, (int(TOP) + 1, int(2 * HALF_WIDTH) + 1))
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    cam_dirs = np.stack([(cols - W / 2) / F, -(rows - H / 2) / F, -np.ones_like(cols)], -1)
    out = []
    for m in c2w:
        d = cam_dirs @ m[:3, :3].T
        t = (TOWER_AT - m[1, 3]) / d[..., 1]
        x, z = m[0, 3] + t * d[..., 0], m[2, 3] + t * d[..., 2]
        on = (t > 0) & (np.abs(x) <= HALF_WIDTH) & (z >= 0) & (z <= TOP)
        lattice = cells[np.clip(z, 0, TOP).astype(int), np.clip(x + HALF_WIDTH, 0, 2 * HALF_WIDTH).astype(int)]
        sky = 180.0 + 40.0 * d[..., 2] / np.linalg.norm(d, axis=-1) + rng.normal(0.0, 2.0, (H, W))
        out.append(np.where(on & tower, lattice, sky))
    return np.stack(out).astype(np.float32)


def sweep(photos: np.ndarray, c2w: np.ndarray, window=(270.0, 330.0)) -> dict | None:
    gray = np.stack([nt.high_pass(p) for p in photos])
    intr = np.tile([F, F, W / 2, H / 2], (len(c2w), 1))
    return nt.next_tower(gray, c2w, intr, np.zeros(3), (0.0, 0.0, 1.0), 0.0, TOP, HALF_WIDTH, math.pi / 2, window)


def test_the_next_tower_is_found_at_its_distance_in_photos_looking_along_the_line():
    c2w = cameras_along_line()
    found = sweep(traced_photos(c2w), c2w)
    assert found is not None
    assert found["length"] == pytest.approx(TOWER_AT, abs=1.0)
    assert found["photos"] == len(c2w)
    assert nt.DEPTH_SIGMA * TOP <= found["sigma"] < 2.0
    assert found["score"] >= nt.MIN_SCORE


def test_the_peak_follows_the_tower_when_the_window_is_off_centre():
    c2w = cameras_along_line()
    found = sweep(traced_photos(c2w), c2w, window=(285.0, 345.0))
    assert found is not None and found["length"] == pytest.approx(TOWER_AT, abs=1.0)


def test_a_window_that_misses_the_tower_finds_nothing():
    c2w = cameras_along_line()
    assert sweep(traced_photos(c2w), c2w, window=(200.0, 260.0)) is None


def test_photos_of_the_sky_alone_find_nothing():
    c2w = cameras_along_line()
    assert sweep(traced_photos(c2w, tower=False), c2w) is None


def test_two_photos_are_too_few_for_a_distance():
    c2w = cameras_along_line()[[0, 7]]
    assert sweep(traced_photos(c2w), c2w) is None


def test_the_peak_is_the_vertex_of_a_sampled_parabola():
    lengths = np.linspace(290.0, 310.0, 21)
    curve = 0.8 - 0.01 * (lengths - 301.37) ** 2
    assert nt.peak(lengths, curve) == pytest.approx(301.37, abs=1e-9)
    assert nt.peak(lengths, lengths) is None          # rising to the window's end: no peak inside


def test_the_jackknife_spread_is_that_of_the_peaks_with_each_photo_left_out():
    lengths = np.linspace(0.0, 20.0, 201)
    pairs = np.array([[0, 1], [0, 2], [1, 2]])
    centres = np.array([9.0, 10.0, 11.5])                 # pair k's parabola peaks at centres[k]
    scores = 1.0 - 0.01 * (lengths[None] - centres[:, None]) ** 2
    # leaving photo 0 out keeps pair (1, 2), photo 1 pair (0, 2), photo 2 pair (0, 1): the pairs' mean
    # of parabolas of one width peaks at the mean of their centres
    left_out = np.array([11.5, 10.0, 9.0])
    want = math.sqrt(2 / 3 * np.sum((left_out - left_out.mean()) ** 2))
    assert nt.jackknife_sigma(lengths, pairs, scores) == pytest.approx(want, rel=1e-6)


def test_one_side_measured_sets_the_curvature_and_the_other_sides_span():
    slopes = {1: np.array([-0.10, -0.1, -0.1]), -1: np.array([-0.12, -0.12, -0.12])}
    calls = []

    def found_on_plus(psi, window):
        calls.append((psi, window))
        return {"length": 318.0, "sigma": 0.5, "score": 0.4, "photos": 5, "pairs": 10} if psi == 0.3 else None

    lengths, (kappa, sigma), measured = cond.side_lengths(slopes, (1 / 1550.0, 1e-5), 0.3, found_on_plus)
    assert kappa == pytest.approx(2 * math.asinh(0.10) / 318.0, rel=1e-12)
    assert lengths[1] == (318.0, 0.5)
    assert lengths[-1][0] == pytest.approx(318.0 * math.asinh(0.12) / math.asinh(0.10), rel=1e-12)
    assert list(measured) == [1]
    # each side searched about the span its slope gives at the pooled curvature
    plus_span = 2 * math.asinh(0.10) * 1550.0
    assert calls[0][0] == 0.3 and calls[1][0] == pytest.approx(0.3 + math.pi)
    assert np.mean(calls[0][1]) == pytest.approx(plus_span, rel=1e-9)
    assert sigma > 0


def test_without_a_next_tower_the_spans_come_from_the_pooled_curvature():
    slopes = {1: np.array([-0.10, -0.1, -0.1]), -1: np.array([])}
    lengths, pooled, measured = cond.side_lengths(slopes, (1 / 1600.0, 1e-5), 0.0, lambda psi, window: None)
    assert lengths[1][0] == pytest.approx(2 * math.asinh(0.10) * 1600.0, rel=1e-12)
    assert lengths[-1] is None and pooled == (1 / 1600.0, 1e-5) and measured == {}


def test_the_search_window_spans_four_sigmas_or_five_percent():
    assert cond.next_tower_window(300.0, 10.0) == (260.0, 340.0)
    assert cond.next_tower_window(300.0, 1.0) == (285.0, 315.0)
