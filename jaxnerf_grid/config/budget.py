"""The training budget: how many steps a run trains, chosen from the capture and a time budget.

The recipes were sized for the synthetic demo (40 frames of 160x120: 1600 steps x 1024 rays, about
two epochs). A real capture has ten to a hundred times the pixels, and the same 1600 steps then
draw each training pixel a fraction of a time: the renders are smeared. `choose_budget` scales the
steps with the capture instead:

    wanted = ceil(TARGET_EPOCHS x training pixels / batch_rays)      (each pixel drawn ~E times)
    cap    = floor(minutes x 60 x rays_per_second / (batch_rays + depth rays))   (what fits in the time budget)
    steps  = min(max(base.max_steps, wanted), cap), rounded to STEP_ROUND

so a capture never trains fewer steps than its recipe (the hash grid needs its iterations whatever
the capture's size: the synthetic demo keeps its 1600 steps), more when the capture has more pixels,
and never more than `minutes` of training at the speed of this machine. The speed is first the
reference estimate (REFERENCE_RAYS_PER_S, figures of the demo's recipe on the reference machines);
when that estimate fills more than MEASURE_SHARE of the minutes, so that the cap may bind, the
entry point's `measure` times the run's own step on this machine (train/speed.py: about 10 s) and
the steps are chosen again at the measured speed. A resumed run plans at the speed its budget.json
recorded (`recorded_speed`), so it finds the steps it began with. A `minutes` below what the
recipe's steps need wins: the user asked for it, and the record says the run is short of its recipe.

The batch stays the recipe's: on the CPU a larger batch trains no more rays a second, only fewer,
larger steps; on a GPU a larger batch does fill the device (docs/GPU.md), and is set with
`--set train.batch_rays=N`: the rule counts rays, so the steps follow the batch.

A capture larger than its recipe's size (limited by "epochs" or "minutes", not "recipe") trains a
larger hash grid (GROWN_GRID: 2^19 rows a level, finest resolution 4096) at its own speed, about
GROWN_GRID_COST times the time a step: where its epochs still fit, over the whole time budget
(limited_by "grid": the steps that fit in the minutes at its speed); where the minutes bind, for
the steps they hold at its speed (limited_by "minutes", fewer steps than the recipe's grid would
get), as long as those are at least the recipe's steps and this machine runs it at no less than
1 / GROWN_GRID_MAX_COST of the recipe grid's reference speed (`grown_grid_pays`); else the recipe's
grid is measured and kept. Measured (docs/RECIPES.md): with epochs to spare the larger grid beat
the recipe's on both Strecha scenes it applies to; at about the same time, with the minutes
binding, it scored higher on the phone capture, Herz-Jesus-P25 and the demo's scene at 640x480.
The synthetic demo (the recipe's steps) keeps the recipe's grid; the grid is left alone when the
user set any model.field key (`grid_free`), and when the field is no hash grid or is as large
already.

`stretch_schedules(train_cfg, steps)` stretches everything that counts steps with the run:
train.max_steps and train.warmup (the learning-rate schedule, optim.lr_schedule, is then the same
function of the fraction of the run); train.robust.warmup and train.robust.refine are fractions of
max_steps already (robust.warmup_steps, robust.refine_step), the samplers have no schedule. Kept
as they are: checkpoint_every and log_every (how often a run is saved and logged, in steps: a
longer run saves and logs more often, so a kill loses as many seconds as before) and
appearance_steps (the test-time NeRF-W fit, not training).

`apply(cfg, train_pixels, ...)` is the one call an entry point makes on a settled RunConfig: it
returns the config with the chosen steps (and grid) and a record ({"steps", "epochs", "limited_by", "why",
...}) that the run keeps in budget.json, metrics.json's "budget" and a line of report.md
(`report_line`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.data import formats, working
from jaxnerf_grid.util.io import DataError

# Each training pixel drawn about this many times: the most that keeps the synthetic demo at its
# 1600 steps (2.13 epochs), where tower-small has saturated (1000 to 2400 steps within 0.05 dB on
# the GPU, docs/GPU.md). On fountain-P11 it gives 3400 steps, +1.3 dB over 1600 (docs/RECIPES.md).
TARGET_EPOCHS = 2.0
# Minutes of training when the user gives none (`--minutes`). A 50-photo phone capture (10.9 M
# training pixels) then trains 7700 steps, 0.73 epochs: more than the 6400 steps (0.6 epochs) that
# made its renders sharp (25.8 dB against 22.9 at 1600), and, with its 219 s of poses and the
# evaluation, about 18 minutes from photos to report on two idle cores (an estimate from those runs).
DEFAULT_MINUTES = 12.0
# Steps are rounded to this (readable step counts; the cap rounds down, the wish up).
STEP_ROUND = 100
# Train rays a second of the demo's recipe (`ours-lean`, 1024 rays a step), per device of a platform.
# cpu: the 2-core machine, idle, one device (two CPU devices on two cores train no faster,
#   docs/GRID.md), 11.1-13.2k (`benchmarks.throughput`, docs/GRID.md "Train rays/s side by side,
#   idle machine"); a real capture's demo trained 1600 steps in 144 s, 11.4k (fountain-P11,
#   docs/RESULTS.md);
# gpu: one H200, the training loop at 1024 rays a step, 2.8 ms a step (docs/GPU.md): 365k.
REFERENCE_RAYS_PER_S = {"cpu": 11000.0, "gpu": 365000.0}
# The speed is measured (`apply`'s `measure`) when the reference estimate fills more than this share
# of the minutes: below it only a machine over 1 / MEASURE_SHARE times slower than the reference
# could overrun. The synthetic demo (2.4 of 12 min) is not measured.
MEASURE_SHARE = 0.25
REFERENCE = "reference estimate"
# The hash grid a capture past its recipe's size trains (model.field.grid keys), and its cost a step
# against the demo recipe's grid: 1.36-1.39x on the 2-core machine (docs/RECIPES.md).
GROWN_GRID = {"log2_table_size": 19, "max_resolution": 4096}
GROWN_GRID_COST = 1.4
# Where the minutes bind, the larger grid is trained only when this machine runs it at no less than
# the recipe grid's reference speed / this (`grown_grid_pays`).
GROWN_GRID_MAX_COST = 2.0


@dataclasses.dataclass(frozen=True)
class Budget:
    """What `choose_budget` chose. steps: optimiser steps; batch_rays: rays a step; epochs: steps x
    batch / training pixels; wanted_steps: the steps TARGET_EPOCHS asks for (before the recipe's
    floor and the cap); cap_steps: the steps that fit in `minutes`; limited_by: "recipe" (the
    recipe's steps, the floor), "epochs" (the target), "minutes" (the time cap), "grid" (the
    larger grid over the whole time budget, `_filled`); minutes: the
    budget; estimated_minutes: steps at rays_per_second; rays_per_second: the estimate used;
    target_epochs: E; recipe_steps: base.max_steps."""

    steps: int
    batch_rays: int
    epochs: float
    wanted_steps: int
    cap_steps: int
    limited_by: str
    minutes: float
    estimated_minutes: float
    rays_per_second: float
    target_epochs: float
    recipe_steps: int
    speed_source: str = REFERENCE


def rays_per_second(platform: str, n_devices: int) -> float:
    """The estimated train rays a second of the demo's recipe on `n_devices` devices of `platform`
    (jax.default_backend(): "cpu", "gpu", ...): REFERENCE_RAYS_PER_S per device, times the devices
    on an accelerator (any platform but "cpu" counts as a GPU); a CPU's devices share its cores."""
    if platform == "cpu":
        return REFERENCE_RAYS_PER_S["cpu"]
    return REFERENCE_RAYS_PER_S["gpu"] * max(1, int(n_devices))


