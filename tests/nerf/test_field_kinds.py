"""The field kinds: one module per kind in `fields.KINDS`, each with its own `Config` (only its
own keys) and the same functions, reached through the registry."""

from __future__ import annotations

import dataclasses
import typing

import jax
import jax.numpy as jnp
import pytest

from jaxnerf_grid.config import schema as config
from jaxnerf_grid.nerf import fields

FUNCTIONS = ("Config", "check", "init", "apply", "encoding_floats", "describe")


def test_every_kind_is_a_module_with_the_same_functions_and_its_own_config():
    assert config.tagged_variants(fields.FieldConfig) == {k: m.Config for k, m in fields.KINDS.items()}
    for kind, module in fields.KINDS.items():
        assert all(hasattr(module, name) for name in FUNCTIONS)
        assert module.Config().kind == kind and fields.module(module.Config()) is module
    names = {k: {f.name for f in dataclasses.fields(m.Config)} for k, m in fields.KINDS.items()}
    assert {"skip", "pos_min_deg", "pos_max_deg"} <= names["mlp"] and not {"grid", "geo_features"} & names["mlp"]
    assert {"grid", "geo_features"} <= names["grid"] and not {"skip", "pos_max_deg"} & names["grid"]
    assert typing.get_type_hints(fields.proposal.init)["cfg"] is fields.grid.Config


@pytest.mark.parametrize("kind", sorted(fields.KINDS))
def test_init_and_apply_dispatch_through_the_registry(kind):
    cfg = fields.KINDS[kind].Config(depth=1, width=8, view_width=8, dir_max_deg=1)
    if kind == "grid":
        small = fields.HashConfig(num_levels=2, log2_table_size=8, min_resolution=4, max_resolution=8)
        cfg = dataclasses.replace(cfg, grid=small, geo_features=3)
    params = fields.init(jax.random.PRNGKey(0), cfg)
    x = jnp.zeros((5, 3))
    out = fields.apply(params, cfg, x, jnp.ones((5, 3)) / jnp.sqrt(3.0))
    assert out["rgb"].shape == (5, 3) and out["sigma"].shape == (5,)
    assert fields.describe(cfg).startswith("MLP" if kind == "mlp" else "hash grid")
    assert fields.encoding_floats(cfg) > 0


def test_each_kind_checks_its_own_rules():
    with pytest.raises(ValueError, match="density_activation"):
        fields.check(fields.mlp.Config(density_activation="exp"))  # the exponential is the grid's
    fields.check(fields.grid.Config(density_activation="exp", depth=0))  # a grid may have no hidden layer
    with pytest.raises(ValueError, match="depth"):
        fields.check(fields.mlp.Config(depth=0))
    with pytest.raises(ValueError, match="proposal field: kind must be 'grid'"):
        fields.proposal.check(fields.mlp.Config())
