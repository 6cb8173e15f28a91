"""How fast this machine trains a config: train rays a second, measured before a run is planned.

The training budget (config/budget.py) turns a time budget into steps at a speed. The reference
figures (budget.REFERENCE_RAYS_PER_S) are one 2-core CPU and one H200; a laptop with more cores,
another GPU, a busy machine or a slower recipe trains at another speed, and a run planned at the
reference speed then ends well before or well after the minutes the user gave. `measure` times the
run's own step on this machine instead:

  * a small random scene (CALIBRATION_FRAMES frames of CALIBRATION_SIZE pixels; the step's cost is
    set by the batch and the model, not by the frames it draws from) and the config's step,
    compiled once (its first call, not timed);
  * then whole rounds of ROUND steps, each round waited for, until `seconds` have passed;
  * rays a second = batch_rays x steps timed / seconds taken.

The robust step and the depth prior's rays are timed as the plain step's rays (the robust step
trains as fast: docs/RECIPES.md; the budget counts the depth rays as rays, `budget.step_rays`).
The measuring costs the compile plus `seconds` (about 10 s on two CPU cores), so the budget asks
for it only when the time cap may bind (budget.apply).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from jaxnerf_grid.config import budget
from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.train import distributed, loop
from jaxnerf_grid.util import parallel

CALIBRATION_FRAMES = 4
CALIBRATION_SIZE = (64, 48)  # (W, H)
ROUND = 5  # steps queued between two waits
SECONDS = 3.0  # timed steps, after the compile


def calibration_scene(frames: int = CALIBRATION_FRAMES, size: tuple[int, int] = CALIBRATION_SIZE) -> Dataset:
    """A random scene to time a step on: `frames` cameras on a circle of radius 3 looking at the
    origin, uniform random colours [frames, H, W, 3]."""
    width, height = size
    rng = np.random.default_rng(0)
    fx = rays_lib.focal_from_fov(np.radians(60), width)
    c2w = [np.asarray(rays_lib.look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0, 0, 0]))
           for a in 2 * np.pi * np.arange(frames) / frames]
    return Dataset(root=Path("calibration"), images=rng.uniform(size=(frames, height, width, 3)).astype(np.float32),
                   c2w=np.asarray(c2w, np.float32),
                   intrinsics=np.tile(np.array([[fx, fx, width / 2, height / 2]], np.float32), (frames, 1)),
                   split={"train": np.arange(frames), "test": np.array([], np.int64)}, near=0.5, far=60.0)


def rays_per_second(run_steps: Callable[[int], None], batch_rays: int, seconds: float = SECONDS,
                    clock: Callable[[], float] = time.perf_counter) -> float:
    """Train rays a second of a step: `run_steps(k)` runs k steps and returns once they are done
    (the first call, one step, is the compile and is not timed); then rounds of ROUND steps until
    `seconds` have passed on `clock`. Returns batch_rays x steps timed / seconds taken."""
    run_steps(1)
    steps, start = 0, clock()
    while True:
        run_steps(ROUND)
        steps += ROUND
        taken = clock() - start
        if taken >= seconds:
            return batch_rays * steps / taken


def timing_config(cfg):
    """The config whose step is timed: the run's, with the robust step and the depth prior off
    (module docstring: their rays cost as the plain step's)."""
    tcfg = cfg.train
    depth = getattr(tcfg, "depth", None)
    plain = dataclasses.replace(tcfg, robust=dataclasses.replace(tcfg.robust, mode="off"))
    if depth is not None:
        plain = dataclasses.replace(plain, depth=dataclasses.replace(depth, weight=0.0))
    return dataclasses.replace(cfg, train=plain)


def measure(cfg, seconds: float = SECONDS) -> float:
    """Train rays a second of RunConfig `cfg`'s step on this machine's step devices (module
    docstring)."""
    scene = calibration_scene()
    timed = config_lib.resolve(timing_config(cfg), scene)
    n = loop.step_devices(timed.train)
    pool = loop.device_pool(scene, timed, n)
    step = loop.make_train_step(timed, n)
    holder = {"state": parallel.replicate(loop.init_state(timed, loop.train_frames_shape(scene)), n)}

    def run_steps(k: int) -> None:
        stats = None
        for _ in range(k):
            holder["state"], stats = step(holder["state"], pool)
        jax.block_until_ready(stats)

    return rays_per_second(run_steps, int(timed.train.batch_rays), seconds)


MEASURED = "measured on this machine"


def planner(run_dir, overwrite: bool = False, say=None):
    """The `measure` an entry point hands the training budget (config/budget.apply): a resumed
    run's recorded speed (`budget.recorded_speed` of run_dir, unless `overwrite`), so it plans the
    steps it began with; else this machine's (`measure`, with a line through `say` first). None in
    a multi-process run: every process must choose the same steps, so they plan at the reference
    estimate."""
    if distributed.is_distributed():
        return None
    if not overwrite and budget.recorded_speed(run_dir) is not None:
        # the speed recorded for the config asked about: the larger grid's where it was timed apart
        return lambda cfg: budget.recorded_speed(run_dir, larger_grid=budget.grid_growth(cfg.model) is None)

    def measured(cfg) -> tuple[float, str]:
        if say is not None:
            say(f"timing the training step on this machine (about {SECONDS + 7:.0f} s) to fit the steps to "
                "the time budget")
        return measure(cfg), MEASURED

    return measured