def _round_up(steps: float) -> int:
    return max(STEP_ROUND, int(math.ceil(steps / STEP_ROUND)) * STEP_ROUND)


def _round_down(steps: float) -> int:
    """Down to a multiple of STEP_ROUND, or to a whole step below STEP_ROUND (at least 1)."""
    if steps >= STEP_ROUND:
        return int(steps // STEP_ROUND) * STEP_ROUND
    return max(1, int(steps))


def step_rays(train_cfg) -> int:
    """Rays a step renders: the batch, plus train.depth's rays when the depth prior is on (they
    cost time like the batch's but are not training pixels drawn, so the epochs leave them out)."""
    depth = getattr(train_cfg, "depth", None)
    return int(train_cfg.batch_rays) + (int(depth.rays) if depth is not None and depth.weight > 0 else 0)


def choose_budget(train_pixels: int, n_devices: int, minutes: float | None, base, platform: str = "cpu",
                  target_epochs: float = TARGET_EPOCHS, speed: float | None = None,
                  speed_source: str = REFERENCE) -> Budget:
    """The steps of a run (module docstring's rule).

    train_pixels: the training frames' pixels at the working resolution (`capture_pixels`);
    n_devices: the train step's devices; minutes: the training time budget (None: DEFAULT_MINUTES);
    base: the recipe's train config (its max_steps, the floor, and batch_rays); platform: the JAX
    backend; speed: train rays a second (None: `rays_per_second(platform, n_devices)`) and
    speed_source: where it comes from (REFERENCE, or how it was measured).
    """
    minutes = DEFAULT_MINUTES if minutes is None else float(minutes)
    config_lib.check_value("run.minutes", minutes, float, config_lib.POSITIVE)
    config_lib.check_value("run.train_pixels", int(train_pixels), int, config_lib.AT_LEAST_ONE)
    batch = int(base.batch_rays)
    speed = rays_per_second(platform, n_devices) if speed is None else float(speed)
    wanted = _round_up(target_epochs * train_pixels / batch)
    rendered = step_rays(base)
    cap = _round_down(minutes * 60.0 * speed / rendered)
    steps, limited_by = max(int(base.max_steps), wanted), ("epochs" if wanted > base.max_steps else "recipe")
    if steps > cap:
        steps, limited_by = cap, "minutes"
    return Budget(steps=steps, batch_rays=batch, epochs=steps * batch / train_pixels, wanted_steps=wanted,
                  cap_steps=cap, limited_by=limited_by, minutes=minutes,
                  estimated_minutes=steps * rendered / speed / 60.0, rays_per_second=speed,
                  target_epochs=float(target_epochs), recipe_steps=int(base.max_steps),
                  speed_source=REFERENCE if speed_source is None else str(speed_source))


def stretch_schedules(train_cfg, steps: int):
    """train_cfg (a TrainConfig) for a run of `steps` steps, its schedules stretched: max_steps =
    steps, warmup scaled by steps / max_steps (rounded); the other keys as they are (module
    docstring: the robust schedules are fractions already, the step-counted I/O keys are not
    schedules)."""
    config_lib.check_value("run.steps", steps, int, config_lib.AT_LEAST_ONE)
    factor = steps / train_cfg.max_steps
    return dataclasses.replace(train_cfg, max_steps=int(steps), warmup=int(round(train_cfg.warmup * factor)))


def capture_pixels(data, max_side: int) -> int:
    """The training pixels of a dataset folder at the working resolution of `max_side`
    (data/working.py): the sum over its training frames of W' x H', read from the dataset's
    record and the images' headers, no pixel decoded. DataError naming the folder as the loaders
    say it."""
    scene = formats.collect_scene(Path(data), load_extras=False)
    total = 0
    for i in scene.split["train"]:
        w, h = _frame_size(scene.frames[int(i)])
        ww, hh = working.working_size(w, h, int(max_side))
        total += ww * hh
    return total


def _frame_size(frame) -> tuple[int, int]:
    """(W, H) of a collected frame: its stated size, else its image's header (an EXIF turn swaps
    W and H, not their product)."""
    if frame.size is not None:
        return int(frame.size[0]), int(frame.size[1])
    from PIL import Image  # Pillow reads the header alone

    try:
        with Image.open(frame.image_path) as img:
            return img.size
    except OSError as err:
        raise DataError(f"{frame.image_path}: cannot read the image's size ({err})") from None


def record(budget: Budget | None, cfg, train_pixels: int, given_by: str | None = None,
           grid: dict | None = None, grid_speed: float | None = None) -> dict:
    """The run's budget record (budget.json, metrics.json's "budget"): the chosen figures and a
    sentence on why; given_by names the flag when the user fixed the steps (then budget is None);
    grid: the model.field.grid keys the budget grew (`grid_growth`), or None; grid_speed: the
    larger grid's speed where the budget timed it and fell back to the recipe's grid."""
    tc = cfg.train
    epochs = tc.max_steps * tc.batch_rays / train_pixels
    if budget is None:
        return {"rule": "given", "steps": tc.max_steps, "batch_rays": tc.batch_rays, "warmup": tc.warmup,
                "train_pixels": int(train_pixels), "epochs": round(epochs, 3),
                "why": f"steps given by the user ({given_by}); no budget chosen"}
    grown = f"a larger hash grid ({', '.join(f'{k} {v}' for k, v in (grid or {}).items())})"
    reason = {"recipe": f"the recipe's steps: the capture needs only {budget.wanted_steps} for "
                        f"{budget.target_epochs:g} epochs",
              "epochs": f"{budget.target_epochs:g} epochs of the capture's training pixels",
              "minutes": f"capped by the time budget: {budget.minutes:g} min at {speed_words(budget)} "
                         f"({budget.target_epochs:g} epochs would need {budget.wanted_steps} steps)"
                         + (f", on {grown}" if grid else ""),
              "grid": f"{grown} over the "
                      f"whole time budget, {budget.minutes:g} min at {speed_words(budget)}, as "
                      f"{budget.target_epochs:g} epochs ({budget.wanted_steps} steps) fit in it with time to spare"
              }[budget.limited_by]
    return {"rule": "budget", "steps": budget.steps, "batch_rays": budget.batch_rays, "warmup": tc.warmup,
            "train_pixels": int(train_pixels), "epochs": round(budget.epochs, 3),
            "target_epochs": budget.target_epochs, "wanted_steps": budget.wanted_steps,
            "cap_steps": budget.cap_steps, "limited_by": budget.limited_by, "minutes": budget.minutes,
            "estimated_minutes": round(budget.estimated_minutes, 2),
            "rays_per_second": round(budget.rays_per_second, 1), "speed_source": budget.speed_source,
            "recipe_steps": budget.recipe_steps, "grid": grid, "grid_rays_per_second": grid_speed, "why": reason}


def speed_words(budget: Budget) -> str:
    """"11.0k rays/s (reference estimate)" or "9.9k rays/s (measured on this machine)"."""
    return f"{budget.rays_per_second / 1000:.1f}k rays/s ({budget.speed_source})"


def grid_growth(mcfg) -> dict | None:
    """The model.field.grid keys that grow a model's hash grid to GROWN_GRID, or None when its
    field is no hash grid or is at least that large on both keys."""
    grid = getattr(mcfg.field, "grid", None)
    if getattr(mcfg.field, "kind", None) != "grid" or grid is None:
        return None
    grow = {k: v for k, v in GROWN_GRID.items() if getattr(grid, k) < v}
    return grow or None


def with_grid(cfg, grow: dict):
    """RunConfig cfg with model.field.grid's keys `grow` replaced."""
    field = cfg.model.field
    field = dataclasses.replace(field, grid=dataclasses.replace(field.grid, **grow))
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, field=field))


