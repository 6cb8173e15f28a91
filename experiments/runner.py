"""Running a table: the command line, the context of one invocation, and one run per condition.

  * `base_parser(...)`, `make_context(...)`: the flags every table shares and what they decide;
  * `run_condition(...)`: train + evaluate one (dataset, method, overrides, seed) in a run
    directory named by a hash of all of it (`run_key`); a run whose metrics.json exists is
    skipped, one that was killed resumes from its last checkpoint (so a table can be
    re-launched), and a run a committed results file records is read back from it
    (`recorded_runs`);
  * `cpu_defaults()`: the scripts' entry points call it (importing sets nothing).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import re
import sys
import time
from pathlib import Path

import jax
import numpy as np

from experiments import settings, tables
from jaxnerf_grid.config import build, run_config
from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.schema import merge
from jaxnerf_grid.data.formats.transforms_json import read_meta
from jaxnerf_grid.nerf import models
from jaxnerf_grid.nerf.fields.base import old_layout
from jaxnerf_grid.nerf.samplers.legacy import flat_keys
from jaxnerf_grid.util import io


def cpu_defaults() -> None:
    """JAX on the CPU with two host devices unless the environment says otherwise: what the
    committed results ran on. Called by the scripts' entry points before any JAX device is
    touched (when JAX is already imported, its platform setting is set too)."""
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    if "jax" in sys.modules:
        import jax

        if not jax.config.jax_platforms:
            jax.config.update("jax_platforms", os.environ["JAX_PLATFORMS"])


def enable_compile_cache(path: Path = settings.CACHE / "jax_cache") -> None:
    """Persistent XLA compilation cache: runs that differ only in the seed share compilations."""
    import jax

    path.mkdir(parents=True, exist_ok=True)
    try:
        jax.config.update("jax_compilation_cache_dir", str(path))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    except Exception as exc:  # an older/newer jax without these options: just slower
        print(f"(no persistent compilation cache: {exc})", file=sys.stderr)


def machine_info() -> dict:
    import jax

    info = {"date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "python": platform.python_version(),
            "platform": platform.platform(), "cpu_count": os.cpu_count(), "jax": jax.__version__,
            "backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()]}
    try:
        info["load_avg_1min"] = os.getloadavg()[0]
    except OSError:
        pass
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu_model"] = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return info


def base_parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--quick", dest="setting", action="store_const", const="quick",
                   help="small scenes and short training (2-core CPU; default)")
    g.add_argument("--standard", dest="setting", action="store_const", const="standard",
                   help="the grid field and proposal sampling for every method, sized to resolve the tower on "
                        "the 2-core CPU (about 5 min per run)")
    g.add_argument("--full", dest="setting", action="store_const", const="full",
                   help="the full setting: 3 seeds, larger scenes, more steps (GPU machine)")
    p.set_defaults(setting="quick")
    p.add_argument("--seeds", type=int, default=None, help="number of seeds (default: 1 quick, 3 full)")
    p.add_argument("--steps", type=int, default=None, help="training steps per run (default: by setting)")
    p.add_argument("--cache", default=str(settings.CACHE),
                   help="scenes, mask variants and runs (default experiments/.cache)")
    p.add_argument("--results", default=None,
                   help="where <table>.json / .md / .png go (default experiments/results/ for --quick, "
                        "experiments/results/<setting>/ otherwise)")
    p.add_argument("--budget-min", type=float, default=None,
                   help="stop launching new runs after this many minutes; missing rows are marked 'not run'")
    p.add_argument("--train-only", default=None, metavar="REGEX",
                   help="train only the runs whose 'LABEL seed N' matches this regular expression (re.search); "
                        "the others come from the cache or are marked 'not run' (to queue runs in a chosen order)")
    p.add_argument("--ignore-recorded", action="store_true",
                   help="train runs that are missing from the cache even when a committed results file records "
                        "them (by default such a run is read back from the results file: `recorded_runs`)")
    p.add_argument("--lpips-weights", default=None, help="LPIPS weights .npz (else LPIPS is reported unavailable)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


@dataclasses.dataclass
class Context:
    """What one table invocation needs: setting, paths, budget, and what has been run."""

    setting: str
    seeds: int
    steps: int
    cache: Path
    results: Path
    budget_s: float | None
    lpips_weights: str | None
    progress: bool
    command: str
    start: float = dataclasses.field(default_factory=time.perf_counter)
    machine: dict = dataclasses.field(default_factory=dict)
    not_run: list = dataclasses.field(default_factory=list)  # "LABEL seed N": over budget or not --train-only
    run_seconds: dict = dataclasses.field(default_factory=dict)  # run dir -> recorded train + eval wall s
    train_only: str | None = None  # regex on "LABEL seed N": runs that may be trained; None = all
    recorded: dict | None = None  # (seed, run key) -> a run read back from committed results (`recorded_runs`)
    restored: list = dataclasses.field(default_factory=list)  # run dirs taken from `recorded` in this invocation

    def may_train(self, name: str) -> bool:
        """Whether the run called `name` ("LABEL seed N") may be trained in this invocation."""
        return self.train_only is None or re.search(self.train_only, name) is not None

    @property
    def overrides(self) -> dict:
        return json.loads(json.dumps(settings.TRAIN_SETTINGS[self.setting]["overrides"]))

    @property
    def distractor_views(self) -> int:
        return settings.TRAIN_SETTINGS[self.setting]["distractor_views"]

    @property
    def cloud_views(self) -> int:
        """Training views whose depth joins the test views' in the tower cloud (eval's geometry_f)."""
        return settings.TRAIN_SETTINGS[self.setting].get("cloud_views", 0)

    def out_of_budget(self) -> bool:
        return self.budget_s is not None and time.perf_counter() - self.start > self.budget_s


def make_context(args, script: str) -> Context:
    setting = args.setting
    seeds = args.seeds or settings.TRAIN_SETTINGS[setting]["seeds"]
    steps = args.steps or settings.TRAIN_SETTINGS[setting]["steps"]
    flags = [f"--{setting}"] + [a for a in sys.argv[1:] if a not in ("--quick", "--standard", "--full")]
    command = f"JAX_PLATFORMS=cpu python -m experiments.{Path(script).stem} " + " ".join(flags)
    results = Path(args.results) if args.results else settings.results_folder(settings.RESULTS, setting)
    ctx = Context(setting, seeds, steps, Path(args.cache), results,
                  None if args.budget_min is None else args.budget_min * 60, args.lpips_weights, not args.quiet,
                  command.strip(), train_only=args.train_only)
    ctx.cache.mkdir(parents=True, exist_ok=True)
    ctx.results.mkdir(parents=True, exist_ok=True)
    enable_compile_cache(ctx.cache / "jax_cache")
    ctx.machine = machine_info()
    if not getattr(args, "ignore_recorded", False):
        folders = {ctx.results, settings.results_folder(settings.RESULTS, setting),
                   settings.results_folder(settings.BENCH_RESULTS, setting)}
        ctx.recorded = recorded_runs(sorted(folders))
    return ctx


# Training settings added after the committed results were made. At their defaults they change
# nothing for those runs (train.max_side 640 leaves every synthetic scene, 320 px wide at most, at
# full size; train.robust "off" is the training they had), so the run key leaves them out there
# and the results files keep their runs; any other value is in the key.
LATER_TRAIN_KEYS = ("max_side", "robust", "robust_quantile", "robust_flagged_quantile", "robust_patch",
                    "robust_patch_stride",
                    "robust_patch_share", "robust_floor", "robust_spread",
                    "robust_warmup", "robust_confirm", "robust_views", "sparse_adam", "robust_scattered", "depth",
                    "lowres_share", "lowres_factor", "error_share", "error_tile",
                    "robust_refine", "robust_prior_grow")  # the last two: scheme "refine_keys_always" keeps them


def run_key(data_dir: Path, method: str, overrides: dict, steps: int, scheme: str = "current",
            meta: dict | None = None) -> str:
    """Hash of the dataset folder's name, the fully resolved RunConfig and the step count.
    meta: the dataset's transforms.json (read here when None).

    scheme "current": LATER_TRAIN_KEYS at their defaults are left out, and so is
    train.robust.strict_readmit wherever it does nothing (`config.strict_readmit_acts` on the
    dataset: off is what ran before it existed); where it acts it is in the key as true.
    scheme "refine_keys_always": the key of runs made while robust_refine, robust_prior_grow
    and robust_strict_readmit (then false by default) were always in the key (`run_keys`); there
    it is true only where it acts, as above, so a run of another mode is found at the default."""
    with_steps = merge(overrides, {"train": {"max_steps": int(steps)}})
    cfg = config_lib.to_dict(run_config.make_config(method, with_steps))
    cfg["model"] = {**{k: v for k, v in cfg["model"].items() if k != "sampler"},  # the flat sampler keys, as
                    **flat_keys(with_steps.get("model", {}))}  # before model.sampler: runs keep their keys
    cfg["model"]["field"] = old_layout(cfg["model"]["field"])  # every kind's keys, as before the field kinds
    cfg["train"] = run_config.flat_robust(cfg["train"])  # the flat robust keys, as before train.robust nested
    defaults = run_config.flat_robust(config_lib.to_dict(run_config.TrainConfig()))
    meta = read_meta(data_dir) if meta is None else meta
    acts = config_lib.strict_readmit_acts(cfg["train"]["robust_strict_readmit"], cfg["train"]["robust"], meta)
    later = LATER_TRAIN_KEYS if scheme == "current" else LATER_TRAIN_KEYS[:-2]
    cfg["train"] = {k: v for k, v in cfg["train"].items()  # settings added since, at their defaults
                    if not (k in later and v == defaults[k]) and k != "robust_strict_readmit"}
    if scheme != "current":
        cfg["train"]["robust_strict_readmit"] = acts
    elif acts:
        cfg["train"]["robust_strict_readmit"] = True
    blob = json.dumps({"data": Path(data_dir).name, "config": cfg}, sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:10]


def run_keys(data_dir: Path, method: str, overrides: dict, steps: int) -> list[str]:
    """The keys an identical finished run may be found under: `run_key`'s current scheme first
    (a new run is made under it), then the "refine_keys_always" scheme's."""
    meta = read_meta(data_dir)
    keys = [run_key(data_dir, method, overrides, steps, scheme, meta) for scheme in ("current", "refine_keys_always")]
    return list(dict.fromkeys(keys))


