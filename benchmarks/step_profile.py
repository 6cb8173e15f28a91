"""Where a training step's time goes: each stage of a recipe's step jitted and timed on its own.

    JAX_PLATFORMS=cpu python -m benchmarks.step_profile [--recipe ours] [--rays 1024] [--repeats 10]
        [--set train.sparse_adam=true ...] [--out benchmarks/results/step_profile.json]

One CPU device, the recipe's config (proposal sampler with a hash-grid main field: the demo's
`ours`) on the throughput benchmark's synthetic scene (`throughput.scene`, random pixels: the
cost does not depend on the content). Each stage is a separately jitted function, run once to
compile, then `--repeats` times (block_until_ready); the median is reported, in ms per step of
`--rays` rays:

  batching          the on-device batch of the step: draw pixel ids, gather rays and targets
                    (`train.gather_batch`)
  proposal_field    every proposal round's density field on its samples, forward + backward
  main_encoding     the main field's hash encoding on `main_samples` points per ray,
                    forward + backward to the table (the gather and its scatter-add)
  main_mlps         the main field's MLPs (trunk, colour branch) on precomputed features,
                    forward + backward
  loss_and_grad     the whole loss of the step and its gradient (`train.batch_terms`, weighted)
  sampling_losses   loss_and_grad minus the three field stages: the sampling, the compositing,
                    the losses and what the stages above do not cover (a remainder, not timed)
  optimizer         `optim.guarded_apply` with the recipe's Adam on the whole parameter tree
  optimizer_sparse  the same with `train.sparse_adam` flipped (dense <-> lazy on hash tables)
  step              the pmapped training step of `train.make_train_step`, the steps chained
                    (dispatch overlaps the previous step); with `--set train.robust=robust` the
                    robust step (patches, evidence, confirmation, the per-pixel record), the
                    stages above staying the plain step's
  step_synced       the same with the host reading the step's `finite` flag after every
                    step, as `train.train`'s loop does

The points fed to the field stages are the step's own (its rays, stratified in s through the
recipe's warp and contracted as `models.field_inputs` does). Prints a markdown table and writes
JSON (`--out`): the stages, the config, the load average before and after (a shared machine
moves every number; the ratios between stages move less).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from benchmarks.throughput import machine_load, scene
from jaxnerf_grid.config import build, recipes
from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.nerf import losses, models
from jaxnerf_grid.nerf.fields import hashgrid, layers, proposal
from jaxnerf_grid.nerf.samplers import s_space as sampling
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import optim
from jaxnerf_grid.util import parallel

STAGES = ("batching", "proposal_field", "main_encoding", "main_mlps", "loss_and_grad", "sampling_losses",
          "optimizer", "optimizer_sparse", "step", "step_synced")
FIELD_STAGES = ("proposal_field", "main_encoding", "main_mlps")


def time_median(fn, args: tuple, repeats: int) -> float:
    """Median seconds of `fn(*args)` (blocked until ready) over `repeats` runs after one warm-up."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def points_along(cfg: models.ModelConfig, batch: dict, key, samples: int) -> jnp.ndarray:
    """`samples` points per ray of `batch`, stratified in s and placed as the model places them.
    Returns [B, samples, 3] in [-1, 1]."""
    _, s_to_t = sampling.ray_warp(cfg.warp, batch["near"][:, None], batch["far"][:, None])
    s_edges = sampling.stratified_s(key, batch["near"].shape, samples)
    return models.field_inputs(cfg, batch["origins"], batch["directions"], s_to_t(s_edges))


def main_mlps(params: dict, field_cfg, features: jnp.ndarray, viewdirs: jnp.ndarray) -> dict:
    """The grid field's MLPs on precomputed hash features (fields.grid.apply without its
    encoding). features: [..., L * F]; viewdirs: [..., 3]. Returns fields.apply's dict."""
    h = features
    for layer in params["trunk"]:
        h = jax.nn.relu(layers.dense(layer, h))
    raw = layers.dense(params["density"], h)
    sigma = layers.activate_density(raw[..., 0], field_cfg.density_activation, field_cfg.density_bias)
    return layers.radiance_outputs(params, field_cfg, sigma, raw[..., 1:], viewdirs, None, None)


def _summed(fn):
    """fn(params, *rest) -> pytree of arrays  ==>  params, *rest -> (sum of every output, grad)."""
    def total(params, *rest):
        return sum(jnp.sum(x) for x in jax.tree_util.tree_leaves(fn(params, *rest)))
    return jax.jit(jax.value_and_grad(total))


