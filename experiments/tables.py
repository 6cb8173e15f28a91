"""A table's numbers and files: aggregates over seeds, paired deltas, verdicts, markdown.

  * `aggregate(...)`: mean / standard deviation over seeds of each metric (METRIC_PATHS);
  * `add_paired_delta(...)`, `verdict(...)`, `claim_line(...)`: a paired effect against the
    paper's figure (VERDICT_RULE);
  * `markdown_table(...)`, `write_results(...)`: results/<name>.json and results/<name>.md
    with the command, settings, machine and wall time.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from experiments import settings
from jaxnerf_grid.nerf.samplers.legacy import upgrade_flat_model
from jaxnerf_grid.util import io

METRIC_PATHS = {
    "psnr": ("metrics", "mean", "psnr"),
    "ssim": ("metrics", "mean", "ssim"),
    "ms_ssim": ("metrics", "mean", "ms_ssim"),
    "lpips": ("metrics", "mean", "lpips"),
    "psnr_tower": ("metrics", "regions_mean", "tower"),
    "psnr_near_ground": ("metrics", "regions_mean", "near_ground"),
    "psnr_far_background": ("metrics", "regions_mean", "far_background"),
    "distractor_psnr": ("metrics", "distractor_psnr"),
    "psnr_right_half": ("metrics", "mean_right_half", "psnr"),
    "seconds_per_step": ("seconds_per_step",),
    "geometry_f": ("metrics", "geometry", "thresholds", "0.02", "fscore"),
    "wall_s": ("wall_s",),  # train + eval wall seconds when the run ran (what `runner.recorded_runs` reads back)
}


def value_at(d, path):
    for k in path:
        if not isinstance(d, dict) or d.get(k) is None:
            return None
        d = d[k]
    return d


def aggregate(records: list[dict | None], extra: dict | None = None) -> dict:
    """Mean / standard deviation (ddof 0) / values over the seeds of one condition.

    records: runner.run_condition results (None = not run). extra: {name: [value per record]}.
    """
    done = [r for r in records if r is not None]
    out = {"n": len(done), "seeds": [r["seed"] for r in done], "runs": [r["run_dir"] for r in done]}
    columns = {k: [value_at(r, p) for r in done] for k, p in METRIC_PATHS.items()}
    for k, vals in (extra or {}).items():
        columns[k] = [v for v, r in zip(vals, records) if r is not None]
    for k, vals in columns.items():
        vals = [float(v) for v in vals if v is not None and np.isfinite(v)]
        out[k] = ({"mean": float(np.mean(vals)), "std": float(np.std(vals)), "values": vals} if vals else None)
    return out


def values_by_seed(agg: dict, key: str = "psnr") -> dict:
    """{seed: value} from agg["seeds"] and agg[key]["values"], or {} when they are not one value per seed."""
    seeds, values = agg["seeds"], agg[key]["values"]
    return dict(zip(seeds, values)) if len(seeds) == len(values) else {}


def add_paired_delta(agg: dict | None, base: dict | None, key: str = "psnr", name: str = "delta_psnr") -> None:
    """agg[name] = mean / std of (agg - base) over the seeds both have (a paired difference: the
    scene-to-scene spread that dominates the per-row std cancels). Nothing when no seed is shared."""
    if not agg or not base or not agg.get(key) or not base.get(key):
        return
    a, b = values_by_seed(agg, key), values_by_seed(base, key)
    d = [a[s] - b[s] for s in sorted(set(a) & set(b))]
    if d:
        agg[name] = {"mean": float(np.mean(d)), "std": float(np.std(d)), "values": d}


VERDICT_RULE = ("Verdict on a paired effect (dB) over seeds: 'reproduced' when every seed's effect is positive and "
                "the mean is at least half the paper's figure; 'partly' when the mean is positive and at least two "
                "thirds of the seeds are, but the mean is below half the paper's figure or a seed is not positive; "
                "'not reproduced' otherwise (the mean is not positive, or the seeds disagree).")


def verdict(effect: dict | None, paper: float) -> str:
    """'reproduced' | 'partly' | 'not reproduced' | 'not run' for a paired effect {mean, std, values}
    against the paper's figure `paper` (same sign convention: positive = the paper's method is better).
    The rule is VERDICT_RULE."""
    if not effect or not effect.get("values"):
        return "not run"
    values = np.asarray(effect["values"], np.float64)
    mean, positive = float(values.mean()), float(np.mean(values > 0))
    if positive == 1.0 and mean >= 0.5 * paper:
        return "reproduced"
    if mean > 0 and positive >= 2 / 3:
        return "partly"
    return "not reproduced"


def claim_line(name: str, effect: dict | None, paper: float) -> str:
    """One markdown line: the claim, the paper's figure, ours (mean ± std, n) and the verdict."""
    if not effect or not effect.get("values"):
        return f"- {name}: paper {paper:+.2f} dB; ours not run."
    return (f"- {name}: paper {paper:+.2f} dB; ours {effect['mean']:+.2f} ± {effect['std']:.2f} dB over "
            f"{len(effect['values'])} seed(s) (values {', '.join(f'{v:+.2f}' for v in effect['values'])}): "
            f"**{verdict(effect, paper)}**.")


def fmt(cell: dict | None, digits: int = 2) -> str:
    if cell is None:
        return "n/a"
    if len(cell["values"]) == 1:
        return f"{cell['mean']:.{digits}f}"
    return f"{cell['mean']:.{digits}f} ± {cell['std']:.{digits}f}"


