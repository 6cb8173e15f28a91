"""Sampling-scheme benchmark: s-space warps x hierarchical resampling x samples per ray.

Warps (jaxnerf_grid.nerf.samplers.s_space): linear (uniform t), disparity (uniform 1/t, ours), log, piecewise
(mip-NeRF 360's linear-then-disparity), each with and without hierarchical resampling, at 16,
32, 64 and 128 samples per ray, trained for the same steps with the same
batch, MLP and seed on the same scene (tower-small without distractors, so masks play no
part; the model is ours otherwise: dual-sphere contraction).

Samples per ray N = the network's sample budget: without hierarchical resampling N coarse
samples; with it N/2 coarse + N/2 fine (the fine pass runs over the union, as in NeRF).
At `--standard` (the grid field of the demo's recipe) the two samplers are proposal sampling
(the setting's proposal round, its first samples stratified in s through the warp, then N
samples of the main field) and coarse/fine (N/2 + N/2, both on the main field), N from 8 to
128; the summary adds the samples each scheme needs to come within 0.5 dB of its own
128-sample PSNR.

Reported: test PSNR overall and per region (tower / near ground / far background), seconds per
training step (median over logged windows after the first; the machine may be shared, see the
load average), and benchmarks/results/sampling_schemes.png, PSNR against samples per ray. The summary
says which scheme wins and whether any scheme matches uniform-t's PSNR with a quarter of the
samples.

  JAX_PLATFORMS=cpu python -m benchmarks.sampling_schemes [--quick | --full] [--seeds N] [--samples 16 32 64]
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

import numpy as np  # noqa: E402

from experiments import figures, runner, scenes, settings, tables  # noqa: E402

WARPS = ("linear", "disparity", "log", "piecewise")
SAMPLES = {"quick": (16, 32, 64, 128), "standard": (8, 16, 32, 64, 128), "full": (16, 32, 64, 128)}
SAMPLERS = {"quick": ("coarse", "hierarchical"), "standard": ("proposal", "hierarchical"),
            "full": ("coarse", "hierarchical")}
COLUMNS = [("psnr", "PSNR", 2), ("psnr_tower", "PSNR tower", 2), ("psnr_near_ground", "PSNR ground", 2),
           ("psnr_far_background", "PSNR far bg", 2), ("ssim", "SSIM", 3), ("seconds_per_step", "s / step", 3),
           ("delta_psnr_vs_linear", "Δ PSNR vs linear (paired)", 2),
           ("delta_far_vs_linear", "Δ far bg vs linear (paired)", 2)]


def scheme_name(warp: str, hierarchical: bool, setting: str = "quick") -> str:
    if hierarchical:
        return f"{warp} + hierarchical"
    return f"{warp} + proposal" if SAMPLERS[setting][0] == "proposal" else warp


def model_overrides(warp: str, hierarchical: bool, n: int, setting: str = "quick") -> dict:
    """The model flags of a scheme at n samples per ray (the second sampler of the setting when
    `hierarchical`, its first otherwise)."""
    if hierarchical:
        return {"warp": warp, "sampler": "hierarchical", "hierarchical": True, "num_coarse": n // 2,
                "num_fine": n - n // 2}
    if SAMPLERS[setting][0] == "proposal":
        return {"warp": warp, "sampler": "proposal", "num_fine": n}
    return {"warp": warp, "hierarchical": False, "num_coarse": n, "num_fine": 0}


def paired_psnr_delta(agg: dict, base: dict) -> dict | None:
    """{mean, std, values} of agg's PSNR minus base's on the seeds both ran (`tables.add_paired_delta`),
    or None when they share none."""
    both = {"seeds": agg["seeds"], "psnr": agg["psnr"]}
    tables.add_paired_delta(both, base, "psnr", "delta")
    return both.get("delta")


def psnr_gap(cell: dict | None, ref: dict | None) -> dict | None:
    """cell's PSNR minus ref's: {"delta": dB, "seeds": n or None}. Paired over the seeds both ran
    when both cells list their seeds (a mean over different seeds would mix the scenes' spread,
    about 0.5 dB, into the gap); the difference of the means when either does not; None when
    either has no PSNR or they share no seed."""
    if not cell or not ref or not cell.get("psnr") or not ref.get("psnr"):
        return None
    if "seeds" not in cell or "seeds" not in ref:
        return {"delta": cell["psnr"]["mean"] - ref["psnr"]["mean"], "seeds": None}
    d = paired_psnr_delta(cell, ref)
    return {"delta": d["mean"], "seeds": len(d["values"])} if d else None


def psnr_on_common_seeds(cells: dict) -> tuple[dict, list]:
    """({scheme: mean PSNR}, seeds) for cells {scheme: aggregate} that ran at one sample count. When
    they ran different seeds, each mean is over the seeds all of them ran (ranking means over
    different seeds would rank the seeds' scenes, which differ by about 1 dB) and `seeds` lists
    them; when they ran the same seeds, share none, or do not list them: their own means and []."""
    own = {k: a["psnr"]["mean"] for k, a in cells.items()}
    by_seed = {k: tables.values_by_seed(a) if a.get("seeds") else {} for k, a in cells.items()}
    if not all(by_seed.values()):
        return own, []
    common_seeds = sorted(set.intersection(*(set(v) for v in by_seed.values())))
    if not common_seeds or all(sorted(v) == common_seeds for v in by_seed.values()):
        return own, []
    return {k: float(np.mean([v[s] for s in common_seeds])) for k, v in by_seed.items()}, common_seeds


def samples_to_reach(table: dict, scheme: str, samples: tuple, within: float = 0.5) -> int | None:
    """The fewest samples per ray at which `scheme`'s PSNR is within `within` dB of its own PSNR
    at the largest sample count (`psnr_gap`: paired by seed), or None when that is not run."""
    top = table.get((scheme, max(samples)))
    for n in sorted(samples):
        gap = psnr_gap(table.get((scheme, n)), top)
        if gap is not None and gap["delta"] >= -within:
            return n
    return None


def gaps_text(table: dict, scheme: str, samples: tuple) -> str:
    """"8: -5.08 dB over 3 seeds, 16: -1.40 dB over 1 seed, ...": `psnr_gap` at each count below the largest."""
    top, parts = table.get((scheme, max(samples))), []
    for n in sorted(samples)[:-1]:
        gap = psnr_gap(table.get((scheme, n)), top)
        if gap is not None:
            over = f" over {gap['seeds']} seed{'s' if gap['seeds'] != 1 else ''}" if gap["seeds"] else ""
            parts.append(f"{n}: {gap['delta']:+.2f} dB{over}")
    return ", ".join(parts)


def paired_text(agg: dict, base: dict) -> str:
    """", paired over seeds [0, 1, 2]: +a +- b dB (each seed +x, +y, +z)" for the PSNR of agg minus
    base on the seeds both ran (same scene and seed), or "" when they share fewer than two."""
    d = paired_psnr_delta(agg, base)
    if not d or len(d["values"]) < 2:
        return ""
    seeds = sorted(set(agg["seeds"]) & set(base["seeds"]))
    each = ", ".join(f"{v:+.2f}" for v in d["values"])
    return f", paired over seeds {seeds}: {d['mean']:+.2f} +- {d['std']:.2f} dB (each seed {each})"


def seeds_text(agg: dict, base: dict) -> str:
    """" (means over 1 and 3 seeds)" when the two cells' seeds differ, else ""."""
    a, b = agg.get("seeds", []), base.get("seeds", [])
    return f" (means over {len(a)} and {len(b)} seeds)" if sorted(a) != sorted(b) else ""


def summary(table: dict, samples: tuple, setting: str = "quick") -> list[str]:
    """Plain statements computed from the aggregated table {(scheme, n): aggregate}."""
    lines = []
    have = {k: v for k, v in table.items() if v is not None and v["n"] and v.get("psnr")}
    if not have:
        return ["No run finished."]
    for n in samples:
        cells = {s: a for (s, m), a in have.items() if m == n}
        if not cells:
            continue
        at_n, seeds = psnr_on_common_seeds(cells)
        best = max(at_n, key=at_n.get)
        ranked = sorted(at_n.values(), reverse=True)
        if len(ranked) == 1:
            lines.append(f"{n} samples/ray: only {best} ran, {at_n[best]:.2f} dB.")
            continue
        on = (f" on seed{'s' if len(seeds) != 1 else ''} {seeds} (the seeds every scheme at {n} ran; "
              if seeds else " (")
        lines.append(f"{n} samples/ray: best {best} at {at_n[best]:.2f} dB{on}"
                     f"{ranked[0] - ranked[1]:+.2f} dB over the runner-up).")
    gaps = [psnr_gap(have.get((scheme_name(w, True, setting), n)), have.get((scheme_name(w, False, setting), n)))
            for w in WARPS for n in samples]
    gains = [g["delta"] for g in gaps if g is not None]
    if gains:
        other = "proposal sampling" if SAMPLERS[setting][0] == "proposal" else "none"
        paired = " (each pair on the seeds both ran)" if all(g["seeds"] for g in gaps if g is not None) else ""
        lines.append(f"Hierarchical resampling vs {other} at equal samples per ray: "
                     f"{np.mean(gains):+.2f} dB on average "
                     f"(range {min(gains):+.2f} to {max(gains):+.2f}) over {len(gains)} (warp, N) pairs{paired}.")
    stds = [a["psnr"]["std"] for a in have.values() if a["n"] > 1]
    if stds:
        lines.append(f"Seed-to-seed standard deviation of PSNR: {np.mean(stds):.2f} dB on average; differences "
                     "smaller than that are not resolved by this run.")
    else:
        lines.append("One seed per cell: the seed-to-seed spread is not measured, so differences of a few hundredths "
                     "of a dB are not evidence either way.")
    for hier in (False, True):
        for warp in WARPS:
            s = scheme_name(warp, hier, setting)
            need = samples_to_reach(have, s, samples)
            if need is not None:
                lines.append(f"{s} comes within 0.5 dB of its own {max(samples)}-sample PSNR at {need} samples/ray "
                             f"(PSNR minus that, paired by seed: {gaps_text(have, s, samples)}).")
    for hier in (False, True):
        base = scheme_name("linear", hier, setting)
        for n in samples:
            if n * 4 not in samples or (base, n * 4) not in have:
                continue
            target = have[(base, n * 4)]["psnr"]["mean"]
            if (base, n) in have and have[(base, n)]["psnr"]["mean"] >= target - 0.1:
                lines.append(f"Caveat: {base} itself at {n} samples/ray is within 0.1 dB of {base} at {n * 4}, so at "
                             "this setting the quarter-samples test below does not discriminate between schemes.")
            for warp in WARPS:
                s = scheme_name(warp, hier, setting)
                if (s, n) in have:
                    got = have[(s, n)]["psnr"]["mean"]
                    verdict = "matches (within 0.1 dB) or beats" if got >= target - 0.1 else "falls short of"
                    cell, ref = have[(s, n)], have[(base, n * 4)]
                    lines.append(f"Quarter-samples test: {s} at {n} samples/ray ({got:.2f} dB) {verdict} "
                                 f"{base} at {n * 4} ({target:.2f} dB), {got - target:+.2f} dB"
                                 f"{paired_text(cell, ref) or seeds_text(cell, ref)}.")
    return lines


def figure(table: dict, samples: tuple, setting: str, steps: int) -> np.ndarray:
    """PSNR against samples per ray, one line per scheme (dashed: hierarchical), +-1 std bars;
    table: {(scheme, n): aggregate or None}. Returns an RGB image [H, W, 3] in [0, 1]."""
    series = []
    for h in (False, True):
        for w in WARPS:
            s = scheme_name(w, h, setting)
            pts = [(n, table[(s, n)]["psnr"]) for n in samples if table.get((s, n)) and table[(s, n)].get("psnr")]
            if pts:
                series.append({"label": s.replace(" + hierarchical", " +hier").replace(" + proposal", " +prop"),
                               "x": [x for x, _ in pts], "y": [c["mean"] for _, c in pts],
                               "err": [c["std"] for _, c in pts], "dashed": h, "colour_index": WARPS.index(w)})
    return figures.line_plot(series, "samples per ray (log2 scale)", "test PSNR (dB)",
                             f"sampling schemes, {steps} steps, {setting} setting, bars: +-1 std over seeds")


def replot(results: Path) -> Path:
    """Redraws results/sampling_schemes.png from results/sampling_schemes.json (no run)."""
    from jaxnerf_grid.util import io

    body = io.read_json(results / "sampling_schemes.json")
    table = {(r["scheme"], r["samples_per_ray"]): r["aggregate"] for r in body["rows"]}
    img = figure(table, tuple(body["samples"]), body["settings"]["setting"], body["settings"]["steps"])
    io.write_png(results / "sampling_schemes.png", np.clip(img, 0, 1))
    return results / "sampling_schemes.png"


def main(argv=None) -> int:
    p = runner.base_parser(__doc__)
    p.add_argument("--samples", type=int, nargs="+", default=None, help="samples per ray (even numbers)")
    p.add_argument("--replot", action="store_true",
                   help="only redraw sampling_schemes.png from the results folder's sampling_schemes.json (no run)")
    args = p.parse_args(argv)
    args.results = args.results or str(settings.results_folder(settings.BENCH_RESULTS, args.setting))
    if args.replot:
        print(f"wrote {replot(Path(args.results))}")
        return 0
    ctx = runner.make_context(args, "sampling_schemes.py")
    ctx.command = ctx.command.replace("-m experiments.", "-m benchmarks.")
    samples = tuple(args.samples or SAMPLES[ctx.setting])
    schemes = [(w, h) for h in (False, True) for w in WARPS]
    records = {(scheme_name(w, h, ctx.setting), n): [] for w, h in schemes for n in samples}
    # smallest and largest budgets first, so a time budget still leaves the quarter-samples comparison
    order = sorted(samples, key=lambda n: (n not in (min(samples), min(samples) * 4), n))
    for seed in range(ctx.seeds):
        data = scenes.scene(ctx, "tower-small", seed, distractors="none")
        for n in order:
            for w, h in schemes:
                tag = f"bench-{w}-{'h' if h else SAMPLERS[ctx.setting][0][0]}{n}"
                rec = runner.run_condition(ctx, data, "ours", seed, tag,
                                           {"model": model_overrides(w, h, n, ctx.setting),
                                            "train": {"use_masks": False}})
                records[(scheme_name(w, h, ctx.setting), n)].append(rec)
    table = {k: (tables.aggregate(v) if any(r is not None for r in v) else None) for k, v in records.items()}
    for (name, n), agg in table.items():  # paired (same scene and seed) difference to uniform t
        base = scheme_name("linear", name.endswith("hierarchical"), ctx.setting)
        if name != base:
            tables.add_paired_delta(agg, table[(base, n)], "psnr", "delta_psnr_vs_linear")
            tables.add_paired_delta(agg, table[(base, n)], "psnr_far_background", "delta_far_vs_linear")
    body = {"samples": list(samples), "rows": [{"scheme": s, "samples_per_ray": n, "aggregate": a}
                                               for (s, n), a in table.items()]}
    md = []
    for n in samples:
        md += [f"## {n} samples per ray", ""]
        md += tables.markdown_table([(scheme_name(w, h, ctx.setting), table[(scheme_name(w, h, ctx.setting), n)])
                                     for w, h in schemes], COLUMNS)
        md += [""]
    lines = summary(table, samples, ctx.setting)
    body["summary"] = lines
    md += ["## Summary (computed from the table)", ""] + [f"- {x}" for x in lines]
    img = figure(table, samples, ctx.setting, ctx.steps)
    figures.write_figure(ctx, "sampling_schemes", img)
    md += ["", "![PSNR against samples per ray](sampling_schemes.png)"]
    notes = ["Scene: tower-small without distractors (no masks); contraction on for every scheme.",
             "Samples per ray: N coarse without hierarchical resampling, N/2 coarse + N/2 fine with it.",
             "s / step: wall seconds per training step on this machine, shared with other jobs, so only roughly "
             "comparable between rows."]
    tables.write_results(ctx, "sampling_schemes", "Sampling-scheme benchmark", body, md, notes)
    return 0


if __name__ == "__main__":
    runner.cpu_defaults()
    sys.exit(main())
