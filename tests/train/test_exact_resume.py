"""Exact resume: a training process killed (SIGKILL) after a checkpoint, then resumed, ends
with the same parameters as an uninterrupted run, even when metrics.jsonl ends in a torn line;
a run resumed at its last step reports its last logged loss, not NaN. The same with the
photometric evidence on (train.robust: its per-pixel record is part of the state), and with
lazy Adam on a grid's tables (train.sparse_adam)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxnerf_grid.train import checkpoint
from jaxnerf_grid.train import loop as train
from tests.train.test_loop import last_state, tiny_config, tiny_dataset


def _config(robust: str):
    if robust == "sparse-adam":  # not the evidence: lazy Adam on a grid's tables (its moments in the checkpoint)
        return tiny_config(field="grid", sparse_adam=True)
    return tiny_config(robust=robust, robust_patch=4, robust_confirm=0.01)


def _child(run_dir: str, robust: str) -> None:
    """Trains the tiny run slowly (a pause after each step) so the parent can kill it mid-run."""
    train.train(tiny_dataset(), _config(robust), run_dir, progress=False, on_step=lambda s: time.sleep(0.2))


@pytest.mark.parametrize("robust", ["dpt+robust", "sparse-adam"])  # sparse-adam runs with the evidence off
def test_killed_run_resumes_exactly(tmp_path, robust):
    killed = tmp_path / "killed"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parents[2]) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, __file__, str(killed), robust], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 900  # a guard against a hung child; a loaded machine is slow to compile it
        while not checkpoint.list_checkpoints(killed):
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.time() < deadline, "no checkpoint appeared"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    steps = [s for s, _ in checkpoint.list_checkpoints(killed)]
    assert steps and max(steps) < 30, steps          # it really died mid-run
    # a full disk or a kill while appending leaves half a line: the resume must trim it
    with open(killed / "metrics.jsonl", "a") as fh:
        fh.write('{"step": 7, "loss": 0.0')
    resumed = train.train(tiny_dataset(), _config(robust), killed, progress=False)
    straight = train.train(tiny_dataset(), _config(robust), tmp_path / "straight", progress=False)
    assert resumed.step == straight.step == 30
    diffs = jax.tree_util.tree_map(lambda a, b: float(np.max(np.abs(np.asarray(a) - np.asarray(b)))),
                                   resumed.params, straight.params)
    assert max(jax.tree_util.tree_leaves(diffs)) <= 1e-6, diffs
    if robust != "sparse-adam":  # the record of the weights used resumes too (it is in the checkpoint)
        states = [last_state(run, _config(robust), tiny_dataset()) for run in (killed, tmp_path / "straight")]
        np.testing.assert_array_equal(states[0]["robust_record"], states[1]["robust_record"])
        assert states[0]["robust_record"].min() < 1
    # the metrics log has each logged step once, in order, despite the replay
    lines = (killed / "metrics.jsonl").read_text().splitlines()
    assert [int(x.split('"step": ')[1].split(",")[0]) for x in lines] == [5, 10, 15, 20, 25, 30]
    again = train.train(tiny_dataset(), _config(robust), killed, progress=False)  # already finished
    assert again.step == 30 and again.steps_run == 0
    assert again.last_loss == resumed.last_loss and np.isfinite(again.last_psnr)


if __name__ == "__main__":
    _child(sys.argv[1], sys.argv[2])
