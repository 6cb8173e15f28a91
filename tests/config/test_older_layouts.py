"""Configs written in an older layout read as the current one: the flat robust keys
(train.robust a mode string, train.robust_X) and a field dict holding every field kind's keys
(older runs' config.json wrote them all). `--set` reaches the nested keys and switches kinds."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from jaxnerf_grid.config import build, recipes
from jaxnerf_grid.config import schema as config
from jaxnerf_grid.config.run_config import RobustConfig, RunConfig, make_config
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.nerf import fields

ROOT = Path(__file__).resolve().parents[2]
# a run trained before the nesting: flat robust keys, a grid field with the MLP's keys at their defaults
OLD_RUN = ROOT / "benchmarks/results/table1_strict_readmit" / \
    "t1-tower-small-built-in_DPT_masks__Eq_7__robust-strict-s0-a916966803/config.json"


def test_flat_robust_keys_load_to_the_same_config_as_the_nested_ones():
    flat = make_config("ours", {"train": {"robust": "dpt+robust", "robust_patch": 8, "robust_quantile": 0.7,
                                          "robust_strict_readmit": True}})
    nested = make_config("ours", {"train": {"robust": {"mode": "dpt+robust", "patch": 8, "quantile": 0.7,
                                                       "strict_readmit": True}}})
    assert flat == nested
    assert nested.train.robust == RobustConfig(mode="dpt+robust", patch=8, quantile=0.7, strict_readmit=True)


def test_a_field_dict_with_both_kinds_keys_at_their_defaults_loads_as_its_kind():
    for name in ("ours", "ours-paper-mlp"):
        cfg = recipes.make_config(name)
        old = fields.base.old_layout(config.to_dict(cfg.model.field))  # every kind's key, as older runs wrote
        assert {"skip", "grid", "geo_features"} <= set(old)
        overrides = recipes.overrides(name)
        overrides["model"]["field"] = old
        assert make_config("ours", overrides) == cfg


def test_an_older_runs_config_json_loads_in_the_current_layout():
    raw = json.loads(OLD_RUN.read_text())
    assert raw["train"]["robust"] == "dpt+robust" and "robust_patch" in raw["train"]
    assert "skip" in raw["model"]["field"] and raw["model"]["field"]["kind"] == "grid"
    cfg = config.from_dict(RunConfig, raw)
    assert cfg.train.robust.mode == "dpt+robust" and cfg.train.robust.patch == raw["train"]["robust_patch"]
    assert cfg.train.robust.strict_readmit is True
    assert isinstance(cfg.model.field, fields.grid.Config)
    assert isinstance(cfg.model.sampler.field, fields.grid.Config)
    assert config.from_dict(RunConfig, config.to_dict(cfg)) == cfg  # and it writes back in the current layout
    assert "robust_patch" not in config.to_dict(cfg)["train"] and "skip" not in config.to_dict(cfg)["model"]["field"]


@pytest.mark.parametrize("kind, key, value, other", [("grid", "skip", 3, "mlp"), ("grid", "pos_max_deg", 6, "mlp"),
                                                     ("mlp", "geo_features", 7, "grid"),
                                                     ("mlp", "grid", {"num_levels": 4}, "grid")])
def test_a_non_default_key_of_another_kind_is_a_one_line_error_naming_it(kind, key, value, other):
    field = {"kind": kind, key: value}
    with pytest.raises(ConfigError) as err:
        make_config("ours", {"model": {"field": field}})
    message = str(err.value)
    assert "\n" not in message and f"{key} = " in message and repr(other) in message and "model.field" in message


def test_set_field_kind_grid_gives_the_grids_defaults(tmp_path):
    built = build.build(build.Request(recipe="ours-paper-mlp", sets=("model.field.kind=grid",)))
    assert built.config().model.field == fields.grid.Config()
    # over a file's MLP settings: the kind is switched with its own defaults, none of the MLP's kept
    path = tmp_path / "mlp.json"
    path.write_text(json.dumps({"model": {"field": {"kind": "mlp", "depth": 6, "skip": 3}}}))
    built = build.build(build.Request(recipe="ours-paper-mlp", config_file=str(path), sets=("model.field.kind=grid",)))
    assert built.config().model.field == fields.grid.Config()
    # a key of the kind it already has merges into it
    built = build.build(build.Request(recipe="ours", sets=("model.field.width=32",)))
    assert built.config().model.field == dataclasses.replace(recipes.make_config("ours").model.field, width=32)


def test_set_train_robust_to_a_mode_sets_the_mode():
    cfg = build.build(build.Request(sets=("train.robust=robust", "train.robust.patch=8"))).config()
    assert (cfg.train.robust.mode, cfg.train.robust.patch) == ("robust", 8)
    # the shorthand after a nested key keeps it: the mode is one key of the section
    cfg = build.build(build.Request(sets=("train.robust.quantile=0.7", "train.robust=dpt+robust"))).config()
    assert (cfg.train.robust.mode, cfg.train.robust.quantile) == ("dpt+robust", 0.7)


def test_an_older_flat_robust_key_in_set_is_refused_with_its_new_name():
    with pytest.raises(ConfigError, match=r"^train\.robust_patch: renamed train\.robust\.patch$"):
        build.build(build.Request(sets=("train.robust_patch=8",)))
    with pytest.raises(ConfigError, match="unknown key 'robust_'"):  # the bare prefix is no older key
        build.build(build.Request(sets=("train.robust_=8",)))


def test_an_older_config_file_then_set_keeps_the_files_robust_mode(tmp_path):
    path = tmp_path / "old.json"
    path.write_text(json.dumps({"train": {"robust": "robust", "robust_patch": 8}}))
    cfg = build.build(build.Request(config_file=str(path), sets=("train.robust.quantile=0.7",))).config()
    assert (cfg.train.robust.mode, cfg.train.robust.patch, cfg.train.robust.quantile) == ("robust", 8, 0.7)
    # a caller's layer with a mode string merges into the nested settings below it
    built = build.build(build.Request(sets=("train.robust.patch=8",)), extra={"train": {"robust": "robust"}})
    assert (built.config().train.robust.mode, built.config().train.robust.patch) == ("robust", 8)
