"""The one configuration of every field kind (`FieldConfig`) and its checks."""

from __future__ import annotations

import dataclasses
import typing

from jaxnerf_grid.config import schema as config
from jaxnerf_grid.nerf.fields.hashgrid import HashConfig
from jaxnerf_grid.nerf.fields.hashgrid import check as check_grid

FIELD_KINDS = ("mlp", "grid")


@dataclasses.dataclass(frozen=True)
class FieldConfig:
    """Shape of one radiance field.

    kind: "mlp" (NeRF's MLP on the positionally encoded point, fields/mlp.py) or "grid"
      (multiresolution hash encoding + small MLPs, fields/grid.py).
    depth, width: hidden layers of the density trunk and their width (MLP: on the encoded
      point, NeRF 8 x 256; grid: on the hash features, Instant-NGP 1 x 64).
    skip: (MLP) the encoded input is concatenated after this many trunk layers (0 or >= depth
      disables it).
    pos_min_deg, pos_max_deg: (MLP) positional-encoding octaves of the point (NeRF: 0..10).
    dir_max_deg: octaves of the view direction (NeRF: 4); use_viewdirs=False drops it.
    view_width, view_depth: hidden width and layer count of the colour branch.
    density_activation: "softplus" (density_bias added first), "relu", or (grid only) "exp"
      (Instant-NGP's truncated exponential, density_bias added first).
    appearance_dim: size of the appearance embedding fed to the colour branch (0 = none).
    transient_dim: size of the transient embedding; > 0 adds NeRF-W's transient head with
      `transient_depth` layers of `transient_width`.
    grid: (grid) the hash encoding; geo_features: (grid) width of the feature the density
      trunk hands to the colour branch.
    """

    kind: str = "mlp"
    depth: int = 4
    width: int = 128
    skip: int = 2
    pos_min_deg: int = 0
    pos_max_deg: int = 10
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
    grid: HashConfig = HashConfig()
    geo_features: int = 15

    # allowed values, checked by config.validate (docs/RELIABILITY.md); `check` adds the
    # rules between fields (an MLP needs depth >= 1)
    RANGES: typing.ClassVar[dict] = {
        "depth": config.NONNEGATIVE, "width": config.AT_LEAST_ONE, "skip": config.NONNEGATIVE,
        "pos_min_deg": config.NONNEGATIVE, "pos_max_deg": config.NONNEGATIVE, "dir_max_deg": config.NONNEGATIVE,
        "view_width": config.AT_LEAST_ONE, "view_depth": config.AT_LEAST_ONE,
        "appearance_dim": config.NONNEGATIVE, "transient_dim": config.NONNEGATIVE,
        "transient_depth": config.AT_LEAST_ONE, "transient_width": config.AT_LEAST_ONE,
        "geo_features": config.AT_LEAST_ONE}


def check(cfg: FieldConfig) -> None:
    """Checks a field config (the hash encoding too, for kind "grid"); raises ValueError
    naming the setting."""
    if cfg.kind not in FIELD_KINDS:
        raise ValueError(f"FieldConfig: unknown kind {cfg.kind!r}; choose from {list(FIELD_KINDS)}")
    if cfg.depth < (1 if cfg.kind == "mlp" else 0) or cfg.width < 1:
        raise ValueError(f"FieldConfig: depth ({cfg.depth}) and width ({cfg.width}) must be >= 1")
    if cfg.view_depth < 1 or cfg.view_width < 1:
        raise ValueError(f"FieldConfig: view_depth ({cfg.view_depth}) and view_width ({cfg.view_width}) must be >= 1")
    allowed = ("softplus", "relu") if cfg.kind == "mlp" else ("softplus", "relu", "exp")
    if cfg.density_activation not in allowed:
        raise ValueError(f"FieldConfig: density_activation must be one of {list(allowed)} for kind "
                         f"{cfg.kind!r}, got {cfg.density_activation!r}")
    if cfg.kind == "grid":
        check_grid(cfg.grid, "grid")