def condition_config(setting: str, method: str, overrides: dict, steps: int) -> build.Built:
    """A condition's config through the one builder (config/build.py): the setting's recipe with
    `method`, the steps pinned (so no training budget applies), the condition's `overrides` (the
    setting's, its space and the table's own, in the flat layout the run keys hash) as the last
    layer. No dataset folder is given: a condition's space is the setting's, never the dataset's
    recorded bounds (the committed runs trained so, and their keys say so)."""
    request = build.Request(recipe=settings.TRAIN_SETTINGS[setting]["recipe"], method=method, steps=int(steps))
    return build.build(request, extra=overrides)


def run_condition(ctx: Context, data_dir: Path, method: str, seed: int, label: str,
                  overrides: dict | None = None, steps: int | None = None) -> dict | None:
    """Trains and evaluates one condition (skipped when its metrics.json exists).

    Returns {"metrics": metrics.json, "run_dir", "train_seconds", "seconds_per_step", "cached"},
    or None when the time budget is spent before the run starts.
    """
    from jaxnerf_grid.eval import evaluate
    from jaxnerf_grid.train import runs

    steps = int(steps or ctx.steps)
    ov = merge(merge(ctx.overrides, settings.space_overrides(ctx.setting, method, overrides)), overrides or {})
    ov = merge(ov, {"train": {"seed": int(seed)}})
    keys = run_keys(data_dir, method, ov, steps)
    key = keys[0]
    run_dir = ctx.cache / "runs" / f"{label}-s{seed}-{key}"
    runs_dir = ctx.cache / "runs"
    same = sorted(runs_dir.glob(f"*-s{seed}-{key}")) + [  # an older key's run only when finished
        d for k in keys[1:] for d in sorted(runs_dir.glob(f"*-s{seed}-{k}")) if (d / "metrics.json").is_file()]
    if not run_dir.exists() and same:  # the identical run made by another table, or under an older key
        run_dir = same[0]
    done = run_dir / "metrics.json"
    info_path = run_dir / "experiment.json"
    if done.is_file() and info_path.is_file():
        info = io.read_json(info_path)
        ctx.run_seconds[str(run_dir)] = info["train_wall_s"] + info["eval_wall_s"]
        return {**info, "wall_s": ctx.run_seconds[str(run_dir)], "metrics": io.read_json(done), "cached": True}
    restored = next((r for r in ((ctx.recorded or {}).get((int(seed), k)) for k in keys) if r is not None), None)
    if restored is not None:
        ctx.restored.append(restored["run_dir"])
        if restored.get("wall_s") is not None:
            ctx.run_seconds[restored["run_dir"]] = restored["wall_s"]
        print(f"[recorded] {label} seed {seed}: from {restored['recorded_in']}", flush=True)
        return restored
    if ctx.out_of_budget() or not ctx.may_train(f"{label} seed {seed}"):
        ctx.not_run.append(f"{label} seed {seed}")
        print(f"[not run] {label} seed {seed} (time budget, or not chosen by --train-only)", flush=True)
        return None
    print(f"[run] {label} seed {seed} ({method}, {steps} steps) -> {run_dir}", flush=True)
    t0 = time.perf_counter()
    from jaxnerf_grid.data.formats import load_dataset

    ds = load_dataset(data_dir, progress=ctx.progress)
    built = condition_config(ctx.setting, method, ov, steps)
    _, cfg, result = runs.train_run(str(data_dir), method, run_dir, built.overrides, steps, progress=ctx.progress,
                                    dataset=ds)
    t_train = time.perf_counter() - t0
    t1 = time.perf_counter()
    metrics = evaluate.evaluate_run(run_dir, ctx.lpips_weights, progress=ctx.progress, dataset=ds,
                                    distractor_views=ctx.distractor_views, cloud_views=ctx.cloud_views)
    t_eval = time.perf_counter() - t1
    # Each run compiles its own programs and jax's caches keep them all: a long table reached Linux's
    # limit of memory mappings per process in the test suite (tests/conftest.py). Free them per run.
    jax.clear_caches()
    info = {"label": label, "seed": seed, "method": method, "steps": steps, "data": str(data_dir),
            "run_dir": str(run_dir), "overrides": ov, "train_wall_s": t_train, "eval_wall_s": t_eval,
            "seconds_per_step": seconds_per_step(run_dir, cfg.train.batch_rays),
            "samples_per_ray": models.samples_per_ray(cfg.model)}
    io.write_json(info_path, info)
    ctx.run_seconds[str(run_dir)] = t_train + t_eval
    print(f"[done] {label} seed {seed}: test PSNR {metrics['mean']['psnr']:.2f} dB "
          f"(train {t_train:.0f} s, eval {t_eval:.0f} s)", flush=True)
    return {**info, "wall_s": t_train + t_eval, "metrics": metrics, "cached": False}


