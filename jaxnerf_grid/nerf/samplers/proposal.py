"""mip-NeRF 360's proposal sampler, in s: density-only proposal fields, then one main pass.

Round 0 is stratified in s (uniform in disparity for "ours"), each later round resamples from
the previous round's weights; each round evaluates its own small density-only field
(fields.proposal, a hash grid). After the last round `main_samples` + 1 edges are resampled
(with the weight floor `padding`, relative to the mean, so no bin is unreachable) for the
main field, which makes the picture and runs once. The proposal levels render no colour: the
interlevel loss (losses.interlevel_ray_loss) teaches them to bound the main field's weights.

Parameters (kept as in earlier runs so their checkpoints load): {"proposal": [field per
round], "fine": the main field}.
"""

from __future__ import annotations

import dataclasses
import typing

import jax

from jaxnerf_grid.config import schema as config
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.nerf import fields
from jaxnerf_grid.nerf.samplers import s_space as sampling
from jaxnerf_grid.nerf.samplers.passes import Passes
from jaxnerf_grid.nerf.volume import alpha_weights

KIND = "proposal"

# The proposal field: a small density-only hash grid (nerfacto's sizes).
PROPOSAL_FIELD = fields.grid.Config(depth=1, width=16, density_activation="exp",
                                    grid=fields.HashConfig(num_levels=5, features_per_level=2, log2_table_size=17,
                                                           min_resolution=16, max_resolution=256))


@dataclasses.dataclass(frozen=True)
class Config:
    """model.sampler = {"kind": "proposal", "samples": [64], "main_samples": 32, "field": {...}, "padding": 0.01}.

    samples: samples of each proposal round; main_samples: the main field's samples;
    field: the proposal fields' config (kind "grid"); padding: the weight floor when resampling.
    """

    kind: str = KIND
    samples: tuple[int, ...] = (64,)
    main_samples: int = 32
    field: fields.grid.Config = PROPOSAL_FIELD
    padding: float = 0.01

    RANGES: typing.ClassVar[dict] = {"samples": config.AT_LEAST_ONE, "main_samples": config.AT_LEAST_ONE,
                                     "padding": config.FRACTION}


def validate(cfg: Config, embeddings: bool) -> None:
    """Rules between the fields (embeddings: the main field carries them, nothing to check)."""
    if not cfg.samples:
        raise ConfigError("model.sampler.samples: give at least one proposal round")
    try:
        fields.proposal.check(cfg.field)
    except ValueError as exc:
        raise ConfigError(f"model.sampler.field: {exc}") from None


def init(k_first, k_main, cfg: Config, init_field) -> dict:
    """{"proposal": [field per round], "fine": the main field}."""
    keys = jax.random.split(k_first, len(cfg.samples))
    return {"proposal": [fields.proposal.init(k, cfg.field) for k in keys], "fine": init_field(k_main, True)}


def main_params(params: dict, cfg: Config) -> dict:
    """The parameters of the field that makes the picture."""
    return params["fine"]


def rounds(params: dict, cfg: Config, passes: Passes, key) -> tuple:
    """The proposal rounds in s and the main field's edges.

    key: PRNG key or None (deterministic). Returns (levels: [{"s_edges": [..., n_k + 1],
    "weights": [..., n_k]}], s_main: [..., main_samples + 1]).
    """
    count = len(cfg.samples)
    keys = [None] * (count + 1) if key is None else list(jax.random.split(key, count + 1))
    out: list = []
    s_edges = sampling.stratified_s(keys[0], passes.batch_shape, cfg.samples[0], passes.single_jitter)
    for k in range(count):
        if k > 0:
            s_edges = sampling.resample_pdf(keys[k], s_edges, out[-1]["weights"], cfg.samples[k] + 1,
                                            passes.single_jitter, cfg.padding)
        t_edges = passes.s_to_t(s_edges)
        sigma = fields.proposal.density(params["proposal"][k], cfg.field, passes.points(t_edges))
        sigma = passes.far_bin(sigma)
        out.append({"s_edges": s_edges, "weights": alpha_weights(sigma, t_edges)})
    s_main = sampling.resample_pdf(keys[-1], s_edges, out[-1]["weights"], cfg.main_samples + 1, passes.single_jitter,
                                   cfg.padding)
    return out, jax.lax.stop_gradient(s_main)


def render(params: dict, cfg: Config, passes: Passes, key) -> dict:
    """{"levels": [proposal rounds ({"s_edges", "weights"}, no colour)..., the main pass],
    "final": the main pass (Passes.shade's dict)}."""
    k_prop = None if key is None else jax.random.fold_in(key, 1)
    levels, s_main = rounds(params, cfg, passes, k_prop)
    main = passes.shade(params["fine"], s_main, True)
    return {"levels": levels + [main], "final": main}


def samples_per_ray(cfg: Config) -> int:
    """Samples drawn per ray: every proposal round's plus the main field's."""
    return sum(cfg.samples) + cfg.main_samples


def field_evaluations(cfg: Config, model_field) -> list:
    """[(samples, field config)] of each pass's field evaluations per ray."""
    return [(sum(cfg.samples), cfg.field), (cfg.main_samples, model_field)]


def describe(cfg: Config) -> str:
    """One line, e.g. "proposal 64 -> 32 main"."""
    return f"proposal {' -> '.join(str(n) for n in cfg.samples)} -> {cfg.main_samples} main"


def label(cfg: Config) -> str:
    """A compact label, e.g. "64p+32"."""
    return "+".join(f"{n}p" for n in cfg.samples) + f"+{cfg.main_samples}"
