"""The methods as compositions of the core pure functions: "ours", "nerf", "nerfw".

One renderer, switched by independent flags of `ModelConfig` so every ablation flips one:

  coarse pass   s_edges = sampling.stratified_s (uniform in s, jittered when training)
                t_edges = s_to_t(s_edges) through the warp `warp` (Eq. 10-11)
                points at the t-midpoints of the bins: x = o + t_mid * d
                z = coords.contract(x, R) when `use_contraction`, fed to the MLP as z / scale
                (scale = R by default, so the encoder sees |z / R| < 1; 1 without contraction)
                weights = render.alpha_weights(sigma, t_edges); render.composite(...)
  fine pass     (`hierarchical`) s samples = sampling.resample_pdf over the *s* edges with the
                coarse weights (so the fine pass resamples in s-space and maps to t via the warp).
                `fine_union=True` (NeRF's choice, the default): the fine pass composites over
                the sorted union of the coarse bin midpoints and the new samples, with bin
                edges at midpoints between them and 0 / 1 at the ends (Nc + Nf bins).
                `fine_union=False`: Nf + 1 resampled values are the fine bin edges (mip-NeRF).

Methods (see `method_config`):
  ours  = contraction (R = contract_radius) + disparity warp + mask-weighted loss (train.py)
  nerf  = no contraction, warp "linear" between the dataset's near and far, masks ignored
  nerfw = nerf + per-image appearance embedding (`use_appearance`, NeRF-A) and/or a transient
          head with per-image transient embeddings (`use_transient`, NeRF-U); both = NeRF-W.
          As in NeRF-W, the coarse field is a plain static field; the fine field carries the
          embeddings. The transient part is composited with the static one (shared
          transmittance) and predicts beta_hat = sum_i w_t,i beta_i + beta_min.

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

from jaxnerf_grid import config, coords, fields, render, sampling
from jaxnerf_grid.config import ConfigError

METHODS = ("ours", "nerf", "nerfw")
SAMPLERS = ("hierarchical", "proposal")

# The proposal field of proposal sampling: a small density-only hash grid (nerfacto's sizes).
PROPOSAL_FIELD = fields.FieldConfig(kind="grid", depth=1, width=16, density_activation="exp",
                                    grid=fields.HashConfig(num_levels=5, features_per_level=2, log2_table_size=17,
                                                           min_resolution=16, max_resolution=256))


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Everything that decides what a ray renders to.

    method: "ours" | "nerf" | "nerfw" (a label; the flags below decide the behaviour).
    field: the MLP (the fine field gets the embedding sizes added for NeRF-W).
    use_contraction, contract_radius: dual-sphere contraction (Eq. 9) with far radius R.
    encoding_scale: points are encoded as z / encoding_scale; 0 = auto (R with contraction,
      1 without).
    warp: s-space warp "linear" | "disparity" | "log" | "piecewise" for the coarse samples.
    sampler: "hierarchical" (NeRF's coarse + fine passes, the flags below) or "proposal"
      (mip-NeRF 360: density-only proposal fields resample in s, the main field runs once).
    num_coarse, num_fine: samples per ray; hierarchical: run the fine pass at all. With the
      proposal sampler num_fine is the main field's sample count (num_coarse is unused).
    proposal_samples: with the proposal sampler, samples of each proposal round (the first
      round is stratified in s through the warp, each later one resampled from the previous
      round's weights); proposal_field: their field (kind "grid"); proposal_padding: weight
      floor (relative to the mean) when resampling from a proposal, so no bin is unreachable.
    fine_union: fine pass over coarse + fine samples (True) or over the fine ones only.
    shared_field: one MLP for both passes (mip-NeRF) instead of two (NeRF).
    near, far: override the dataset's bounds (None: use the dataset's).
    background: grey level behind the last bin.
    opaque_far: make the last bin of every pass opaque (its density infinite), so a ray that
      reaches the far bound takes the colour of the field there: the sky is modelled at the far
      sphere instead of as a dome of haze near the cameras (multinerf's opaque background).
    use_appearance, appearance_dim; use_transient, transient_dim; beta_min, lambda_u: NeRF-W.
    num_images: size of the embedding tables (set from the dataset by the trainer).
    """

    method: str = "ours"
    field: fields.FieldConfig = fields.FieldConfig()
    use_contraction: bool = True
    contract_radius: float = 2.0
    encoding_scale: float = 0.0
    warp: str = "disparity"
    sampler: str = "hierarchical"
    num_coarse: int = 48
    num_fine: int = 48
    hierarchical: bool = True
    fine_union: bool = True
    shared_field: bool = False
    proposal_samples: tuple[int, ...] = (64,)
    proposal_field: fields.FieldConfig = PROPOSAL_FIELD
    proposal_padding: float = 0.01
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
        "num_coarse": config.NONNEGATIVE, "num_fine": config.NONNEGATIVE, "proposal_samples": config.AT_LEAST_ONE,
        "proposal_padding": config.FRACTION, "near": config.POSITIVE, "far": config.POSITIVE,
        "background": config.UNIT, "appearance_dim": config.AT_LEAST_ONE, "transient_dim": config.AT_LEAST_ONE,
        "beta_min": config.NONNEGATIVE, "lambda_u": config.NONNEGATIVE, "num_images": config.NONNEGATIVE}


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
    if cfg.sampler not in SAMPLERS:
        raise ConfigError(f"model.sampler: unknown sampler {cfg.sampler!r}; choose from {list(SAMPLERS)}")
    if cfg.use_contraction and not cfg.contract_radius > 1.0:
        raise ConfigError(f"model.contract_radius must be > 1, got {cfg.contract_radius}")
    for name, field_cfg in (("model.field", cfg.field), ("model.proposal_field", cfg.proposal_field)):
        try:
            fields.check(field_cfg)
        except ValueError as exc:
            raise ConfigError(f"{name}: {exc}") from None
    embeddings = cfg.use_appearance or cfg.use_transient
    if cfg.sampler == "proposal":
        if not cfg.proposal_samples or min(cfg.proposal_samples) < 1 or cfg.num_fine < 1:
            raise ConfigError("model.proposal_samples (each) and num_fine must be >= 1 with the proposal sampler")
        if cfg.proposal_field.kind != "grid":
            raise ConfigError("model.proposal_field.kind must be 'grid'")
        if not 0 <= cfg.proposal_padding < 1:
            raise ConfigError(f"model.proposal_padding must be in [0, 1), got {cfg.proposal_padding}")
    else:
        if cfg.num_coarse < 1 or (cfg.hierarchical and cfg.num_fine < 1):
            raise ConfigError("model.num_coarse (and num_fine when hierarchical) must be >= 1")
        if cfg.shared_field and embeddings:
            raise ConfigError("model.shared_field cannot be combined with NeRF-W embeddings")
        if embeddings and not cfg.hierarchical:
            raise ConfigError("model: NeRF-W embeddings live in the fine field; set hierarchical=true")
    if embeddings and cfg.num_images < 1:
        raise ConfigError("model.num_images must be set (>= 1) for NeRF-W embeddings")
    if cfg.near is not None and cfg.far is not None and not 0 < cfg.near < cfg.far:
        raise ConfigError(f"model: need 0 < near < far, got near={cfg.near}, far={cfg.far}")


