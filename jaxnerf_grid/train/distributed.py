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

import errno
import os
import socket
import time

import jax

from jaxnerf_grid.config.schema import ConfigError


def env_seconds(name: str, default: int) -> int:
    """A timeout in whole seconds from the environment variable `name` (default when unset);
    ConfigError naming the variable when it is not an integer >= 1."""
    value = os.environ.get(name, "")
    if value == "":
        return default
    try:
        seconds = int(value)
    except ValueError:
        raise ConfigError(f"{name}={value!r}: must be a whole number of seconds") from None
    if seconds < 1:
        raise ConfigError(f"{name}={value!r}: must be >= 1 second")
    return seconds


HEARTBEAT_DEFAULT_S, INIT_DEFAULT_S, SHUTDOWN_DEFAULT_S = 60, 300, 7200
# at exit every process waits for the others in the runtime's shutdown barrier; processes 1..N-1
# finish training while process 0 still evaluates / writes the report, and a barrier that times out
# aborts *every* process (process 0 mid-report included: seen with 1 s), so it is long
# A process other than 0 first connects to the coordinator itself (`probe_coordinator`), retrying
# a refused connection (process 0 may start a little later) for CONNECT_DEFAULT_S, so a wrong
# address is one line after that time instead of the runtime's abort after INIT_TIMEOUT_S.
CONNECT_DEFAULT_S = 20
CONNECT_RETRY_S = 0.5


def timeouts() -> dict:
    """{"heartbeat", "init", "shutdown", "connect"} in seconds: JAXNERF_HEARTBEAT_TIMEOUT,
    JAXNERF_INIT_TIMEOUT, JAXNERF_SHUTDOWN_TIMEOUT, JAXNERF_CONNECT_TIMEOUT or their defaults."""
    return {"heartbeat": env_seconds("JAXNERF_HEARTBEAT_TIMEOUT", HEARTBEAT_DEFAULT_S),
            "init": env_seconds("JAXNERF_INIT_TIMEOUT", INIT_DEFAULT_S),
            "shutdown": env_seconds("JAXNERF_SHUTDOWN_TIMEOUT", SHUTDOWN_DEFAULT_S),
            "connect": env_seconds("JAXNERF_CONNECT_TIMEOUT", CONNECT_DEFAULT_S)}


def parse_address(text: str, key: str = "distributed.coordinator") -> tuple[str, int]:
    """"HOST:PORT" (or "[IPv6]:PORT") -> (host, port); ConfigError naming `key` for another form
    or a port outside 1..65535."""
    text = str(text).strip()
    host, sep, port = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port.isdigit() or any(c.isspace() for c in host):
        raise ConfigError(f"{key} = {text!r}: expected HOST:PORT (e.g. 10.0.0.1:12345) or auto")
    if not 1 <= int(port) <= 65535:
        raise ConfigError(f"{key} = {text!r}: the port must be in 1..65535")
    return host, int(port)


