"""Frozen dataclasses for every stage, with a JSON round-trip, and where a config is settled.

`to_dict(cfg)` / `from_dict(cls, d)` work for any (nested) frozen dataclass defined here or in
other modules; unknown keys are an error naming the key, so a typo in a config file is caught.
`merge(base, extra)` lays nested override dicts on top of each other (--config files, recipes).
`resolve(cfg, dataset)` is the one place the dataset fills in a run config: the embedding
tables' `model.num_images` and the ray bounds `model.near` / `model.far` (None = the dataset's).
`validate(cfg)` is the one type-and-range pass over a (nested) config: every field is checked
against its type hint (an int rejects floats, strings and bools; a float rejects NaN, inf and
strings) and against the `Range` its class lists in a `RANGES` class variable, with a one-line
`ConfigError` naming the key, the value and the allowed range (docs/RELIABILITY.md).
`parse_sets(["model.warp=log", ...], cls)` turns `--set key=value` flags into an override dict.

Tagged unions: a field whose type hint is a union of dataclasses that each have a `kind` field
(`ModelConfig.sampler`, `ModelConfig.field`) holds one of them, chosen by "kind" in its dict.
`from_dict` lays the given keys over that kind's defaults (an unknown key for that kind is a
ConfigError naming it; a dict without "kind" is laid over the field's default); `merge`
replaces, rather than merges into, a tagged dict of another kind, so
`--set model.sampler.kind=proposal` switches to the proposal sampler with its defaults, and
`--set model.field.kind=grid` to the grid field with its.
A class may define `upgrade_dict(data) -> data` (a static method) to read an older layout of
its dict; `from_dict` calls it first (ModelConfig: the flat sampler keys of older runs; each
field kind: the other kinds' keys older runs wrote; TrainConfig: the flat robust keys).
A section class may name a `SHORTHAND` key: `--set train.robust=robust` (a plain value where
the section is) sets that key, `train.robust.mode`.

This module imports nothing of the NeRF side (models, train): it sits below them, so they
import it and it only reads the duck-typed fields of the configs it is given.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from typing import Any, TypeVar

from jaxnerf_grid.util.io import DataError

T = TypeVar("T")


class ConfigError(ValueError):
    """A bad configuration value or file; the message names the field."""


@dataclasses.dataclass(frozen=True)
class Range:
    """An allowed interval of a numeric config value: lo / hi (None = unbounded), open or closed."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return not (self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi))

    def __str__(self) -> str:
        if self.lo is not None and self.hi is not None:
            return f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
        if self.lo is not None:
            return f"{'>' if self.lo_open else '>='} {self.lo:g}"
        if self.hi is not None:
            return f"{'<' if self.hi_open else '<='} {self.hi:g}"
        return "any value"


POSITIVE = Range(0, lo_open=True)   # > 0
NONNEGATIVE = Range(0)              # >= 0
AT_LEAST_ONE = Range(1)             # >= 1 (counts)
UNIT = Range(0, 1)                  # [0, 1]
FRACTION = Range(0, 1, hi_open=True)  # [0, 1)


