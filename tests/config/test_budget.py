"""The training budget (budget.py): the rule against steps computed by hand, the schedules
stretched with the steps, the training pixels of a dataset folder, and the record a run keeps."""

import dataclasses
import json

import pytest

from jaxnerf_grid.config import budget
from jaxnerf_grid.config.run_config import TrainConfig
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.masks import robust
from jaxnerf_grid.train import optim
from jaxnerf_grid.util import progress

# the demo recipe's train settings (recipes.py "ours-lean"): 1600 steps x 1024 rays, warm-up 50
DEMO_TRAIN = TrainConfig(batch_rays=1024, max_steps=1600, warmup=50, lr_init=2e-2, lr_final=2e-3)


def test_small_capture_keeps_the_recipes_steps():
    # the synthetic demo: 40 frames of 160x120 = 768 000 px; 2 epochs = 1500 steps < the recipe's 1600
    b = budget.choose_budget(40 * 160 * 120, 1, 12, DEMO_TRAIN, "cpu", target_epochs=2.0, speed=11000.0)
    assert (b.steps, b.wanted_steps, b.limited_by) == (1600, 1500, "recipe")
    assert b.cap_steps == 7700                    # 12 x 60 x 11000 / 1024 = 7734.4, down to 7700
    assert b.epochs == pytest.approx(1600 * 1024 / 768000)


def test_the_defaults_keep_the_synthetic_demo_at_1600_steps():
    b = budget.choose_budget(40 * 160 * 120, 1, None, DEMO_TRAIN)
    assert b.steps == 1600 and b.minutes == budget.DEFAULT_MINUTES
    # the demo's whole config on tower-small (40 training frames of 160x120) is the recipe's, unchanged
    from jaxnerf_grid import demo
    from jaxnerf_grid.config import recipes

    cfg = recipes.make_config(demo.DEMO_RECIPE)
    assert budget.apply(cfg, 40 * 160 * 120)[0] == cfg


def test_medium_capture_gets_its_epochs():
    # 9 training frames of 533x355 (fountain-P11 at the working resolution): 1 702 935 px;
    # 2 epochs = 3326.05 steps, up to 3400
    b = budget.choose_budget(9 * 533 * 355, 1, 12, DEMO_TRAIN, "cpu", target_epochs=2.0, speed=11000.0)
    assert (b.steps, b.limited_by) == (3400, "epochs")
    assert b.estimated_minutes == pytest.approx(3400 * 1024 / 11000 / 60)


def test_large_capture_is_capped_by_the_minutes():
    # 49 frames of 353x628 (the phone capture): 10 862 516 px; 2 epochs = 21215.9 -> 21300 steps,
    # 12 min at 11000 rays/s fit 7734 -> 7700
    b = budget.choose_budget(49 * 353 * 628, 1, 12, DEMO_TRAIN, "cpu", target_epochs=2.0, speed=11000.0)
    assert (b.wanted_steps, b.cap_steps, b.steps, b.limited_by) == (21300, 7700, 7700, "minutes")
    # 30 minutes: 30 x 60 x 11000 / 1024 = 19335.9 -> 19300
    assert budget.choose_budget(49 * 353 * 628, 1, 30, DEMO_TRAIN, "cpu", target_epochs=2.0,
                                speed=11000.0).steps == 19300


def test_the_depth_priors_rays_count_in_the_time_but_not_in_the_epochs():
    from jaxnerf_grid.config.run_config import DepthConfig

    with_depth = dataclasses.replace(DEMO_TRAIN, depth=DepthConfig(weight=0.1, rays=128))
    # 12 x 60 x 11000 / (1024 + 128) = 6875 -> 6800 steps; the epochs count the 1024 colour rays
    b = budget.choose_budget(49 * 353 * 628, 1, 12, with_depth, "cpu", target_epochs=2.0, speed=11000.0)
    assert (b.cap_steps, b.steps) == (6800, 6800)
    assert b.epochs == pytest.approx(6800 * 1024 / (49 * 353 * 628))
    assert b.estimated_minutes == pytest.approx(6800 * 1152 / 11000 / 60)
    # off (weight 0) its rays cost nothing
    off = dataclasses.replace(DEMO_TRAIN, depth=DepthConfig(weight=0.0, rays=128))
    assert budget.choose_budget(49 * 353 * 628, 1, 12, off, "cpu", target_epochs=2.0, speed=11000.0).steps == 7700


