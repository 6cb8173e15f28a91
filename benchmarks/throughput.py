"""Training and rendering throughput (rays/s) per method and config, and their ratios, measured
in one run with the cases interleaved.

    JAX_PLATFORMS=cpu XLA_FLAGS=--xla_force_host_platform_device_count=2 \
        python -m benchmarks.throughput [--steps 5] [--repeats 3] [--configs mlp,grid-hierarchical,demo]
        [--methods ours] [--batch-rays N]

Configs: "mlp" (the MLP field with 32 + 32 hierarchical samples, the demo before the grid),
"grid-hierarchical" (the demo's hash grid with that sampler), "demo" (the `ours` recipe, the
experiments': hash grid + proposal sampling, 64 -> 32 samples), "paper-small" (an 8 x 256 MLP, 64 + 128);
"demo-linear", "demo-log", "demo-piecewise", "mlp-linear", ... (that ray warp instead of disparity);
"demo-sparse-adam" (the demo with train.sparse_adam), "ours-fast" (`ours` with a smaller proposal
field, docs/GRID.md), "ours-lean" (ours-fast with a leaner main field: the demo's recipe now);
any of them + "-fused" (e.g. "demo-piecewise-fused"): traced without
fields.hashgrid.computed_once, to measure what it saves; + "-concat" (e.g. "ours-fast-concat"):
traced with the colour branch's input concatenated at every sample, to measure what
fields.layers.first_colour_layer saves. `--variant NAME=BASE:KEY=VALUE;...` adds a config NAME, BASE
with `--set` style changes (e.g. `--variant m24=ours-fast:model.sampler.main_samples=24 --configs
ours-fast,m24`).

Every (method, config) is set up and compiled first (compile time reported separately). Then
`--repeats` rounds, each timing `--steps` training steps (block_until_ready) and the rendering
of `--render-rays` rays of every case in turn (round-robin), so a change in the machine's load
hits all cases alike. Reported per case: the median over the rounds; per case against the
first: the median of the per-round ratios (train and render rays/s), which is the number to
compare, as absolute rays/s move with whatever else runs on a shared machine. The load average
(os.getloadavg) before and after and the CPU count are written with the results. The scene is a
160x120, 8-frame synthetic dataset of random pixels (throughput does not depend on the content).
Prints a table and writes benchmarks/results/throughput.json.

`--processes` (docs/DISTRIBUTED.md) instead compares, on this machine, training with
1 process x 2 CPU devices against 2 processes x 1 device (jax.distributed, gloo), each in fresh
subprocesses, for the first --configs entry: rays/s of each and their ratio, and the cost of the
cross-process collective (the median time of a psum of a parameter-sized pytree, both ways).
Writes benchmarks/results/throughput_processes.json.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.convergence import MLP_CONFIG, RUNS
from jaxnerf_grid.config import recipes
from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.schema import merge
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.nerf import models
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.nerf.fields import hashgrid
from jaxnerf_grid.render import views
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train import speed
from jaxnerf_grid.util import parallel

CONFIGS = {
    "mlp": MLP_CONFIG,
    "grid-hierarchical": RUNS["grid-hierarchical"],
    "demo": recipes.overrides("ours"),
    "paper-small": {"model": {"field": {"depth": 8, "width": 256, "skip": 4, "view_width": 128},
                              "sampler": {"kind": "hierarchical", "samples": [64, 128]}},
                    "train": {"batch_rays": 1024}},
}
# The demo recipe and the MLP with each of the other ray warps (their own is disparity).
for _warp in ("linear", "log", "piecewise"):
    for _name in ("demo", "mlp"):
        CONFIGS[f"{_name}-{_warp}"] = {**CONFIGS[_name], "model": {**CONFIGS[_name]["model"], "warp": _warp}}
# The demo with lazy Adam on its hash tables, and the recipe ours-fast (the
# demo with a smaller proposal field, recipes.SAMPLERS; measured beside "demo", docs/GRID.md).
CONFIGS["demo-sparse-adam"] = merge(CONFIGS["demo"], {"train": {"sparse_adam": True}})
CONFIGS["ours-fast"] = recipes.overrides("ours-fast")
# The demo's recipe now, ours-fast with a leaner main field (docs/GRID.md)
CONFIGS["ours-lean"] = recipes.overrides("ours-lean")
# The demo trained with the photometric evidence (4x4 patches), without and with the
# multi-view confirmation (photo_consistency.py), to price the confirmation (docs/ROBUST.md).
CONFIGS["demo-robust"] = merge(CONFIGS["demo"], {"train": {"robust": "robust", "robust_confirm": 0.0}})
CONFIGS["demo-robust-confirm"] = merge(CONFIGS["demo"], {"train": {"robust": "robust", "robust_confirm": 0.01}})
# A config name ending in FUSED (e.g. "demo-piecewise-fused") is that config traced with
# fields.hashgrid.computed_once as a no-op: the code before it, where XLA:CPU recomputed the
# points' chain (warp, contraction) in every corner fusion of the hash grid. A name ending in
# CONCAT (e.g. "ours-fast-concat") is traced with the colour branch's input concatenated at every
# sample, the view direction encoded per sample: the code before fields.layers.first_colour_layer
# (docs/GRID.md).
FUSED = "-fused"
CONCAT = "-concat"


def _per_sample_first_colour_layer(layer, feature, viewdirs, appearance, cfg):
    """fields.layers.first_colour_layer as it was before the per-ray direction: [feature, encoded direction,
    appearance] broadcast and concatenated at every sample, then one dense layer."""
    from jaxnerf_grid.nerf import coords
    from jaxnerf_grid.nerf.fields import layers

    branch = [feature]
    lead = feature.shape[:-1]
    if cfg.use_viewdirs:
        branch.append(coords.positional_encoding(jnp.broadcast_to(viewdirs, (*lead, 3)), 0, cfg.dir_max_deg))
    if cfg.appearance_dim > 0:
        app = appearance if appearance is not None else jnp.zeros((cfg.appearance_dim,), feature.dtype)
        branch.append(jnp.broadcast_to(app, (*lead, cfg.appearance_dim)))
    return layers.dense(layer, jnp.concatenate(branch, axis=-1))


@contextlib.contextmanager
def _tracing_as_before(suffix: str):
    """Traces with the code before the change named by a config's suffix (FUSED, CONCAT, or "")."""
    from jaxnerf_grid.nerf.fields import layers

    saved = hashgrid.computed_once, layers.first_colour_layer
    if suffix == FUSED:
        hashgrid.computed_once = lambda x: x
    if suffix == CONCAT:
        layers.first_colour_layer = _per_sample_first_colour_layer
    try:
        yield
    finally:
        hashgrid.computed_once, layers.first_colour_layer = saved


