"""The one config builder: every entry point (`train`, `demo`, the experiments and benchmarks)
turns what a user asked for into a run's config here, in one order.

    recipe (its method's defaults and its settings, config/recipes.py)
      -> the dataset's bounds (model.near / far / contract_radius, capture/bounds.py; only for a
         method that contracts space, and only when the dataset records them)
      -> the caller's defaults for the dataset (`defaults`: e.g. the demo's depth prior on a
         capture from `poses`, which the user's settings below change)
      -> a config file (`--config FILE`, a JSON object {"model": {...}, "train": {...}})
      -> `--set KEY=VALUE` flags, in their order
      -> the working resolution (`--max-side N`: train.max_side)
      -> the step count (`--steps N`: train.max_steps)
      -> the caller's own layer (`extra`: e.g. the demo's mask plan, which wins over --set)
      -> the training budget (config/budget.py: when neither --steps nor train.max_steps was
         given, the steps from the capture's training pixels within `--minutes`; only when the
         caller names how to count its devices, `devices_of`)

Each later layer wins over the ones before it. `build` returns the recipe's name, the method,
the overrides dict (what `runs.train_run` lays over the method's defaults), the bounds it used
(None: the recipe's constants) and the budget's record (None: no budget asked), after checking
the whole config (`run_config.make_config`), so a bad key or value fails in one line before
anything is written.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

from jaxnerf_grid.capture.bounds import folder_bounds, folder_camera_bounds, recipe_with_bounds
from jaxnerf_grid.config import budget as budget_lib
from jaxnerf_grid.config import recipes
from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.run_config import RunConfig, make_config, upgrade_flat_robust, upgrade_run_dict
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.util import io


@dataclasses.dataclass(frozen=True)
class Request:
    """What a user asked for, from every source a run's config can come from (None / empty: not given)."""
    recipe: str | None = None
    method: str | None = None
    config_file: str | None = None
    sets: tuple[str, ...] = ()
    max_side: int | None = None
    steps: int | None = None
    minutes: float | None = None


@dataclasses.dataclass(frozen=True)
class Built:
    """The outcome of `build`: recipe name, method, the overrides over the method's defaults, the
    dataset bounds laid in (None when the recipe's constants stand) and the training budget's
    record (None when no budget was asked for)."""
    recipe: str
    method: str
    overrides: dict
    bounds: dict | None
    budget: dict | None = None

    def config(self) -> RunConfig:
        """The checked RunConfig (before it is settled on a dataset)."""
        return make_config(self.method, self.overrides)


def read_config_file(path: str | Path | None) -> dict:
    """A --config file's overrides ({} when no file is given): a JSON object; its `data` key is
    dropped (the dataset is run.data) and the older flat sampler and robust keys are upgraded
    (`run_config.upgrade_run_dict`), so the layers laid over it meet the current layout."""
    if not path:
        return {}
    data = io.read_json(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must hold a JSON object")
    data = dict(data)
    data.pop("data", None)
    return upgrade_run_dict(data)


def with_robust_nested(layer: dict) -> dict:
    """An override layer with its flat robust keys nested (`run_config.upgrade_flat_robust`),
    so a mode string merges into, rather than replaces, the train.robust dict below it. (Its
    flat sampler keys stay: alone they would read as over the old defaults, not the layers below;
    `make_config` reads them once every layer is merged.)"""
    if not isinstance(layer.get("train"), dict):
        return layer
    return dict(layer, train=upgrade_flat_robust(layer["train"]))


def with_sets(overrides: dict | None, sets: list[str] | tuple[str, ...] | None) -> dict:
    """overrides with the --set KEY=VALUE flags laid on top (config.parse_sets against RunConfig:
    an unknown key is a ConfigError naming it). `data` is refused: the run's dataset is run.data,
    and train_run would silently replace a value set here."""
    sets_ = config_lib.parse_sets(list(sets or []), RunConfig)
    if "data" in sets_:
        raise ConfigError("data: not a setting; the dataset is given as run.data")
    return config_lib.merge(overrides or {}, sets_)


def with_steps(overrides: dict | None, steps: int | None) -> dict:
    """overrides with train.max_steps = steps (when given); the input is not changed."""
    overrides = dict(overrides or {})
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ConfigError(f"run.steps = {steps}: must be an integer >= 1")
        overrides["train"] = {**overrides.get("train", {}), "max_steps": int(steps)}
    return overrides


def with_max_side(overrides: dict, max_side: int | None) -> dict:
    """overrides with train.max_side = max_side (when given), checked as a --set value would be."""
    return overrides if max_side is None else with_sets(overrides, [f"train.max_side={max_side}"])


def build(request: Request, data: str | Path | None = None, extra: dict | None = None,
          devices_of: Callable[[Any], int] | None = None, platform: str = "cpu",
          defaults: dict | None = None, measure=None) -> Built:
    """The run config's overrides from a Request, in the module's order (recipe -> bounds of the
    dataset folder `data` -> defaults -> config file -> sets -> max_side -> steps -> extra ->
    budget), checked.
    devices_of: train config -> the training step's device count (`train.loop.step_devices`);
    given with `data`, the budget chooses the steps; platform: JAX's backend ("cpu", "gpu");
    measure: the budget's speed measurement (`budget.apply`, `train.speed.planner`; None: the
    reference estimate)."""
    recipe, method = recipes.resolve(request.recipe, request.method)
    if request.minutes is not None:
        config_lib.check_value("run.minutes", request.minutes, float, config_lib.POSITIVE)
    overrides = recipes.overrides(recipe)
    bounds = folder_bounds(data) if data is not None and Path(data).is_dir() else None
    recipe_model = make_config(method, overrides).model
    if bounds and not recipe_model.use_contraction:
        bounds = None  # a method in a bounded box keeps its own near / far
    elif bounds is None and recipe_model.use_contraction and data is not None and Path(data).is_dir():
        bounds = folder_camera_bounds(data, recipe_model)  # None unless a camera is nearer than the recipe's near
    overrides = recipe_with_bounds(overrides, bounds)
    overrides = config_lib.merge(overrides, defaults or {})
    user = with_sets(read_config_file(request.config_file), request.sets)  # what the user set by key
    overrides = config_lib.merge(overrides, user)
    overrides = with_max_side(overrides, request.max_side)
    overrides = with_steps(overrides, request.steps)
    overrides = config_lib.merge(overrides, with_robust_nested(extra or {}))
    settled = make_config(method, overrides)  # every key and value checked before anything is written
    chosen = None
    if data is not None and devices_of is not None and Path(data).is_dir():  # a missing folder: train_run says so
        pixels = budget_lib.capture_pixels(data, settled.train.max_side)
        field_set = bool((user.get("model") or {}).get("field"))  # the user's own field: left as it is
        _, chosen = budget_lib.apply(settled, pixels, devices_of(settled.train), request.minutes,
                                     budget_lib.steps_given_by(request.steps, user), platform, measure,
                                     grid_free=not field_set)
        if chosen.get("rule") == "budget":
            overrides = config_lib.merge(overrides, budget_lib.run_overrides(chosen))
    return Built(recipe, method, overrides, bounds, chosen)
