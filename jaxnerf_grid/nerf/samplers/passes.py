"""What a sampler gets from the model to run its passes along a batch of rays (models.render_ray).

A sampler decides where along each ray (in the normalised ray coordinate s in [0, 1]) which
field is evaluated; the model owns everything else: the warp from s to t, the contraction and
scale of the points, the NeRF fields and their embeddings, the compositing. `Passes` carries
the model's part as plain functions, so a sampler module never imports models.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple


class Passes(NamedTuple):
    """The model's functions for one batch of rays.

    batch_shape: the rays' batch shape [...]; single_jitter: one jitter offset per ray;
    far_bin: sigma [..., S] -> sigma with the last bin made opaque when the model asks for it
      (`opaque_far`), else unchanged;
    s_to_t: s [..., n] -> t [..., n] (the ray's warp);
    points: t_edges [..., S + 1] -> field inputs [..., S, 3] (the bin midpoints, mapped);
    shade: (field params, s_edges [..., S + 1], main) -> the composite of one NeRF-field pass
      (render.composite's rgb, opacity, depth, median_depth, weights, plus s_edges, t_edges);
      main=True is the field that makes the picture (with NeRF-W's embeddings and transient
      part), main=False a plain static field (a first pass).
    """

    batch_shape: tuple
    single_jitter: bool
    far_bin: Callable
    s_to_t: Callable
    points: Callable
    shade: Callable

