"""Sampling along rays: the s-space warps of Eq. 10-11, stratified samples, PDF resampling.

A warp g maps metric distance t to a monotone function value; the normalised distance is

    s = (g(t) - g(t_near)) / (g(t_far) - g(t_near))              (Eq. 10)
    t = g^-1(s * g(t_far) + (1 - s) * g(t_near))                 (Eq. 11)

so s runs from 0 at t_near to 1 at t_far whether g increases or decreases. Uniform samples in s
are uniform in t for g = t, uniform in disparity for g = 1/t (the paper's choice: dense near,
sparse far), and mip-NeRF 360's near-linear-far-disparity split for "piecewise".
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

Warp = tuple[Callable[[jnp.ndarray], jnp.ndarray], Callable[[jnp.ndarray], jnp.ndarray]]


def _piecewise(t):
    return jnp.where(t < 1.0, 0.5 * t, 1.0 - 0.5 / jnp.maximum(t, 1.0))


def _piecewise_inv(x):
    return jnp.where(x < 0.5, 2.0 * x, 0.5 / jnp.maximum(1.0 - x, 1e-12))


WARP_FUNCTIONS: dict[str, Warp] = {
    "linear": (lambda t: t, lambda x: x),
    "disparity": (lambda t: 1.0 / t, lambda x: 1.0 / x),
    "log": (jnp.log, jnp.exp),
    "piecewise": (_piecewise, _piecewise_inv),
}


def ray_warp(kind, t_near, t_far) -> Warp:
    """Builds (t_to_s, s_to_t) for Eq. 10-11.

    kind: one of WARP_FUNCTIONS' names, or a pair of callables (g, g_inv).
    t_near, t_far: scalars or arrays broadcastable against the t / s values later passed in
    (for per-ray bounds [...] and samples [..., S], pass t_near[..., None]).
    Returns t_to_s(t: [...]) -> s, s_to_t(s: [...]) -> t.
    """
    if isinstance(kind, str):
        if kind not in WARP_FUNCTIONS:
            raise ValueError(f"ray_warp: unknown warp {kind!r}; choose from {sorted(WARP_FUNCTIONS)} "
                             "or pass a pair of callables (g, g_inv)")
        g, g_inv = WARP_FUNCTIONS[kind]
    else:
        try:
            g, g_inv = kind
        except (TypeError, ValueError):
            raise ValueError("ray_warp: kind must be a warp name or a pair (g, g_inv)") from None
        if not (callable(g) and callable(g_inv)):
            raise ValueError("ray_warp: (g, g_inv) must both be callable")
    g_near = g(jnp.asarray(t_near, jnp.float32))
    g_far = g(jnp.asarray(t_far, jnp.float32))

    def t_to_s(t):
        return (g(t) - g_near) / (g_far - g_near)

    def s_to_t(s):
        return g_inv(s * g_far + (1.0 - s) * g_near)

    return t_to_s, s_to_t


def stratified_s(key, batch_shape: tuple, num_samples: int, single_jitter: bool = False) -> jnp.ndarray:
    """Bin edges in s, one bin per sample.

    The i-th sample sits at s = (i + u_i) / N with u_i ~ U[0, 1) (u_i = 0.5 when key is None),
    and the edges are the midpoints between consecutive samples, with 0 and 1 at the ends.
    With key None the edges are exactly linspace(0, 1, N + 1).
    Returns: [*batch_shape, N + 1], sorted, from 0 to 1.
    """
    if key is None:
        offsets = jnp.full((*batch_shape, num_samples), 0.5)
    else:
        jitter_shape = (*batch_shape, 1) if single_jitter else (*batch_shape, num_samples)
        offsets = jnp.broadcast_to(jax.random.uniform(key, jitter_shape), (*batch_shape, num_samples))
    centres = (jnp.arange(num_samples) + offsets) / num_samples
    middle = 0.5 * (centres[..., 1:] + centres[..., :-1])
    zeros = jnp.zeros((*batch_shape, 1))
    return jnp.concatenate([zeros, middle, zeros + 1.0], axis=-1)


def resample_pdf(key, edges: jnp.ndarray, weights: jnp.ndarray, num_samples: int,
                 single_jitter: bool = False, weight_floor: float = 1e-5) -> jnp.ndarray:
    """Hierarchical sampling: inverse-CDF samples of the piecewise-constant PDF over the bins.

    edges: [..., S + 1] sorted bin edges (in t or s); weights: [..., S] non-negative bin masses.
    A floor of `weight_floor` (relative to the mean mass) keeps every bin reachable.
    Stratified in the CDF: u_j = (j + jitter) / num_samples (jitter 0.5 when key is None).
    Returns: [..., num_samples] sorted samples, with a stop-gradient.
    """
    edges = jax.lax.stop_gradient(edges)
    weights = jax.lax.stop_gradient(jnp.maximum(weights, 0.0))
    num_bins = weights.shape[-1]
    mass = weights + weight_floor * jnp.mean(weights, axis=-1, keepdims=True) + 1e-12
    pdf = mass / jnp.sum(mass, axis=-1, keepdims=True)
    cdf = jnp.concatenate([jnp.zeros_like(pdf[..., :1]), jnp.cumsum(pdf, axis=-1)], axis=-1)
    cdf = cdf.at[..., -1].set(1.0)
    batch_shape = weights.shape[:-1]
    if key is None:
        offsets = jnp.full((*batch_shape, num_samples), 0.5)
    else:
        jitter_shape = (*batch_shape, 1) if single_jitter else (*batch_shape, num_samples)
        offsets = jnp.broadcast_to(jax.random.uniform(key, jitter_shape, maxval=1.0 - 1e-6),
                                   (*batch_shape, num_samples))
    u = (jnp.arange(num_samples) + offsets) / num_samples
    flat_cdf = cdf.reshape(-1, num_bins + 1)
    flat_edges = edges.reshape(-1, num_bins + 1)
    flat_u = u.reshape(-1, num_samples)
    samples = jax.vmap(jnp.interp)(flat_u, flat_cdf, flat_edges)
    return jax.lax.stop_gradient(samples.reshape(*batch_shape, num_samples))


def intervals_from_samples(samples: jnp.ndarray, low, high) -> jnp.ndarray:
    """Bin edges around sorted sample points: midpoints inside, [low, high] at the ends.

    samples: [..., N] sorted; low, high: [...] or scalars. Returns: [..., N + 1].
    """
    low = jnp.broadcast_to(jnp.asarray(low, samples.dtype), samples.shape[:-1])[..., None]
    high = jnp.broadcast_to(jnp.asarray(high, samples.dtype), samples.shape[:-1])[..., None]
    middle = 0.5 * (samples[..., 1:] + samples[..., :-1])
    return jnp.concatenate([low, middle, high], axis=-1)


def merge_edges(edges_a: jnp.ndarray, edges_b: jnp.ndarray) -> jnp.ndarray:
    """Sorted union of two sets of edges on the same rays (NeRF's two-pass union).

    edges_a: [..., A], edges_b: [..., B] -> [..., A + B].
    """
    return jnp.sort(jnp.concatenate([edges_a, edges_b], axis=-1), axis=-1)