def scene(width=160, height=120, frames=8) -> Dataset:
    """The budget's calibration scene (random colours, a ring of cameras), its last frame held out."""
    ds = speed.calibration_scene(frames, (width, height))
    return dataclasses.replace(ds, root=Path("bench"), split={"train": np.arange(frames - 1),
                                                              "test": np.array([frames - 1])})


def samples_per_ray(mcfg) -> str:
    """Samples per ray by pass, e.g. "64p+32" (proposal + main) or "32+32" (models.label)."""
    return models.label(mcfg)


class Case:
    """One (method, config): its compiled training step and renderer, state and rays, ready to time."""

    def __init__(self, method: str, name: str, render_rays: int, batch_rays: int = 0):
        self.suffix = next((x for x in (FUSED, CONCAT) if name.endswith(x)), "")
        overrides = json.loads(json.dumps(CONFIGS[name.removesuffix(self.suffix)]))
        overrides.setdefault("train", {})["max_steps"] = 1000
        if batch_rays:  # --batch-rays: every case at this batch (a GPU needs more than the recipe's)
            overrides["train"]["batch_rays"] = batch_rays
        cfg = train.make_config(method, overrides)
        ds = scene()
        self.cfg = cfg = config_lib.resolve(cfg, ds)  # as train.train settles it
        self.method, self.name = method, name
        self.n = n = train.step_devices(cfg.train)  # every process's devices under jax.distributed
        self.pool = train.device_pool(ds, cfg, n)
        self.state = parallel.replicate(train.init_state(cfg, train.train_frames_shape(ds)), n)
        self.step = train.make_train_step(cfg, n)
        self.render_fn = None  # None: render through views' renderer, cached per config
        if self.suffix:  # fresh (uncached) functions, traced below with the code before
            self.step = train._make_train_step.__wrapped__(dataclasses.replace(cfg, data=None), n)
            self.render_fn = views._render_chunk_fn.__wrapped__(cfg.model, n, False)
        r = views.camera_rays(ds, 7, ds.near, ds.far)
        self.rays = rays_lib.Rays(*(np.asarray(x).reshape(-1, *np.asarray(x).shape[2:])[:render_rays] for x in r))
        t = time.perf_counter()
        with _tracing_as_before(self.suffix):
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
        cached = views._render_chunk_fn
        if self.render_fn is not None:
            views._render_chunk_fn = lambda *args: self.render_fn
        try:
            t = time.perf_counter()
            views.render_rays_chunked(params, self.cfg.model, self.rays, 0, None, self.cfg.train.chunk,
                                      train.resolve_devices(self.cfg.train))
            return time.perf_counter() - t
        finally:
            views._render_chunk_fn = cached

    def describe(self) -> dict:
        m = self.cfg.model
        return {"method": self.method, "config": self.name, "devices": self.n, "batch_rays": self.cfg.train.batch_rays,
                "samples_per_ray": samples_per_ray(m), "field": f"{m.field.kind} {m.field.depth}x{m.field.width}",
                "sampler": m.sampler.kind, "compile_s": self.compile_s}


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