def check_port_free(host: str, port: int, key: str = "distributed.coordinator") -> None:
    """Process 0 serves the coordinator on `port`: ConfigError when another program listens there."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a TIME_WAIT socket does not count
        sock.bind(("", port))
    except OSError as err:
        if err.errno == errno.EADDRINUSE:
            raise ConfigError(f"{key} = {host}:{port}: port {port} is already in use on this host (another run's "
                              "coordinator?); choose another port") from None
    finally:
        sock.close()


def probe_coordinator(host: str, port: int, timeout_s: float, key: str = "distributed.coordinator") -> None:
    """Connects to the coordinator's address until it accepts or `timeout_s` passes (a refused
    connection is retried every CONNECT_RETRY_S: process 0 may start later); ConfigError naming
    the address and the last reason otherwise. A host name that does not resolve fails at once."""
    deadline = time.monotonic() + timeout_s
    reason = "no answer"
    while True:
        left = deadline - time.monotonic()
        try:
            with socket.create_connection((host, port), timeout=max(0.1, min(left, 5.0))):
                return
        except socket.gaierror as err:
            raise ConfigError(f"{key} = {host}:{port}: the host name does not resolve ({err.strerror or err})"
                              ) from None
        except OSError as err:
            reason = err.strerror or str(err) or type(err).__name__
        if time.monotonic() + CONNECT_RETRY_S >= deadline:
            raise ConfigError(f"{key} = {host}:{port}: no coordinator answered within {timeout_s:g} s ({reason}); "
                              "start process 0 first, or check the address (JAXNERF_CONNECT_TIMEOUT sets the wait)")
        time.sleep(CONNECT_RETRY_S)


HEARTBEAT_TIMEOUT_S = HEARTBEAT_DEFAULT_S  # the defaults; `initialize` reads the environment (`timeouts`)
INIT_TIMEOUT_S = INIT_DEFAULT_S
SHUTDOWN_TIMEOUT_S = SHUTDOWN_DEFAULT_S


class DistributedError(RuntimeError):
    """A cross-process collective failed: another process of the run died or lost the network."""


def wanted(coordinator: str | None = None, num_processes: int | None = None,
           process_id: int | None = None) -> bool:
    """True when the flags or the environment ask for a multi-process run."""
    return (coordinator is not None or num_processes is not None or process_id is not None
            or "JAX_COORDINATOR_ADDRESS" in os.environ or "JAX_NUM_PROCESSES" in os.environ)


def _env_int(name: str) -> int | None:
    """An integer environment value (None when unset); ConfigError naming the variable otherwise."""
    value = os.environ.get(name)
    if value in (None, ""):
        return None
    try:
        return int(value)
    except ValueError:
        raise ConfigError(f"{name}={value!r}: must be an integer") from None


def check_settings(coordinator: str | None, num_processes: int | None, process_id: int | None) -> None:
    """ConfigError naming the key or variable for a bad setting of a multi-process run:
    num_processes >= 1, process_id in [0, num_processes), the coordinator "auto" or HOST:PORT."""
    if num_processes is not None and num_processes < 1:
        raise ConfigError(f"distributed.num_processes = {num_processes}: must be >= 1")
    if process_id is not None and process_id < 0:
        raise ConfigError(f"distributed.process_id = {process_id}: must be >= 0")
    if process_id is not None and num_processes is not None and not process_id < num_processes:
        raise ConfigError(f"distributed.process_id = {process_id}: must be in [0, {num_processes})")
    if coordinator not in (None, "auto"):
        parse_address(coordinator)


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, *, heartbeat_timeout_s: int | None = None) -> bool:
    """Starts jax.distributed when asked (see `wanted`); returns True when this is a
    multi-process run. Must run before anything touches a JAX device. Idempotent.

    coordinator "auto": let JAX detect the cluster (SLURM, Open MPI, Kubernetes, mpi4py).
    """
    from jax._src import distributed as _dist  # the runtime's state: initialised already?

    if _dist.global_state.client is not None:
        return jax.process_count() > 1
    limits = timeouts()  # every value checked before anything starts, also in a single-process run
    if not wanted(coordinator, num_processes, process_id):
        return False
    if num_processes is None:
        num_processes = _env_int("JAX_NUM_PROCESSES")
    if process_id is None:
        process_id = _env_int("JAX_PROCESS_ID")
    if coordinator is None and os.environ.get("JAX_COORDINATOR_ADDRESS"):
        address = os.environ["JAX_COORDINATOR_ADDRESS"]
        if address != "auto":
            parse_address(address, "JAX_COORDINATOR_ADDRESS")
        coordinator = address
    check_settings(coordinator, num_processes, process_id)
    if coordinator == "auto":
        coordinator = None
    if coordinator is not None and process_id is not None:
        host, port = parse_address(coordinator)
        if process_id == 0:
            check_port_free(host, port)
        else:
            probe_coordinator(host, port, limits["connect"])
    # cross-process collectives on CPU devices need gloo (the default CPU client has none);
    # the setting only concerns the CPU client, so it is harmless on GPU hosts
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    # everything given: no cluster detection (on SLURM it would pin each process to one device,
    # SLURM_LOCALID; explicit flags mean one process per host with all its devices)
    explicit = None not in (coordinator, num_processes, process_id)
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id, initialization_timeout=limits["init"],
                               cluster_detection_method="deactivate" if explicit else None,
                               heartbeat_timeout_seconds=heartbeat_timeout_s or limits["heartbeat"],
                               shutdown_timeout_seconds=limits["shutdown"])
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