def coarse_field_config(cfg: ModelConfig) -> fields.FieldConfig:
    return dataclasses.replace(cfg.field, appearance_dim=0, transient_dim=0)


def fine_field_config(cfg: ModelConfig) -> fields.FieldConfig:
    return dataclasses.replace(cfg.field,
                               appearance_dim=cfg.appearance_dim if cfg.use_appearance else 0,
                               transient_dim=cfg.transient_dim if cfg.use_transient else 0)


def has_coarse_field(cfg: ModelConfig) -> bool:
    return cfg.sampler == "hierarchical"


def has_fine_field(cfg: ModelConfig) -> bool:
    return cfg.sampler == "proposal" or (cfg.hierarchical and not cfg.shared_field)


def init(key, cfg: ModelConfig) -> dict:
    """Parameters: {["coarse": field], ["fine": field], ["proposal": [field per round]],
    ["appearance": [N, A]], ["transient": [N, T]]}. The proposal sampler has no coarse field:
    its main field is "fine".

    Embeddings start as N(0, 0.01^2) (small, so every image starts near the shared look).
    """
    validate(cfg)
    k_coarse, k_fine, k_app, k_tr = jax.random.split(key, 4)
    params = {}
    if has_coarse_field(cfg):
        params["coarse"] = fields.init(k_coarse, coarse_field_config(cfg))
    else:
        keys = jax.random.split(k_coarse, len(cfg.proposal_samples))
        params["proposal"] = [fields.proposal.init(k, cfg.proposal_field) for k in keys]
    if has_fine_field(cfg):
        params["fine"] = fields.init(k_fine, fine_field_config(cfg))
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
    Returns {"coarse": dict, "fine": dict (when hierarchical)} of render.composite outputs
    (rgb [..., 3], opacity, depth, median_depth, weights, s_edges, t_edges); a transient fine
    pass adds rgb_static, beta, transient_sigma_mean, transient_opacity. The proposal sampler
    returns {"proposals": [{"s_edges", "weights"}, ...], "fine": dict} (no coarse pass).
    """
    near = jnp.asarray(near, jnp.float32)
    far = jnp.asarray(far, jnp.float32)
    batch_shape = jnp.broadcast_shapes(near.shape, far.shape, origin.shape[:-1])
    _, s_to_t = sampling.ray_warp(cfg.warp, near[..., None], far[..., None])
    if cfg.sampler == "proposal":
        return _render_ray_proposal(params, cfg, origin, direction, s_to_t, batch_shape, key, image_index,
                                    appearance)
    if key is None:
        k_coarse = k_fine = None
    else:
        k_coarse, k_fine = jax.random.split(key)
    s_coarse = sampling.stratified_s(k_coarse, batch_shape, cfg.num_coarse, cfg.single_jitter)
    result = {"coarse": _one_pass(params["coarse"], coarse_field_config(cfg), cfg, origin, direction,
                                  s_coarse, s_to_t)}
    if not cfg.hierarchical:
        return result
    weights = result["coarse"]["weights"]
    if cfg.fine_union:
        s_new = sampling.resample_pdf(k_fine, s_coarse, weights, cfg.num_fine, cfg.single_jitter)
        s_mid = 0.5 * (s_coarse[..., 1:] + s_coarse[..., :-1])
        s_points = sampling.merge_edges(s_mid, s_new)
        s_fine = sampling.intervals_from_samples(s_points, 0.0, 1.0)
    else:
        s_fine = sampling.resample_pdf(k_fine, s_coarse, weights, cfg.num_fine + 1, cfg.single_jitter)
    s_fine = jax.lax.stop_gradient(s_fine)
    app, tr = _embeddings(params, cfg, image_index, appearance)
    fine_params = params["coarse"] if cfg.shared_field else params["fine"]
    result["fine"] = _one_pass(fine_params, fine_field_config(cfg), cfg, origin, direction, s_fine, s_to_t,
                               app, tr)
    return result


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


def proposal_rounds(params: dict, cfg: ModelConfig, origin, direction, s_to_t, batch_shape, key) -> tuple:
    """The proposal sampler's rounds in s (mip-NeRF 360, with the paper's warp first).

    Round 0 is stratified in s (uniform in disparity for "ours"), each later round resamples
    from the previous round's weights; after the last round num_fine + 1 edges are resampled
    for the main field. origin, direction: [..., 3]; key: PRNG key or None (deterministic).
    Returns (rounds: [{"s_edges": [..., n_k + 1], "weights": [..., n_k]}], s_main: [..., num_fine + 1]).
    """
    count = len(cfg.proposal_samples)
    keys = [None] * (count + 1) if key is None else list(jax.random.split(key, count + 1))
    rounds = []
    s_edges = sampling.stratified_s(keys[0], batch_shape, cfg.proposal_samples[0], cfg.single_jitter)
    for k in range(count):
        if k > 0:
            s_edges = sampling.resample_pdf(keys[k], s_edges, rounds[-1]["weights"], cfg.proposal_samples[k] + 1,
                                            cfg.single_jitter, cfg.proposal_padding)
        t_edges = s_to_t(s_edges)
        sigma = fields.proposal.density(params["proposal"][k], cfg.proposal_field,
                                        field_inputs(cfg, origin, direction, t_edges))
        if cfg.opaque_far:
            sigma = opaque_last_bin(sigma)
        rounds.append({"s_edges": s_edges, "weights": render.alpha_weights(sigma, t_edges)})
    s_main = sampling.resample_pdf(keys[-1], s_edges, rounds[-1]["weights"], cfg.num_fine + 1, cfg.single_jitter,
                                   cfg.proposal_padding)
    return rounds, jax.lax.stop_gradient(s_main)


def _render_ray_proposal(params, cfg: ModelConfig, origin, direction, s_to_t, batch_shape, key, image_index,
                         appearance) -> dict:
    """{"proposals": proposal rounds, "fine": the main field's pass} (see render_ray)."""
    k_prop = None if key is None else jax.random.fold_in(key, 1)
    rounds, s_main = proposal_rounds(params, cfg, origin, direction, s_to_t, batch_shape, k_prop)
    app, tr = _embeddings(params, cfg, image_index, appearance)
    fine = _one_pass(params["fine"], fine_field_config(cfg), cfg, origin, direction, s_main, s_to_t, app, tr)
    return {"proposals": rounds, "fine": fine}


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


def final_pass(outputs: dict) -> dict:
    """The pass whose outputs are the picture: fine when present, else coarse."""
    return outputs["fine"] if "fine" in outputs else outputs["coarse"]


def static_rgb(outputs: dict) -> jnp.ndarray:
    """The picture without the transient part (NeRF-W evaluation renders the static scene)."""
    final = final_pass(outputs)
    return final.get("rgb_static", final["rgb"])