def _filled(b: Budget) -> Budget:
    """Budget b (limited by its epochs) with its steps raised to its cap: the whole time budget,
    limited_by "grid"."""
    grow = b.cap_steps / b.steps
    return dataclasses.replace(b, steps=b.cap_steps, epochs=b.epochs * grow, limited_by="grid",
                               estimated_minutes=b.estimated_minutes * grow)


def grown_grid_pays(grown: Budget, reference_speed: float) -> bool:
    """Whether the larger grid's plan `grown` (limited by the minutes, at its speed) is trained:
    it keeps at least the recipe's steps and this machine runs it at no less than
    1 / GROWN_GRID_MAX_COST of the recipe grid's reference_speed (rays a second). Where the minutes
    bind, the larger grid won at the same time with 1.4x a step (module docstring); a machine
    that runs it slower than that is not where it was measured."""
    return grown.steps >= grown.recipe_steps and grown.rays_per_second * GROWN_GRID_MAX_COST >= reference_speed


def _planned(cfg, train_pixels: int, n_devices: int, minutes, platform: str, measure, cost: float = 1.0):
    """choose_budget for cfg at the reference speed / cost, then, where the minutes may bind
    (MEASURE_SHARE), at the speed `measure` gives for cfg."""
    ref = rays_per_second(platform, n_devices) / cost
    chosen = choose_budget(train_pixels, n_devices, minutes, cfg.train, platform, speed=ref)
    if measure is not None and chosen.estimated_minutes > MEASURE_SHARE * chosen.minutes:
        speed, source = measure(cfg)
        chosen = choose_budget(train_pixels, n_devices, minutes, cfg.train, platform, speed=speed,
                               speed_source=source)
    return chosen