def profile(recipe: str = "ours", rays: int = 1024, repeats: int = 10, extra: dict | None = None,
            size: tuple[int, int, int] = (160, 120, 8)) -> dict:
    """Times every stage of STAGES (see the module's docstring). Returns
    {"stages_ms": {stage: ms}, "config": {...}}."""
    ds = scene(*size)
    overrides = config_lib.merge({"train": {"batch_rays": rays, "num_devices": 1, "max_steps": 1000}}, extra or {})
    cfg = config_lib.resolve(recipes.make_config(recipe, overrides), ds)
    mcfg, tcfg = cfg.model, cfg.train
    if mcfg.sampler.kind != "proposal" or mcfg.field.kind != "grid":
        raise SystemExit(f"step_profile: recipe {recipe!r} is not a grid field with proposal sampling")
    pool_host = train.build_pool(ds, cfg)
    pool = jax.device_put({k: v for k, v in pool_host.items() if k not in ("near", "far")})
    pool_near_far = {"near": pool_host["near"], "far": pool_host["far"]}
    state = train.init_state(cfg, train.train_frames_shape(ds) if tcfg.robust.mode != "off" else None)
    params = state["params"]
    key = jax.random.PRNGKey(0)
    ms = {}

    @jax.jit
    def draw(pool, key):
        ids = jax.random.randint(key, (rays,), 0, pool["pixels"].shape[0])
        return train.gather_batch({**pool, **pool_near_far}, pool["pixels"][ids])

    ms["batching"] = time_median(draw, (pool, key), repeats)
    batch = draw(pool, key)
    ray_keys = jax.random.split(key, rays)

    sampler = mcfg.sampler
    prop_params, prop_cfg = params["proposal"], sampler.field
    prop_points = [points_along(mcfg, batch, jax.random.fold_in(key, k), n) for k, n in enumerate(sampler.samples)]
    prop_fn = _summed(lambda p, xs: [proposal.density(pk, prop_cfg, x) for pk, x in zip(p, xs)])
    ms["proposal_field"] = time_median(prop_fn, (prop_params, prop_points), repeats)

    main_params, main_cfg = models.main_field(params, mcfg)
    main_points = points_along(mcfg, batch, jax.random.fold_in(key, 99), sampler.main_samples)
    enc_fn = _summed(lambda p, x: hashgrid.encode(p, main_cfg.grid, x))
    ms["main_encoding"] = time_median(enc_fn, (main_params["encoding"], main_points), repeats)

    features = hashgrid.encode(main_params["encoding"], main_cfg.grid, main_points)
    viewdirs = jnp.broadcast_to(batch["directions"][:, None, :], main_points.shape)
    mlp_params = {k: v for k, v in main_params.items() if k != "encoding"}
    mlp_fn = _summed(lambda p, h, d: main_mlps(p, main_cfg, h, d))
    ms["main_mlps"] = time_median(mlp_fn, (mlp_params, features, viewdirs), repeats)

    total = jnp.sum(batch["weight"])

    @jax.jit
    def loss_and_grad(params, batch, ray_keys):
        def loss_fn(p):
            _, terms = train.batch_terms(p, cfg, batch, ray_keys)
            return losses.weighted_mean(terms["loss"], batch["weight"], total)
        return jax.value_and_grad(loss_fn)(params)

    ms["loss_and_grad"] = time_median(loss_and_grad, (params, batch, ray_keys), repeats)
    ms["sampling_losses"] = ms["loss_and_grad"] - sum(ms[s] for s in FIELD_STAGES)
    loss, grads = loss_and_grad(params, batch, ray_keys)

    for stage, sparse in (("optimizer", tcfg.sparse_adam), ("optimizer_sparse", not tcfg.sparse_adam)):
        opt = train.make_optimizer(dataclasses.replace(tcfg, sparse_adam=sparse))
        apply = jax.jit(lambda p, s, g, lo, opt=opt: optim.guarded_apply(opt, p, s, g, lo))
        ms[stage] = time_median(apply, (params, opt.init(params), grads, loss), repeats)

    step_fn = train.make_train_step(cfg, 1)
    state_r = parallel.replicate(state, 1)
    pool_r = train.device_pool(ds, cfg, 1)  # what the training loop's step draws from
    state_r, stats = step_fn(state_r, pool_r)  # compile
    jax.block_until_ready(stats)
    for stage, synced in (("step", False), ("step_synced", True)):
        t = time.perf_counter()
        for _ in range(repeats):
            state_r, stats = step_fn(state_r, pool_r)
            if synced:
                bool(stats["finite"][0])
        jax.block_until_ready(stats)
        ms[stage] = (time.perf_counter() - t) / repeats

    return {"stages_ms": {s: 1e3 * ms[s] for s in STAGES},
            "config": {"recipe": recipe, "rays": rays, "samples": list(sampler.samples),
                       "main_samples": sampler.main_samples, "main_levels": main_cfg.grid.num_levels,
                       "proposal_levels": prop_cfg.grid.num_levels, "sparse_adam": tcfg.sparse_adam,
                       "robust": tcfg.robust.mode,
                       "params": int(sum(x.size for x in jax.tree_util.tree_leaves(params))),
                       "scene": {"width": size[0], "height": size[1], "frames": size[2]},
                       "repeats": repeats, "device": str(jax.local_devices()[0])}}


def markdown(result: dict) -> str:
    """The stages as a markdown table: stage, ms, share of the step."""
    ms = result["stages_ms"]
    step = ms["step"]
    lines = ["| stage | ms per step | share of the step |", "|---|---|---|"]
    for stage in STAGES:
        share = "" if stage.startswith("step") or stage == "optimizer_sparse" else f"{100 * ms[stage] / step:.0f} %"
        lines.append(f"| {stage} | {ms[stage]:.1f} | {share} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--recipe", default="ours")
    p.add_argument("--rays", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--size", default="160,120,8", help="scene width,height,frames")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config override")
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "step_profile.json"))
    args = p.parse_args(argv)
    load_before = machine_load()
    size = tuple(int(x) for x in args.size.split(","))
    result = profile(args.recipe, args.rays, args.repeats, build.with_sets({}, args.set), size)
    result["machine"] = {**machine_load(), "load_before": load_before}
    print(markdown(result))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