def _type_problem(value: Any, hint: Any) -> str | None:
    """Why `value` does not fit the type hint `hint` (int, float, bool, str, X | None,
    tuple[X, ...]); None when it fits. Ints reject bools and floats; floats accept ints but
    reject bools, NaN and inf."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        problems = [_type_problem(value, a) for a in args if a is not type(None)]
        return None if any(p is None for p in problems) else problems[0]
    if origin is tuple:
        if not isinstance(value, (tuple, list)):
            return "must be a list"
        args = typing.get_args(hint)
        for v in value:
            p = _type_problem(v, args[0])
            if p:
                return f"each entry {p}"
        return None
    if hint is bool:
        return None if isinstance(value, bool) else "must be true or false"
    if hint is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else "must be an integer"
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return "must be a number"
        return None if math.isfinite(value) else "must be a finite number"
    if hint is str:
        return None if isinstance(value, str) else "must be a string"
    return None


def validate(cfg: Any, where: str = "") -> None:
    """Checks every field of a (nested) frozen dataclass against its type hint and the `Range`
    of its class's `RANGES` class variable (tuples: each entry). Raises ConfigError naming the
    key, e.g. "train.batch_rays = 0: must be > 0"."""
    hints = typing.get_type_hints(type(cfg))
    ranges = getattr(type(cfg), "RANGES", {})
    for f in dataclasses.fields(cfg):
        key = f"{where}.{f.name}" if where else f.name
        value = getattr(cfg, f.name)
        hint = hints[f.name]
        variants = tagged_variants(hint)
        if dataclasses.is_dataclass(hint) or variants:
            if not dataclasses.is_dataclass(value) or (variants and type(value) not in variants.values()):
                raise ConfigError(f"{key} = {value!r}: must be an object")
            validate(value, key)
            continue
        check_value(key, value, hint, ranges.get(f.name))


def check_value(key: str, value: Any, hint: Any, rng: Range | None = None) -> None:
    """One value against a type hint (as `validate` reads them) and an optional `Range` (a tuple
    or list: each entry). Raises ConfigError naming `key` (a config key, or a command's key such as
    mask.dilate: the CLI shows its flag), e.g. "mask.dilate = -2: must be an integer >= 0"."""
    problem = _type_problem(value, hint)
    if problem:
        raise ConfigError(f"{key} = {_show(value)}: {problem}")
    if rng is not None and value is not None:
        for v in (value if isinstance(value, (tuple, list)) else (value,)):
            if not rng.contains(v):
                kind = "an integer " if _type_problem(1.5, hint) else ""  # int keys say so
                raise ConfigError(f"{key} = {_show(value)}: must be {kind}{rng}")


def tagged_variants(hint: Any) -> dict | None:
    """{kind: dataclass} when `hint` is a tagged union (a union of dataclasses that each have a
    `kind` field with a default), else None."""
    if typing.get_origin(hint) not in (typing.Union, types.UnionType):
        return None
    args = typing.get_args(hint)
    if not all(dataclasses.is_dataclass(a) for a in args):
        return None
    out = {}
    for cls in args:
        kind = {f.name: f.default for f in dataclasses.fields(cls)}.get("kind", dataclasses.MISSING)
        if not isinstance(kind, str):
            return None
        out[kind] = cls
    return out


def _fields_of(target: Any) -> tuple[set, dict]:
    """(field names, type hints) of a dataclass, or of every variant of a tagged union (the
    first variant holding a name gives its hint); empty for a plain value."""
    classes = list((tagged_variants(target) or {}).values()) or ([target] if dataclasses.is_dataclass(target) else [])
    names: set = set()
    hints: dict = {}
    for cls in classes:
        for name, hint in typing.get_type_hints(cls).items():
            if name in {f.name for f in dataclasses.fields(cls)}:
                names.add(name)
                hints.setdefault(name, hint)
    return names, hints


def _is_section(hint: Any) -> bool:
    return dataclasses.is_dataclass(hint) or tagged_variants(hint) is not None


def _show(value: Any) -> str:
    """A config value as it would be written in JSON (NaN as NaN)."""
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return repr(value)


def _parse_value(text: str) -> Any:
    """A --set value: JSON when it parses (numbers, true/false, null, lists, quoted strings),
    else the text itself as a string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _renamed(cls: type, part: str) -> str | None:
    """The dotted name an older key `part` of section `cls` has now (the section's
    RENAMED_PREFIXES, e.g. TrainConfig's robust_X -> robust.X), or None."""
    for old, new in getattr(cls, "RENAMED_PREFIXES", {}).items():
        if part.startswith(old) and len(part) > len(old):
            return new + part[len(old):]
    return None


