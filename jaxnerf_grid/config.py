"""Frozen dataclasses for every stage, with a JSON round-trip, and where a config is settled.

`to_dict(cfg)` / `from_dict(cls, d)` work for any (nested) frozen dataclass defined here or in
other modules; unknown keys are an error naming the key, so a typo in a config file is caught.
`merge(base, extra)` lays nested override dicts on top of each other (--config files, recipes).
`resolve(cfg, dataset)` is the one place the dataset fills in a run config: the embedding
tables' `model.num_images` and the ray bounds `model.near` / `model.far` (None = the dataset's).

This module imports nothing of the NeRF side (models, train): it sits below them, so they
import it and it only reads the duck-typed fields of the configs it is given.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """A bad configuration value or file; the message names the field."""


def to_dict(cfg: Any) -> dict:
    """A (nested) dataclass as plain JSON-able dicts/lists."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: to_dict(v) for k, v in cfg.items()}
    return cfg


def from_dict(cls: type[T], data: dict, where: str = "config") -> T:
    """Builds dataclass `cls` from a dict; nested dataclasses recurse, tuples are restored."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {sorted(names)}")
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            value = from_dict(hint, value, f"{where}.{name}")
        elif typing.get_origin(hint) is tuple and isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)


def merge(base: dict, extra: dict) -> dict:
    """`extra` laid over `base`, recursing into dicts both hold; neither input is changed."""
    out = dict(base)
    for k, v in extra.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def near_far(model_cfg: Any, dataset: Any) -> tuple[float, float]:
    """The ray bounds of a model config on a dataset: model.near / model.far, or the dataset's
    near / far where they are None."""
    near = model_cfg.near if model_cfg.near is not None else dataset.near
    far = model_cfg.far if model_cfg.far is not None else dataset.far
    return float(near), float(far)


def resolve(cfg: T, dataset: Any, bounds: bool = True) -> T:
    """A run config (anything with a `.model` holding num_images / near / far) settled on a
    dataset: model.num_images at least the dataset's frame count (the embedding tables' size),
    and, with `bounds`, model.near / model.far filled from the dataset where None.

    bounds=False keeps near / far as configured (None = the dataset's): what a run's
    config.json stores, so it stays valid for the dataset however it is normalised.
    """
    changes = {"num_images": max(cfg.model.num_images, dataset.num_frames)}
    if bounds:
        changes["near"], changes["far"] = near_far(cfg.model, dataset)
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, **changes))

