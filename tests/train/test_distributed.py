"""Multi-process training (jax.distributed, docs/DISTRIBUTED.md): two local CPU processes with one
device each reach the parameters of one process with two devices (same seed, same steps), after
both are killed mid-run and resumed (the steps before the kill ran straight); a process that dies
makes the survivor stop with an error within the stated time instead of hanging.

The children run this file as a script: `python test_distributed.py MODE PORT PROCESS_ID RUN_DIR`,
with XLA_FLAGS giving them one CPU device each and gloo for the collectives.
"""

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from tests.conftest import with_compile_fast_flags

STEPS = int(os.environ.get("JAXNERF_DISTRIBUTED_STEPS", "12"))  # the issue asks 50; 12 keeps CI under its limit
HEARTBEAT_S = 10  # the children's heartbeat timeout for the death test
ROOT = Path(__file__).parents[2]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _config(num_devices: int, **kw):
    from tests.train.test_loop import tiny_config

    return tiny_config(max_steps=STEPS, num_devices=num_devices, checkpoint_every=4, **kw)


def _child(mode: str, port: int, pid: int, run_dir: str) -> None:
    from jaxnerf_grid.train import distributed
    from jaxnerf_grid.train import loop as train
    from tests.train.test_loop import tiny_dataset

    distributed.initialize(f"127.0.0.1:{port}", 2, pid, heartbeat_timeout_s=HEARTBEAT_S)
    assert jax.process_count() == 2 and jax.device_count() == 2
    on_step = None
    if mode == "slow":          # pause after each step so the parent can kill it mid-run
        on_step = lambda s: time.sleep(0.2)  # noqa: E731
    if mode == "die":           # process 1 exits abruptly after step 3; process 0 must stop
        def on_step(s):
            if pid == 1 and s == 3:
                os._exit(3)
    try:
        result = train.train(tiny_dataset(), _config(0), run_dir, progress=False, on_step=on_step)
    except distributed.DistributedError as err:
        print(f"DistributedError: {err}", file=sys.stderr, flush=True)
        os._exit(7)
    np.savez(Path(run_dir) / f"params_{pid}.npz",
             *[np.asarray(x) for x in jax.tree_util.tree_leaves(result.params)])


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    """A JAX compilation cache the children share: only the first launch compiles the step."""
    return tmp_path_factory.mktemp("jax-cache")


def _launch(mode: str, run_dirs: list[Path], cache: Path) -> list[subprocess.Popen]:
    """Two child processes on a free port, sharing the compilation cache `cache`."""
    port = _free_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               JAX_PLATFORMS="cpu", XLA_FLAGS=with_compile_fast_flags("--xla_force_host_platform_device_count=1"),
               JAX_COMPILATION_CACHE_DIR=str(cache),
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    env.pop("JAX_COORDINATOR_ADDRESS", None)
    return [subprocess.Popen([sys.executable, __file__, mode, str(port), str(i), str(run_dirs[i])], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE) for i in range(2)]


def _wait(procs, timeout: float) -> list[tuple[int, str]]:
    deadline = time.time() + timeout
    out = []
    try:
        for p in procs:
            _, err = p.communicate(timeout=max(1.0, deadline - time.time()))
            out.append((p.returncode, err.decode(errors="replace")))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return out


def _leaves(path: Path) -> list[np.ndarray]:
    with np.load(path) as z:
        return [z[f"arr_{i}"] for i in range(len(z.files))]


def _reference(tmp_path: Path) -> list[np.ndarray]:
    from jaxnerf_grid.train import loop as train
    from tests.train.test_loop import tiny_dataset

    if jax.local_device_count() < 2:
        pytest.skip("needs 2 local devices (XLA_FLAGS=--xla_force_host_platform_device_count=2)")
    result = train.train(tiny_dataset(), _config(2), tmp_path / "one", progress=False)
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(result.params)]


def _assert_close(got: list[np.ndarray], want: list[np.ndarray]) -> None:
    assert len(got) == len(want)
    worst = max(float(np.max(np.abs(a - b))) for a, b in zip(got, want))
    print(f"max |2 processes x 1 device - 1 process x 2 devices| = {worst:.3g}")
    assert worst <= 1e-5, worst


def test_two_processes_match_one_process_with_two_devices_after_kill_and_resume(tmp_path, cache):
    """Both processes SIGKILLed after a checkpoint mid-run, then restarted: the steps before the
    kill ran straight, those after it from process 0's checkpoint; process 1's run folder is a
    different, empty one (it resumes from process 0's broadcast) and stays without checkpoints."""
    from jaxnerf_grid.train import checkpoint

    want = _reference(tmp_path)
    dirs = [tmp_path / "k0", tmp_path / "k1"]
    procs = _launch("slow", dirs, cache)
    try:
        deadline = time.time() + 600  # a net against a hang, not a speed target: the children's
        # compilation under a loaded machine took over 150 s once (nice 19 beside a training job)
        while not checkpoint.list_checkpoints(dirs[0]):
            assert all(p.poll() is None for p in procs), [p.stderr.read().decode()[-3000:] for p in procs]
            assert time.time() < deadline, "no checkpoint appeared"
            time.sleep(0.05)
    finally:
        for p in procs:
            p.kill()
            p.wait()
    steps = [s for s, _ in checkpoint.list_checkpoints(dirs[0])]
    assert steps and max(steps) < STEPS, steps     # it really died mid-run
    results = _wait(_launch("plain", dirs, cache), 600)
    assert all(rc == 0 for rc, _ in results), [err[-3000:] for _, err in results]
    assert [s for s, _ in checkpoint.list_checkpoints(dirs[0])][-1] == STEPS
    assert not checkpoint.list_checkpoints(dirs[1])  # only process 0 writes
    for i in range(2):
        _assert_close(_leaves(dirs[i] / f"params_{i}.npz"), want)


def test_a_dead_process_stops_the_survivor_with_an_error(tmp_path, cache):
    """The survivor ends with an error within the heartbeat timeout's reach of the death (timed
    from the death, not the launch: starting and compiling take what the machine allows)."""
    procs = _launch("die", [tmp_path / "d0", tmp_path / "d1"], cache)
    try:
        rc1 = procs[1].wait(timeout=600)   # a net against a hang, not a speed target
        died = time.time()
        _, err0 = procs[0].communicate(timeout=600)
        after_death = time.time() - died
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    err0 = err0.decode(errors="replace")
    assert rc1 == 3
    assert procs[0].returncode != 0, err0[-3000:]
    assert "DistributedError" in err0 or "distributed service detected fatal errors" in err0, err0[-3000:]
    assert after_death < 60 + 2 * HEARTBEAT_S, after_death


def test_without_flags_or_environment_nothing_starts(monkeypatch):
    from jaxnerf_grid.train import distributed

    for var in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        monkeypatch.delenv(var, raising=False)
    assert not distributed.wanted()
    assert distributed.initialize() is False and jax.process_count() == 1 and distributed.is_main()
    distributed.barrier("nothing")                    # no-ops in one process
    assert distributed.broadcast_from_main({"a": 1})["a"] == 1


def test_a_bad_process_id_is_a_one_line_error(capsys):
    from jaxnerf_grid import cli

    rc = cli.main(["train", "--data", "nowhere", "--coordinator", "127.0.0.1:1", "--num-processes", "2",
                   "--process-id", "2", "--quiet"])
    assert rc == 1
    assert "--process-id = 2: must be in [0, 2)" in capsys.readouterr().err


if __name__ == "__main__":
    _child(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
