"""Training and rendering throughput (rays/s) per method and config on this machine.

    JAX_PLATFORMS=cpu XLA_FLAGS=--xla_force_host_platform_device_count=2 \
        python benchmarks/throughput.py [--steps 5] [--configs mlp,grid-hierarchical,demo] [--methods ours]

Configs: "mlp" (the MLP field with 32 + 32 hierarchical samples, the demo before the grid),
"grid-hierarchical" (the demo's hash grid with that sampler), "demo" (the demo recipe: hash
grid + proposal sampling, 64 -> 32 samples), "paper-small" (an 8 x 256 MLP, 64 + 128).

For every (method, config): compiles the pmapped training step (time reported separately),
then times `--steps` steps (block_until_ready) and rendering of `--render-rays` rays in
chunks. The scene is a 160x120, 8-frame synthetic dataset of random pixels (throughput does
not depend on the content). Prints a table and writes benchmarks/results/throughput.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

from jaxnerf_grid import config as config_lib, parallel, rays as rays_lib, train, views
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.demo import DEMO_CONFIG

sys.path.insert(0, str(Path(__file__).resolve().parent))
from convergence import MLP_CONFIG, RUNS  # noqa: E402

CONFIGS = {
    "mlp": MLP_CONFIG,
    "grid-hierarchical": RUNS["grid-hierarchical"],
    "demo": DEMO_CONFIG,
    "paper-small": {"model": {"field": {"depth": 8, "width": 256, "skip": 4, "view_width": 128},
                              "num_coarse": 64, "num_fine": 128},
                    "train": {"batch_rays": 1024}},
}


def scene(width=160, height=120, frames=8) -> Dataset:
    rng = np.random.default_rng(0)
    fx = rays_lib.focal_from_fov(np.radians(60), width)
    c2w = []
    for k in range(frames):
        a = 2 * np.pi * k / frames
        c2w.append(np.asarray(rays_lib.look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0, 0, 0])))
    return Dataset(root=Path("bench"), images=rng.uniform(size=(frames, height, width, 3)).astype(np.float32),
                   c2w=np.asarray(c2w, np.float32),
                   intrinsics=np.tile(np.array([[fx, fx, width / 2, height / 2]], np.float32), (frames, 1)),
                   split={"train": np.arange(frames - 1), "test": np.array([frames - 1])}, near=0.5, far=60.0)


def samples_per_ray(mcfg) -> str:
    """Field evaluations per ray, e.g. "64p+32" (proposal + main) or "32+32"."""
    if mcfg.sampler == "proposal":
        return "+".join(f"{n}p" for n in mcfg.proposal_samples) + f"+{mcfg.num_fine}"
    return f"{mcfg.num_coarse}+{mcfg.num_fine}" if mcfg.hierarchical else str(mcfg.num_coarse)


def bench(method: str, name: str, steps: int, render_rays: int) -> dict:
    overrides = json.loads(json.dumps(CONFIGS[name]))
    overrides.setdefault("train", {})["max_steps"] = 1000
    cfg = train.make_config(method, overrides)
    ds = scene()
    cfg = config_lib.resolve(cfg, ds)  # as train.train settles it
    n = train.resolve_devices(cfg.train)
    pool = parallel.replicate(train.build_pool(ds, cfg), n)
    state = parallel.replicate(train.init_state(cfg), n)
    step = train.make_train_step(cfg, n)
    t = time.perf_counter()
    state, stats = step(state, pool)
    jax.block_until_ready(stats)
    compile_s = time.perf_counter() - t
    t = time.perf_counter()
    for _ in range(steps):
        state, stats = step(state, pool)
    jax.block_until_ready(stats)
    train_s = (time.perf_counter() - t) / steps
    params = jax.device_get(jax.tree_util.tree_map(lambda x: x[0], state["params"]))
    r = views.camera_rays(ds, 7, ds.near, ds.far)
    flat = rays_lib.Rays(*(np.asarray(x).reshape(-1, *np.asarray(x).shape[2:])[:render_rays] for x in r))
    views.render_rays_chunked(params, cfg.model, flat, 0, None, cfg.train.chunk, n)  # compile
    t = time.perf_counter()
    views.render_rays_chunked(params, cfg.model, flat, 0, None, cfg.train.chunk, n)
    render_s = time.perf_counter() - t
    return {"method": method, "config": name, "devices": n, "batch_rays": cfg.train.batch_rays,
            "samples_per_ray": samples_per_ray(cfg.model),
            "field": f"{cfg.model.field.kind} {cfg.model.field.depth}x{cfg.model.field.width}",
            "sampler": cfg.model.sampler,
            "compile_s": compile_s, "step_s": train_s, "train_rays_per_s": cfg.train.batch_rays / train_s,
            "render_rays_per_s": len(flat.near) / render_s}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--render-rays", type=int, default=8192)
    p.add_argument("--configs", default="mlp,grid-hierarchical,demo")
    p.add_argument("--methods", default="ours")
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "throughput.json"))
    args = p.parse_args()
    rows = []
    for name in args.configs.split(","):
        for method in args.methods.split(","):
            row = bench(method, name, args.steps, args.render_rays)
            rows.append(row)
            print(f"{method:6s} {name:18s} {row['field']:12s} {row['samples_per_ray']:>7s} samples  "
                  f"train {row['train_rays_per_s']:8.0f} rays/s ({row['step_s']:.2f} s/step, "
                  f"compile {row['compile_s']:.0f} s)  render {row['render_rays_per_s']:8.0f} rays/s", flush=True)
    out = {"machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                       "devices": [str(d) for d in jax.local_devices()],
                       "load_average": os.getloadavg()},
           "note": "measured on a shared machine; the load average at the end is recorded",
           "results": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
