"""The model contract (models.py): the sampler as a tagged choice in the config, the flat keys
of older configs read into it, and no module outside models.py and samplers/ naming passes.

The grep test reads the source; the config tests check against hand-written expected dicts.
"""

import json
import re
from pathlib import Path

import pytest

from jaxnerf_grid.config import build
from jaxnerf_grid.config import schema as config
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.nerf import models
from jaxnerf_grid.nerf.samplers import hierarchical, legacy, proposal
from jaxnerf_grid.train import loop as train

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "jaxnerf_grid"
# what only models.py and the sampler modules may say: pass names and the flat sampler keys
PASS_WORDS = re.compile(r"\b(coarse|fine|num_coarse|num_fine|fine_union|proposal_samples|proposal_field|"
                        r"proposal_padding|mse_coarse|mse_fine|final_pass)\b", re.IGNORECASE)
# outside the package (benchmarks/, experiments/): no code reading a pass or a flat key of a config
PASS_READS = re.compile(r"\[[\"'](coarse|fine|proposals)[\"']\]|\.(num_coarse|num_fine|fine_union|hierarchical|"
                        r"proposal_samples|proposal_field|proposal_padding)\b|final_pass|fine_field_config|"
                        r"coarse_field_config|mse_coarse|mse_fine")


def offenders(paths, pattern) -> list[str]:
    return [f"{p.relative_to(ROOT)}:{n}: {line.strip()}" for p in paths
            for n, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]


# The synthetic scene generator is not the NeRF (its "fine" is ground texture), and its source
# is hashed into the experiments' scene and run keys (experiments.scenes.generator_digest), so
# it stays byte-identical to the source the committed results were made with.
GENERATOR = set((PACKAGE / "data" / "synthetic").glob("*.py"))


def test_no_module_outside_models_and_the_samplers_names_a_pass():
    inside = {PACKAGE / "nerf" / "models.py"} | set((PACKAGE / "nerf" / "samplers").glob("*.py")) | GENERATOR
    bad = offenders([p for p in sorted(PACKAGE.rglob("*.py")) if p not in inside], PASS_WORDS)
    assert not bad, "\n".join(bad)
    assert offenders([PACKAGE / "nerf" / "models.py"], PASS_WORDS)  # the pattern does find the words where they live


def test_benchmarks_and_experiments_read_no_pass_or_flat_sampler_key():
    paths = sorted((ROOT / "benchmarks").glob("*.py")) + sorted((ROOT / "experiments").glob("*.py"))
    bad = offenders(paths, PASS_READS)
    assert not bad, "\n".join(bad)


def test_the_words_test_sees_what_it_should():
    assert PASS_WORDS.search('params["fine"]') and PASS_WORDS.search("cfg.num_coarse")
    assert not PASS_WORDS.search("define refine finer coarsely")
    assert PASS_READS.search('out["coarse"]') and PASS_READS.search("m.proposal_samples")
    assert not PASS_READS.search('"coarse + fine as in the settings"')


def test_the_sampler_is_a_tagged_choice_with_its_own_keys():
    cfg = train.make_config("ours", {"model": {"sampler": {"kind": "proposal", "samples": [64, 32], "main_samples": 16,
                                                           "field": {"density_bias": -2.0}}}})
    s = cfg.model.sampler
    assert isinstance(s, proposal.Config) and s.samples == (64, 32) and s.main_samples == 16
    # a partial proposal field is laid over the proposal field's defaults, not FieldConfig's
    assert s.field.kind == "grid" and s.field.width == 16 and s.field.density_bias == -2.0
    assert config.to_dict(cfg)["model"]["sampler"] == {
        "kind": "proposal", "samples": [64, 32], "main_samples": 16, "field": config.to_dict(s.field), "padding": 0.01}
    assert config.from_dict(train.RunConfig, config.to_dict(cfg)) == cfg
    with pytest.raises(ConfigError, match=r"model\.sampler: unknown key\(s\) \['union'\] for kind 'proposal'"):
        train.make_config("ours", {"model": {"sampler": {"kind": "proposal", "union": True}}})
    with pytest.raises(ConfigError, match=r"model\.sampler\.kind = \"stratified\""):
        train.make_config("ours", {"model": {"sampler": {"kind": "stratified"}}})
    with pytest.raises(ConfigError, match=r"model\.sampler\.samples"):
        train.make_config("ours", {"model": {"sampler": {"samples": [8, 8, 8]}}})
    with pytest.raises(ConfigError, match=r"model\.sampler\.padding = 1\.5"):
        train.make_config("ours", {"model": {"sampler": {"kind": "proposal", "padding": 1.5}}})


