"""What every field kind's config shares (`FieldBase`), its checks, and reading the older
single-config layout of a field.

Each kind's `Config` (fields/mlp.py, fields/grid.py) is a `FieldBase` with its `kind` defaulted
and only its own keys. `model.field` is a tagged choice of them (config/schema.py, "Tagged
unions"): {"kind": "grid", ...} is laid over the grid's defaults.

Older configs (runs' config.json, --config files) held one field config with every kind's keys;
a field dict of one kind then also held the other kinds' keys at these defaults (OTHER_KEYS).
`drop_other_kinds` reads that layout: another kind's key at its old default is dropped, at any
other value it is a ConfigError naming it (it would be silently ignored). `old_layout` goes the
other way for what identifies a run (the experiments' run keys hash the old layout).
"""

from __future__ import annotations

import dataclasses
import json
import typing
from typing import Any

from jaxnerf_grid.config import schema as config
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.nerf.fields.hashgrid import HashConfig


@dataclasses.dataclass(frozen=True)
class FieldBase:
    """The keys of every field kind.

    kind: the field kind (its module in fields.KINDS).
    depth, width: hidden layers of the density trunk and their width (MLP: on the encoded
      point, NeRF 8 x 256; grid: on the hash features, Instant-NGP 1 x 64).
    dir_max_deg: octaves of the view direction (NeRF: 4); use_viewdirs=False drops it.
    view_width, view_depth: hidden width and layer count of the colour branch.
    density_activation: "softplus" (density_bias added first), "relu", or (grid only) "exp"
      (Instant-NGP's truncated exponential, density_bias added first).
    appearance_dim: size of the appearance embedding fed to the colour branch (0 = none).
    transient_dim: size of the transient embedding; > 0 adds NeRF-W's transient head with
      `transient_depth` layers of `transient_width`.
    """

    kind: str = ""
    depth: int = 4
    width: int = 128
    dir_max_deg: int = 4
    use_viewdirs: bool = True
    view_width: int = 64
    view_depth: int = 1
    density_activation: str = "softplus"
    density_bias: float = -1.0
    appearance_dim: int = 0
    transient_dim: int = 0
    transient_depth: int = 4
    transient_width: int = 64

    # allowed values, checked by config.validate (docs/RELIABILITY.md); each kind's `check` adds
    # the rules between fields (an MLP needs depth >= 1)
    RANGES: typing.ClassVar[dict] = {
        "depth": config.NONNEGATIVE, "width": config.AT_LEAST_ONE, "dir_max_deg": config.NONNEGATIVE,
        "view_width": config.AT_LEAST_ONE, "view_depth": config.AT_LEAST_ONE,
        "appearance_dim": config.NONNEGATIVE, "transient_dim": config.NONNEGATIVE,
        "transient_depth": config.AT_LEAST_ONE, "transient_width": config.AT_LEAST_ONE}


def check_shared(cfg: FieldBase, min_depth: int, activations: tuple[str, ...]) -> None:
    """The rules every kind shares: depth >= min_depth, width, the colour branch, the density
    activation among `activations`; raises ValueError naming the setting."""
    if cfg.depth < min_depth or cfg.width < 1:
        raise ValueError(f"FieldConfig: depth ({cfg.depth}) and width ({cfg.width}) must be >= 1")
    if cfg.view_depth < 1 or cfg.view_width < 1:
        raise ValueError(f"FieldConfig: view_depth ({cfg.view_depth}) and view_width ({cfg.view_width}) must be >= 1")
    if cfg.density_activation not in activations:
        raise ValueError(f"FieldConfig: density_activation must be one of {list(activations)} for kind "
                         f"{cfg.kind!r}, got {cfg.density_activation!r}")


# Each kind's own keys with the defaults the single field config of older configs gave them.
OTHER_KEYS: dict[str, dict[str, Any]] = {
    "mlp": {"skip": 2, "pos_min_deg": 0, "pos_max_deg": 10},
    "grid": {"grid": config.to_dict(HashConfig()), "geo_features": 15},
}


def _at_default(value: Any, default: Any) -> bool:
    """Whether `value` (JSON-like) says nothing but `default`: equal, or a dict whose every key
    is at the default's."""
    if isinstance(value, dict) and isinstance(default, dict):
        return all(k in default and _at_default(v, default[k]) for k, v in value.items())
    if isinstance(value, (list, tuple)) and isinstance(default, (list, tuple)):
        return list(value) == list(default)
    return value == default


def drop_other_kinds(data: Any, kind: str) -> Any:
    """A field dict of kind `kind` without the other kinds' keys that sit at their old defaults
    (OTHER_KEYS); one at another value is a ConfigError naming it. Not a dict: unchanged."""
    if not isinstance(data, dict):
        return data
    out = dict(data)
    for other, keys in OTHER_KEYS.items():
        if other == kind:
            continue
        for key, default in keys.items():
            if key in out:
                if not _at_default(out[key], default):
                    raise ConfigError(f"{key} = {json.dumps(out[key])} is a key of field kind {other!r}, "
                                      f"not of {kind!r}")
                del out[key]
    return out


def old_layout(field: dict) -> dict:
    """A field dict (any kind, as `to_dict` writes it) in the older single-config layout:
    every kind's key, the other kinds' at their old defaults."""
    out = config.to_dict(FieldBase(kind="mlp"))
    for keys in OTHER_KEYS.values():
        out.update(keys)
    return config.merge(out, field)