def test_a_short_budget_wins_over_the_recipe_and_warns():
    # 1 minute: 60 x 11000 / 1024 = 644.5 -> 600 steps, below the recipe's 1600
    b = budget.choose_budget(40 * 160 * 120, 1, 1, DEMO_TRAIN, "cpu", target_epochs=2.0, speed=11000.0)
    assert (b.steps, b.limited_by) == (600, "minutes")
    cfg = type("Cfg", (), {"train": dataclasses.replace(DEMO_TRAIN, max_steps=600)})()
    assert "fewer than the recipe's 1600" in budget.warning(budget.record(b, cfg, 40 * 160 * 120))
    # a budget below one rounding unit still trains at least one step
    tiny = budget.choose_budget(10 ** 6, 1, 1e-4, DEMO_TRAIN, "cpu", speed=11000.0)
    assert tiny.steps == 1


def test_the_rule_counts_rays_so_a_larger_batch_takes_fewer_steps():
    # the phone capture on a GPU at 4 M rays/s: 2 epochs of 10 862 516 px are 21215.9 steps of 1024
    # rays (-> 21300) or 2651.99 steps of 8192 (-> 2700); 12 min fit 351 562 steps of 8192
    pixels = 49 * 353 * 628
    small = budget.choose_budget(pixels, 1, 12, DEMO_TRAIN, "gpu", target_epochs=2.0, speed=4e6)
    big = budget.choose_budget(pixels, 1, 12, dataclasses.replace(DEMO_TRAIN, batch_rays=8192), "gpu",
                               target_epochs=2.0, speed=4e6)
    assert (small.steps, big.steps, big.batch_rays, big.limited_by) == (21300, 2700, 8192, "epochs")


def test_devices_add_up_on_a_gpu_not_on_a_cpu():
    assert budget.rays_per_second("cpu", 2) == budget.rays_per_second("cpu", 1)
    assert budget.rays_per_second("gpu", 2) == 2 * budget.rays_per_second("gpu", 1)


def test_a_bad_budget_is_a_config_error_naming_the_key():
    with pytest.raises(ConfigError, match="run.minutes"):
        budget.choose_budget(1000, 1, 0, DEMO_TRAIN)
    with pytest.raises(ConfigError, match="run.steps"):
        budget.stretch_schedules(DEMO_TRAIN, 0)


@pytest.mark.parametrize("steps", [6400, 400])
def test_stretched_schedules_take_the_same_values_at_the_same_fractions_of_the_run(steps):
    """lr_schedule (warm-up and decay), the robust warm-up and the refine step of the stretched
    config, at fractions of the run, equal the recipe's at the same fractions."""
    base = dataclasses.replace(DEMO_TRAIN, warmup=100, robust=dataclasses.replace(DEMO_TRAIN.robust, warmup=0.2,
                                                                                   refine=0.5))
    out = budget.stretch_schedules(base, steps)
    assert out.max_steps == steps and out.warmup == 100 * steps // 1600
    for fraction in (0.0, 0.01, 0.03, 0.0625, 0.1, 0.5, 0.9, 1.0):   # 0.0625: the end of the warm-up
        def lr(tc, f=fraction):
            return float(optim.lr_schedule(f * tc.max_steps, tc.lr_init, tc.lr_final, tc.warmup, tc.max_steps))
        assert lr(out) == pytest.approx(lr(base), rel=1e-5), fraction
    assert robust.warmup_steps(out.robust.warmup, steps) / steps == robust.warmup_steps(0.2, 1600) / 1600
    assert robust.refine_step(out.robust.refine, steps) / steps == robust.refine_step(0.5, 1600) / 1600
    # the rest of the config is the recipe's
    assert dataclasses.replace(out, max_steps=base.max_steps, warmup=base.warmup) == base


