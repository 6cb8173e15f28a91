"""NeRF's hierarchical sampler: a first pass stratified in s, a second pass resampled from it.

First pass: `samples[0]` bins stratified in s (uniform in s, jittered when training), mapped to
t through the ray's warp, evaluated by a plain static field. Second pass (when `samples` has a
second count): `samples[1]` new samples drawn in *s* from the first pass's weights
(sampling.resample_pdf), so the resampling happens in s-space and maps to t via the warp.
`union=True` (NeRF's choice): the second pass composites over the sorted union of the first
pass's bin midpoints and the new samples, with bin edges at midpoints between them and 0 / 1 at
the ends (samples[0] + samples[1] bins); `union=False`: samples[1] + 1 resampled values are the
bin edges (mip-NeRF). `shared_field`: one field for both passes (mip-NeRF) instead of two
(NeRF). The second pass's field makes the picture and carries NeRF-W's embeddings.

Parameters (kept as in earlier runs so their checkpoints load): {"coarse": first field,
["fine": second field (two passes, not shared)]}.
"""

from __future__ import annotations

import dataclasses
import typing

import jax

from jaxnerf_grid.config import schema as config
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.nerf.samplers import s_space as sampling
from jaxnerf_grid.nerf.samplers.passes import Passes

KIND = "hierarchical"


@dataclasses.dataclass(frozen=True)
class Config:
    """model.sampler = {"kind": "hierarchical", "samples": [48, 48], "union": true, "shared_field": false}.

    samples: [first pass] or [first pass, new samples of the second pass]; union, shared_field:
    see the module docstring.
    """

    kind: str = KIND
    samples: tuple[int, ...] = (48, 48)
    union: bool = True
    shared_field: bool = False

    RANGES: typing.ClassVar[dict] = {"samples": config.AT_LEAST_ONE}


def validate(cfg: Config, embeddings: bool) -> None:
    """Rules between the fields; embeddings: the model has NeRF-W embeddings."""
    if len(cfg.samples) not in (1, 2):
        raise ConfigError(f"model.sampler.samples = {list(cfg.samples)}: give one count (one pass) or two "
                          "(first pass, new samples of the second pass)")
    if embeddings and cfg.shared_field:
        raise ConfigError("model.sampler.shared_field cannot be combined with NeRF-W embeddings")
    if embeddings and len(cfg.samples) < 2:
        raise ConfigError("model.sampler.samples: NeRF-W embeddings live in the second pass's field; give two counts")


def init(k_first, k_main, cfg: Config, init_field) -> dict:
    """The sampler's fields: {"coarse": [, "fine"]} (see the module docstring)."""
    params = {"coarse": init_field(k_first, False)}
    if len(cfg.samples) == 2 and not cfg.shared_field:
        params["fine"] = init_field(k_main, True)
    return params


def main_params(params: dict, cfg: Config) -> dict:
    """The parameters of the field that makes the picture (the last pass's)."""
    return params["fine"] if "fine" in params else params["coarse"]


def render(params: dict, cfg: Config, passes: Passes, key) -> dict:
    """{"levels": [first pass, (second pass)], "final": the last pass}; every level is a whole
    pass (Passes.shade's dict, with colour). key: PRNG key or None (deterministic: bin centres)."""
    k_first, k_second = (None, None) if key is None else jax.random.split(key)
    s_first = sampling.stratified_s(k_first, passes.batch_shape, cfg.samples[0], passes.single_jitter)
    first = passes.shade(params["coarse"], s_first, False)
    if len(cfg.samples) == 1:
        return {"levels": [first], "final": first}
    weights = first["weights"]
    if cfg.union:
        s_new = sampling.resample_pdf(k_second, s_first, weights, cfg.samples[1], passes.single_jitter)
        s_mid = 0.5 * (s_first[..., 1:] + s_first[..., :-1])
        s_points = sampling.merge_edges(s_mid, s_new)
        s_second = sampling.intervals_from_samples(s_points, 0.0, 1.0)
    else:
        s_second = sampling.resample_pdf(k_second, s_first, weights, cfg.samples[1] + 1, passes.single_jitter)
    s_second = jax.lax.stop_gradient(s_second)
    second = passes.shade(main_params(params, cfg), s_second, True)
    return {"levels": [first, second], "final": second}


def samples_per_ray(cfg: Config) -> int:
    """Samples drawn per ray over both passes (NeRF's N_c + N_f)."""
    return sum(cfg.samples)


def field_evaluations(cfg: Config, model_field) -> list:
    """[(samples, field config)] of each pass's field evaluations per ray."""
    if len(cfg.samples) == 1:
        return [(cfg.samples[0], model_field)]
    second = sum(cfg.samples) if cfg.union else cfg.samples[1]
    return [(cfg.samples[0], model_field), (second, model_field)]


def describe(cfg: Config) -> str:
    """One line, e.g. "hierarchical 48 + 48 (union)" or "one pass of 64"."""
    if len(cfg.samples) == 1:
        return f"one pass of {cfg.samples[0]}"
    notes = [n for n, on in (("union", cfg.union), ("shared field", cfg.shared_field)) if on]
    return f"hierarchical {cfg.samples[0]} + {cfg.samples[1]}" + (f" ({', '.join(notes)})" if notes else "")


def label(cfg: Config) -> str:
    """A compact label, e.g. "48+48" or "64"."""
    return "+".join(str(n) for n in cfg.samples)
