"""Measuring the training speed (train/speed.py) and planning a run's steps at it (budget.apply):
the rate against a closed form on a stand-in clock, the budget asking for it only when the time
cap may bind, a resumed run planning at its recorded speed, and the real step timed."""

import dataclasses
import json
import math

import pytest

from jaxnerf_grid.config import budget
from jaxnerf_grid.config.run_config import RunConfig, TrainConfig
from jaxnerf_grid.train import distributed, speed
from tests.train.test_loop import tiny_config

DEMO_TRAIN = TrainConfig(batch_rays=1024, max_steps=1600, warmup=50, lr_init=2e-2, lr_final=2e-3)


class StandInSteps:
    """run_steps(k) on a clock that a compile moves by `compile_s` and each step by `step_s`."""

    def __init__(self, compile_s: float, step_s: float):
        self.now, self.compile_s, self.step_s, self.calls = 0.0, compile_s, step_s, []

    def clock(self) -> float:
        return self.now

    def __call__(self, k: int) -> None:
        self.now += self.compile_s if not self.calls else self.step_s * k
        self.calls.append(k)


def test_the_rate_is_the_timed_rays_over_the_timed_seconds_leaving_the_compile_out():
    steps = StandInSteps(compile_s=30.0, step_s=0.125)
    rate = speed.rays_per_second(steps, 1024, seconds=2.0, clock=steps.clock)
    assert rate == pytest.approx(1024 / 0.125)
    # the compile is one step; then rounds of ROUND steps until 2 s: 0.625 s a round -> 4 rounds (2.5 s)
    assert steps.calls == [1] + [speed.ROUND] * 4


def test_the_budget_measures_only_when_the_time_cap_may_bind_and_plans_at_the_measured_speed():
    calls = []

    def measure(cfg):
        calls.append(cfg)
        return 5500.0, "measured on a stand-in"

    cfg = RunConfig(train=DEMO_TRAIN)
    # the synthetic demo: 1600 steps at 11k rays/s = 2.48 min, under a quarter of 12: not measured
    small, rec = budget.apply(cfg, 40 * 160 * 120, minutes=12, measure=measure)
    assert calls == [] and small.train.max_steps == 1600 and rec["speed_source"] == budget.REFERENCE
    # the phone capture (10.9 M px): the cap binds; at 5500 rays/s, 12 min fit
    # 12 x 60 x 5500 / 1024 = 3867.2 steps -> 3800
    large, rec = budget.apply(cfg, 49 * 353 * 628, minutes=12, measure=measure)
    assert len(calls) == 1 and large.train.max_steps == rec["steps"] == 3800
    assert rec["limited_by"] == "minutes" and rec["rays_per_second"] == 5500.0
    assert rec["speed_source"] == "measured on a stand-in" and "5.5k rays/s (measured on a stand-in)" in rec["why"]
    assert "5.5k rays/s (measured on a stand-in)" in budget.report_line(rec)
    # fountain-P11's 1.7 M px: 3400 steps fill 5.3 of 12 min at 11k, over a quarter, so measured;
    # at half the speed its 2 epochs still fit (cap 12 x 60 x 5500 / 1024 -> 3800)
    mid, rec = budget.apply(cfg, 9 * 533 * 355, minutes=12, measure=measure)
    assert len(calls) == 2 and (mid.train.max_steps, rec["limited_by"]) == (3400, "epochs")


def test_a_resumed_run_plans_at_the_speed_its_budget_recorded(tmp_path, monkeypatch):
    cfg = RunConfig(train=DEMO_TRAIN)
    first, rec = budget.apply(cfg, 49 * 353 * 628, minutes=12, measure=lambda c: (7321.0, speed.MEASURED))
    (tmp_path / "budget.json").write_text(json.dumps(rec))
    assert budget.recorded_speed(tmp_path) == (7321.0, f"as planned when the run began: {speed.MEASURED}")

    def never(cfg, seconds=speed.SECONDS):
        raise AssertionError("a resumed run must not time the step again")

    monkeypatch.setattr(speed, "measure", never)
    again, rec2 = budget.apply(cfg, 49 * 353 * 628, minutes=12, measure=speed.planner(tmp_path))
    # 12 x 60 x 7321 / 1024 = 5147.6 steps -> 5100
    assert again.train.max_steps == first.train.max_steps == 5100
    assert rec2["rays_per_second"] == 7321.0 and rec2["speed_source"].startswith("as planned when the run began")


def test_a_run_that_fell_back_to_the_recipes_grid_resumes_with_the_same_grid_and_steps(tmp_path, monkeypatch):
    from jaxnerf_grid.config import recipes

    def measure(cfg):  # the larger grid too slow for fountain-P11's 2 epochs on this machine
        return (3000.0 if cfg.model.field.grid.log2_table_size == 19 else 11000.0), speed.MEASURED

    lean = recipes.make_config("ours-lean")
    first, rec = budget.apply(lean, 9 * 533 * 355, minutes=12, grid_free=True, measure=measure)
    (tmp_path / "budget.json").write_text(json.dumps(rec))
    monkeypatch.setattr(speed, "measure", lambda cfg, seconds=speed.SECONDS: 1 / 0)  # never timed again
    again, rec2 = budget.apply(lean, 9 * 533 * 355, minutes=12, grid_free=True, measure=speed.planner(tmp_path))
    assert first.model.field.grid.log2_table_size == again.model.field.grid.log2_table_size == 16
    assert first.train.max_steps == again.train.max_steps == 3400 and rec2["grid_rays_per_second"] == 3000.0


def test_no_recorded_speed_for_a_new_run_given_steps_or_a_bad_record(tmp_path):
    assert budget.recorded_speed(tmp_path) is None
    (tmp_path / "budget.json").write_text(json.dumps({"rule": "given", "steps": 300}))
    assert budget.recorded_speed(tmp_path) is None
    (tmp_path / "budget.json").write_text("{not json")
    assert budget.recorded_speed(tmp_path) is None
    (tmp_path / "budget.json").write_text(json.dumps({"rule": "budget", "rays_per_second": -3}))
    assert budget.recorded_speed(tmp_path) is None


def test_overwrite_ignores_the_record_and_a_multi_process_run_plans_at_the_reference(tmp_path, monkeypatch):
    (tmp_path / "budget.json").write_text(json.dumps({"rule": "budget", "rays_per_second": 7321.0}))
    timed = []
    monkeypatch.setattr(speed, "measure", lambda cfg: timed.append(cfg) or 4000.0)
    said = []
    rate, source = speed.planner(tmp_path, overwrite=True, say=said.append)(RunConfig(train=DEMO_TRAIN))
    assert (rate, source, len(timed), len(said)) == (4000.0, speed.MEASURED, 1, 1)
    monkeypatch.setattr(distributed, "is_distributed", lambda: True)
    assert speed.planner(tmp_path) is None


def test_the_timed_config_is_the_plain_step_without_the_depth_rays():
    from jaxnerf_grid.config.run_config import DepthConfig

    cfg = tiny_config("ours", "grid")
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(
        cfg.train, depth=DepthConfig(weight=0.1, rays=128),
        robust=dataclasses.replace(cfg.train.robust, mode="robust")))
    timed = speed.timing_config(cfg)
    assert timed.train.robust.mode == "off" and timed.train.depth.weight == 0.0
    assert timed.model == cfg.model and timed.train.batch_rays == cfg.train.batch_rays


def test_measuring_times_the_real_step():
    rate = speed.measure(tiny_config("ours", "grid"), seconds=0.2)
    assert math.isfinite(rate) and rate > 0
