"""The methods as compositions of the core pure functions: "ours", "nerf", "nerfw".

One renderer, switched by independent flags of `ModelConfig` so every ablation flips one.
The sampler (`cfg.sampler`, a tagged choice: one module of jaxnerf_grid/nerf/samplers/) decides
where along each ray in s which field is evaluated; this module does the rest of a pass:

  a pass        s_edges (the sampler's) -> t_edges = s_to_t(s_edges) through the warp `warp`
                (Eq. 10-11); points at the t-midpoints of the bins: x = o + t_mid * d;
                z = coords.contract(x, R) when `use_contraction`, fed to the field as z / scale
                (scale = R by default, so the encoder sees |z / R| < 1; 1 without contraction)
                weights = render.alpha_weights(sigma, t_edges); render.composite(...)
  hierarchical  (samplers/hierarchical.py) NeRF's coarse pass stratified in s and a fine pass
                resampled in s from the coarse weights (over the union of both, or alone)
  proposal      (samplers/proposal.py) mip-NeRF 360's density-only proposal rounds in s, then
                one pass of the main field

The contract for everything outside models.py and the sampler modules (losses, views, evaluate,
report, export, benchmarks): `render_rays` returns {"levels": [...], "final": {...}} (see
`render_ray`), `main_field(params, cfg)` is the field that makes the picture, and
`samples_per_ray(cfg)` / `describe(cfg)` / `label(cfg)` say how a ray is sampled. Nothing
outside reads the parameters' keys or the pass names.

Methods (see `method_config`):
  ours  = contraction (R = contract_radius) + disparity warp + mask-weighted loss (train.py)
  nerf  = no contraction, warp "linear" between the dataset's near and far, masks ignored
  nerfw = nerf + per-image appearance embedding (`use_appearance`, NeRF-A) and/or a transient
          head with per-image transient embeddings (`use_transient`, NeRF-U); both = NeRF-W.
          As in NeRF-W, the coarse field is a plain static field; the main field (the fine
          pass's, or the proposal sampler's main field) carries the embeddings. The transient
          part is composited with the static one (shared transmittance) and predicts
          beta_hat = sum_i w_t,i beta_i + beta_min.

Background: the colour `background` (a constant grey level, default 0 = black) is added
behind the last bin with weight 1 - opacity. For "ours" the last bin ends at the dataset's far
bound (or `far`), which contraction maps to just inside the sphere of radius R, so the sky is
modelled as density near the far sphere; for "nerf" the far plane is the dataset's far.
"""

from __future__ import annotations

import dataclasses
import typing

import jax
import jax.numpy as jnp

from jaxnerf_grid.config import schema as config
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.nerf import coords, fields, samplers
from jaxnerf_grid.nerf import volume as render
from jaxnerf_grid.nerf.samplers import s_space as sampling
from jaxnerf_grid.nerf.samplers.legacy import upgrade_flat_model
from jaxnerf_grid.nerf.samplers.passes import Passes