def _process_child(config: str, steps: int, port: int, pid: int, nproc: int) -> None:
    """One process of the --processes comparison: prints a JSON line {rays_per_s, psum_s}."""
    import sys

    from jaxnerf_grid.train import distributed

    if nproc > 1:
        distributed.initialize(f"127.0.0.1:{port}", nproc, pid)
    case = Case("ours", config, 16)
    n = case.n
    case.train_steps(2)  # warm
    times = [case.train_steps(steps) for _ in range(3)]
    params = case.state["params"]
    psum = jax.pmap(lambda t: jax.lax.psum(t, parallel.AXIS), axis_name=parallel.AXIS,
                    devices=parallel.devices(n))
    jax.block_until_ready(psum(params))
    psum_times = []
    for _ in range(20):
        t = time.perf_counter()
        jax.block_until_ready(psum(params))
        psum_times.append(time.perf_counter() - t)
    floats = sum(int(np.prod(x.shape[1:])) for x in jax.tree_util.tree_leaves(params))
    print("RESULT " + json.dumps({"process": pid, "processes": nproc, "devices": n,
                                  "step_s": statistics.median(times),
                                  "rays_per_s": case.cfg.train.batch_rays / statistics.median(times),
                                  "psum_s": statistics.median(psum_times), "param_floats": floats}), flush=True)
    sys.stdout.flush()


