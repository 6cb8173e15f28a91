"""The recipe registry (jaxnerf_grid/config/recipes.py), `jaxnerf-grid recipes` and `train --recipe / --method`.

The references are written out here: the demo's recipe as it stood when its figures were
measured, RunConfig()'s defaults for the paper's setting, NeRF's bounded space by hand.
"""

import dataclasses
import json

import pytest

from experiments import settings
from jaxnerf_grid import cli, demo
from jaxnerf_grid.config import build, recipes
from jaxnerf_grid.config import schema as config
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.nerf.samplers.legacy import upgrade_flat_model
from jaxnerf_grid.train import loop as train

# demo.DEMO_CONFIG as committed before the registry (the recipe of docs/GRID.md's figures)
DEMO_BEFORE = {
    "model": {"sampler": "proposal", "proposal_samples": [64], "num_fine": 32, "contract_radius": 2.0,
              "field": {"kind": "grid", "depth": 1, "width": 64, "view_depth": 2, "view_width": 64,
                        "dir_max_deg": 3, "density_activation": "exp", "density_bias": -4.0,
                        "grid": {"num_levels": 12, "features_per_level": 2, "log2_table_size": 17,
                                 "min_resolution": 16, "max_resolution": 1024}},
              "proposal_field": {"density_bias": -4.0},
              "near": 1.0, "far": 1000.0, "opaque_far": True},
    "train": {"batch_rays": 1024, "max_steps": 2400, "lr_init": 2e-2, "lr_final": 2e-3, "warmup": 50,
              "adam_eps": 1e-15, "adam_b2": 0.99, "max_grad_norm": 0.0, "distortion_loss_weight": 0.002,
              "checkpoint_every": 300, "log_every": 50, "chunk": 4096},
}
SAMPLER_KEYS = {"sampler", "num_coarse", "num_fine", "hierarchical", "fine_union", "shared_field",
                "proposal_samples", "proposal_field", "proposal_padding"}


def as_dict(cfg) -> dict:
    return config.to_dict(cfg)


def test_ours_is_the_demo_recipe_key_for_key():
    # the recipe holds the demo's settings with its sampler in the tagged form (samplers/legacy.py)
    model, upgraded = recipes.overrides("ours")["model"], upgrade_flat_model(DEMO_BEFORE["model"])
    assert {k: v for k, v in model.items() if k != "sampler"} == {k: v for k, v in upgraded.items() if k != "sampler"}
    assert model["sampler"] == {k: v for k, v in upgraded["sampler"].items() if k in model["sampler"]}
    assert {k: v for k, v in recipes.overrides("ours").items() if k != "model"} == \
        {k: v for k, v in DEMO_BEFORE.items() if k != "model"}
    assert demo.DEMO_RECIPE == "ours-lean" and demo.DEMO_CONFIG == recipes.overrides("ours-lean")
    assert recipes.get(demo.DEMO_RECIPE).method == "ours"
    assert as_dict(recipes.make_config("ours")) == as_dict(train.make_config("ours", DEMO_BEFORE))
    # the experiments record it flat, with the same content and key order as the results files
    before = json.loads(json.dumps(DEMO_BEFORE))
    before["train"].pop("max_steps")
    assert json.dumps(settings._without_steps("ours")) == json.dumps(before)


def test_paper_mlp_is_runconfig_defaults_for_ours():
    cfg = recipes.make_config("ours-paper-mlp")
    assert as_dict(cfg) == as_dict(train.RunConfig())  # RunConfig() is ours' defaults already
    assert cfg.model.field.kind == "mlp" and cfg.model.sampler.kind == "hierarchical" and cfg.train.use_masks


@pytest.mark.parametrize("name", ["nerf", "nerfw"])
def test_baselines_are_ours_in_a_bounded_space(name):
    by_hand = json.loads(json.dumps(DEMO_BEFORE))
    by_hand["model"].update({"far": 40.0, "encoding_scale": 44.0})
    cfg = recipes.make_config(name)
    assert as_dict(cfg) == as_dict(train.make_config(name, by_hand))
    assert (cfg.model.method, cfg.model.use_contraction, cfg.model.warp, cfg.train.use_masks) == \
        (name, False, "linear", False)
    assert cfg.model.use_appearance == cfg.model.use_transient == (name == "nerfw")


def test_every_sampler_key_sits_in_samplers():
    for name in recipes.names():
        assert not SAMPLER_KEYS & set(recipes.SETTINGS[name].get("model", {})), name
        assert set(recipes.SAMPLERS[name]) <= SAMPLER_KEYS, name
        assert set(recipes.SAMPLERS[name]) <= set(recipes.overrides(name)["model"]), name


def test_ours_fast_is_ours_with_a_smaller_proposal_field_and_1600_steps():
    fast, ours = recipes.make_config("ours-fast"), recipes.make_config("ours")
    assert (fast.train.max_steps, ours.train.max_steps) == (1600, 2400)
    fast = dataclasses.replace(fast, train=ours.train)
    assert (fast.model.sampler.field.grid.num_levels, fast.model.sampler.field.grid.max_resolution,
            fast.model.sampler.field.grid.log2_table_size) == (3, 64, 15)
    assert dataclasses.replace(fast.model.sampler.field, grid=ours.model.sampler.field.grid) == ours.model.sampler.field
    same_sampler = dataclasses.replace(fast.model.sampler, field=ours.model.sampler.field)
    assert dataclasses.replace(fast, model=dataclasses.replace(fast.model, sampler=same_sampler)) == ours


