"""Data parallelism over all local devices (pmap), shared by rendering and training."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp


def num_devices() -> int:
    return jax.local_device_count()


def shard(tree, n: int | None = None):
    """Splits every leaf's leading axis into [n, B / n, ...]. B must divide by n."""
    n = n or num_devices()

    def split(x):
        x = jnp.asarray(x)
        if x.shape[0] % n:
            raise ValueError(f"shard: leading axis {x.shape[0]} does not divide by {n} devices")
        return x.reshape(n, x.shape[0] // n, *x.shape[1:])

    return jax.tree_util.tree_map(split, tree)


def unshard(tree):
    """Inverse of `shard`: [n, B / n, ...] -> [B, ...]."""
    return jax.tree_util.tree_map(lambda x: x.reshape(-1, *x.shape[2:]), tree)


def replicate(tree, n: int | None = None):
    """Copies every leaf to each local device: [...] -> [n, ...]."""
    n = n or num_devices()
    # jax.device_put_replicated is gone from current JAX; pmap shards a stacked leading axis.
    return jax.tree_util.tree_map(lambda x: jnp.stack([jnp.asarray(x)] * n), tree)


def pad_to_multiple(x: jnp.ndarray, multiple: int) -> tuple[jnp.ndarray, int]:
    """Pads the leading axis (repeating the last row) to a multiple. Returns (padded, original B)."""
    count = x.shape[0]
    remainder = (-count) % multiple
    if remainder:
        x = jnp.concatenate([x, jnp.repeat(x[-1:], remainder, axis=0)], axis=0)
    return x, count


def pmap_over_batch(fn: Callable, n: int | None = None) -> Callable:
    """Wraps fn(batch_tree) -> out_tree so the batch is split over n devices and re-joined.

    fn must act row-wise on its leading axis. Non-divisible batches are padded and trimmed.
    """
    n = n or num_devices()
    mapped = jax.pmap(fn)

    def run(batch):
        leaves = jax.tree_util.tree_leaves(batch)
        count = leaves[0].shape[0]
        padded = jax.tree_util.tree_map(lambda x: pad_to_multiple(jnp.asarray(x), n)[0], batch)
        out = unshard(mapped(shard(padded, n)))
        return jax.tree_util.tree_map(lambda x: x[:count], out)

    return run
