"""The samplers: where along each ray which field is evaluated. One module per sampler.

`model.sampler` is a tagged choice (config.py, "Tagged unions"): a `Config` of one sampler
module, chosen by its `kind`, each with only its own fields:

  {"kind": "hierarchical", "samples": [48, 48], "union": true, "shared_field": false}
  {"kind": "proposal", "samples": [64], "main_samples": 32, "field": {...}, "padding": 0.01}

Each module has the same functions, which models.py calls through `MODULES[cfg.kind]`:
`Config`, `validate(cfg, embeddings)`, `init(k_first, k_main, cfg, init_field)` (init_field:
(PRNG key, main) -> a NeRF field's parameters, main as in `passes.Passes.shade`),
`main_params(params, cfg)`, `render(params, cfg, passes, key) -> {"levels", "final"}`,
`samples_per_ray(cfg)`, `field_evaluations(cfg, model_field)`, `describe(cfg)`, `label(cfg)`.
A new sampler is one new module here, added to MODULES and to `SamplerConfig`.
The flat sampler keys of older configs are read by `legacy.upgrade_flat_model`.
"""

from __future__ import annotations

from jaxnerf_grid.nerf.samplers import hierarchical, proposal

MODULES = {hierarchical.KIND: hierarchical, proposal.KIND: proposal}

SamplerConfig = hierarchical.Config | proposal.Config


def module(cfg: SamplerConfig):
    """The module of a sampler config."""
    return MODULES[cfg.kind]