def test_set_flags_switch_the_kind_and_reach_its_keys():
    sets = config.parse_sets(["model.sampler.kind=proposal", "model.sampler.main_samples=24",
                              "model.sampler.field.width=8"], train.RunConfig)
    assert sets == {"model": {"sampler": {"kind": "proposal", "main_samples": 24, "field": {"width": 8}}}}
    cfg = train.make_config("ours", sets)  # laid over the default hierarchical sampler: replaced, not merged
    assert cfg.model.sampler == proposal.Config(main_samples=24, field=config.from_dict(
        type(proposal.PROPOSAL_FIELD), {**config.to_dict(proposal.PROPOSAL_FIELD), "width": 8}))
    with pytest.raises(ConfigError, match="unknown key 'num_fine'"):
        config.parse_sets(["model.num_fine=8"], train.RunConfig)
    with pytest.raises(ConfigError, match=r"model\.sampler: unknown key\(s\) \['main_samples'\] for kind 'hier"):
        train.make_config("ours", config.parse_sets(["model.sampler.main_samples=8"], train.RunConfig))


# old flat model dicts and the tagged sampler they mean (written out by hand)
FLAT_CASES = [
    ({}, None),  # nothing flat: unchanged
    ({"num_coarse": 16, "num_fine": 8},
     {"kind": "hierarchical", "samples": [16, 8], "union": True, "shared_field": False}),
    ({"hierarchical": False, "num_coarse": 64, "num_fine": 0},
     {"kind": "hierarchical", "samples": [64], "union": True, "shared_field": False}),
    ({"num_coarse": 12, "num_fine": 8, "fine_union": False, "shared_field": True},
     {"kind": "hierarchical", "samples": [12, 8], "union": False, "shared_field": True}),
    ({"sampler": "proposal", "proposal_samples": [64], "num_fine": 32, "proposal_field": {"density_bias": -4.0}},
     {"kind": "proposal", "samples": [64], "main_samples": 32, "field": {"density_bias": -4.0}, "padding": 0.01}),
    ({"sampler": "proposal"}, {"kind": "proposal", "samples": [64], "main_samples": 48, "field": {}, "padding": 0.01}),
    # flat keys laid over a tagged sampler already in the dict (a later override layer)
    ({"sampler": {"kind": "proposal", "samples": [32], "main_samples": 16, "padding": 0.1}, "num_fine": 24},
     {"kind": "proposal", "samples": [32], "main_samples": 24, "field": {}, "padding": 0.1}),
]


@pytest.mark.parametrize("flat, tagged", FLAT_CASES)
def test_flat_sampler_keys_of_older_configs_are_read_into_the_tagged_choice(flat, tagged):
    model = {"warp": "log", **flat}
    got = legacy.upgrade_flat_model(model)
    assert got == ({"warp": "log", "sampler": tagged} if tagged is not None else model)
    assert model == {"warp": "log", **flat}  # the input is not changed


def test_an_older_run_config_json_loads_and_resolves_to_the_same_model(tmp_path):
    """A config.json as written before model.sampler (the flat keys, every default written out)
    loads through runs.load_run into the tagged sampler; old flat overrides give the same
    RunConfig as the tagged ones."""
    from jaxnerf_grid.train import runs

    new = train.make_config("ours", {"model": {"sampler": {"kind": "hierarchical", "samples": [16, 8],
                                                           "union": False}}})
    old = config.to_dict(new)
    old["model"].pop("sampler")
    old["model"].update({"sampler": "hierarchical", "num_coarse": 16, "num_fine": 8, "hierarchical": True,
                         "fine_union": False, "shared_field": False, "proposal_samples": [64],
                         "proposal_field": config.to_dict(proposal.PROPOSAL_FIELD), "proposal_padding": 0.01})
    (tmp_path / "config.json").write_text(json.dumps(old))
    cfg, _ = runs.load_run(tmp_path)
    assert cfg == new
    assert train.make_config("ours", {"model": {"num_coarse": 16, "num_fine": 8, "fine_union": False}}) == new
    # resuming it with the same config in the tagged form is the same run
    (tmp_path / runs.RUN_MARKER).write_text("")
    runs.check_existing(tmp_path, config.to_dict(new), overwrite=False)
    with pytest.raises(ConfigError, match="different config"):
        other = train.make_config("ours", {"model": {"sampler": {"samples": [16, 8]}}})
        runs.check_existing(tmp_path, config.to_dict(other), overwrite=False)


