"""The catenary of a span, as the conductors' fit (export/conductors.py) parametrises it, and the
polyline a report draws of it: pure NumPy.

theta = (c, z_A, psi, m0, kappa): the span leaves its attachment A = C + c e_across + z_A up (C
the tower's axis point, c the offset across the line, z_A the height) along the horizontal
direction e_line(psi), and hangs as
    z(s) = z_A + s sinhc(kappa s / 2) sinh(kappa s / 2 - beta),   beta = asinh(-m0)
of the horizontal distance s (kappa = 1 / a, m0 the slope at A; kappa -> 0 is a straight line).
The far attachment is taken at A's height (a level span): the lowest point is at x_v = beta /
kappa, the span 2 x_v and the sag (cosh(beta) - 1) / kappa.
"""

from __future__ import annotations

import math

import numpy as np


def line_axes(psi: float, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(e_line, e_across, up) [3] each: the horizontal line direction at azimuth psi (about `up`,
    from the frame's x projected on the horizontal), the horizontal across it, and up."""
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    ref = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ u) * u
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    line = math.cos(psi) * e1 + math.sin(psi) * e2
    return line, np.cross(u, line), u


def sag_profile(s: np.ndarray, m0: float, kappa: float) -> np.ndarray:
    """Height of the catenary above its attachment at horizontal distances s [K] (module
    docstring): s sinhc(kappa s / 2) sinh(kappa s / 2 - asinh(-m0)); a line of slope m0 at kappa 0."""
    s = np.asarray(s, np.float64)
    half = 0.5 * kappa * s
    sinhc = np.where(np.abs(half) < 1e-8, 1.0, np.sinh(half) / np.where(half == 0, 1.0, half))
    return s * sinhc * np.sinh(half - math.asinh(-m0))


def curve_points(theta, centre, s: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Points [K, 3] of a span at horizontal distances s [K] from its attachment.
    theta = (c, z_a, psi, m0, kappa) (module docstring); centre [3]: the tower's axis point whose
    height is the frame's zero of z_a (its component along up is ignored)."""
    c, z_a, psi, m0, kappa = (float(v) for v in theta)
    line, across, u = line_axes(psi, up)
    base = np.asarray(centre, np.float64)
    base = base - (base @ u) * u
    z = z_a + sag_profile(s, m0, kappa)
    return base[None] + c * across[None] + np.asarray(s, np.float64)[:, None] * line[None] + z[:, None] * u[None]


def derived(theta, centre, up=(0.0, 0.0, 1.0)) -> dict:
    """The span's figures from theta (module docstring), level span assumed:
    {"attachment" [3], "far_attachment" [3], "lowest_point" [3], "catenary_parameter" (a = 1/kappa),
    "sag", "span" (2 x_v), "lowest_station" (x_v)}; the sag-dependent ones NaN for kappa <= 0
    or a rising wire (m0 >= 0: no lowest point ahead)."""
    c, z_a, psi, m0, kappa = (float(v) for v in theta)
    beta = math.asinh(-m0)
    attach = curve_points(theta, centre, np.zeros(1), up)[0]
    nan3 = np.full(3, np.nan)
    if kappa <= 0 or beta <= 0:
        return {"attachment": attach, "far_attachment": nan3, "lowest_point": nan3,
                "catenary_parameter": float("nan"), "sag": float("nan"), "span": float("nan"),
                "lowest_station": float("nan")}
    xv = beta / kappa
    ends = curve_points(theta, centre, np.array([xv, 2 * xv]), up)
    return {"attachment": attach, "far_attachment": ends[1], "lowest_point": ends[0],
            "catenary_parameter": 1.0 / kappa, "sag": (math.cosh(beta) - 1.0) / kappa, "span": 2 * xv,
            "lowest_station": xv}


def sample_span(theta, centre, spacing: float, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Points [K, 3] along a span every `spacing` (horizontally) from its attachment to its far end
    (the level span's; the observed reach when the sag is undetermined: `stations_end`)."""
    d = derived(theta, centre, up)
    end = d["span"] if math.isfinite(d["span"]) else 0.0
    count = max(int(math.ceil(end / spacing)), 1) + 1
    return curve_points(theta, centre, np.linspace(0.0, end, count), up)
