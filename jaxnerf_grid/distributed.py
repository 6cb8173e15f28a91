"""Multi-process data parallelism (`jax.distributed`): one process per host, collectives across hosts.

`initialize` starts JAX's multi-process runtime from flags (`--coordinator HOST:PORT
--num-processes N --process-id I`) or from the environment (`JAX_COORDINATOR_ADDRESS`, plus
`JAX_NUM_PROCESSES` / `JAX_PROCESS_ID`, or a cluster JAX detects itself: SLURM, Open MPI,
Kubernetes; `--coordinator auto` asks for that detection explicitly). With neither, nothing
happens and training stays the single-process pmap it always was.

Once initialised, the same pmapped train step runs on every process over *all* devices of the
run (`jax.devices()`), so `jax.lax.psum` and `jax.lax.axis_index` span processes: the batch
split, the ray draw and the gradient mean are those of one process holding every device
(docs/DISTRIBUTED.md). Process 0 (`is_main`) writes run files, checkpoints and logs.

Failure detection (the runtime's own settings, passed to `jax.distributed.initialize`):
a collective whose peer died fails at once on the survivors (gloo on CPU: "Connection reset by
peer"; `train` turns it into `DistributedError`); a peer that stops sending heartbeats for
`HEARTBEAT_TIMEOUT_S` is declared dead by the coordination service, which then terminates every
other process ("Terminating process because the JAX distributed service detected fatal
errors"). `INIT_TIMEOUT_S` bounds the wait for all processes to connect at start-up;
`SHUTDOWN_TIMEOUT_S` the wait at exit for the others (process 0 evaluates after training).
"""

from __future__ import annotations

import os

import jax

HEARTBEAT_TIMEOUT_S = int(os.environ.get("JAXNERF_HEARTBEAT_TIMEOUT", "60"))
INIT_TIMEOUT_S = int(os.environ.get("JAXNERF_INIT_TIMEOUT", "300"))
# at exit every process waits for the others in the runtime's shutdown barrier; processes 1..N-1
# finish training while process 0 still evaluates / writes the report, and a barrier that times out
# aborts *every* process (process 0 mid-report included: seen with 1 s), so it is long
SHUTDOWN_TIMEOUT_S = int(os.environ.get("JAXNERF_SHUTDOWN_TIMEOUT", "7200"))


class DistributedError(RuntimeError):
    """A cross-process collective failed: another process of the run died or lost the network."""


def wanted(coordinator: str | None = None, num_processes: int | None = None,
           process_id: int | None = None) -> bool:
    """True when the flags or the environment ask for a multi-process run."""
    return (coordinator is not None or num_processes is not None or process_id is not None
            or "JAX_COORDINATOR_ADDRESS" in os.environ or "JAX_NUM_PROCESSES" in os.environ)


def _env_int(name: str) -> int | None:
    value = os.environ.get(name)
    return int(value) if value not in (None, "") else None


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, *, heartbeat_timeout_s: int | None = None) -> bool:
    """Starts jax.distributed when asked (see `wanted`); returns True when this is a
    multi-process run. Must run before anything touches a JAX device. Idempotent.

    coordinator "auto": let JAX detect the cluster (SLURM, Open MPI, Kubernetes, mpi4py).
    """
    from jax._src import distributed as _dist  # the runtime's state: initialised already?

    if _dist.global_state.client is not None:
        return jax.process_count() > 1
    if not wanted(coordinator, num_processes, process_id):
        return False
    if num_processes is None:
        num_processes = _env_int("JAX_NUM_PROCESSES")
    if process_id is None:
        process_id = _env_int("JAX_PROCESS_ID")
    if coordinator == "auto":
        coordinator = None
    if num_processes is not None and num_processes < 1:
        raise ValueError(f"distributed.num_processes = {num_processes}: must be >= 1")
    if process_id is not None and num_processes is not None and not 0 <= process_id < num_processes:
        raise ValueError(f"distributed.process_id = {process_id}: must be in [0, {num_processes})")
    # cross-process collectives on CPU devices need gloo (the default CPU client has none);
    # the setting only concerns the CPU client, so it is harmless on GPU hosts
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    # everything given: no cluster detection (on SLURM it would pin each process to one device,
    # SLURM_LOCALID; explicit flags mean one process per host with all its devices)
    explicit = None not in (coordinator, num_processes, process_id)
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id, initialization_timeout=INIT_TIMEOUT_S,
                               cluster_detection_method="deactivate" if explicit else None,
                               heartbeat_timeout_seconds=heartbeat_timeout_s or HEARTBEAT_TIMEOUT_S,
                               shutdown_timeout_seconds=SHUTDOWN_TIMEOUT_S)
    return jax.process_count() > 1


def is_distributed() -> bool:
    return jax.process_count() > 1


def is_main() -> bool:
    """True on the process that writes files (process 0; always True in a single process)."""
    return jax.process_index() == 0


def barrier(name: str) -> None:
    """Waits until every process reaches `name` (no-op in a single process)."""
    if is_distributed():
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def broadcast_from_main(tree):
    """Process 0's value of a pytree of arrays / scalars, on every process (identity in one
    process). Used so that every process resumes from process 0's checkpoint."""
    if not is_distributed():
        return tree
    from jax.experimental import multihost_utils

    return jax.device_get(multihost_utils.broadcast_one_to_all(tree))