METHODS = ("ours", "nerf", "nerfw")
SAMPLERS = tuple(samplers.MODULES)


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Everything that decides what a ray renders to.

    method: "ours" | "nerf" | "nerfw" (a label; the flags below decide the behaviour).
    field: the NeRF field (the main field gets the embedding sizes added for NeRF-W).
    use_contraction, contract_radius: dual-sphere contraction (Eq. 9) with far radius R.
    encoding_scale: points are encoded as z / encoding_scale; 0 = auto (R with contraction,
      1 without).
    warp: s-space warp "linear" | "disparity" | "log" | "piecewise" (s -> t along a ray).
    sampler: a tagged choice (jaxnerf_grid/nerf/samplers/): {"kind": "hierarchical", "samples":
      [48, 48], "union": true, "shared_field": false} (NeRF's coarse + fine passes) or
      {"kind": "proposal", "samples": [64], "main_samples": 32, "field": {...}, "padding": 0.01}
      (mip-NeRF 360: density-only proposal fields resample in s, the main field runs once).
      Older flat keys (num_coarse, num_fine, ...) are read by samplers.legacy.
    near, far: override the dataset's bounds (None: use the dataset's).
    background: grey level behind the last bin.
    opaque_far: make the last bin of every pass opaque (its density infinite), so a ray that
      reaches the far bound takes the colour of the field there: the sky is modelled at the far
      sphere instead of as a dome of haze near the cameras (multinerf's opaque background).
    use_appearance, appearance_dim; use_transient, transient_dim; beta_min, lambda_u: NeRF-W.
    num_images: size of the embedding tables (set from the dataset by the trainer).
    """

    method: str = "ours"
    field: fields.FieldConfig = fields.mlp.Config()
    use_contraction: bool = True
    contract_radius: float = 2.0
    encoding_scale: float = 0.0
    warp: str = "disparity"
    sampler: samplers.SamplerConfig = samplers.hierarchical.Config()
    near: float | None = None
    far: float | None = None
    background: float = 0.0
    opaque_far: bool = False
    single_jitter: bool = False
    use_appearance: bool = False
    appearance_dim: int = 48
    use_transient: bool = False
    transient_dim: int = 16
    beta_min: float = 0.1
    lambda_u: float = 0.01
    num_images: int = 0

    # allowed values, checked by config.validate (docs/RELIABILITY.md); `validate` below adds
    # the rules between fields (near < far, the sampler's sample counts, ...)
    RANGES: typing.ClassVar[dict] = {
        "contract_radius": config.POSITIVE, "encoding_scale": config.NONNEGATIVE,
        "near": config.POSITIVE, "far": config.POSITIVE,
        "background": config.UNIT, "appearance_dim": config.AT_LEAST_ONE, "transient_dim": config.AT_LEAST_ONE,
        "beta_min": config.NONNEGATIVE, "lambda_u": config.NONNEGATIVE, "num_images": config.NONNEGATIVE}

    # config.from_dict reads older model dicts (the flat sampler keys) through this
    upgrade_dict = staticmethod(upgrade_flat_model)


def method_defaults(method: str) -> dict:
    """The flag values that define a method, as a dict of ModelConfig fields."""
    if method == "ours":
        return {"method": "ours", "use_contraction": True, "warp": "disparity"}
    if method == "nerf":
        return {"method": "nerf", "use_contraction": False, "warp": "linear"}
    if method == "nerfw":
        return {"method": "nerfw", "use_contraction": False, "warp": "linear",
                "use_appearance": True, "use_transient": True}
    raise ConfigError(f"unknown method {method!r}; choose from {list(METHODS)}")


def validate(cfg: ModelConfig) -> None:
    if cfg.method not in METHODS:
        raise ConfigError(f"model.method: unknown method {cfg.method!r}; choose from {list(METHODS)}")
    if cfg.warp not in sampling.WARP_FUNCTIONS:
        raise ConfigError(f"model.warp: unknown warp {cfg.warp!r}; choose from {sorted(sampling.WARP_FUNCTIONS)}")
    kind = getattr(cfg.sampler, "kind", None)
    if kind not in samplers.MODULES or not isinstance(cfg.sampler, samplers.MODULES[kind].Config):
        raise ConfigError(f"model.sampler.kind: unknown sampler {kind!r}; choose from {list(SAMPLERS)}")
    if cfg.use_contraction and not cfg.contract_radius > 1.0:
        raise ConfigError(f"model.contract_radius must be > 1, got {cfg.contract_radius}")
    try:
        fields.check(cfg.field)
    except ValueError as exc:
        raise ConfigError(f"model.field: {exc}") from None
    embeddings = cfg.use_appearance or cfg.use_transient
    samplers.module(cfg.sampler).validate(cfg.sampler, embeddings)
    if embeddings and cfg.num_images < 1:
        raise ConfigError("model.num_images must be set (>= 1) for NeRF-W embeddings")
    if cfg.near is not None and cfg.far is not None and not 0 < cfg.near < cfg.far:
        raise ConfigError(f"model: need 0 < near < far, got near={cfg.near}, far={cfg.far}")


def field_config(cfg: ModelConfig, main: bool) -> fields.FieldConfig:
    """The NeRF field's config: main=True the field that makes the picture (with NeRF-W's
    embedding sizes), main=False a plain static field (the hierarchical sampler's coarse pass)."""
    if not main:
        return dataclasses.replace(cfg.field, appearance_dim=0, transient_dim=0)
    return dataclasses.replace(cfg.field,
                               appearance_dim=cfg.appearance_dim if cfg.use_appearance else 0,
                               transient_dim=cfg.transient_dim if cfg.use_transient else 0)


def main_field(params: dict, cfg: ModelConfig) -> tuple[dict, fields.FieldConfig]:
    """(parameters, config) of the field that makes the picture and holds the geometry (the
    fine pass's field, or the coarse one when it runs alone or is shared; the proposal
    sampler's main field; never a proposal field)."""
    return samplers.module(cfg.sampler).main_params(params, cfg.sampler), field_config(cfg, True)


def samples_per_ray(cfg: ModelConfig) -> int:
    """Samples drawn per ray over every pass (hierarchical: coarse + fine; proposal: every
    round's + the main field's)."""
    return samplers.module(cfg.sampler).samples_per_ray(cfg.sampler)


def field_evaluations(cfg: ModelConfig) -> list[tuple[int, fields.FieldConfig]]:
    """[(samples, field config)] of the field evaluations of one ray, pass by pass (the NeRF
    field as `cfg.field`)."""
    return samplers.module(cfg.sampler).field_evaluations(cfg.sampler, cfg.field)


def describe(cfg: ModelConfig) -> str:
    """How a ray is sampled, one line: e.g. "proposal 64 -> 32 main", "hierarchical 48 + 48 (union)"."""
    return samplers.module(cfg.sampler).describe(cfg.sampler)


def label(cfg: ModelConfig) -> str:
    """A compact label of the samples per pass: e.g. "64p+32", "48+48"."""
    return samplers.module(cfg.sampler).label(cfg.sampler)


def init(key, cfg: ModelConfig) -> dict:
    """Parameters: the sampler's fields (samplers/: hierarchical {"coarse", ["fine"]},
    proposal {"proposal": [field per round], "fine"}; read them through `main_field`),
    ["appearance": [N, A]], ["transient": [N, T]].

    Embeddings start as N(0, 0.01^2) (small, so every image starts near the shared look).
    """
    validate(cfg)
    k_first, k_main, k_app, k_tr = jax.random.split(key, 4)

    def init_field(k, main):
        return fields.init(k, field_config(cfg, main))

    params = samplers.module(cfg.sampler).init(k_first, k_main, cfg.sampler, init_field)
    if cfg.use_appearance:
        params["appearance"] = 0.01 * jax.random.normal(k_app, (cfg.num_images, cfg.appearance_dim))
    if cfg.use_transient:
        params["transient"] = 0.01 * jax.random.normal(k_tr, (cfg.num_images, cfg.transient_dim))
    return params


def encoding_scale(cfg: ModelConfig) -> float:
    if cfg.encoding_scale > 0:
        return float(cfg.encoding_scale)
    return float(cfg.contract_radius) if cfg.use_contraction else 1.0


def field_inputs(cfg: ModelConfig, origin: jnp.ndarray, direction: jnp.ndarray,
                 t_edges: jnp.ndarray) -> jnp.ndarray:
    """Points fed to the MLP for bins along rays.

    origin, direction: [..., 3]; t_edges: [..., S + 1]. Returns [..., S, 3]: the bin
    t-midpoints, contracted when cfg.use_contraction, divided by encoding_scale(cfg).
    """
    t_mid = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
    x = origin[..., None, :] + t_mid[..., None] * direction[..., None, :]
    if cfg.use_contraction:
        x = coords.contract(x, cfg.contract_radius)
    return x / encoding_scale(cfg)


OPAQUE_DENSITY = 1e10


def opaque_last_bin(sigma: jnp.ndarray) -> jnp.ndarray:
    """sigma: [..., S] -> the same with the last bin's density set to OPAQUE_DENSITY (alpha 1)."""
    return sigma.at[..., -1].set(OPAQUE_DENSITY)


def _transient_composite(out: dict, t_edges: jnp.ndarray, background: float, beta_min: float) -> dict:
    """NeRF-W compositing of a static and a transient component with shared transmittance.

    out: field outputs with sigma [..., S], rgb [..., S, 3], transient_sigma, transient_rgb,
    beta; t_edges: [..., S + 1] (unit directions). Returns rgb [..., 3], beta [...] (with
    beta_min), transient_sigma_mean [...], transient_opacity [...].
    """
    delta = jnp.diff(t_edges, axis=-1)
    tau_s = out["sigma"] * delta
    tau_t = out["transient_sigma"] * delta
    tau = tau_s + tau_t
    trans = jnp.exp(-jnp.concatenate([jnp.zeros_like(tau[..., :1]), jnp.cumsum(tau[..., :-1], axis=-1)], axis=-1))
    w_s = trans * (1.0 - jnp.exp(-tau_s))
    w_t = trans * (1.0 - jnp.exp(-tau_t))
    rgb = jnp.sum(w_s[..., None] * out["rgb"] + w_t[..., None] * out["transient_rgb"], axis=-2)
    opacity = jnp.sum(w_s, axis=-1) + jnp.sum(w_t, axis=-1)
    rgb = rgb + jnp.clip(1.0 - opacity, 0.0, 1.0)[..., None] * background
    return {"rgb": rgb, "beta": jnp.sum(w_t * out["beta"], axis=-1) + beta_min,
            "transient_sigma_mean": jnp.mean(out["transient_sigma"], axis=-1),
            "transient_opacity": jnp.sum(w_t, axis=-1)}


def _one_pass(field_params, field_cfg, cfg: ModelConfig, origin, direction, s_edges, s_to_t,
              appearance=None, transient=None) -> dict:
    """Evaluates a field on the bins `s_edges` [..., S + 1] of rays and composites them."""
    t_edges = s_to_t(s_edges)
    x = field_inputs(cfg, origin, direction, t_edges)
    out = fields.apply(field_params, field_cfg, x, direction[..., None, :], appearance, transient)
    if cfg.opaque_far:
        out = dict(out, sigma=opaque_last_bin(out["sigma"]))
    weights = render.alpha_weights(out["sigma"], t_edges)
    result = render.composite(weights, out["rgb"], t_edges, background=cfg.background)
    result["s_edges"] = s_edges
    result["t_edges"] = t_edges
    if "transient_sigma" in out:
        mixed = _transient_composite(out, t_edges, cfg.background, cfg.beta_min)
        result["rgb_static"] = result["rgb"]
        result.update(mixed)
    return result


def render_ray(params: dict, cfg: ModelConfig, origin, direction, near, far, key=None,
               image_index=None, appearance=None) -> dict:
    """Renders one ray (or a batch of rays sharing one key).

    origin, direction: [..., 3] (unit direction); near, far: [...]; key: PRNG key for the
    stratified jitter and the PDF resampling (None: deterministic, bin centres);
    image_index: [...] int (embedding lookup, NeRF-W); appearance: [..., A] overrides the
    table lookup (used when fitting a test image's embedding).
    Returns {"levels": [level, ...], "final": dict}:
      levels: every pass in order, the last one the final pass; each has "s_edges" [..., n + 1]
        and "weights" [..., n] in s; a level that renders colour is a whole pass (the dict of
        `final` below, with "rgb" [..., 3]: the hierarchical sampler's coarse pass), one that
        does not has only those two (a proposal round);
      final: the pass that makes the picture, render.composite's outputs (rgb [..., 3],
        opacity, depth, median_depth, weights, s_edges, t_edges); with NeRF-W's transient
        part also rgb_static, beta, transient_sigma_mean, transient_opacity.
    """
    near = jnp.asarray(near, jnp.float32)
    far = jnp.asarray(far, jnp.float32)
    batch_shape = jnp.broadcast_shapes(near.shape, far.shape, origin.shape[:-1])
    _, s_to_t = sampling.ray_warp(cfg.warp, near[..., None], far[..., None])

    def shade(field_params, s_edges, main):
        app, tr = _embeddings(params, cfg, image_index, appearance) if main else (None, None)
        return _one_pass(field_params, field_config(cfg, main), cfg, origin, direction, s_edges, s_to_t, app, tr)

    passes = Passes(batch_shape=batch_shape, single_jitter=cfg.single_jitter,
                    far_bin=opaque_last_bin if cfg.opaque_far else (lambda sigma: sigma), s_to_t=s_to_t,
                    points=lambda t_edges: field_inputs(cfg, origin, direction, t_edges), shade=shade)
    return samplers.module(cfg.sampler).render(params, cfg.sampler, passes, key)


def _embeddings(params: dict, cfg: ModelConfig, image_index, appearance) -> tuple:
    """NeRF-W's per-sample embeddings: (appearance [..., 1, A] or None, transient [..., 1, T] or None)."""
    app = tr = None
    if cfg.use_appearance:
        app = appearance if appearance is not None else params["appearance"][image_index]
        app = app[..., None, :]
    if cfg.use_transient:
        if image_index is None:
            raise ValueError("render_ray: a transient model needs image_index")
        tr = params["transient"][image_index][..., None, :]
    return app, tr


def render_rays(params: dict, cfg: ModelConfig, origins, directions, near, far, keys=None,
                image_index=None, appearance=None) -> dict:
    """Renders a batch of rays, each with its own PRNG key (so a ray's samples do not depend
    on which device or chunk renders it).

    origins, directions: [B, 3]; near, far: [B]; keys: [B, 2] uint32 keys or None
    (deterministic); image_index: [B] int or None; appearance: [B, A] or None.
    Returns the `render_ray` dict with every leaf batched over [B].
    """
    batch = origins.shape[0]
    if image_index is None:
        image_index = jnp.zeros((batch,), jnp.int32)

    def one(o, d, n, f, k, i, a):
        return render_ray(params, cfg, o, d, n, f, k, i, a)

    return jax.vmap(one, in_axes=(0, 0, 0, 0, None if keys is None else 0, 0,
                                  None if appearance is None else 0))(
        origins, directions, near, far, keys, image_index, appearance)


def static_rgb(outputs: dict) -> jnp.ndarray:
    """The picture without the transient part (NeRF-W evaluation renders the static scene)."""
    final = outputs["final"]
    return final.get("rgb_static", final["rgb"])