def apply(cfg, train_pixels: int, n_devices: int = 1, minutes: float | None = None, given_by: str | None = None,
          platform: str = "cpu", measure=None, grid_free: bool = False) -> tuple:
    """(cfg with the budget's steps and stretched schedules, its record) for a settled RunConfig
    whose recipe steps are train.max_steps. given_by: the setting that fixed the steps
    (`steps_given_by`: run.steps, train.max_steps) or None; when given, cfg is returned as it is and the record
    says so. measure: None, or callable(cfg) -> (train rays a second, where the figure comes from),
    called when the reference estimate fills more than MEASURE_SHARE of the minutes (module
    docstring); the steps are then chosen at its speed. grid_free: the user set no model.field key,
    so a capture past its recipe's size may train the larger grid (module docstring)."""
    if given_by is not None:
        return cfg, record(None, cfg, train_pixels, given_by)
    estimate = choose_budget(train_pixels, n_devices, minutes, cfg.train, platform)
    grow = grid_growth(cfg.model) if grid_free and estimate.limited_by != "recipe" else None
    chosen, grid_speed = None, None
    if grow is not None:
        grown = _planned(with_grid(cfg, grow), train_pixels, n_devices, minutes, platform, measure,
                         GROWN_GRID_COST)
        if grown.limited_by == "epochs":  # its epochs still fit at the larger grid's speed: fill the minutes
            cfg, chosen = with_grid(cfg, grow), _filled(grown)
        elif grown_grid_pays(grown, estimate.rays_per_second):  # the minutes bind: fewer, larger-grid steps
            cfg, chosen = with_grid(cfg, grow), grown
        else:  # kept in the record, so that a resumed run falls back as this one did
            grow, grid_speed = None, grown.rays_per_second
    if chosen is None:
        chosen = _planned(cfg, train_pixels, n_devices, minutes, platform, measure)
    out = dataclasses.replace(cfg, train=stretch_schedules(cfg.train, chosen.steps))
    return out, record(chosen, out, train_pixels, grid=grow, grid_speed=grid_speed)


