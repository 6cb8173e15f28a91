"""Coordinate maps: the dual-sphere contraction (Eq. 9, corrected) and positional encoding.

The paper's Eq. 9 is misprinted (docs/CONVENTIONS.md). Here, with a near sphere of radius 1 and a far
sphere of radius R > 1:

    contract(x) = x                                 if |x| <= 1
                = (R - (R - 1) / |x|) * x / |x|     otherwise

which is continuous and C1 at |x| = 1, monotone in |x|, and maps infinity to radius R
(R = 2 is mip-NeRF 360's). Its inverse, for |z| < R, is |x| = (R - 1) / (R - |z|).
"""

from __future__ import annotations

import jax.numpy as jnp

_TINY = 1e-12


def _check_radius(radius) -> None:
    try:
        value = float(radius)
    except TypeError:  # a traced value: cannot be checked here
        return
    if not value > 1.0:
        raise ValueError(f"contract: the far-sphere radius must be > 1, got {value}")


def _safe_norm(x: jnp.ndarray) -> jnp.ndarray:
    """Euclidean norm on the last axis with a finite gradient at 0. x: [..., D] -> [..., 1]."""
    return jnp.sqrt(jnp.maximum(jnp.sum(x * x, axis=-1, keepdims=True), _TINY))


def contract(x: jnp.ndarray, radius: float = 2.0) -> jnp.ndarray:
    """Dual-sphere contraction of points. x: [..., 3] (any D) -> z: [..., D] with |z| < radius."""
    _check_radius(radius)
    norm = _safe_norm(x)
    outside_norm = jnp.maximum(norm, 1.0)  # keeps the unused branch finite inside the unit ball
    scale = (radius - (radius - 1.0) / outside_norm) / outside_norm
    return jnp.where(norm <= 1.0, x, scale * x)


def inv_contract(z: jnp.ndarray, radius: float = 2.0) -> jnp.ndarray:
    """Inverse of `contract`. z: [..., D] with |z| < radius -> x: [..., D].

    Points at or beyond the far sphere are clipped just inside it (they map to very large |x|).
    """
    _check_radius(radius)
    norm = _safe_norm(z)
    outside_norm = jnp.clip(norm, 1.0, radius * (1.0 - 1e-6))
    x_norm = (radius - 1.0) / (radius - outside_norm)
    return jnp.where(norm <= 1.0, z, z * (x_norm / outside_norm))


def positional_encoding(x: jnp.ndarray, min_deg: int, max_deg: int,
                        append_identity: bool = True) -> jnp.ndarray:
    """NeRF's sinusoidal encoding with frequencies 2^min_deg .. 2^(max_deg-1).

    x: [..., D] -> [..., D * 2 * (max_deg - min_deg) (+ D if append_identity)], ordered as
    [sin(2^k x) for all k, d] then [cos(...)] then the identity.
    """
    if max_deg < min_deg:
        raise ValueError(f"positional_encoding: max_deg ({max_deg}) < min_deg ({min_deg})")
    scales = 2.0 ** jnp.arange(min_deg, max_deg, dtype=x.dtype)
    scaled = (x[..., None, :] * scales[:, None]).reshape(*x.shape[:-1], -1)
    encoded = jnp.sin(jnp.concatenate([scaled, scaled + 0.5 * jnp.pi], axis=-1))
    if append_identity:
        encoded = jnp.concatenate([encoded, x], axis=-1)
    return encoded


def encoded_size(dim: int, min_deg: int, max_deg: int, append_identity: bool = True) -> int:
    """Width of `positional_encoding`'s output for a [..., dim] input."""
    return dim * 2 * (max_deg - min_deg) + (dim if append_identity else 0)
