"""Named training recipes: what `ours`, `nerf`, ... mean, in one place.

A recipe is a method (`models.method_defaults`: what defines ours / NeRF / NeRF-W) and the
settings it lays over `RunConfig()`'s defaults, so `train.make_config(recipe.method,
overrides(name))` is a complete, checked config. `jaxnerf-grid train --recipe NAME` (and
`--method M` alone, which is `--recipe M`), `demo`, the experiments and the benchmarks start
from these; `jaxnerf-grid recipes` prints them one line each (docs/RECIPES.md).

  ours            the recipe that resolves the tower (the experiments'; docs/GRID.md)
  ours-paper-mlp  the paper's MLP setting: `RunConfig()`'s defaults for ours
  nerf, nerfw     the baselines as the tables compare them at `--standard`: ours' field,
                  sampler, steps and rays in NeRF's bounded space (BOUNDED_SPACE)
  ours-fast       ours with a smaller proposal field and 1600 steps (the demo's until ours-lean)
  ours-lean       the demo's: ours-fast with a leaner main field

Every sampler key of every recipe sits in SAMPLERS (one entry per recipe), apart from the
other settings (SETTINGS), so the sampler can change shape in one place.
"""

from __future__ import annotations

import dataclasses
import json

from jaxnerf_grid.config import run_config
from jaxnerf_grid.config.schema import ConfigError, merge

# Without contraction a grid field must cover every sample point: NeRF and NeRF-W sample
# linearly in t from the near bound to a far plane at 40 units (800 m, past the tree line and
# buildings; the sky is the opaque far bin) and their grid spans +-44 units, the far plane plus
# the farthest camera (3.7 units). That is NeRF's bounded parameterisation; contraction is what
# ours has and they lack. The experiments lay this on every run without contraction.
BOUNDED_SPACE = {"far": 40.0, "encoding_scale": 44.0}

# ------------------------------------------------------------------ the sampler of each recipe
# Every recipe's `model.sampler` (a tagged choice: samplers/, docs/ARCHITECTURE.md "The model contract").
_PROPOSAL_64_32 = {"sampler": {"kind": "proposal", "samples": [64], "main_samples": 32,
                               "field": {"density_bias": -4.0}}}
# ours' sampler with a proposal field sized down: 3 levels up to 64 cells, 2^15 rows per
# level, below nerfacto's smallest proposal network (5 levels to 128)
_SMALL_PROPOSAL = merge(_PROPOSAL_64_32, {"sampler": {"field": {
    "grid": {"num_levels": 3, "max_resolution": 64, "log2_table_size": 15}}}})
SAMPLERS = {
    # one density-only proposal round of 64 samples stratified in s, then 32 samples of the main field
    "ours": _PROPOSAL_64_32,
    "ours-fast": _SMALL_PROPOSAL,
    # ours-fast's with 24 main samples instead of 32; the demo's (demo.DEMO_RECIPE)
    "ours-lean": merge(_SMALL_PROPOSAL, {"sampler": {"main_samples": 24}}),
    # NeRF's two passes, 48 + 48 samples, the second over the union, two fields
    "ours-paper-mlp": {"sampler": {"kind": "hierarchical", "samples": [48, 48], "union": True,
                                   "shared_field": False}},
    "nerf": _PROPOSAL_64_32,
    "nerfw": _PROPOSAL_64_32,
}
# ------------------------------------------------------------------ end of the samplers

# The demo's CPU recipe without its sampler (docs/GRID.md): a hash-grid field on the contracted
# coordinates, the interlevel and distortion losses (in s), an opaque far bin at 1000 units so
# the sky sits at infinity, Instant-NGP's Adam settings. Each choice was measured at 1000 steps
# on tower-small (docs/GRID.md, "How the recipe was chosen").
_GRID = {
    "model": {"contract_radius": 2.0,
              "field": {"kind": "grid", "depth": 1, "width": 64, "view_depth": 2, "view_width": 64,
                        "dir_max_deg": 3, "density_activation": "exp", "density_bias": -4.0,
                        "grid": {"num_levels": 12, "features_per_level": 2, "log2_table_size": 17,
                                 "min_resolution": 16, "max_resolution": 1024}},
              # The three distances below are used as they are only for a dataset that records no
              # `scene_bounds` (the synthetic tower); a dataset from `jaxnerf-grid poses` records
              # them from its points and cameras and they replace these (data/bounds.py,
              # docs/BOUNDS.md; the user's --set flags still win).
              # near: the drone orbits 45-70 m (2.2-3.5 units) from the tower; with the dataset's
              # near of 0.5 the disparity warp puts 3/4 of the samples in the empty first 2 units.
              # Rays start at 1 unit (20 m): birds nearer than that are distractors, masked anyway.
              # The data rule (0.9 x the nearest camera's distance to the unit sphere) gives 1.05
              # on tower-small's cameras (its low pass, 2.16 units from the centre).
              # far: 1000 units (20 km), an opaque bin: the sky, at the far sphere. Holds for any
              # capture normalised so the region of interest is the unit ball: with contract_radius
              # R = 2 a point 1000 units out is contracted to within 0.05 % of the outer radius R, so
              # farther changes nothing (data.bounds.far_for_radius).
              # contract_radius: not a distance in the scene but the outer radius of the contracted
              # space (coords.contract keeps the unit ball, maps the rest into the shell 1..R); 2
              # gives the background a shell as thick as the region of interest's radius, for any
              # capture normalised that way.
              "near": 1.0, "far": 1000.0, "opaque_far": True},
    "train": {"batch_rays": 1024, "max_steps": 2400, "lr_init": 2e-2, "lr_final": 2e-3, "warmup": 50,
              "adam_eps": 1e-15, "adam_b2": 0.99, "max_grad_norm": 0.0, "distortion_loss_weight": 0.002,
              "checkpoint_every": 300, "log_every": 50, "chunk": 4096},
}