def parse_sets(items: list[str] | None, cls: type) -> dict:
    """--set flags ["model.field.width=64", "train.lr_init=1e-3", ...] as a nested override dict
    for the dataclass `cls` (later flags win). Each dotted key must name a field of `cls` (a
    nested dataclass's fields below it; a tagged union's: the fields of any of its kinds, the
    kind's own checked by `from_dict`); an unknown key is a ConfigError naming it."""
    out: dict = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"{item!r}: expected key=value, e.g. model.warp=log")
        parts = key.split(".")
        target, node = cls, out
        for depth, part in enumerate(parts):
            names, hints = _fields_of(target)
            renamed = _renamed(target, part)
            if part not in names and renamed:
                raise ConfigError(f"{key}: renamed {'.'.join([*parts[:depth], renamed, *parts[depth + 1:]])}")
            if part not in names:
                prefix = ".".join(parts[:depth]) or "the config"
                raise ConfigError(f"{key}: unknown key {part!r} in {prefix}; known: {sorted(names)}")
            target = hints[part]
            if depth < len(parts) - 1:
                if not _is_section(target):
                    raise ConfigError(f"{key}: {'.'.join(parts[:depth + 1])} is a value, not a section")
                node = node.setdefault(part, {})
            else:
                if _is_section(target):
                    value = _parse_value(text)
                    shorthand = getattr(target, "SHORTHAND", None)
                    if not isinstance(value, dict) and shorthand:
                        value = {shorthand: value}  # e.g. train.robust=robust: train.robust.mode
                    if not isinstance(value, dict):
                        raise ConfigError(f"{key}: a section; give a JSON object or set its keys")
                    node[part] = merge(node.get(part, {}), value)
                else:
                    node[part] = _parse_value(text)
    return out


def to_dict(cfg: Any) -> Any:
    """A (nested) dataclass as plain JSON-able dicts/lists."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: to_dict(v) for k, v in cfg.items()}
    return cfg


def from_dict(cls: type[T], data: dict, where: str = "config") -> T:
    """Builds dataclass `cls` from a dict; nested dataclasses recurse, tuples are restored, a
    tagged union's dict is laid over the defaults of its "kind"."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected an object, got {type(data).__name__}")
    data = _upgraded(cls, data, where)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(typing.cast(Any, cls))}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {sorted(fields)}")
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        variants = tagged_variants(hint)
        if variants:
            default = fields[name].default
            if isinstance(value, dict) and "kind" not in value and dataclasses.is_dataclass(default):
                value = merge(to_dict(default), value)  # no kind given: the default's kind and keys
            value = _tagged_from_dict(variants, value, f"{where}.{name}")
        elif dataclasses.is_dataclass(hint):
            value = from_dict(typing.cast(type, hint), value, f"{where}.{name}")
        elif typing.get_origin(hint) is tuple and isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)


