"""The one config builder: recipe -> dataset bounds -> config file -> --set -> --max-side -> --steps -> the
caller's layer -> the training budget, each later layer winning, checked before anything is written; what
`train` and `demo` both call."""

import json

import numpy as np
import pytest

from jaxnerf_grid.config import build, recipes
from jaxnerf_grid.config.schema import ConfigError

BOUNDS = {"near": 0.25, "far": 9.5, "contract_radius": 3.0, "roi_radius": 0.8, "roi_centre": [0.0, 0.0, 0.1]}


def dataset_folder(tmp_path, bounds=BOUNDS):
    folder = tmp_path / "data"
    folder.mkdir()
    meta = {"frames": []}
    if bounds is not None:
        meta["scene_bounds"] = bounds
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def test_without_any_request_it_is_the_recipe_alone():
    built = build.build(build.Request(recipe="ours-lean"))
    assert built.overrides == recipes.overrides("ours-lean")
    assert built.recipe == "ours-lean" and built.method == recipes.get("ours-lean").method
    assert built.bounds is None


def test_each_layer_wins_over_the_ones_before_it(tmp_path):
    data = dataset_folder(tmp_path)
    config_file = tmp_path / "c.json"
    # the file sets far (over the bounds) and near; --set then sets near again; --max-side and --steps last
    config_file.write_text(json.dumps({"model": {"far": 7.0, "near": 0.3}, "train": {"max_side": 100}}))
    request = build.Request(recipe="ours-lean", config_file=str(config_file), sets=("model.near=0.4",
                            "train.max_side=200", "train.max_steps=5"), max_side=320, steps=7)
    built = build.build(request, data=data, extra={"model": {"contract_radius": 2.5}, "train": {"max_steps": 9}})
    model, train = built.overrides["model"], built.overrides["train"]
    assert model["far"] == 7.0  # the file over the bounds' 9.5
    assert model["near"] == 0.4  # --set over the file's 0.3 and the bounds' 0.25
    assert train["max_side"] == 320  # --max-side over --set's 200 and the file's 100
    assert model["contract_radius"] == 2.5  # the caller's layer over the bounds' 3.0
    assert train["max_steps"] == 9  # the caller's layer over --steps' 7 and --set's 5
    assert built.bounds["far"] == 9.5 and built.budget is None  # no devices_of: no budget
    cfg = built.config()
    assert (cfg.model.near, cfg.model.far, cfg.train.max_side, cfg.train.max_steps) == (0.4, 7.0, 320, 9)


def test_the_callers_defaults_lie_under_the_users_settings(tmp_path):
    data = dataset_folder(tmp_path)
    defaults = {"train": {"depth": {"weight": 0.1, "rays": 64}}}
    alone = build.build(build.Request(recipe="ours-lean"), data=data, defaults=defaults).config()
    assert (alone.train.depth.weight, alone.train.depth.rays) == (0.1, 64)
    user = build.build(build.Request(recipe="ours-lean", sets=("train.depth=0",)), data=data, defaults=defaults)
    assert (user.config().train.depth.weight, user.config().train.depth.rays) == (0.0, 64)


