"""Gaussian-blob test images whose centroid is known in closed form (used to check where a
loader, resampler or undistorter moves a point)."""

from __future__ import annotations

import numpy as np


def blob(u0, v0, w, h, sigma=1.5):
    """An [h, w, 3] float32 image of a Gaussian centred at pixel coordinates (u0, v0)
    (pixel centres at +0.5)."""
    uu, vv = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    g = np.exp(-((uu - u0) ** 2 + (vv - v0) ** 2) / (2 * sigma**2))
    return np.repeat(g[..., None], 3, axis=-1).astype(np.float32)


def centroid(img):
    """Intensity-weighted centroid (u, v) of channel 0 of an [h, w, C] image."""
    g = img[..., 0].astype(np.float64)
    uu, vv = np.meshgrid(np.arange(g.shape[1]) + 0.5, np.arange(g.shape[0]) + 0.5)
    return (g * uu).sum() / g.sum(), (g * vv).sum() / g.sum()