def test_set_flags_land_on_the_sampler_of_an_older_config_file(tmp_path):
    """An older --config file (flat keys) with --set model.sampler.* on top: the flag wins."""

    path = tmp_path / "old.json"
    path.write_text(json.dumps({"model": {"sampler": "proposal", "proposal_samples": [32], "num_fine": 16}}))
    ov = build.with_sets(build.read_config_file(str(path)), ["model.sampler.main_samples=24"])
    assert ov == {"model": {"sampler": {"kind": "proposal", "samples": [32], "main_samples": 24, "field": {},
                                        "padding": 0.01}}}
    assert train.make_config("ours", ov).model.sampler == proposal.Config(samples=(32,), main_samples=24)


def test_flat_keys_give_the_old_layout_for_run_keys():
    """What the experiments' run keys hash: the flat keys a tagged or flat override stands for,
    the proposal field with every field kind's keys (the older single field layout)."""
    field = {**config.to_dict(proposal.PROPOSAL_FIELD), "skip": 2, "pos_min_deg": 0, "pos_max_deg": 10}
    tagged = legacy.flat_keys({"sampler": {"kind": "proposal", "samples": [64], "main_samples": 32,
                                           "field": {"density_bias": -4.0}}})
    flat = legacy.flat_keys({"sampler": "proposal", "proposal_samples": [64], "num_fine": 32,
                             "proposal_field": {"density_bias": -4.0}})
    assert tagged == flat == {"sampler": "proposal", "num_coarse": 48, "num_fine": 32, "hierarchical": True,
                              "fine_union": True, "shared_field": False, "proposal_samples": [64],
                              "proposal_field": {**field, "density_bias": -4.0}, "proposal_padding": 0.01}


def test_samples_per_ray_describe_and_label():
    prop = models.ModelConfig(sampler=proposal.Config(samples=(64,), main_samples=32))
    assert (models.samples_per_ray(prop), models.describe(prop), models.label(prop)) == \
        (96, "proposal 64 -> 32 main", "64p+32")
    two = models.ModelConfig(sampler=hierarchical.Config(samples=(48, 32), union=False))
    assert (models.samples_per_ray(two), models.describe(two), models.label(two)) == \
        (80, "hierarchical 48 + 32", "48+32")
    one = models.ModelConfig(sampler=hierarchical.Config(samples=(64,)))
    assert (models.samples_per_ray(one), models.describe(one), models.label(one)) == (64, "one pass of 64", "64")
    # field evaluations per ray: the union pass evaluates the first pass's samples again
    union = models.ModelConfig(sampler=hierarchical.Config(samples=(48, 32)))
    assert [n for n, _ in models.field_evaluations(union)] == [48, 80]
    assert models.field_evaluations(prop) == [(64, prop.sampler.field), (32, prop.field)]


def test_merge_replaces_only_a_tagged_union_of_another_kind():
    base = {"sampler": {"kind": "proposal", "samples": [64], "main_samples": 32},
            "field": {"kind": "grid", "view_depth": 2, "width": 64}}
    out = config.merge(base, {"sampler": {"kind": "hierarchical", "samples": [8, 8]},
                              "field": {"kind": "mlp", "width": 32}})
    assert out["sampler"] == {"kind": "hierarchical", "samples": [8, 8]}  # another kind: replaced
    assert out["field"] == {"kind": "mlp", "width": 32}  # the field is a tagged choice too
    assert config.merge(base, {"sampler": {"samples": [16]}})["sampler"] == \
        {"kind": "proposal", "samples": [16], "main_samples": 32}  # same kind: merged
    assert config.merge(base, {"field": {"width": 32}})["field"] == {"kind": "grid", "view_depth": 2, "width": 32}
