"""Rendering a trained model: rays of a dataset's camera, rendered in fixed-size chunks.

Rays go through `models.render_rays` in chunks of one compiled shape (the last one padded),
with deterministic samples (bin centres), split over the local devices (pmap). Outputs are
NumPy: rgb (the static part for NeRF-W), z-depth (the median depth along the ray times the
cosine to the camera axis), expected z-depth and opacity. `fit_appearance` is NeRF-W's
test-time fit of one appearance embedding with the network frozen.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.run_config import RunConfig, TrainConfig, resolve_devices
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.nerf import models
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.train import optim
from jaxnerf_grid.util import parallel
from jaxnerf_grid.util import progress as progress_lib


@functools.lru_cache(maxsize=32)
def _render_chunk_fn(mcfg: models.ModelConfig, num_devices: int, with_appearance: bool):
    def fn(params, batch):
        out = models.render_rays(params, mcfg, batch["origins"], batch["directions"], batch["near"],
                                 batch["far"], None, batch["image_index"],
                                 batch["appearance"] if with_appearance else None)
        final = out["final"]
        return {"rgb": models.static_rgb(out), "depth": final["median_depth"] * batch["cos"],
                "expected_depth": final["depth"] * batch["cos"], "opacity": final["opacity"]}

    return jax.pmap(fn, in_axes=(None, 0), devices=parallel.devices(num_devices))


def render_rays_chunked(params, mcfg: models.ModelConfig, r: rays_lib.Rays, image_index: int = 0,
                        appearance=None, chunk: int = 4096, num_devices: int | None = None,
                        progress: bool = False) -> dict:
    """Renders any number of rays in fixed-size chunks (one compiled shape).

    r: Rays with batch shape [...]; appearance: [A] or None (NeRF-W: overrides the table).
    Returns dict of NumPy arrays with batch shape [...]: rgb [..., 3], depth (z-depth from the
    median ray depth), expected_depth (z-depth of the mean), opacity.
    """
    n = num_devices or jax.local_device_count()
    shape = r.origins.shape[:-1]
    count = int(np.prod(shape))
    chunk = max(n, (chunk // n) * n)
    flat = {"origins": np.asarray(r.origins, np.float32).reshape(count, 3),
            "directions": np.asarray(r.directions, np.float32).reshape(count, 3),
            "near": np.asarray(r.near, np.float32).reshape(count),
            "far": np.asarray(r.far, np.float32).reshape(count),
            "cos": np.asarray(r.cos_to_axis, np.float32).reshape(count),
            "image_index": np.full((count,), image_index, np.int32)}
    with_app = appearance is not None and mcfg.use_appearance
    if with_app:
        flat["appearance"] = np.broadcast_to(np.asarray(appearance, np.float32), (count, mcfg.appearance_dim))
    fn = _render_chunk_fn(mcfg, n, with_app)
    pieces = []
    starts = range(0, count, chunk)
    if progress:
        starts = progress_lib.bar(starts, desc="render", unit="chunk", leave=False)
    for start in starts:
        part = {k: parallel.pad_to_multiple(v[start:start + chunk], chunk)[0] for k, v in flat.items()}
        valid = min(chunk, count - start)
        out = parallel.run_sharded(functools.partial(fn, params), part, n)
        pieces.append({k: v[:valid] for k, v in out.items()})
    return {k: np.concatenate([p[k] for p in pieces]).reshape(*shape, *pieces[0][k].shape[1:]) for k in pieces[0]}


# Rays per step of `frame_renderer`'s loop: the intermediates of 128 rays (L x 8 corner rows and
# weights of every sample) stay in the CPU's caches; measured in docs/VIDEOS.md ("Cost").
FRAME_BLOCK = 128


@functools.lru_cache(maxsize=8)
def _render_frame_fn(mcfg: models.ModelConfig, num_devices: int, block: int):
    """pmapped (params [n, ...], batch {origins, directions [n, R, 3], near, far, cos [n, R]}) ->
    {"rgb" [n, R, 3], "depth" [n, R]}, R a multiple of `block`, rendered `block` rays at a time
    (lax.map) inside one compiled call."""
    def blocks(params, batch):
        out = models.render_rays(params, mcfg, batch["origins"], batch["directions"], batch["near"], batch["far"],
                                 None, jnp.zeros(batch["near"].shape, jnp.int32))
        return {"rgb": models.static_rgb(out), "depth": out["final"]["median_depth"] * batch["cos"]}

    def fn(params, batch):
        split = jax.tree_util.tree_map(lambda x: x.reshape(-1, block, *x.shape[1:]), batch)
        out = jax.lax.map(functools.partial(blocks, params), split)
        return jax.tree_util.tree_map(lambda x: x.reshape(-1, *x.shape[2:]), out)

    return jax.pmap(fn, devices=parallel.devices(num_devices))


def frame_renderer(params, mcfg: models.ModelConfig, num_devices: int | None = None, block: int = FRAME_BLOCK):
    """A renderer for many frames of one size (the videos): the parameters are copied onto the
    devices once, and each call renders all of a frame's rays in one compiled call (one compile
    for every frame of a shape), `block` rays at a time. Returns render(r: Rays [...]) ->
    {"rgb" [..., 3], "depth" [...]} (NumPy, as `render_rays_chunked`'s, image 0's embedding,
    equal to it up to float rounding: the order of XLA's arithmetic differs with the shapes)."""
    n = num_devices or jax.local_device_count()
    fn = _render_frame_fn(mcfg, n, block)
    on_devices = parallel.replicate(params, n)

    def render(r: rays_lib.Rays) -> dict:
        shape = r.origins.shape[:-1]
        count = int(np.prod(shape))
        flat = {"origins": np.asarray(r.origins, np.float32).reshape(count, 3),
                "directions": np.asarray(r.directions, np.float32).reshape(count, 3),
                "near": np.asarray(r.near, np.float32).reshape(count),
                "far": np.asarray(r.far, np.float32).reshape(count),
                "cos": np.asarray(r.cos_to_axis, np.float32).reshape(count)}
        padded = {k: parallel.pad_to_multiple(v, n * block)[0] for k, v in flat.items()}
        out = parallel.unshard(jax.device_get(fn(on_devices, parallel.shard(padded, n))))
        return {k: v[:count].reshape(*shape, *v.shape[1:]) for k, v in out.items()}

    return render


def camera_rays(dataset: Dataset, index: int, near: float, far: float) -> rays_lib.Rays:
    """Rays [H, W] of frame `index` of a dataset."""
    fx, fy, cx, cy = (float(v) for v in dataset.intrinsics[index])
    return rays_lib.generate_rays(jnp.asarray(dataset.c2w[index]), fx, fy, cx, cy, dataset.width, dataset.height,
                                  near, far)


def held_out_appearance(params, cfg: RunConfig, dataset: Dataset, index: int) -> np.ndarray | None:
    """The appearance embedding [A] a frame renders with when it did not train (its row of the
    table was never fitted): the mean of the training frames' rows; None for a training frame
    (its own row) or a model without the embedding."""
    train_ids = np.asarray(dataset.split["train"], np.int64)
    if not cfg.model.use_appearance or int(index) in train_ids or "appearance" not in params:
        return None
    table = np.asarray(params["appearance"])
    return table[train_ids[train_ids < len(table)]].mean(axis=0)


def render_view(params, cfg: RunConfig, dataset: Dataset, index: int, appearance=None,
                progress: bool = False) -> dict:
    """Renders frame `index` of the dataset. Returns rgb [H, W, 3], depth, expected_depth,
    opacity [H, W] (NumPy). appearance: [A] or None (a training frame's own embedding, a held-out
    frame's `held_out_appearance`)."""
    r = camera_rays(dataset, index, *config_lib.near_far(cfg.model, dataset))
    image_index = min(int(index), max(cfg.model.num_images - 1, 0))
    if appearance is None:
        appearance = held_out_appearance(params, cfg, dataset, index)
    return render_rays_chunked(params, cfg.model, r, image_index, appearance, cfg.train.chunk,
                               resolve_devices(cfg.train), progress)


# --------------------------------------------------------------------------- NeRF-W test-time


def fit_appearance(params, mcfg: models.ModelConfig, tcfg: TrainConfig, r: rays_lib.Rays,
                   target: np.ndarray, key, start=None) -> np.ndarray:
    """Fits one appearance embedding to some pixels with the network frozen (NeRF-W's test
    protocol, used on the left half of a test image).

    r: Rays [M]; target: [M, 3]; start: [A], the embedding the fit starts from (the held-out
    frame's `held_out_appearance`; None: the mean of every row of the table). Runs
    `appearance_steps` Adam steps on batches of `appearance_rays` pixels against the static
    rendering. Returns [A] NumPy.
    """
    if not mcfg.use_appearance:
        raise ValueError("fit_appearance: the model has no appearance embedding")
    count = r.origins.shape[0]
    opt = optim.adam(tcfg.appearance_lr)
    emb = jnp.mean(params["appearance"], axis=0) if start is None else jnp.asarray(start, jnp.float32)
    opt_state = opt.init(emb)

    @jax.jit
    def step(emb, opt_state, ids):
        def loss_fn(e):
            out = models.render_rays(params, mcfg, r.origins[ids], r.directions[ids], r.near[ids], r.far[ids],
                                     None, jnp.zeros(ids.shape, jnp.int32),
                                     jnp.broadcast_to(e, (ids.shape[0], e.shape[0])))
            return jnp.mean(jnp.square(models.static_rgb(out) - target[ids]))

        loss, grad = jax.value_and_grad(loss_fn)(emb)
        emb, opt_state, _ = optim.guarded_apply(opt, emb, opt_state, grad, loss)
        return emb, opt_state

    target = jnp.asarray(target, jnp.float32)
    batch = min(tcfg.appearance_rays, count)
    for i in range(tcfg.appearance_steps):
        ids = jax.random.choice(jax.random.fold_in(key, i), count, (batch,), replace=batch > count)
        emb, opt_state = step(emb, opt_state, ids)
    return np.asarray(emb)
