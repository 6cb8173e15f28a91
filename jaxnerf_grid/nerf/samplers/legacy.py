"""Reading the flat sampler keys of older configs (runs' config.json, --config files, recipes).

Before the sampler became a tagged choice (`model.sampler = {"kind": ...}`), ModelConfig held
it as flat keys, with these defaults:

  sampler "hierarchical" | "proposal"     num_coarse 48, num_fine 48, hierarchical true,
  fine_union true, shared_field false     proposal_samples [64], proposal_field {...},
  proposal_padding 0.01

They map to the tagged choice as

  hierarchical: {"kind": "hierarchical", "samples": [num_coarse, num_fine] (or [num_coarse]
                 when hierarchical is false), "union": fine_union, "shared_field": shared_field}
  proposal:     {"kind": "proposal", "samples": proposal_samples, "main_samples": num_fine,
                 "field": proposal_field, "padding": proposal_padding}

`upgrade_flat_model` is applied by `config.from_dict` to every model dict (ModelConfig's
`upgrade_dict`), after all override layers are merged, so a flat key anywhere still means
what it meant: the flat keys are laid over the sampler the dict already holds (a "kind" dict,
read back as flat keys, or a "sampler" string), the old defaults fill in what neither gives.
A dict without flat keys (and with no "sampler" string) is returned unchanged.

Within one dict the flat keys win over a tagged sampler. So the forms are best not mixed across
override layers merged before they are read: after `config.merge` a flat "sampler" string
replaces a tagged dict below it (losing, e.g., its proposal field), and flat keys override a
tagged dict even where it came from a later layer. `train.make_config` reads its overrides and
`config.build.read_config_file` a --config file through `upgrade_flat_model` before laying anything over
them (so `--set model.sampler...` lands on an older file's sampler); layers kept in the flat
form (the experiments' settings, whose run keys hash the flat layout) put a tagged recipe into
that form first with `flat_model(model)`.

`flat_keys(model_overrides)` goes the other way for what identifies a run: the flat keys (as an
older full config.json held them) that a model override dict, in either form, stands for on
top of the old defaults; the experiments' run keys hash them, so a run keeps its key and the
committed results files keep finding their runs.
"""

from __future__ import annotations

from typing import Any

from jaxnerf_grid.config import schema as config
from jaxnerf_grid.nerf.fields.base import old_layout
from jaxnerf_grid.nerf.samplers import proposal

TAGGED_KEYS = {"hierarchical": ("kind", "samples", "union", "shared_field"),
               "proposal": ("kind", "samples", "main_samples", "field", "padding")}
FLAT_KEYS = ("num_coarse", "num_fine", "hierarchical", "fine_union", "shared_field", "proposal_samples",
             "proposal_field", "proposal_padding")
OLD_DEFAULTS = {"sampler": "hierarchical", "num_coarse": 48, "num_fine": 48, "hierarchical": True,
                "fine_union": True, "shared_field": False, "proposal_samples": [64], "proposal_field": {},
                "proposal_padding": 0.01}


def _as_flat(sampler: dict) -> dict:
    """A tagged sampler dict as the flat keys it stands for (only the keys it gives)."""
    kind = sampler.get("kind")
    flat = {"sampler": kind} if kind is not None else {}
    samples = sampler.get("samples")
    if kind == "hierarchical":
        if isinstance(samples, (list, tuple)) and samples:
            flat["num_coarse"] = samples[0]
            flat["hierarchical"] = len(samples) > 1
            if len(samples) > 1:
                flat["num_fine"] = samples[1]
        names = {"union": "fine_union", "shared_field": "shared_field"}
    elif kind == "proposal":
        if samples is not None:
            flat["proposal_samples"] = samples
        names = {"main_samples": "num_fine", "field": "proposal_field", "padding": "proposal_padding"}
    else:
        names = {}
    flat.update({names[k]: v for k, v in sampler.items() if k in names})
    return flat


def _from_flat(flat: dict) -> dict:
    """The tagged sampler dict of a complete set of flat keys."""
    if flat["sampler"] == "proposal":
        return {"kind": "proposal", "samples": flat["proposal_samples"], "main_samples": flat["num_fine"],
                "field": flat["proposal_field"], "padding": flat["proposal_padding"]}
    if flat["sampler"] == "hierarchical":
        samples = [flat["num_coarse"], flat["num_fine"]] if flat["hierarchical"] else [flat["num_coarse"]]
        return {"kind": "hierarchical", "samples": samples, "union": flat["fine_union"],
                "shared_field": flat["shared_field"]}
    return {"kind": flat["sampler"]}  # an unknown sampler: config.from_dict names it


def flat_model(model: dict) -> dict:
    """A model override dict with its tagged sampler (if any) as the flat keys it gives."""
    if not isinstance(model.get("sampler"), dict):
        return model
    return {**{k: v for k, v in model.items() if k != "sampler"}, **_as_flat(model["sampler"])}


def flat_keys(model_overrides: dict) -> dict:
    """The flat sampler keys, complete, of a model override dict (flat or tagged, merged over
    the old defaults), as an older full config.json would hold them: every key of OLD_DEFAULTS,
    proposal_field as a full field dict of the older layout (every kind's keys, fields/base.py)."""
    flat: dict[str, Any] = dict(OLD_DEFAULTS, proposal_field=old_layout(config.to_dict(proposal.PROPOSAL_FIELD)))
    current = model_overrides.get("sampler")
    layers = [_as_flat(current) if isinstance(current, dict) else ({"sampler": current} if current else {}),
              {k: model_overrides[k] for k in FLAT_KEYS if k in model_overrides}]
    for layer in layers:
        for k, v in layer.items():
            flat[k] = config.merge(flat[k], v) if k == "proposal_field" and isinstance(v, dict) else v
    return flat


def upgrade_flat_model(model: dict) -> dict:
    """A model dict with the flat sampler keys (see the module docstring) in the tagged form;
    returned unchanged when it has none. Neither input is changed."""
    if not isinstance(model, dict):
        return model
    given = {k: model[k] for k in FLAT_KEYS if k in model}
    current = model.get("sampler")
    if not given and not isinstance(current, str):
        return model
    flat = dict(OLD_DEFAULTS)
    if isinstance(current, dict):
        flat.update(_as_flat(current))
    elif current is not None:
        flat["sampler"] = current
    flat.update(given)
    out = {k: v for k, v in model.items() if k not in FLAT_KEYS}
    out["sampler"] = _from_flat(flat)
    if isinstance(current, dict):  # keys that are not its kind's stay, for config.from_dict to name
        known = TAGGED_KEYS.get(str(current.get("kind")), ())
        out["sampler"].update({k: v for k, v in current.items() if k not in known})
    return out