def frames_folder(tmp_path, count, width, height):
    """A dataset folder of `count` training photos of width x height (budget.capture_pixels reads
    their headers), no recorded bounds."""
    from jaxnerf_grid.util import io

    folder = tmp_path / "frames"
    folder.mkdir()
    frames = []
    for i in range(count):
        io.write_png(folder / f"{i}.png", np.zeros((height, width, 3), np.float32))
        frames.append({"file_path": f"{i}.png", "transform_matrix": np.eye(4).tolist()})
    meta = {"fl_x": 100.0, "fl_y": 100.0, "cx": width / 2, "cy": height / 2, "w": width, "h": height,
            "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def test_the_budget_chooses_the_steps_last_unless_the_user_gave_them(tmp_path):
    """200 photos of 640x480 at 1024 rays a step: 2 epochs want ceil(2 x 61.44 M / 1024 / 100) x 100 =
    120,000 steps, more than 12 minutes allow on the larger grid the budget then trains, at 11k / 1.4
    rays/s (floor(12 x 60 x 7857.1 / 1024 / 100) x 100 = 5,500); --steps or train.max_steps keep
    the user's count."""
    data = frames_folder(tmp_path, 200, 640, 480)
    one = lambda train_cfg: 1  # noqa: E731
    built = build.build(build.Request(recipe="ours-lean"), data=data, devices_of=one)
    assert built.budget["rule"] == "budget" and built.budget["limited_by"] == "minutes"
    assert built.overrides["train"]["max_steps"] == 5500 == built.config().train.max_steps
    given = build.build(build.Request(recipe="ours-lean", steps=50), data=data, devices_of=one)
    assert given.budget["rule"] == "given" and given.config().train.max_steps == 50
    by_set = build.build(build.Request(recipe="ours-lean", sets=("train.max_steps=60",)), data=data, devices_of=one)
    assert by_set.budget["rule"] == "given" and by_set.config().train.max_steps == 60


def test_a_capture_past_the_recipes_size_trains_the_larger_grid_unless_the_user_set_the_field(tmp_path):
    """12 photos of 640x480, 10 of them training (3.07 M px): 2 epochs = 6000 steps, 13.0 min at the
    larger grid's 11k / 1.4 rays/s: the minutes bind, so the larger grid for the 5500 steps they hold
    (12 x 60 x 11000 / 1.4 / 1024 = 5524.6); 4 photos, 3 training (0.92 M px, 1800 steps), fit in
    3.9 min at 1.4x, so the larger grid over the 12 minutes, the same 5500 steps; --set
    model.field... keeps it from being chosen; 2 photos of 160x120 (the recipe's size) keep the
    recipe's grid and 1600 steps."""
    one = lambda train_cfg: 1  # noqa: E731
    for name in ("ten", "four", "two"):
        (tmp_path / name).mkdir()
    ten = build.build(build.Request(recipe="ours-lean"), data=frames_folder(tmp_path / "ten", 12, 640, 480),
                      devices_of=one)
    assert ten.budget["grid"] == {"log2_table_size": 19, "max_resolution": 4096}
    assert ten.budget["limited_by"] == "minutes" and ten.config().model.field.grid.log2_table_size == 19
    assert ten.config().train.max_steps == 5500
    two = build.build(build.Request(recipe="ours-lean"), data=frames_folder(tmp_path / "two", 2, 160, 120),
                      devices_of=one)
    assert two.budget["grid"] is None and two.config().model.field.grid.log2_table_size == 16
    assert two.config().train.max_steps == 1600
    four = frames_folder(tmp_path / "four", 4, 640, 480)
    built = build.build(build.Request(recipe="ours-lean"), data=four, devices_of=one)
    grid = built.config().model.field.grid
    assert (grid.log2_table_size, grid.max_resolution, built.config().train.max_steps) == (19, 4096, 5500)
    own = build.build(build.Request(recipe="ours-lean", sets=("model.field.grid.num_levels=10",)), data=four,
                      devices_of=one)
    grid = own.config().model.field.grid
    assert (grid.log2_table_size, grid.max_resolution, grid.num_levels) == (16, 1024, 10) and own.budget["grid"] is None
    assert own.config().train.max_steps == 1800


def test_recorded_bounds_replace_the_recipes_constants(tmp_path):
    built = build.build(build.Request(recipe="ours-lean"), data=dataset_folder(tmp_path))
    assert {k: built.overrides["model"][k] for k in ("near", "far", "contract_radius")} == \
        {"near": 0.25, "far": 9.5, "contract_radius": 3.0}


def test_a_method_in_a_bounded_box_keeps_its_own_near_and_far(tmp_path):
    built = build.build(build.Request(method="nerf"), data=dataset_folder(tmp_path))
    assert built.bounds is None
    assert built.overrides == recipes.overrides("nerf")


def test_a_dataset_without_bounds_keeps_the_recipe(tmp_path):
    built = build.build(build.Request(recipe="ours-lean"), data=dataset_folder(tmp_path, bounds=None))
    assert built.bounds is None and built.overrides == recipes.overrides("ours-lean")


@pytest.mark.parametrize("request_, key", [
    (build.Request(sets=("model.nope=1",)), "model.nope"),
    (build.Request(sets=("data=x",)), "data"),
    (build.Request(steps=0), "run.steps"),
    (build.Request(max_side=-3), "train.max_side"),
    (build.Request(recipe="no-such-recipe"), "no-such-recipe"),
])
def test_a_bad_request_is_one_config_error_naming_the_key(request_, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        build.build(request_)


def test_a_config_file_that_is_not_an_object_is_refused(tmp_path):
    path = tmp_path / "c.json"
    path.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="c.json: a config file must hold a JSON object"):
        build.build(build.Request(config_file=str(path)))


def test_train_and_demo_build_their_configs_here(monkeypatch, tmp_path):
    """Both entry points go through build.build (a spy sees each call and its request)."""
    from jaxnerf_grid import demo
    from jaxnerf_grid.cli import train as train_cli

    seen = []

    class Stop(Exception):
        pass

    def spy(request, data=None, extra=None, devices_of=None, platform="cpu", **kwargs):
        seen.append((request, data))
        raise Stop

    monkeypatch.setattr(build, "build", spy)
    with pytest.raises(Stop):
        train_cli.main(["--data", str(tmp_path), "--recipe", "ours-lean", "--set", "train.batch_rays=64",
                        "--max-side", "99", "--steps", "3"])
    with pytest.raises(Stop):
        demo.run_demo(None, tmp_path / "out", steps=4, sets=["train.batch_rays=32"], max_side=88)
    assert seen[0] == (build.Request("ours-lean", None, None, ("train.batch_rays=64",), 99, 3, None), str(tmp_path))
    assert seen[1][0] == build.Request(recipe=demo.DEMO_RECIPE, sets=("train.batch_rays=32",), max_side=88, steps=4)