def compare_processes(config: str, steps: int, out_path: str) -> dict:
    """1 process x 2 devices against 2 processes x 1 device (see the module's docstring)."""
    import socket
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]

    def launch(nproc: int, devices: int) -> list[dict]:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        env = dict(os.environ, PYTHONPATH=str(root), JAX_PLATFORMS="cpu",
                   XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")
        procs = [subprocess.Popen([sys.executable, "-m", "benchmarks.throughput", "--child",
                                   f"{config},{steps},{port},{i},{nproc}"], env=env, cwd=root,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE) for i in range(nproc)]
        rows = []
        for proc in procs:
            out, err = proc.communicate(timeout=900)
            lines = [x for x in out.decode().splitlines() if x.startswith("RESULT ")]
            if proc.returncode or not lines:
                raise RuntimeError(f"child failed ({proc.returncode}): {err.decode()[-2000:]}")
            rows.append(json.loads(lines[-1][7:]))
        return rows

    one = launch(1, 2)[0]
    two = launch(2, 1)
    two_rays = min(r["rays_per_s"] for r in two)  # the processes step together: the slower one's pace
    result = {"config": config, "steps_timed": f"3 x {steps}, median", "one_process_two_devices": one,
              "two_processes_one_device": two, "ratio_two_processes_to_one": two_rays / one["rays_per_s"],
              "psum_ms_one_process": 1e3 * one["psum_s"],
              "psum_ms_two_processes": 1e3 * max(r["psum_s"] for r in two),
              "machine": machine_load()}
    print(f"{config}: 1 process x 2 devices {one['rays_per_s']:.0f} rays/s; 2 processes x 1 device "
          f"{two_rays:.0f} rays/s (x{result['ratio_two_processes_to_one']:.2f}); psum of the "
          f"{one['param_floats']} parameter floats: {result['psum_ms_one_process']:.2f} ms in one process, "
          f"{result['psum_ms_two_processes']:.2f} ms across two (gloo over TCP), per step "
          f"{one['step_s'] * 1e3:.0f} ms", flush=True)
    Path(out_path).parent.mkdir(parents=True, exist_ok=True)
    Path(out_path).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out_path}")
    return result


def parse_variant(text: str) -> tuple[str, str, dict]:
    """'NAME=BASE:KEY=VALUE;KEY=VALUE' -> (NAME, BASE, the nested changes), the keys checked as
    `--set` checks them (config.parse_sets); a bad one is a ConfigError naming it."""
    name, _, rest = text.partition("=")
    base, _, changes = rest.partition(":")
    if not name or not base or base not in CONFIGS:
        raise config_lib.ConfigError(f"--variant {text!r}: expected NAME=BASE:KEY=VALUE[;KEY=VALUE], BASE one of "
                                     f"{', '.join(CONFIGS)}")
    return name, base, config_lib.parse_sets([c for c in changes.split(";") if c], train.RunConfig)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--processes", action="store_true",
                   help="compare 1 process x 2 devices with 2 processes x 1 device (jax.distributed)")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    p.add_argument("--steps", type=int, default=5, help="training steps timed per case per round")
    p.add_argument("--repeats", type=int, default=3, help="rounds over all cases")
    p.add_argument("--render-rays", type=int, default=8192)
    p.add_argument("--configs", default="mlp,grid-hierarchical,demo")
    p.add_argument("--methods", default="ours")
    p.add_argument("--batch-rays", type=int, default=0,
                   help="train every case at this many rays a step (default: each config's own)")
    p.add_argument("--variant", action="append", default=[], metavar="NAME=BASE:KEY=VALUE[;KEY=VALUE]",
                   help="add a config NAME: config BASE with --set style changes, e.g. "
                        "'m24=ours-fast:model.sampler.main_samples=24'; list NAME in --configs (repeatable)")
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "throughput.json"))
    args = p.parse_args(argv)
    for text in args.variant:
        name, base, changes = parse_variant(text)
        CONFIGS[name] = merge(CONFIGS[base], changes)
    if args.child:
        config, steps, port, pid, nproc = args.child.split(",")
        _process_child(config, int(steps), int(port), int(pid), int(nproc))
        return
    if args.processes:
        compare_processes(args.configs.split(",")[0], args.steps,
                          str(Path(args.out).with_name("throughput_processes.json")))
        return
    load_before = machine_load()
    cases = [Case(method, name, args.render_rays, args.batch_rays) for name in args.configs.split(",")
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
