"""Data parallelism over the local devices (pmap): the plumbing training and rendering share.

Host-side arrays are laid out as `jax.pmap` wants them, a leading device axis [n, ...]:
`replicate` copies a pytree onto n devices (parameters, optimiser state, the ray pool),
`shard` / `unshard` split a batch's leading axis over the devices and join it back, and
`run_sharded` does the whole round trip for a pmapped function of a batch of any size.
The pmap axis is named `AXIS`; collectives inside a step (`jax.lax.psum`) use it.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np

AXIS = "batch"


def spans_processes(n: int) -> bool:
    """True when n devices means every device of a multi-process run (jax.distributed): then
    a pmap runs on all of them, each process feeding its own local devices."""
    return jax.process_count() > 1 and n == jax.device_count()


def devices(n: int) -> list:
    """The first n local devices (what every pmap here runs on); in a multi-process run with
    n = the global device count, every device of every process (`spans_processes`)."""
    return jax.devices() if spans_processes(n) else jax.local_devices()[:n]


def local_count(n: int) -> int:
    """How many of the n devices of a pmap are this process's (n itself in one process)."""
    return jax.local_device_count() if spans_processes(n) else n


def replicate(tree, n: int):
    """Copies every leaf onto the first n local devices: [...] -> [n, ...], resident there, so
    a pmapped step does not copy it again each call. When n spans processes, each process
    holds its local copies [local_count(n), ...] of the global [n, ...] (what pmap takes)."""
    stacked = jax.tree_util.tree_map(lambda x: np.stack([np.asarray(x)] * local_count(n)), tree)
    return jax.pmap(lambda x: x, axis_name=AXIS, devices=devices(n))(stacked)


def unreplicate(tree):
    """The first device's copy of a replicated pytree, on the host: [n, ...] -> [...]."""
    return jax.device_get(jax.tree_util.tree_map(lambda x: x[0], tree))


def pad_to_multiple(x, multiple: int) -> tuple[np.ndarray, int]:
    """Pads the leading axis to a multiple by repeating the last row. Returns (padded, B)."""
    x = np.asarray(x)
    count = x.shape[0]
    remainder = (-count) % multiple
    if remainder:
        x = np.concatenate([x, np.repeat(x[-1:], remainder, axis=0)], axis=0)
    return x, count


def shard(tree, n: int):
    """Splits every leaf's leading axis over n devices: [B, ...] -> [n, B / n, ...]."""
    def split(x):
        x = np.asarray(x)
        if x.shape[0] % n:
            raise ValueError(f"shard: leading axis {x.shape[0]} does not divide by {n} devices")
        return x.reshape(n, x.shape[0] // n, *x.shape[1:])

    return jax.tree_util.tree_map(split, tree)


def unshard(tree):
    """Inverse of `shard`: [n, B / n, ...] -> [B, ...]."""
    return jax.tree_util.tree_map(lambda x: x.reshape(-1, *x.shape[2:]), tree)


def run_sharded(pmapped: Callable, batch, n: int):
    """pmapped(batch [n, B' / n, ...]) for a batch [B, ...] of any size B: the batch is padded
    to a multiple of n, sharded, run, fetched to the host, joined and trimmed back to B rows.

    `pmapped` must act row-wise and map over the leading axis of its one argument (close over
    anything replicated). Returns the output pytree as NumPy [B, ...].
    """
    leaves = jax.tree_util.tree_leaves(batch)
    count = leaves[0].shape[0]
    padded = jax.tree_util.tree_map(lambda x: pad_to_multiple(x, n)[0], batch)
    out = unshard(jax.device_get(pmapped(shard(padded, n))))
    return jax.tree_util.tree_map(lambda x: x[:count], out)