def steps_given_by(steps: int | None, overrides: dict | None) -> str | None:
    """Which of the user's settings fixed the steps: "run.steps" (steps not None), "train.max_steps"
    (in the --config / --set overrides), else None (the budget chooses)."""
    if steps is not None:
        return "run.steps"
    if "max_steps" in ((overrides or {}).get("train") or {}):
        return "train.max_steps"
    return None


def recorded_speed(run_dir, larger_grid: bool = False) -> tuple[float, str] | None:
    """(rays a second, source) a run folder's budget.json planned with, so that a resumed run
    chooses the steps (and grid) it began with; larger_grid: the speed the larger grid was timed
    at where the budget then fell back to the recipe's grid (`grid_rays_per_second`; else the
    record's one speed). None when the folder has no budget record (a new run, or steps given by
    the user) or an unreadable one."""
    path = Path(run_dir) / "budget.json"
    try:
        rec = json.loads(path.read_text())
        key = "grid_rays_per_second" if larger_grid and rec.get("grid_rays_per_second") else "rays_per_second"
        speed = float(rec[key])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if rec.get("rule") != "budget" or not math.isfinite(speed) or speed <= 0:
        return None
    return speed, f"as planned when the run began: {rec.get('speed_source', REFERENCE)}"


def run_overrides(rec: dict) -> dict:
    """The override dict of what a budget record chose ({"train": {"max_steps", "warmup"}}, and
    {"model": {"field": {"grid": ...}}} when it grew the grid), to lay over a run's overrides."""
    out: dict = {"train": {"max_steps": int(rec["steps"]), "warmup": int(rec["warmup"])}}
    if rec.get("grid"):
        out["model"] = {"field": {"grid": dict(rec["grid"])}}
    return out


def report_line(rec: dict) -> str:
    """report.md's line on the training budget (a budget record)."""
    if rec.get("rule") == "given":
        return (f"Training budget: {rec['steps']} steps x {rec['batch_rays']} rays, {rec['epochs']:.2f} epochs of "
                f"{rec['train_pixels'] / 1e6:.2f} M training pixels ({rec['why']}).")
    return (f"Training budget: {rec['steps']} steps x {rec['batch_rays']} rays, {rec['epochs']:.2f} epochs of "
            f"{rec['train_pixels'] / 1e6:.2f} M training pixels, about {rec['estimated_minutes']:.1f} min at "
            f"{rec['rays_per_second'] / 1000:.1f}k rays/s ({rec.get('speed_source', REFERENCE)}); why: {rec['why']} "
            f"(docs/RECIPES.md \"The training budget\").")


# Below this many epochs a capture's renders were smeared (the 50-photo phone capture: smeared at
# 0.15 epochs, sharp at 0.6).
FEW_EPOCHS = 0.5


def warning(rec: dict) -> str | None:
    """A one-line warning before a run the budget expects to be poor: fewer steps than its recipe
    (a short time budget), or under FEW_EPOCHS epochs; None otherwise."""
    if rec.get("rule") == "budget" and rec["steps"] < rec["recipe_steps"]:
        return (f"warning: a time budget of {rec['minutes']:g} min allows {rec['steps']} steps, fewer than the "
                f"recipe's {rec['recipe_steps']}: expect a softer model")
    if rec["epochs"] < FEW_EPOCHS:
        return (f"warning: {rec['steps']} steps draw each training pixel {rec['epochs']:.2f} times "
                f"(under {FEW_EPOCHS:g}): expect smeared renders; give a longer time budget or more steps")
    return None