def _upgraded(cls: type, data: dict, where: str) -> dict:
    """`data` read through cls.upgrade_dict (an older layout of its dict), if it has one; its
    ConfigError names `where`."""
    upgrade = getattr(cls, "upgrade_dict", None)
    if upgrade is None:
        return data
    try:
        return upgrade(data)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _tagged_from_dict(variants: dict, data: Any, where: str) -> Any:
    """The variant named by data["kind"], its defaults overridden by `data`."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected an object with a \"kind\" ({sorted(variants)}), got {_show(data)}")
    kind = data.get("kind")
    if kind not in variants:
        raise ConfigError(f"{where}.kind = {_show(kind)}: choose from {sorted(variants)}")
    cls = variants[kind]
    data = _upgraded(cls, data, where)
    names = {f.name for f in dataclasses.fields(typing.cast(Any, cls))}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown} for kind {kind!r}; known: {sorted(names)}")
    return from_dict(cls, merge(to_dict(cls()), data), where)


# The keys whose value is a tagged union (a dataclass chosen by its "kind", each kind with only
# its own fields): `model.sampler`, `model.field` (and the proposal sampler's grid `field`, so a
# dict of another kind replaces it there too, for its check to name).
TAGGED_UNION_KEYS = ("sampler", "field")


def merge(base: dict, extra: dict) -> dict:
    """`extra` laid over `base`, recursing into dicts both hold; neither input is changed. Under
    a TAGGED_UNION_KEYS key, a dict of another "kind" replaces the old one instead of merging."""
    out = dict(base)
    for k, v in extra.items():
        both = isinstance(v, dict) and isinstance(out.get(k), dict)
        if both and k in TAGGED_UNION_KEYS and v.get("kind", out[k].get("kind")) != out[k].get("kind"):
            both = False
        out[k] = merge(out[k], v) if both else v
    return out


def near_far(model_cfg: Any, dataset: Any) -> tuple[float, float]:
    """The ray bounds of a model config on a dataset: model.near / model.far, or the dataset's
    near / far where they are None."""
    near = model_cfg.near if model_cfg.near is not None else dataset.near
    far = model_cfg.far if model_cfg.far is not None else dataset.far
    return float(near), float(far)


def strict_readmit_auto(meta: dict) -> bool:
    """train.robust.strict_readmit's automatic value (None) on a dataset whose transforms.json
    gave `meta`: on, unless `mask` judged the dataset's DPT masks out of their domain
    (`mask_domain.out_of_domain`, masking.domain_verdict). In its domain the prior is trusted
    more, and strict re-admission gains on every seed of Table 1's dpt+robust row; out of it a
    flagged static pixel no neighbour confirms would stay out (docs/ROBUST.md)."""
    domain = meta.get("mask_domain") if isinstance(meta, dict) else None
    return not (isinstance(domain, dict) and bool(domain.get("out_of_domain")))


def strict_readmit_acts(setting: bool | None, robust: str, meta: dict) -> bool:
    """Whether strict re-admission acts in a run with train.robust.strict_readmit `setting`
    (None: `strict_readmit_auto` on the dataset's `meta`) and train.robust.mode `robust`: only
    "dpt+robust" has flagged pixels to re-admit."""
    strict = strict_readmit_auto(meta) if setting is None else bool(setting)
    return strict and robust == "dpt+robust"


def resolve(cfg: Any, dataset: Any, bounds: bool = True) -> Any:
    """A run config (anything with a `.model` holding num_images / near / far) settled on a
    dataset: model.num_images at least the dataset's frame count (the embedding tables' size),
    and, with `bounds`, model.near / model.far filled from the dataset where None; a
    `.train.robust.strict_readmit` of None (automatic) becomes `strict_readmit_acts`: on the
    dataset's meta with train.robust.mode "dpt+robust", else false (it acts in no other mode, and
    false is what runs recorded before it was automatic, so they resume), whatever `bounds`
    (what trained is what a run's config.json records).

    bounds=False keeps near / far as configured (None = the dataset's): what a run's
    config.json stores, so it stays valid for the dataset however it is normalised.
    """
    validate(cfg)
    changes = {"num_images": max(cfg.model.num_images, dataset.num_frames)}
    train_cfg = getattr(cfg, "train", None)
    robust = getattr(train_cfg, "robust", None)
    if train_cfg is not None and robust is not None and robust.strict_readmit is None:
        acts = strict_readmit_acts(None, robust.mode, getattr(dataset, "meta", {}))
        robust = dataclasses.replace(robust, strict_readmit=acts)
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(train_cfg, robust=robust))
    if bounds:
        changes["near"], changes["far"] = near_far(cfg.model, dataset)
        if not 0 < changes["near"] < changes["far"]:
            got = f"need 0 < near < far, got near={changes['near']:g}, far={changes['far']:g}"
            if cfg.model.near is None and cfg.model.far is None:
                raise DataError(f"{getattr(dataset, 'root', 'dataset')}: the dataset's ray bounds: {got}")
            raise ConfigError(f"model.near / model.far (with the dataset's where None): {got}")
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, **changes))

