"""config.merge and config.resolve: the one dict merge and the one place a dataset settles a run config."""

import dataclasses
from types import SimpleNamespace

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.train import loop as train


def test_merge_recurses_and_leaves_its_inputs_alone():
    base = {"model": {"field": {"width": 64, "depth": 4}, "near": None}, "train": {"lr_init": 1e-3}}
    extra = {"model": {"field": {"width": 32}}, "train": 5}
    out = config_lib.merge(base, extra)
    assert out == {"model": {"field": {"width": 32, "depth": 4}, "near": None}, "train": 5}
    assert base["model"]["field"]["width"] == 64 and base["train"] == {"lr_init": 1e-3}


def test_resolve_fills_num_images_and_bounds_from_the_dataset():
    ds = SimpleNamespace(num_frames=7, near=0.5, far=40.0)
    cfg = train.make_config("nerfw")
    assert cfg.model.num_images == 0 and cfg.model.near is None
    full = config_lib.resolve(cfg, ds)
    assert full.model.num_images == 7 and (full.model.near, full.model.far) == (0.5, 40.0)
    stored = config_lib.resolve(cfg, ds, bounds=False)      # what a run's config.json keeps
    assert stored.model.num_images == 7 and stored.model.near is None and stored.model.far is None
    given = train.make_config("ours", {"model": {"near": 1.0, "num_images": 9}})
    settled = config_lib.resolve(given, ds)
    assert settled.model.num_images == 9 and (settled.model.near, settled.model.far) == (1.0, 40.0)
    assert config_lib.near_far(given.model, ds) == (1.0, 40.0)
    # the one train key settled on the dataset: strict re-admission, false where it cannot act
    # (train.robust off here); with dpt+robust on where no `mask` verdict says the masks are out of
    # their domain (this dataset has no meta at all)
    assert cfg.train.robust.strict_readmit is None
    settled = dataclasses.replace(cfg.train, robust=dataclasses.replace(cfg.train.robust, strict_readmit=False))
    assert stored.train == settled == full.train
    mixed = train.make_config("ours", {"train": {"robust": "dpt+robust"}})
    assert config_lib.resolve(mixed, ds).train.robust.strict_readmit is True
    robust = train.make_config("ours", {"train": {"robust": "robust"}})
    assert config_lib.resolve(robust, ds).train.robust.strict_readmit is False


def test_run_config_holds_the_data_path_and_the_compiled_step_ignores_it():
    """config.json is `to_dict` of the RunConfig, the data path included (docs/ARCHITECTURE.md);
    two runs of one model on two dataset folders share one compiled step."""
    import dataclasses

    from jaxnerf_grid.train import runs

    a = dataclasses.replace(train.RunConfig(), data="/surveys/a")
    b = dataclasses.replace(train.RunConfig(), data="/surveys/b")
    written = runs.run_config_dict(a)
    assert list(written) == ["data", "model", "train"] and written["data"] == "/surveys/a"
    assert config_lib.from_dict(train.RunConfig, written) == a
    assert runs.run_config_dict(a, "/elsewhere")["data"] == "/elsewhere"
    assert train.make_train_step(a, 1) is train.make_train_step(b, 1)
    assert train.make_train_step(a, 1) is not train.make_train_step(
        dataclasses.replace(a, train=dataclasses.replace(a.train, seed=a.train.seed + 1)), 1)