def seconds_per_step(run_dir: Path, batch_rays: int) -> float | None:
    """Median seconds per step over the logged windows after the first (which holds the compilation)."""
    path = Path(run_dir) / "metrics.jsonl"
    if not path.is_file():
        return None
    rates = [json.loads(line)["rays_per_s"] for line in path.read_text().splitlines() if line.strip()]
    rates = rates[1:] or rates
    return float(batch_rays / np.median(rates)) if rates else None


RUN_DIR_NAME = re.compile(r"-s(\d+)-([0-9a-f]{10})$")  # LABEL-sSEED-KEY, as run_condition names run folders


def _put(tree: dict, path: tuple, value) -> None:
    for k in path[:-1]:
        tree = tree.setdefault(k, {})
    tree[path[-1]] = value


def _aggregates(obj):
    """Every aggregate (a dict with aligned "seeds" and "runs" lists) anywhere inside a results JSON."""
    if isinstance(obj, dict):
        if isinstance(obj.get("runs"), list) and isinstance(obj.get("seeds"), list) \
                and len(obj["runs"]) == len(obj["seeds"]):
            yield obj
        for v in obj.values():
            yield from _aggregates(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _aggregates(v)


def recorded_date(data) -> str:
    """A results file's `machine.date_utc` ("" where the file has none: a file of another
    benchmark may hold anything, e.g. `machine` as a sentence)."""
    machine = data.get("machine") if isinstance(data, dict) else None
    return str(machine.get("date_utc", "")) if isinstance(machine, dict) else ""


def recorded_runs(folders) -> dict:
    """Finished runs as the committed results files record them: {(seed, run key): record}.

    The cache (experiments/.cache) is git-ignored, so a fresh clone has no finished run; the
    results files have every run's numbers. Each aggregate in each *.json directly under `folders`
    lists its run folders (LABEL-sSEED-KEY, KEY = `run_key`: the dataset folder's name, the fully
    resolved config and the step count, so an equal key is the identical run) and, per metric of
    tables.METRIC_PATHS, the values in the same order. A record is shaped like run_condition's return
    (each metric at its METRIC_PATHS place, "recorded_in" the file); a metric is taken only where
    its values line up one-to-one with the runs (aggregate drops missing values, so a shorter list
    cannot be assigned). Where two files record one run differently (a table assembled before the
    run was evaluated again), the newest file (machine.date_utc) wins, with a warning.
    """
    files = [f for folder in folders if Path(folder).is_dir() for f in sorted(Path(folder).glob("*.json"))]
    loaded = []
    for f in files:
        try:
            loaded.append((f, json.loads(f.read_text())))
        except (OSError, ValueError) as exc:
            print(f"(results file {f} not read as a record of runs: {exc})", file=sys.stderr)
    loaded.sort(key=lambda fd: recorded_date(fd[1]), reverse=True)
    out: dict = {}
    for f, data in loaded:
        where = str(settings.portable(str(f.resolve())))
        for agg in _aggregates(data):
            aligned = {k: agg[k]["values"] for k in tables.METRIC_PATHS
                       if isinstance(agg.get(k), dict) and len(agg[k].get("values", [])) == len(agg["runs"])}
            for i, (seed, run) in enumerate(zip(agg["seeds"], agg["runs"])):
                m = RUN_DIR_NAME.search(Path(str(run)).name)
                if m is None or int(m.group(1)) != int(seed):
                    continue
                rec = out.setdefault((int(seed), m.group(2)), {"seed": int(seed), "run_dir": str(run),
                                                              "label": Path(str(run)).name[:m.start()],
                                                              "cached": True, "recorded_in": where})
                for k, vals in aligned.items():
                    old = tables.value_at(rec, tables.METRIC_PATHS[k])
                    if old is None:
                        _put(rec, tables.METRIC_PATHS[k], vals[i])
                    elif abs(float(old) - float(vals[i])) > 1e-9 * max(1.0, abs(float(old))):
                        print(f"(run {Path(str(run)).name}: {k} is {old} in {rec['recorded_in']} but {vals[i]} in "
                              f"{where}; the newer file's is kept)", file=sys.stderr)
    return out