def test_apply_leaves_steps_the_user_gave():
    from jaxnerf_grid.config.run_config import RunConfig

    cfg = RunConfig(train=dataclasses.replace(DEMO_TRAIN, max_steps=300))
    same, rec = budget.apply(cfg, 12 * 10 ** 6, given_by="run.steps")
    assert same == cfg and rec["rule"] == "given" and rec["steps"] == 300 and "run.steps" in rec["why"]
    assert rec["epochs"] == pytest.approx(300 * 1024 / 12e6, abs=1e-3)
    assert budget.warning(rec).startswith("warning: 300 steps draw each training pixel 0.03 times")
    chosen, rec = budget.apply(RunConfig(train=DEMO_TRAIN), 9 * 533 * 355, minutes=12)
    assert chosen.train.max_steps == rec["steps"] == budget.choose_budget(9 * 533 * 355, 1, 12, DEMO_TRAIN).steps
    assert chosen.train.warmup == round(50 * rec["steps"] / 1600)
    assert budget.run_overrides(rec) == {"train": {"max_steps": rec["steps"], "warmup": chosen.train.warmup}}
    json.dumps(rec)     # the record is JSON (budget.json, metrics.json)
    line = budget.report_line(rec)
    assert line.startswith(f"Training budget: {rec['steps']} steps x 1024 rays") and rec["why"] in line


def test_steps_given_by_names_the_flag_or_key():
    assert budget.steps_given_by(5, {}) == "run.steps"
    assert budget.steps_given_by(None, {"train": {"max_steps": 9}}) == "train.max_steps"
    assert budget.steps_given_by(None, {"train": {"batch_rays": 9}}) is None
    assert budget.steps_given_by(None, None) is None


def test_capture_pixels_counts_the_training_frames_at_the_working_resolution(tmp_path):
    from jaxnerf_grid.data.formats import save_transforms_json
    from tests.train.test_loop import tiny_dataset

    ds = tiny_dataset(width=16, height=12, frames=5)    # 4 training frames, 1 test frame
    ds.frame_paths = [f"images/frame_{i:03d}.png" for i in range(ds.num_frames)]
    save_transforms_json(ds, tmp_path / "data")
    assert budget.capture_pixels(tmp_path / "data", 0) == 4 * 16 * 12
    assert budget.capture_pixels(tmp_path / "data", 8) == 4 * 8 * 6       # factor 2
    assert budget.capture_pixels(tmp_path / "data", 5) == 4 * 4 * 3       # factor 4: 16/4 x 12/4
    # the same as the loaded dataset's training frames at that working resolution
    from jaxnerf_grid.data.formats import load_dataset

    loaded = load_dataset(tmp_path / "data", max_side=5, progress=False, cache=False)
    assert loaded.images[loaded.split["train"]].shape[:3] == (4, 3, 4)
    # without a stated size, the images' headers give it
    meta = json.loads((tmp_path / "data" / "transforms.json").read_text())
    for key in ("w", "h"):
        meta.pop(key, None)
    (tmp_path / "data" / "transforms.json").write_text(json.dumps(meta))
    assert budget.capture_pixels(tmp_path / "data", 0) == 4 * 16 * 12


def test_the_progress_line_says_the_time_left():
    assert progress.seconds_left(30, 100, 10, 40.0) == pytest.approx(140.0)   # 20 units in 40 s, 70 to go
    assert progress.seconds_left(100, 100, 0, 40.0) is None
    assert progress.seconds_left(10, 100, 10, 40.0) is None and progress.seconds_left(5, None, 0, 1.0) is None
    import io as pyio

    class Clock:
        now = 0.0

        def __call__(self):
            return self.now

    stream, clock = pyio.StringIO(), Clock()
    bar = progress.bar(total=400, desc="train ours", unit="step", stream=stream, clock=clock, interval=10.0)
    clock.now = 30.0   # the first step carries the compile: no rate from it
    bar.update(1)
    assert stream.getvalue().splitlines()[0] == "train ours: 1/400 steps (0%), 30.0 s"
    clock.now = 40.0   # 99 steps in 10 s since the first: 300 steps to go take 300 x 10 / 99 s
    bar.update(99)
    assert stream.getvalue().splitlines()[1] == "train ours: 100/400 steps (25%), 40.0 s, 30.3 s left"
    bar.close()
    assert stream.getvalue().splitlines()[-1] == "train ours: 100/400 steps (25%), 40.0 s, 30.3 s left"


