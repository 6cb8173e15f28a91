"""benchmarks/step_profile.py: runs end to end on a tiny config, its JSON has every stage, and
its separately jitted MLP stage with the hash encoding is the grid field itself."""

import json

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import step_profile
from jaxnerf_grid.config import recipes
from jaxnerf_grid.nerf import fields, models

TINY = ["model.field.grid.num_levels=2", "model.field.grid.log2_table_size=8", "model.field.grid.max_resolution=32",
        "model.field.width=16", "model.field.view_width=16", "model.sampler.samples=[8]",
        "model.sampler.main_samples=4", "model.sampler.field.grid.num_levels=2",
        "model.sampler.field.grid.log2_table_size=8", "model.sampler.field.grid.max_resolution=32"]


def test_step_profile_writes_every_stage(tmp_path, capsys):
    out = tmp_path / "profile.json"
    step_profile.main(["--rays", "16", "--repeats", "1", "--size", "16,12,3", "--out", str(out)]
                      + [f"--set={s}" for s in TINY])
    result = json.loads(out.read_text())
    assert set(result["stages_ms"]) == set(step_profile.STAGES)
    timed = [s for s in step_profile.STAGES if s != "sampling_losses"]  # the remainder may be < 0
    assert all(result["stages_ms"][s] > 0 for s in timed), result["stages_ms"]
    remainder = result["stages_ms"]["loss_and_grad"] - sum(result["stages_ms"][s] for s in step_profile.FIELD_STAGES)
    assert abs(result["stages_ms"]["sampling_losses"] - remainder) < 1e-9
    assert result["config"]["main_levels"] == 2 and result["config"]["samples"] == [8]
    assert "load_average" in result["machine"]
    printed = capsys.readouterr().out
    assert all(f"| {s} |" in printed for s in step_profile.STAGES)


def test_main_mlps_on_the_encoding_is_the_grid_field():
    cfg = recipes.make_config("ours", {"model": {"field": {"grid": {"num_levels": 2, "log2_table_size": 8}}}}).model
    params, field_cfg = models.main_field(models.init(jax.random.PRNGKey(0), cfg), cfg)
    x = jax.random.uniform(jax.random.PRNGKey(1), (5, 3), minval=-1.0, maxval=1.0)
    d = jnp.tile(jnp.asarray([[0.0, 0.6, 0.8]]), (5, 1))
    reference = fields.apply(params, field_cfg, x, d)
    features = fields.hashgrid.encode(params["encoding"], field_cfg.grid, x)
    got = step_profile.main_mlps({k: v for k, v in params.items() if k != "encoding"}, field_cfg, features, d)
    for key in ("sigma", "rgb"):
        np.testing.assert_allclose(np.asarray(got[key]), np.asarray(reference[key]), rtol=1e-6, atol=1e-6)
