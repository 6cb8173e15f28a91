"""Volume rendering: the quadrature of Eq. 1 (alpha compositing) and what it yields.

For bins [t_i, t_{i+1}) with density sigma_i, delta_i = (t_{i+1} - t_i) * |d|:
    alpha_i = 1 - exp(-sigma_i delta_i)
    T_i     = exp(-sum_{j<i} sigma_j delta_j)
    w_i     = T_i alpha_i
Transmittance is accumulated in log space (a sum of sigma * delta), so densities of 1e6 give
finite values and gradients.
"""

from __future__ import annotations

import jax.numpy as jnp


def alpha_weights(density: jnp.ndarray, t_edges: jnp.ndarray, dirs: jnp.ndarray | None = None) -> jnp.ndarray:
    """Compositing weights of each bin.

    density: [..., S] >= 0; t_edges: [..., S + 1]; dirs: optional [..., 3] ray directions (the
    bin lengths are multiplied by |dirs|; None or unit dirs: t is metric distance).
    Returns weights: [..., S], each in [0, 1], summing to at most 1.
    """
    delta = jnp.diff(t_edges, axis=-1)
    if dirs is not None:
        delta = delta * jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    optical = jnp.maximum(density, 0.0) * delta
    alpha = 1.0 - jnp.exp(-optical)
    exclusive = jnp.concatenate([jnp.zeros_like(optical[..., :1]),
                                 jnp.cumsum(optical[..., :-1], axis=-1)], axis=-1)
    return alpha * jnp.exp(-exclusive)


def composite(weights: jnp.ndarray, rgb: jnp.ndarray, t_edges: jnp.ndarray,
              background=None) -> dict[str, jnp.ndarray]:
    """Composites per-sample colours into per-ray outputs.

    weights: [..., S]; rgb: [..., S, 3]; t_edges: [..., S + 1];
    background: None (black), a scalar, or [..., 3] / [3] colour behind the last bin.
    Returns dict:
      rgb [..., 3];
      opacity [...] (sum of weights);
      depth [...]: expected distance sum(w t_mid) / opacity, clipped to [t_first, t_last]
        (t_last where the ray is empty);
      median_depth [...]: distance where the accumulated weight reaches half the opacity
        (piecewise-linear within the bin);
      weights [..., S].
    """
    opacity = jnp.sum(weights, axis=-1)
    colour = jnp.sum(weights[..., None] * rgb, axis=-2)
    if background is not None:
        colour = colour + (1.0 - opacity[..., None]) * jnp.asarray(background, colour.dtype)
    t_mid = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
    t_first, t_last = t_edges[..., 0], t_edges[..., -1]
    raw_depth = jnp.sum(weights * t_mid, axis=-1) / jnp.maximum(opacity, 1e-10)
    depth = jnp.where(opacity > 1e-10, jnp.clip(raw_depth, t_first, t_last), t_last)
    return {
        "rgb": colour,
        "opacity": opacity,
        "depth": depth,
        "median_depth": median_depth(weights, t_edges),
        "weights": weights,
    }


def median_depth(weights: jnp.ndarray, t_edges: jnp.ndarray) -> jnp.ndarray:
    """Distance at which the accumulated weight reaches half of its total.

    weights: [..., S]; t_edges: [..., S + 1] -> [...]; t_last for an empty ray.
    """
    cdf = jnp.concatenate([jnp.zeros_like(weights[..., :1]), jnp.cumsum(weights, axis=-1)], axis=-1)
    total = cdf[..., -1:]
    half = 0.5 * total
    # Index of the bin where the CDF crosses `half` (first edge index with cdf >= half, minus 1).
    above = cdf >= half
    upper = jnp.clip(jnp.argmax(above[..., 1:], axis=-1) + 1, 1, weights.shape[-1])
    lower = upper - 1
    take = lambda a, i: jnp.take_along_axis(a, i[..., None], axis=-1)[..., 0]  # noqa: E731
    c0, c1 = take(cdf, lower), take(cdf, upper)
    t0, t1 = take(t_edges, lower), take(t_edges, upper)
    frac = jnp.clip((half[..., 0] - c0) / jnp.maximum(c1 - c0, 1e-12), 0.0, 1.0)
    return jnp.where(total[..., 0] > 1e-10, t0 + frac * (t1 - t0), t_edges[..., -1])