def _lean():
    from jaxnerf_grid.config import recipes

    return recipes.make_config("ours-lean")  # its grid: 2^16 rows, finest resolution 1024


def test_a_capture_with_minutes_to_spare_trains_the_larger_grid_over_the_whole_budget():
    # fountain-P11: 3400 steps x 1024 rays at 11k rays/s = 5.27 min; at 1.4x a step 7.39 min <= 12,
    # so the larger grid, for what 12 min hold at 11000 / 1.4 rays/s: 12 x 60 x 7857.1 / 1024 = 5524.6 -> 5500
    out, rec = budget.apply(_lean(), 9 * 533 * 355, minutes=12, grid_free=True)
    grid = out.model.field.grid
    assert (grid.log2_table_size, grid.max_resolution, out.train.max_steps) == (19, 4096, 5500)
    assert rec["grid"] == {"log2_table_size": 19, "max_resolution": 4096} and rec["limited_by"] == "grid"
    assert rec["why"].startswith("a larger hash grid (log2_table_size 19, max_resolution 4096) over the whole "
                                 "time budget, 12 min at 7.9k rays/s (reference estimate), as 2 epochs (3400 steps)")
    assert rec["rays_per_second"] == pytest.approx(11000 / 1.4, abs=0.1)
    assert rec["epochs"] == pytest.approx(5500 * 1024 / (9 * 533 * 355), abs=1e-3)
    assert rec["estimated_minutes"] == pytest.approx(5500 * 1024 / (11000 / 1.4) / 60, abs=0.01)
    assert budget.run_overrides(rec) == {"train": {"max_steps": 5500, "warmup": round(50 * 5500 / 1600)},
                                         "model": {"field": {"grid": {"log2_table_size": 19, "max_resolution": 4096}}}}


def test_where_the_minutes_bind_the_larger_grid_trains_the_steps_the_minutes_hold_at_its_speed():
    lean = _lean()
    # 3.2 M px: 2 epochs want ceil(6250) -> 6300 steps; the larger grid at 11000 / 1.4 rays/s holds
    # 12 x 60 x 7857.1 / 1024 = 5524.6 -> 5500 in the minutes: those, on the larger grid
    # a 50-photo phone capture, 49 x 353 x 628 px: the same 5500 (the recipe's grid would train 7700)
    for pixels in (3_200_000, 49 * 353 * 628):
        out, rec = budget.apply(lean, pixels, minutes=12, grid_free=True)
        grid = out.model.field.grid
        assert (grid.log2_table_size, grid.max_resolution, out.train.max_steps) == (19, 4096, 5500)
        assert rec["limited_by"] == "minutes" and rec["grid"] == {"log2_table_size": 19, "max_resolution": 4096}
        assert rec["epochs"] == pytest.approx(5500 * 1024 / pixels, abs=1e-3)
        assert rec["why"].endswith("on a larger hash grid (log2_table_size 19, max_resolution 4096)")
        assert out.train.warmup == round(50 * 5500 / 1600)
    # timed on this machine: the larger grid's speed is what it measures, once
    timed = []
    out, rec = budget.apply(lean, 49 * 353 * 628, minutes=12, grid_free=True,
                            measure=lambda cfg: timed.append(cfg.model.field.grid.log2_table_size)
                            or (7000.0, "stand-in"))
    # 12 x 60 x 7000 / 1024 = 4921.9 -> 4900
    assert timed == [19] and out.model.field.grid.log2_table_size == 19 and out.train.max_steps == 4900


