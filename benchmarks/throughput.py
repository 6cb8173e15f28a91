"""Training and rendering throughput (rays/s) per method and config, and their ratios, measured
in one run with the cases interleaved.

    JAX_PLATFORMS=cpu XLA_FLAGS=--xla_force_host_platform_device_count=2 \
        python -m benchmarks.throughput [--steps 5] [--repeats 3] [--configs mlp,grid-hierarchical,demo]
        [--methods ours]

Configs: "mlp" (the MLP field with 32 + 32 hierarchical samples, the demo before the grid),
"grid-hierarchical" (the demo's hash grid with that sampler), "demo" (the demo recipe: hash
grid + proposal sampling, 64 -> 32 samples), "paper-small" (an 8 x 256 MLP, 64 + 128).

Every (method, config) is set up and compiled first (compile time reported separately). Then
`--repeats` rounds, each timing `--steps` training steps (block_until_ready) and the rendering
of `--render-rays` rays of every case in turn (round-robin), so a change in the machine's load
hits all cases alike. Reported per case: the median over the rounds; per case against the
first: the median of the per-round ratios (train and render rays/s), which is the number to
compare, as absolute rays/s move with whatever else runs on a shared machine. The load average
(os.getloadavg) before and after and the CPU count are written with the results. The scene is a
160x120, 8-frame synthetic dataset of random pixels (throughput does not depend on the content).
Prints a table and writes benchmarks/results/throughput.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import numpy as np

from benchmarks.convergence import MLP_CONFIG, RUNS
from jaxnerf_grid import config as config_lib, parallel, rays as rays_lib, train, views
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.demo import DEMO_CONFIG

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


class Case:
    """One (method, config): its compiled training step and renderer, state and rays, ready to time."""

    def __init__(self, method: str, name: str, render_rays: int):
        overrides = json.loads(json.dumps(CONFIGS[name]))
        overrides.setdefault("train", {})["max_steps"] = 1000
        cfg = train.make_config(method, overrides)
        ds = scene()
        self.cfg = cfg = config_lib.resolve(cfg, ds)  # as train.train settles it
        self.method, self.name = method, name
        self.n = n = train.resolve_devices(cfg.train)
        self.pool = parallel.replicate(train.build_pool(ds, cfg), n)
        self.state = parallel.replicate(train.init_state(cfg), n)
        self.step = train.make_train_step(cfg, n)
        r = views.camera_rays(ds, 7, ds.near, ds.far)
        self.rays = rays_lib.Rays(*(np.asarray(x).reshape(-1, *np.asarray(x).shape[2:])[:render_rays] for x in r))
        t = time.perf_counter()
        self.train_steps(1)
        self.render()
        self.compile_s = time.perf_counter() - t

    def train_steps(self, steps: int) -> float:
        """Seconds per step over `steps` steps."""
        t = time.perf_counter()
        for _ in range(steps):
            self.state, stats = self.step(self.state, self.pool)
        jax.block_until_ready(stats)
        return (time.perf_counter() - t) / steps

    def render(self) -> float:
        """Seconds to render the case's rays."""
        params = jax.device_get(jax.tree_util.tree_map(lambda x: x[0], self.state["params"]))
        t = time.perf_counter()
        views.render_rays_chunked(params, self.cfg.model, self.rays, 0, None, self.cfg.train.chunk, self.n)
        return time.perf_counter() - t

    def describe(self) -> dict:
        m = self.cfg.model
        return {"method": self.method, "config": self.name, "devices": self.n, "batch_rays": self.cfg.train.batch_rays,
                "samples_per_ray": samples_per_ray(m), "field": f"{m.field.kind} {m.field.depth}x{m.field.width}",
                "sampler": m.sampler, "compile_s": self.compile_s}


def interleaved(cases: list[Case], steps: int, repeats: int) -> list[dict]:
    """`repeats` rounds over all cases (round-robin); per case the median step / render seconds,
    rays/s, and the median of the per-round ratios of its rays/s to the first case's."""
    step_s = [[0.0] * repeats for _ in cases]
    render_s = [[0.0] * repeats for _ in cases]
    for k in range(repeats):
        for i, case in enumerate(cases):
            step_s[i][k] = case.train_steps(steps)
            render_s[i][k] = case.render()
    rows = []
    for i, case in enumerate(cases):
        rays = len(case.rays.near)
        rows.append({**case.describe(), "step_s": statistics.median(step_s[i]),
                     "train_rays_per_s": case.cfg.train.batch_rays / statistics.median(step_s[i]),
                     "render_rays_per_s": rays / statistics.median(render_s[i]),
                     # rays/s relative to case 0 in the same round (batch sizes may differ)
                     "train_ratio_to_first": statistics.median(
                         (case.cfg.train.batch_rays / step_s[i][k]) / (cases[0].cfg.train.batch_rays / step_s[0][k])
                         for k in range(repeats)),
                     "render_ratio_to_first": statistics.median(
                         (rays / render_s[i][k]) / (len(cases[0].rays.near) / render_s[0][k]) for k in range(repeats)),
                     "step_s_per_round": step_s[i], "render_s_per_round": render_s[i]})
    return rows


def machine_load() -> dict:
    """The 1, 5 and 15 minute load averages and the CPU count (is the machine shared right now?)."""
    return {"load_average": list(os.getloadavg()), "cpu_count": os.cpu_count()}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=5, help="training steps timed per case per round")
    p.add_argument("--repeats", type=int, default=3, help="rounds over all cases")
    p.add_argument("--render-rays", type=int, default=8192)
    p.add_argument("--configs", default="mlp,grid-hierarchical,demo")
    p.add_argument("--methods", default="ours")
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "throughput.json"))
    args = p.parse_args(argv)
    load_before = machine_load()
    cases = [Case(method, name, args.render_rays) for name in args.configs.split(",")
             for method in args.methods.split(",")]
    rows = interleaved(cases, args.steps, args.repeats)
    first = f"{rows[0]['method']}/{rows[0]['config']}"
    for row in rows:
        print(f"{row['method']:6s} {row['config']:18s} {row['field']:12s} {row['samples_per_ray']:>7s} samples  "
              f"train {row['train_rays_per_s']:8.0f} rays/s (x{row['train_ratio_to_first']:.2f} of {first}, "
              f"{row['step_s']:.2f} s/step, compile {row['compile_s']:.0f} s)  render "
              f"{row['render_rays_per_s']:8.0f} rays/s (x{row['render_ratio_to_first']:.2f})", flush=True)
    out = {"machine": {"platform": platform.platform(), "devices": [str(d) for d in jax.local_devices()],
                       **machine_load(), "load_before": load_before},
           "protocol": f"{args.repeats} interleaved rounds of {args.steps} steps and one render per case; "
                       "medians; ratios per round against the first case",
           "results": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