def test_ours_lean_is_ours_fast_with_24_main_samples_8_levels_of_2_16_rows_and_one_colour_layer():
    lean, fast = recipes.make_config("ours-lean"), recipes.make_config("ours-fast")
    assert lean.train == fast.train and lean.train.max_steps == 1600
    assert (lean.model.sampler.main_samples, fast.model.sampler.main_samples) == (24, 32)
    assert lean.model.sampler.field == fast.model.sampler.field
    grid, fast_grid = lean.model.field.grid, fast.model.field.grid
    assert (grid.num_levels, grid.log2_table_size, fast_grid.num_levels, fast_grid.log2_table_size) == (8, 16, 12, 17)
    # the same finest and coarsest cells as ours: only the steps between levels are larger
    assert (grid.min_resolution, grid.max_resolution) == (fast_grid.min_resolution, fast_grid.max_resolution)
    assert (lean.model.field.view_depth, fast.model.field.view_depth) == (1, 2)
    field = dataclasses.replace(lean.model.field, view_depth=2, grid=fast_grid)
    sampler = dataclasses.replace(lean.model.sampler, main_samples=32)
    assert dataclasses.replace(lean, model=dataclasses.replace(lean.model, field=field, sampler=sampler)) == fast


def test_overrides_are_fresh_copies():
    a, b = recipes.overrides("ours"), recipes.overrides("ours")
    a["model"]["field"]["grid"]["num_levels"] = 1
    a["model"]["sampler"]["samples"].append(8)
    assert recipes.overrides("ours") == b != a


def test_resolve_recipe_and_method():
    assert recipes.resolve(None, None) == ("ours", "ours")
    assert recipes.resolve(None, "nerf") == ("nerf", "nerf")
    assert recipes.resolve("nerfw", None) == ("nerfw", "nerfw")
    assert recipes.resolve("ours-paper-mlp", "nerf") == ("ours-paper-mlp", "nerf")
    # --recipe ours-paper-mlp --method nerf is what `train --method nerf` trained before the registry
    assert as_dict(recipes.make_config("ours-paper-mlp", method="nerf")) == as_dict(train.make_config("nerf"))
    with pytest.raises(ConfigError, match="'mine'.*ours, ours-paper-mlp, nerf, nerfw, ours-fast, ours-lean"):
        recipes.get("mine")


def test_recipes_command_prints_one_line_each(capsys):
    assert cli.main(["recipes"]) == 0
    lines = capsys.readouterr().out.splitlines()
    listed = [line.split()[0] for line in lines[:len(recipes.RECIPES)]]
    assert listed == ["ours", "ours-paper-mlp", "nerf", "nerfw", "ours-fast", "ours-lean"]
    assert all(recipes.RECIPES[n].description in line for n, line in zip(listed, lines))
    assert cli.main(["recipes", "--show", "nerf"]) == 0
    assert json.loads(capsys.readouterr().out) == recipes.overrides("nerf")
    assert cli.main(["recipes", "--show", "mine"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mine" in err[0]


class Called(Exception):
    pass


@pytest.fixture
def train_args(monkeypatch):
    """`train`'s call to runs.train_run, captured (nothing is trained): (method, overrides, out)."""
    from jaxnerf_grid.train import runs

    def capture(data, method, out, overrides=None, steps=None, *args, **kwargs):
        raise Called(method, build.with_steps(overrides, steps), out)

    monkeypatch.setattr(runs, "train_run", capture)

    def run(argv):
        with pytest.raises(Called) as got:
            cli.main(["train", "--data", "somewhere", *argv])
        return got.value.args

    return run


def test_train_method_ours_trains_the_demo_config(train_args, tmp_path):
    method, overrides, out = train_args(["--method", "ours", "--steps", "7"])
    assert method == "ours" and out == "runs/ours"
    # what demo.run_demo trains with --steps 7
    demo_cfg = train.make_config("ours", {**DEMO_BEFORE, "train": {**DEMO_BEFORE["train"], "max_steps": 7}})
    assert as_dict(train.make_config(method, overrides)) == as_dict(demo_cfg)
    assert train_args(["--steps", "7"])[:2] == train_args(["--recipe", "ours", "--steps", "7"])[:2] == \
        (method, overrides)


def test_train_recipe_with_method_config_and_set(train_args, tmp_path):
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(json.dumps({"train": {"batch_rays": 256}}))
    method, overrides, out = train_args(["--recipe", "ours-paper-mlp", "--method", "nerf", "--config", str(cfg_file),
                                         "--set", "model.sampler.samples=[16,16]"])
    cfg = train.make_config(method, overrides)
    expected = train.make_config("nerf", {"model": {"sampler": {"samples": [16, 16]}}, "train": {"batch_rays": 256}})
    assert as_dict(cfg) == as_dict(expected) and out == "runs/ours-paper-mlp"


def test_train_unknown_recipe_is_one_line(capsys):
    assert cli.main(["train", "--data", "somewhere", "--recipe", "mine"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mine" in err[0] and "Traceback" not in err[0]
