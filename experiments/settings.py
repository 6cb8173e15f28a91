"""What the experiments run with and where they write: scene sizes, training settings, paths.

Settings come in three sizes:
  * "quick": CI's smoke setting: the paper's MLP setting (recipe `ours-paper-mlp`) shrunk to an
    MLP 3x64 with 16 + 16 samples, 200 steps, 80x60 scenes; no run resolves the tower;
  * "standard": the paper's tables on the 2-core CPU. Every method trains the recipe that
    resolves the tower (recipe `ours`, the demo's) with the same steps, rays and samples per
    ray; the methods differ only in what defines them (contraction and warp, masks, NeRF-W's
    embeddings; `models.method_defaults`), and a run without contraction trains in NeRF's
    bounded space (`recipes.BOUNDED_SPACE`, as the `nerf` / `nerfw` recipes do). 1200 steps x
    1024 rays on the demo's 160x120 scenes: ours resolves the tower there (docs/GRID.md);
  * "full": 3 seeds, larger scenes and more steps of the MLP, for a GPU machine.
A table changes only what it varies on top of these (`runner.run_condition`'s overrides).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from jaxnerf_grid.config import recipes
from jaxnerf_grid.nerf.samplers.legacy import flat_model

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = Path(__file__).resolve().parent
RESULTS = EXPERIMENTS / "results"
BENCH_RESULTS = ROOT / "benchmarks" / "results"
CACHE = EXPERIMENTS / ".cache"


# The experiments record their settings, and hash their run keys, with the sampler in the flat
# keys it had before `model.sampler` became a tagged choice (samplers/legacy.py), in this order,
# so the committed results files keep their runs.
FLAT_KEY_ORDER = ("sampler", "proposal_samples", "num_coarse", "num_fine", "hierarchical", "fine_union",
                  "shared_field", "contract_radius", "encoding_scale", "field", "proposal_field", "near", "far",
                  "opaque_far")


def _without_steps(recipe: str) -> dict:
    """A recipe's overrides without its step count (each setting has its own), its sampler in
    the flat keys (FLAT_KEY_ORDER)."""
    out = recipes.overrides(recipe)
    out["train"].pop("max_steps", None)
    model = flat_model(out["model"])
    rank = {k: i for i, k in enumerate(FLAT_KEY_ORDER)}
    out["model"] = dict(sorted(model.items(), key=lambda kv: rank.get(kv[0], len(rank))))
    return out


def _paper_mlp(changes: dict) -> dict:
    """The `ours-paper-mlp` recipe's settings (its sampler keys are RunConfig's defaults, left
    out, so the recorded settings list only the changes) with `changes` on top."""
    return json.loads(json.dumps({**recipes.SETTINGS["ours-paper-mlp"], **changes}))


# NeRF's bounded space (recipes.BOUNDED_SPACE): the far plane and the grid's half width
NERF_FAR = recipes.BOUNDED_SPACE["far"]
NERF_GRID_HALF_WIDTH = recipes.BOUNDED_SPACE["encoding_scale"]


# Scene sizes: (width, height, num_train, num_test, supersample) per preset and setting.
SCENE_SIZES = {
    "quick": {"tower-small": (80, 60, 20, 3, 1), "ttpla-like": (96, 54, 20, 3, 1), "plad-like": (84, 56, 20, 3, 1)},
    "standard": {"tower-small": (160, 120, 40, 8, 2), "ttpla-like": (192, 108, 40, 8, 2),
                 "plad-like": (180, 120, 40, 8, 2)},
    "full": {"tower-small": (160, 120, 40, 8, 2), "ttpla-like": (320, 180, 60, 8, 2),
             "plad-like": (300, 200, 60, 8, 2)},
}


# Model / optimiser settings shared by every table (a method's own flags come on top): the
# recipe each setting starts from ("recipe") and what the setting changes in it ("overrides").
TRAIN_SETTINGS = {
    "quick": {"recipe": "ours-paper-mlp", "steps": 200, "seeds": 1, "distractor_views": 2, "overrides": _paper_mlp({
        "model": {"field": {"depth": 3, "width": 64, "skip": 0, "pos_max_deg": 7, "dir_max_deg": 2,
                            "view_width": 32},
                  "num_coarse": 16, "num_fine": 16},
        "train": {"batch_rays": 256, "lr_init": 4e-3, "lr_final": 3e-4, "warmup": 20, "checkpoint_every": 100,
                  "log_every": 20, "chunk": 4096, "appearance_steps": 20}})},
    "standard": {"recipe": "ours", "steps": 1200, "seeds": 3, "distractor_views": 4, "cloud_views": 16,
                 "overrides": _without_steps("ours")},
    "full": {"recipe": "ours-paper-mlp", "steps": 5000, "seeds": 3, "distractor_views": 4, "overrides": _paper_mlp({
        "model": {"field": {"depth": 6, "width": 128, "skip": 3, "pos_max_deg": 10, "dir_max_deg": 4,
                            "view_width": 64},
                  "num_coarse": 48, "num_fine": 48},
        "train": {"batch_rays": 2048, "lr_init": 2e-3, "lr_final": 5e-5, "warmup": 200, "checkpoint_every": 1000,
                  "log_every": 50, "chunk": 8192}})},
}


def space_overrides(setting: str, method: str, overrides: dict | None = None) -> dict:
    """The bounded space of a run without contraction. At `standard` the setting is the `ours`
    recipe (near 1, far 1000, contracted); a run without contraction (NeRF, NeRF-W, Table 2's
    rows without it) keeps its field, sampler, samples, steps and rays, in NeRF's bounded space
    instead (`recipes.BOUNDED_SPACE`: far NERF_FAR, the grid over +-NERF_GRID_HALF_WIDTH), as
    the `nerf` and `nerfw` recipes do. `overrides`: the condition's own."""
    from jaxnerf_grid.nerf import models

    if setting != "standard":
        return {}
    own = (overrides or {}).get("model", {})
    if own.get("use_contraction", models.method_defaults(method).get("use_contraction", False)):
        return {}
    return {"model": dict(recipes.BOUNDED_SPACE)}


def results_folder(root: Path, setting: str) -> Path:
    """Where a setting's results go by default: `root` for quick (CI's smoke setting, whose files
    came first), root/<setting>/ for the others, so a table at one setting never overwrites another's."""
    return Path(root) if setting == "quick" else Path(root) / setting


def portable(obj):
    """`obj` (JSON-able) with every string path inside the repository made relative to its root,
    so committed results name no machine's folders."""
    if isinstance(obj, dict):
        return {k: portable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [portable(v) for v in obj]
    if isinstance(obj, str):
        return obj.replace(str(ROOT) + os.sep, "")
    return obj