def test_the_grid_stays_the_recipes_for_the_demo_a_slow_machine_or_the_users_field():
    lean = _lean()
    recipe_grid = lean.model.field.grid
    # the synthetic demo: the recipe's steps, the recipe's grid, nothing timed
    out, rec = budget.apply(lean, 40 * 160 * 120, minutes=12, grid_free=True,
                            measure=lambda cfg: pytest.fail("timed"))
    assert out.model.field.grid == recipe_grid and rec["grid"] is None and out.train.max_steps == 1600
    # this machine runs the larger grid at 5000 rays/s, under 11000 / GROWN_GRID_MAX_COST (2): the
    # recipe's grid, timed next at 9000: 12 x 60 x 9000 / 1024 = 6328 -> 6300 steps
    timed = []

    def measure(cfg):
        timed.append(cfg.model.field.grid.log2_table_size)
        return (5000.0 if cfg.model.field.grid.log2_table_size == 19 else 9000.0), "stand-in"

    out, rec = budget.apply(lean, 49 * 353 * 628, minutes=12, grid_free=True, measure=measure)
    assert timed == [19, 16] and out.model.field.grid == recipe_grid and out.train.max_steps == 6300
    assert rec["grid"] is None and rec["grid_rays_per_second"] == 5000.0 and rec["limited_by"] == "minutes"
    # at 5500 rays/s, 11000 / 2 exactly, the larger grid is trained: 12 x 60 x 5500 / 1024 = 3867 -> 3800
    out = budget.apply(lean, 49 * 353 * 628, minutes=12, grid_free=True,
                       measure=lambda cfg: (5500.0, "stand-in"))[0]
    assert out.model.field.grid.log2_table_size == 19 and out.train.max_steps == 3800
    # a short time budget whose larger-grid steps fall under the recipe's 1600: the recipe's grid
    out, rec = budget.apply(lean, 49 * 353 * 628, minutes=3, grid_free=True)
    # at 7857.1 rays/s, 3 x 60 x 7857.1 / 1024 = 1381 -> 1300 < 1600; the recipe's: 1933 -> 1900
    assert out.model.field.grid == recipe_grid and out.train.max_steps == 1900
    # the user set a model.field key: the grid is never grown
    for pixels in (9 * 533 * 355, 49 * 353 * 628):
        out, rec = budget.apply(lean, pixels, minutes=12, grid_free=False)
        assert out.model.field.grid == recipe_grid and rec["grid"] is None
    # a grid already as large
    big = budget.with_grid(lean, {"log2_table_size": 20, "max_resolution": 8192})
    assert budget.grid_growth(big.model) is None


def test_a_larger_grid_too_slow_on_this_machine_gives_way_to_the_recipes():
    timed = []

    def measure(cfg):  # this machine: the larger grid at 3000 rays/s, the recipe's at 11000
        timed.append(cfg.model.field.grid.log2_table_size)
        return (3000.0 if cfg.model.field.grid.log2_table_size == 19 else 11000.0), "stand-in"

    out, rec = budget.apply(_lean(), 9 * 533 * 355, minutes=12, grid_free=True, measure=measure)
    # 12 x 60 x 3000 / 1024 = 2109 steps < 3400: the larger grid would cut the epochs, so it is dropped
    assert timed == [19, 16] and out.model.field.grid.log2_table_size == 16 and out.train.max_steps == 3400
    assert rec["grid"] is None and rec["rays_per_second"] == 11000.0 and rec["grid_rays_per_second"] == 3000.0
    timed.clear()
    fast = budget.apply(_lean(), 9 * 533 * 355, minutes=12, grid_free=True,
                        measure=lambda cfg: timed.append(1) or (8000.0, "stand-in"))[0]
    # measured once, the grid kept, over 12 x 60 x 8000 / 1024 = 5625 -> 5600 steps
    assert timed == [1] and fast.model.field.grid.log2_table_size == 19 and fast.train.max_steps == 5600