def markdown_table(rows: list[tuple[str, dict]], columns: list[tuple[str, str, int]]) -> list[str]:
    """rows: (label, aggregate); columns: (aggregate key, header, digits). Missing rows: 'not run'."""
    lines = ["| condition | n | " + " | ".join(h for _, h, _ in columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    for label, agg in rows:
        if agg is None or agg["n"] == 0:
            lines.append(f"| {label} | 0 | " + " | ".join("not run" for _ in columns) + " |")
        else:
            lines.append(f"| {label} | {agg['n']} | " + " | ".join(fmt(agg.get(k), d) for k, _, d in columns) + " |")
    return lines


def field_summary(model: dict) -> str:
    """One phrase for a setting's field and sampler, e.g. 'MLP 3x64, 16+16 samples per ray'."""
    field = model["field"]
    if field.get("kind") == "grid":
        g = field["grid"]
        text = (f"hash-grid field ({g['num_levels']} levels, 2^{g['log2_table_size']} entries, resolution "
                f"{g['min_resolution']}-{g['max_resolution']}) with a {field['depth']}x{field['width']} MLP")
    else:
        text = f"MLP {field['depth']}x{field['width']}"
    sampler = upgrade_flat_model(model)["sampler"]
    if sampler["kind"] == "proposal":
        rounds = "+".join(map(str, sampler["samples"]))
        return text + f", proposal sampling {rounds} -> {sampler['main_samples']} samples"
    return text + f", {'+'.join(map(str, sampler['samples']))} samples per ray"


def settings_summary(ctx) -> dict:
    return {"setting": ctx.setting, "seeds": ctx.seeds, "steps": ctx.steps, "overrides": ctx.overrides,
            "scene_sizes": {k: dict(zip(("width", "height", "num_train", "num_test", "supersample"), v))
                            for k, v in settings.SCENE_SIZES[ctx.setting].items()}}


def machine_line(info: dict) -> str:
    cpu = info.get("cpu_model", "CPU")
    load = f", 1-min load average {info['load_avg_1min']:.1f} at the start" if "load_avg_1min" in info else ""
    return (f"{info['cpu_count']} x {cpu}, JAX {info['jax']} on {info['backend']} "
            f"({len(info['devices'])} devices){load}, {info['date_utc']}")


def not_run_text(entries: list[str]) -> str:
    """"LABEL seed N" entries, each label once, grouped by the seeds it misses:
    ["a seed 0", "b seed 0", "a seed 1"] -> "seeds 0, 1: a; seed 0: b"."""
    seeds_of: dict[str, list[int]] = {}
    for e in entries:
        label, _, seed = e.rpartition(" seed ")
        seeds_of.setdefault(label, []).append(int(seed))
    groups: dict[tuple, list[str]] = {}
    for label, seeds in seeds_of.items():
        groups.setdefault(tuple(sorted(seeds)), []).append(label)
    order = sorted(groups, key=lambda k: (-len(k), k))
    return "; ".join(f"seed{'s' if len(k) > 1 else ''} {', '.join(map(str, k))}: {', '.join(groups[k])}" for k in order)


def write_results(ctx, name: str, title: str, body: dict, md_lines: list[str], notes: list[str]) -> Path:
    """results/<name>.json (body + provenance) and results/<name>.md (title, command, machine, tables, notes).
    Paths inside the repository are written relative to its root (`settings.portable`)."""
    wall = time.perf_counter() - ctx.start
    lpips_note = ("LPIPS computed from " + ctx.lpips_weights) if ctx.lpips_weights else \
        "LPIPS unavailable (no --lpips-weights given); never a made-up number"
    restored = set(ctx.restored)
    num_runs = len(set(ctx.run_seconds) | restored)
    payload = {"table": name, "title": title, "command": ctx.command, "machine": ctx.machine,
               "settings": settings_summary(ctx), "wall_seconds": wall,
               "runs_seconds": sum(ctx.run_seconds.values()), "num_runs": num_runs, "lpips": lpips_note,
               "not_run_for_budget": ctx.not_run, "runs_from_results_files": sorted(restored),
               **body, "notes": notes}
    io.write_json(ctx.results / f"{name}.json", settings.portable(payload))
    o = settings.TRAIN_SETTINGS[ctx.setting]["overrides"]
    untimed = (f"; {len(restored)} of them read back from the committed results files, "
               f"{len(restored - set(ctx.run_seconds))} of those with no recorded wall time, not counted"
               ) if restored else ""
    head = [f"# {title}", "", f"Command: `{ctx.command}`", "",
            f"Machine: {machine_line(ctx.machine)}. The table's {num_runs} NeRF runs took "
            f"{sum(ctx.run_seconds.values()) / 60:.1f} min of train + eval wall time as recorded when each ran "
            f"(runs shared with another table counted in both{untimed}); this invocation took {wall / 60:.1f} min "
            "(runs already done in the cache are not re-run).", "",
            f"Setting `{ctx.setting}`: {ctx.seeds} seed(s), {ctx.steps} steps per run, "
            f"{o['train']['batch_rays']} rays per step, {field_summary(o['model'])} unless stated; "
            "scenes " + ", ".join(f"{k} {v[0]}x{v[1]} ({v[2]} train / {v[3]} test views)"
                                  for k, v in settings.SCENE_SIZES[ctx.setting].items()) + ".",
            "Cells: mean ± standard deviation over seeds (one value when n = 1). " + lpips_note + ".", ""]
    tail = [""] + [f"- {n}" for n in notes]
    if ctx.not_run:
        tail.append(f"- Not run (time budget, or not chosen by --train-only; {len(ctx.not_run)} runs): "
                    f"{not_run_text(ctx.not_run)}.")
    text = settings.portable("\n".join(head + md_lines + tail) + "\n")
    (ctx.results / f"{name}.md").write_text(text)
    print(text)
    return ctx.results / f"{name}.md"