_GRID_1600 = merge(_GRID, {"train": {"max_steps": 1600}})

# Every setting of each recipe but its sampler, over RunConfig()'s defaults.
SETTINGS = {
    "ours": _GRID,
    # ours with a smaller proposal field: 1600 steps reach ours' figures at 2400 on tower-small
    # (docs/GRID.md)
    "ours-fast": _GRID_1600,
    # the demo's recipe: ours-fast with a leaner main field, 8 hash
    # levels (16 to 1024 cells, as ours' 12) of at most 2^16 rows and one colour layer: each step
    # about 1.8x faster, the demo's figures within 0.2 dB (docs/GRID.md "The demo's recipe")
    "ours-lean": merge(_GRID_1600, {"model": {"field": {"view_depth": 1,
                                                        "grid": {"num_levels": 8, "log2_table_size": 16}}}}),
    "ours-paper-mlp": {},
    "nerf": merge(_GRID, {"model": BOUNDED_SPACE}),
    "nerfw": merge(_GRID, {"model": BOUNDED_SPACE}),
}


@dataclasses.dataclass(frozen=True)
class Recipe:
    """name; method: ours | nerf | nerfw (its defining flags: `models.method_defaults`);
    description: one line."""

    name: str
    method: str
    description: str


RECIPES = {r.name: r for r in (
    Recipe("ours", "ours", "the tower recipe (the experiments'): hash grid on contracted space, proposal sampling "
                           "64 -> 32 in disparity, opaque far bin at 1000 units, masked loss; 2400 steps x 1024 rays"),
    Recipe("ours-paper-mlp", "ours", "the paper's MLP setting: MLP 4x128 on positional encoding, two passes "
                                     "48 + 48 samples, contraction, disparity warp, masked loss; "
                                     "2000 steps x 1024 rays"),
    Recipe("nerf", "nerf", "NeRF as the tables compare it: ours' grid, sampler, steps and rays without "
                           "contraction (linear t to a far plane at 40 units, grid over +-44), no masks"),
    Recipe("nerfw", "nerfw", "NeRF-W: the nerf recipe plus appearance and transient embeddings "
                             "(the appearance fitted on the left half of each test view)"),
    Recipe("ours-fast", "ours", "ours with a smaller proposal field (3 levels up to 64 cells, 2^15 rows) and "
                                "1600 steps x 1024 rays (the demo's before ours-lean)"),
    Recipe("ours-lean", "ours", "the demo's: ours-fast with a leaner main field (24 samples a ray, "
                                "8 hash levels of 2^16 rows, one colour layer); 1600 steps x 1024 rays"),
)}

# The model keys in this order when a recipe is written out (the sampler first, then the space,
# the fields and the bounds); keys not named keep their order after these.
KEY_ORDER = ("sampler", "contract_radius", "encoding_scale", "field", "near", "far", "opaque_far")


def names() -> list[str]:
    """The recipes' names, in the order they are listed."""
    return list(RECIPES)


def get(name: str) -> Recipe:
    """The recipe called `name`; an unknown name is a ConfigError listing the known ones."""
    if name not in RECIPES:
        raise ConfigError(f"recipe {name!r}: unknown recipe; choose from {', '.join(RECIPES)}")
    return RECIPES[name]


def _in_order(model: dict) -> dict:
    """`model` with its keys in KEY_ORDER's order (the others after, as they came)."""
    rank = {k: i for i, k in enumerate(KEY_ORDER)}
    return dict(sorted(model.items(), key=lambda kv: rank.get(kv[0], len(rank))))


def overrides(name: str) -> dict:
    """The recipe's settings over RunConfig()'s defaults, sampler included, as a fresh nested
    dict {"model": {...}, "train": {...}} (the caller may change it)."""
    get(name)
    out = merge(SETTINGS[name], {"model": SAMPLERS[name]})
    out["model"] = _in_order(out["model"])
    return json.loads(json.dumps(out))


def resolve(recipe: str | None, method: str | None) -> tuple[str, str]:
    """(recipe name, method) of `train --recipe R --method M`: R's own method when M is None;
    with only M, the recipe named M; with both, R's settings with M's defining flags (e.g.
    `--recipe ours-paper-mlp --method nerf`: the paper's MLP setting for NeRF). Neither: ours."""
    if recipe is None:
        recipe = method or "ours"
    r = get(recipe)
    return r.name, method or r.method


def make_config(name: str, extra: dict | None = None, method: str | None = None):
    """The checked RunConfig of recipe `name` (its method, or `method`) with `extra` on top."""
    name, method = resolve(name, method)
    return run_config.make_config(method, merge(overrides(name), extra or {}))


def listing() -> list[str]:
    """One line per recipe: name, method, description."""
    width = max(len(n) for n in RECIPES)
    return [f"{r.name:{width}s}  {'(' + r.method + ')':7s}  {r.description}" for r in RECIPES.values()]
