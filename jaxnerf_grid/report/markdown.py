"""report.md for a run: metrics table, configuration summary, side-by-side views, provenance.

Every figure referenced by the report is a file in the run directory (docs/CONVENTIONS.md):
`report_views.png` (ground truth | render | depth, one row per test view, full frames) and
`report_crops.png` (the same three panels cropped to the bounding box of the tower class in
the semantic map, 2x nearest-neighbour, when semantics exist).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from jaxnerf_grid.nerf import fields, models
from jaxnerf_grid.util import io


def colourise_depth(depth: np.ndarray, lo: float | None = None, hi: float | None = None) -> np.ndarray:
    """Depth [H, W] -> RGB [H, W, 3] in [0, 1]: inverse depth through OpenCV's TURBO map
    (near = warm), scaled between the 2nd and 98th percentiles unless lo/hi are given."""
    import cv2

    inv = 1.0 / np.maximum(np.asarray(depth, np.float64), 1e-6)
    finite = inv[np.isfinite(inv)]
    lo = np.percentile(finite, 2) if lo is None else lo
    hi = np.percentile(finite, 98) if hi is None else hi
    unit = np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1)
    bgr = cv2.applyColorMap(np.round(unit * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    return bgr[..., ::-1].astype(np.float32) / 255.0


def side_by_side(rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]], gap: int = 2) -> np.ndarray:
    """Stacks (gt, render, depth-colour) triplets, each [H, W, 3], into one image with white gaps."""
    lines = []
    for gt, pred, depth in rows:
        h = gt.shape[0]
        sep = np.ones((h, gap, 3), np.float32)
        lines.append(np.concatenate([gt, sep, pred, sep, depth], axis=1))
    width = max(x.shape[1] for x in lines)
    out = []
    for x in lines:
        pad = np.ones((x.shape[0], width - x.shape[1], 3), np.float32)
        out += [np.concatenate([x, pad], axis=1), np.ones((gap, width, 3), np.float32)]
    return np.concatenate(out[:-1], axis=0)


def tower_box(semantic: np.ndarray, margin: int = 4) -> tuple[slice, slice] | None:
    """Bounding box (rows, cols) of tower pixels (class 1; conductors span the frame), or None."""
    ys, xs = np.nonzero(semantic == 1)
    if ys.size == 0:
        return None
    h, w = semantic.shape
    return (slice(max(ys.min() - margin, 0), min(ys.max() + margin + 1, h)),
            slice(max(xs.min() - margin, 0), min(xs.max() + margin + 1, w)))


def _fmt(v, digits=2) -> str:
    if v is None:
        return "unavailable"
    if isinstance(v, float):
        if not np.isfinite(v):
            return "n/a"
        return f"{v:.{digits}f}"
    return str(v)


def _samples_line(model) -> str:
    """How a ray is sampled, from a run config's `model` (models.ModelConfig)."""
    return (f"sampling in s: {models.describe(model)}, {models.samples_per_ray(model)} samples per ray"
            f"{', opaque far bin' if model.opaque_far else ''}")


def _robust_mode(train_cfg) -> str:
    """train.robust.mode of a run config's `train` ("off" for a config from before it)."""
    return getattr(getattr(train_cfg, "robust", None), "mode", "off")


def _field_line(field) -> str:
    """The field's kind and shape, from a run config's `model.field` (fields.FieldConfig)."""
    return fields.describe(field)


def geometry_lines(geometry: dict | None) -> list[str]:
    """Markdown lines of the "Tower geometry" section from metrics["geometry"] (`geometry.score_points`
    plus "reference"); no lines when it is None."""
    if not geometry:
        return []
    lines = ["## Tower geometry", "",
             f"`tower_points.ply` against `{geometry.get('reference', 'the reference cloud')}`, "
             f"{geometry.get('units', 'normalised scene units')}; both clouds cropped to the reference "
             f"tower's box less a {_fmt(geometry.get('ground_strip'), 3)}-unit ground strip "
             f"({geometry.get('num_pred', '?')} predicted, {geometry.get('num_ref', '?')} reference points).", "",
             "| threshold | precision | recall | F-score |", "|---|---|---|---|"]
    for tau, row in geometry.get("thresholds", {}).items():
        lines.append(f"| {tau} | {_fmt(row.get('precision'), 4)} | {_fmt(row.get('recall'), 4)} | "
                     f"{_fmt(row.get('fscore'), 4)} |")
    lines += ["", f"Chamfer distance (mean of the two mean nearest-neighbour distances): "
                  f"{_fmt(geometry.get('chamfer'), 4)}", ""]
    return lines


EXPORT_HEADING = "## Tower model (export)"
LEGS_MISSING = 0.05   # "lower part missing" when the mesh begins higher than this share of the height
# "tilt doubtful" past this many degrees from vertical: the towers measured here lean 0.02-1.74
# degrees in their exports (docs/EXPORT.md); a ghost of a model leaned 7.25.
TILT_DOUBTFUL = 3.0


def lower_part_missing(m: dict) -> float | None:
    """How far above the ground the model's tower begins, from measurements.json `m` (the base
    centre's `extrapolated`), when that is more than LEGS_MISSING of a positive height; else None.
    The report's "lower part missing" row and `jaxnerf-grid export`'s warning both ask this."""
    low = (((m.get("survey") or {}).get("base_centre")) or {}).get("extrapolated") or 0.0
    return float(low) if low > LEGS_MISSING * float(m.get("height") or 0.0) > 0 else None


def tilt_doubtful(m: dict) -> float | None:
    """The tower axis' tilt from vertical in degrees, from measurements.json `m` (its survey's
    `tilt_degrees`), when it is more than TILT_DOUBTFUL; else None. The report's "tilt doubtful"
    row and `jaxnerf-grid export`'s warning both ask this."""
    tilt = ((m.get("survey") or {}).get("tilt_degrees") or {}).get("value")
    return float(tilt) if tilt is not None and float(tilt) > TILT_DOUBTFUL else None


TILT_WORDS = ("a standing lattice tower leans under 2 degrees in every export measured here: either this one "
              "leans, or the model's tower is incomplete or misplaced (look at report_views.png), and its "
              "height, cross-arm levels and the conductors' clearance are doubtful")


def tilt_doubt_words(m: dict) -> str | None:
    """The words of the "tilt doubtful" finding of measurements.json `m` (`tilt_doubtful`); None
    when the tower does not lean past TILT_DOUBTFUL."""
    tilt = tilt_doubtful(m)
    return None if tilt is None else f"the tower's axis leans {_fmt(tilt)} deg from vertical: {TILT_WORDS}"


LOWEST_POINT = "the conductors' lowest reconstructed point"


def lowest_point_doubtful(m: dict, unit: str) -> str | None:
    """Why the clearance of the conductors' lowest reconstructed point (measurements.json `m`'s
    `conductors`, `export.measure.conductor_clearance`) is doubtful, from its `ground_seen`
    (`export.clearance.lowest_point_ground_seen`); None when it is sound, unchecked or not
    reconstructed. The report's mark and row and `jaxnerf-grid export`'s warning ask this."""
    cond = m.get("conductors") or {}
    seen = cond.get("ground_seen") or {}
    return ground_doubt_words(seen, unit) if cond.get("reconstructed") and seen.get("doubtful") else None


def clearance_doubt_words(m: dict, unit: str) -> list[str]:
    """The words of each "clearance doubtful" finding of measurements.json `m`: "{spans}: {why}"
    per group of `clearance_doubtful`, then "{LOWEST_POINT}: {why}" (`lowest_point_doubtful`)."""
    out = [f"{span}: {words}" for span, words in clearance_doubtful(m, unit)]
    lowest = lowest_point_doubtful(m, unit)
    return out + ([f"{LOWEST_POINT}: {lowest}"] if lowest is not None else [])


def doubt_rows(m: dict, unit: str) -> list[tuple[str, str]]:
    """(label, words) of every doubt about measurements.json `m`: ("tilt doubtful",
    `tilt_doubt_words`), then ("clearance doubtful", each of `clearance_doubt_words`); [] when
    sound. report.md's bold rows and report.html's warning block show these."""
    tilt = tilt_doubt_words(m)
    return ([("tilt doubtful", tilt)] if tilt is not None else []) + \
        [("clearance doubtful", words) for words in clearance_doubt_words(m, unit)]


def clearance_doubtful(m: dict, unit: str) -> list[tuple[str, str]]:
    """(the spans, as the conductors' table numbers them, the words) for the spans in
    measurements.json `m` whose clearance over the ground rests on a doubtful ground (their
    clearance's `ground_seen`, `export.clearance.ground_seen`); spans with the same words share one
    entry ("span 1 (side +)", or "8 spans (1-4, 9-12)"): a cloud that holds the ground only around
    the tower makes every span's the same. [] when none. The report's "clearance doubtful" rows
    and `jaxnerf-grid export`'s warnings both ask this."""
    groups: dict[str, list[tuple[int, int]]] = {}
    for i, r in enumerate(((m.get("conductor_spans") or {}).get("spans")) or []):
        seen = (r.get("clearance") or {}).get("ground_seen") or {}
        if seen.get("doubtful"):
            groups.setdefault(ground_doubt_words(seen, unit), []).append((i + 1, r.get("side", 1)))
    out = []
    for words, spans in groups.items():
        if len(spans) == 1:
            number, side = spans[0]
            out.append((f"span {number} (side {'+' if side > 0 else '-'})", words))
        else:
            out.append((f"{len(spans)} spans ({number_ranges([n for n, _ in spans])})", words))
    return out


def number_ranges(numbers: list[int]) -> str:
    """Sorted distinct integers as runs: [1, 2, 3, 5, 7, 8] -> "1-3, 5, 7-8"."""
    runs: list[list[int]] = []
    for n in sorted(numbers):
        if runs and n == runs[-1][1] + 1:
            runs[-1][1] = n
        else:
            runs.append([n, n])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)


def ground_doubt_words(seen: dict, unit: str) -> str:
    """Why a span's clearance over the ground is doubtful, from its `ground_seen` record."""
    if seen["count"] < seen["min_count"]:
        return (f"only {seen['count']} ground points of the cloud within {_fmt(seen['radius'])} {unit} of the point "
                f"beneath the lowest point (at least {seen['min_count']} needed): the ground there is not seen, and "
                "the clearance over the ground is the fitted plane's extrapolation")
    return (f"the cloud's ground within {_fmt(seen['radius'])} {unit} of the point beneath the lowest point has a "
            f"median height of {_fmt(seen['median_height'])} {unit} above the fitted plane (beyond +- "
            f"{_fmt(seen['tolerance'])} {unit}): the plane does not fit the ground there, and the clearance over the "
            "ground is off by about that much")


def _xyz(v, digits=2) -> str:
    return "(" + ", ".join(_fmt(x, digits) for x in v) + ")" if v is not None else "n/a"


def _pm(fig: dict | None, unit: str, digits: int = 2) -> str:
    """'12.34 +- 0.05 m' of a `survey` figure {"value", "sigma"} (sigma None: 'not estimated')."""
    if not fig:
        return "unavailable"
    sigma = fig.get("sigma")
    return f"{_fmt(fig['value'], digits)} {unit} +- " + (f"{_fmt(sigma, digits)} {unit}" if sigma is not None
                                                           else "(not estimated)")


def _survey_lines(m: dict, unit: str) -> list[str]:
    """The table rows of measurements.json's `survey` (1-sigma uncertainties, tilt,
    base centre, conductors; docs/EXPORT.md)."""
    sv = m.get("survey") or {}
    if not sv:
        return []
    lines = [f"| height with its 1-sigma uncertainty | {_pm(sv.get('height'), unit)} |"]
    if sv.get("footprint"):
        lines.append("| base footprint widths | " + " x ".join(_pm(f, unit) for f in sv["footprint"]) + " |")
    heights = sv.get("cross_arm_heights") or []
    if heights:
        spans = sv.get("cross_arm_spans") or [None] * len(heights)
        lines.append("| cross-arm heights above the ground (spans) | " + "; ".join(
            _pm(f, unit) + (f" ({_pm(s, unit)})" if s else "") for f, s in zip(heights, spans)) + " |")
    if sv.get("tilt_degrees"):
        lines.append(f"| tilt of the tower's axis from vertical | {_pm(sv['tilt_degrees'], 'deg')}; top offset "
                     f"{_pm(sv.get('top_offset'), unit)} |")
    base = sv.get("base_centre")
    if base:
        where = (f"{_xyz(base['crs'], 3)} in {base['crs_name']}" if base.get("crs") else
                 f"{_xyz(base['local'], 3)} (the dataset's frame)")
        sigma = base.get("sigma")
        spread = f"{_fmt(sigma)} {unit}" if sigma is not None else "(not estimated)"
        lines.append(f"| base centre | {where} +- {spread} |")
        low = lower_part_missing(m)
        if low is not None:
            lines.append(f"| **lower part missing** | the model's tower begins {_fmt(low)} {unit} above the ground: "
                         "its legs were not reconstructed there, so the base centre and the tilt come from the "
                         "axis extended down that far (train longer, or add low oblique photos) |")
    tilt = tilt_doubt_words(m)
    if tilt is not None:
        lines.append(f"| **tilt doubtful** | {tilt} |")
    vertical = sv.get("vertical")
    if vertical:
        lines.append(f"| heights of the CRS coordinates (base centre, tower_points.las, tower_mesh_crs.ply) | "
                     f"{vertical['reference']} |")
    cond = m.get("conductors") or {}
    if cond.get("reconstructed"):
        lines.append(f"| conductors' lowest reconstructed point above the ground | "
                     f"{_pm(sv.get('conductor_clearance'), unit)}"
                     + (" (doubtful)" if lowest_point_doubtful(m, unit) is not None else "") + " |")
    elif cond:
        lines.append(f"| conductors | not reconstructed: {cond.get('why', '')} |")
    return lines


# what the training batches' PSNR beside the held-out PSNR tells a reader
FIT_WORDS = ("The training batches' PSNR is how well the model fits the photos it trained on. Far above the "
             "held-out PSNR, the held-out views show what the training photos do not (frame edges, sides no "
             "photo saw, floaters between the cameras): more photos around the scene help more than more "
             "steps. Close to it and low, the model has not yet fitted its photos: more steps (a longer "
             "time budget) help.")


def export_lines(info: dict | None) -> list[str]:
    """Markdown lines of the "Tower model (export)" section (docs/EXPORT.md) from
    {"measurements": measurements.json, "image": the picture's path relative to the report,
    optional "score": `eval.export_score.score_export`}; no lines when it is None."""
    if not info or not info.get("measurements"):
        return []
    m = info["measurements"]
    unit = "m" if m.get("units") == "metres" else "units"
    lines = [EXPORT_HEADING, "",
             "`jaxnerf-grid export`: `tower_mesh.ply`, `tower_points.ply`, `box.json`, `measurements.json`; "
             + ("metres." if m.get("units") == "metres" else
                "**units unknown** (the dataset has no metric scale: its original units)."), "",
             "| measurement | value |", "|---|---|",
             f"| tower height above the fitted ground | {_fmt(m.get('height'))} {unit} |"]
    fp = m.get("footprint") or {}
    if fp:
        lines.append(f"| base footprint (minimum-area rectangle of the lowest band) | {_fmt(fp.get('width_a'))} x "
                     f"{_fmt(fp.get('width_b'))} {unit} |")
    arms = (m.get("cross_arms") or {}).get("levels") or []
    if arms:
        lines.append("| cross-arm levels (height: span, heuristic) | " + "; ".join(
            f"{_fmt(a['height'], 1)}: {_fmt(a['span'], 1)}" for a in arms) + f" {unit} |")
    lines += _survey_lines(m, unit)
    lines += [f"| **clearance doubtful** | {words} |" for words in clearance_doubt_words(m, unit)]
    g = m.get("ground") or {}
    if g:
        lines.append(f"| ground plane n . x + d = 0 | n = {_xyz(g.get('normal'), 4)}, d = {_fmt(g.get('offset'), 3)} "
                     f"(tilt {_fmt(g.get('tilt_degrees'), 2)} deg) |")
    mesh = m.get("mesh") or {}
    lines += [f"| mesh | {mesh.get('vertices', '?')} vertices, {mesh.get('faces', '?')} faces, "
              f"{_fmt(100 * mesh.get('kept_face_fraction', float('nan')), 1)} % of the faces kept after removing "
              f"small components, closed: {mesh.get('closed')} |",
              f"| fused points | {(m.get('points') or {}).get('count', '?')} |",
              f"| box ({(m.get('box') or {}).get('source', '?')}) | {_xyz((m.get('box') or {}).get('min'))} - "
              f"{_xyz((m.get('box') or {}).get('max'))} {unit} |",
              f"| voxel, threshold | {_fmt(m.get('voxel_size'), 3)} {unit}, density "
              f"{_fmt((m.get('threshold') or {}).get('density'), 1)} per normalised unit (one voxel "
              f"{_fmt((m.get('threshold') or {}).get('opacity_per_voxel'), 2)} opaque) |", ""]
    score = info.get("score")
    if score:
        lines += [f"Against the reference tower ({score.get('reference_points', '?')} points; both cropped to its box "
                  f"less a {_fmt(score.get('ground_strip'))} {unit} ground strip):", "",
                  "| cloud | " + " | ".join(f"F@{t}" for t in (score.get("mesh") or score.get("points") or {})
                                            .get("thresholds", {})) + " | Chamfer |",
                  "|---|" + "---|" * (len((score.get("mesh") or score.get("points") or {}).get("thresholds", {})) + 1)]
        for key in ("mesh", "points"):
            sc = score.get(key)
            if sc:
                lines.append(f"| {'mesh vertices' if key == 'mesh' else 'fused points'} | " + " | ".join(
                    _fmt(r["fscore"], 3) for r in sc["thresholds"].values()) + f" | {_fmt(sc.get('chamfer'), 3)} |")
        hgt = score.get("height")
        if hgt:
            lines += ["", f"Height: {_fmt(hgt['export'])} against {_fmt(hgt['reference'])} {unit}, error "
                          f"{_fmt(hgt['error'])} {unit} ({_fmt(hgt['error_percent'])} %)."]
        lines.append("")
    if info.get("image"):
        lines += [f"![front | side | top]({info['image']})", ""]
    lines += conductor_lines(m, unit, info.get("conductors_image"))
    return lines


def _sig(fig: dict | None, digits: int = 2, index: int | None = None) -> str:
    """'8.01 +- 0.02' of a conductor figure {"value", "sigma"} (index: one coordinate of a point)."""
    if not fig or fig.get("value") is None:
        return "n/a"
    v, s = fig["value"], fig.get("sigma")
    if index is not None:
        v, s = v[index], None if s is None else s[index]
    return f"{_fmt(float(v), digits)} +- {_fmt(float(s), digits)}" if s is not None else _fmt(float(v), digits)


def span_sources(spans: list[dict], unit: str) -> str:
    """Where each side's span length came from, in words (the records' `span_length_shared` and
    `next_tower`, `export.conductors.side_lengths`): measured at the next tower seen along the
    line, or from the wires' slopes and curvature; "the curvature from the photos alone" where no
    side shares one."""
    parts = []
    for side in (1, -1):
        rec = next((r for r in spans if r["side"] == side and r.get("span_length_shared")), None)
        if rec is None:
            continue
        length, sigma = rec["span_length_shared"]
        nt = rec.get("next_tower")
        how = (f"measured at the next tower, seen along the line in {nt['photos']} photos" if nt
               else "from the wires' slopes and curvature")
        parts.append(f"side {'+' if side > 0 else '-'}: {_fmt(length)} +- {_fmt(sigma)} {unit}, {how}")
    if not parts:
        return "each wire's curvature from the photos alone. "
    return "the span of " + "; ".join(parts) + ". "


def conductor_lines(m: dict, unit: str, image: str | None = None) -> list[str]:
    """The "Conductors" table of the export section: one row per span fitted in the photos
    (`export.conductors`, measurements.json's `conductor_spans`), each figure +- its 1-sigma;
    the clearances (`export.clearance`) and the flag against --min-clearance."""
    cs = m.get("conductor_spans")
    if not cs:
        return []
    lines = ["### Conductors", ""]
    if not cs.get("spans"):
        return lines + [f"No conductor found in the {cs.get('photos', '?')} photos: {cs.get('why') or ''}", ""]
    limit = cs.get("min_clearance")
    length = cs.get("span_length")
    spacing = (f"each a level span of {_fmt(float(length))} {unit} (`export.span_length`). " if length is not None
               else "each far end assumed level with the near one (no `export.span_length`); "
                    + span_sources(cs["spans"], unit))
    lines += [f"{cs['found']} spans fitted as catenaries to the wires detected in {cs.get('photos', '?')} photos, "
              + spacing
              + (f"Flagged: clearance below {_fmt(float(limit))} {unit}: **{cs.get('flagged', 0)}**."
                 if limit is not None else "No clearance given (`export.min_clearance`): nothing flagged."), "",
              f"| span | side | attachment height ({unit}) | sag ({unit}) | catenary parameter ({unit}) | "
              f"lowest point above the ground ({unit}) | clearance over objects beneath ({unit}; horizontal "
              "offset) | fit (px, share on wires) | flag |",
              "|---|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(cs["spans"]):
        c = r.get("clearance") or {}
        obj = c.get("objects") or {}
        over = (f"{_fmt(obj['clearance'])} ({_fmt(obj['horizontal_distance'])})" if obj.get("clearance") is not None
                else "none seen" + (f" (cloud covers {_fmt(obj['covered'][0], 0)}-{_fmt(obj['covered'][1], 0)})"
                                    if obj.get("covered") else ""))
        ground = "n/a" if c.get("ground") is None else (
            f"{_fmt(c['ground'])} +- {_fmt(c['ground_sigma'])}" if c.get("ground_sigma") is not None
            else _fmt(c["ground"])) + (" (doubtful)" if (c.get("ground_seen") or {}).get("doubtful") else "")
        flag = {None: "-", True: "**below**", False: "ok"}[c.get("flag")]
        lines.append(f"| {i + 1} | {'+' if r['side'] > 0 else '-'} | {_sig(r['attachment'], 2, 2)} | "
                     f"{_sig(r['sag'])} | {_sig(r['catenary_parameter'], 0)} | {ground} | {over} | "
                     f"{_fmt(r.get('sigma_px'), 2)}, {_fmt(r.get('inlier_share'), 2)} | {flag} |")
    lines.append("")
    if image:
        lines += [f"![the fitted conductors on the photos]({image})", ""]
    return lines


def weights_figure(run_dir, rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> list[str]:
    """Writes run_dir/report_weights.png: per training frame, photo | the DPT's weight 1 - M_w |
    the weight training used (train.robust's record; black = ignored). rows: (photo [H, W, 3],
    prior [H, W], used [H, W]) in [0, 1]. Returns the report's Markdown lines (none without rows)."""
    if not rows:
        return []
    grey = lambda a: np.repeat(np.asarray(a, np.float32)[..., None], 3, axis=-1)  # noqa: E731
    io.write_png(Path(run_dir) / "report_weights.png",
                 side_by_side([(np.asarray(photo, np.float32), grey(prior), grey(used))
                               for photo, prior, used in rows]))
    return ["Training weights (photo | DPT weight 1 - M_w | weight training used; black = ignored): "
            "![training weights](report_weights.png)"]


def set_section(path, heading: str, lines: list[str]) -> Path:
    """Replaces the section `heading` (a "## " line up to the next "## " line) of the Markdown
    file `path` by `lines`, or appends them; creates the file when it does not exist. Bytes of
    the file that are not UTF-8 (a report edited in Latin-1) are kept as they were."""
    path = Path(path)
    old = path.read_bytes().decode("utf-8", "surrogateescape").split("\n") if path.is_file() else []
    if heading in old:
        start = old.index(heading)
        end = next((k for k in range(start + 1, len(old)) if old[k].startswith("## ")), len(old))
        new = old[:start] + list(lines) + old[end:]
    else:
        new = old + ([""] if old and old[-1] != "" else []) + list(lines)
    io.atomic_write_bytes(path, "\n".join(new).encode("utf-8", "surrogateescape"))
    return path


def write_report(run_dir, metrics: dict, cfg, data, views: list[dict], extra_lines: Sequence[str] = ()) -> Path:
    """Writes run_dir/report.md (and its PNGs).

    metrics: the metrics.json dict (keys "mean", "regions", "protocol", ...);
    cfg: the run's config (RunConfig, read by attribute); data: the dataset path;
    views: [{"name", "gt" [H,W,3], "rgb", "depth" [H,W], optional "semantic" [H,W]}] for the figures;
    extra_lines: Markdown lines for the notes.
    Returns the report's path.
    """
    run_dir = Path(run_dir)
    rows, crops = [], []
    for v in views[:4]:
        dcol = colourise_depth(v["depth"])
        rows.append((v["gt"], np.clip(v["rgb"], 0, 1), dcol))
        if v.get("semantic") is not None:
            box = tower_box(v["semantic"])
            if box is not None:
                up = lambda a: np.repeat(np.repeat(a[box], 2, axis=0), 2, axis=1)  # noqa: E731, B023 (used in this iteration)
                crops.append((up(v["gt"]), up(np.clip(v["rgb"], 0, 1)), up(dcol)))
    figure_lines = []
    if rows:
        io.write_png(run_dir / "report_views.png", side_by_side(rows))
        figure_lines.append("![ground truth | render | depth](report_views.png)")
    if crops:
        io.write_png(run_dir / "report_crops.png", side_by_side(crops))
        figure_lines.append("")
        figure_lines.append("Tower crops (2x): ![tower crops](report_crops.png)")

    model, train_cfg = cfg.model, cfg.train
    mean = metrics.get("mean", {})
    lines = [f"# Run report: {model.method}", ""]
    lines += [f"Data: `{data}`  ", f"Trained steps: {metrics.get('step', '?')}  ",
              f"Evaluated views: {metrics.get('num_views', '?')} ({metrics.get('target', 'images')})", ""]
    lines += ["## Metrics (mean over test views)", "",
              "| metric | value |", "|---|---|"]
    for key in ("psnr", "ssim", "ms_ssim", "lpips"):
        lines.append(f"| {key.upper().replace('_', '-')} | {_fmt(mean.get(key), 4 if key != 'psnr' else 2)} |")
    if mean.get("ms_ssim_scales") is not None:
        lines.append(f"| MS-SSIM scales | {mean['ms_ssim_scales']} |")
    right = metrics.get("mean_right_half")
    if right:
        lines.append(f"| PSNR, right half | {_fmt(right.get('psnr'))} |")
        lines.append(f"| SSIM, right half | {_fmt(right.get('ssim'), 4)} |")
    regions = metrics.get("regions_mean") or {}
    for name, value in regions.items():
        lines.append(f"| PSNR, {name.replace('_', ' ')} | {_fmt(value)} |")
    if metrics.get("distractor_psnr") is not None:
        lines.append(f"| PSNR inside distractors (train views vs clean) | {_fmt(metrics['distractor_psnr'])} |")
    fit = metrics.get("training_fit")
    if fit:
        lines.append(f"| PSNR of the training batches, last tenth of the run | {_fmt(fit['psnr'])} |")
    lines += ["", f"Protocol: {metrics.get('protocol', '')}", ""]
    if fit:
        lines += [FIT_WORDS, ""]
    if metrics.get("region_definition"):
        lines += [f"Regions: {metrics['region_definition']}", ""]
    lines += geometry_lines(metrics.get("geometry"))
    lines += export_lines(metrics.get("export"))
    lines += ["## Method and configuration", "",
              f"- method `{model.method}`: contraction {model.use_contraction} "
              f"(R = {model.contract_radius}), warp `{model.warp}`, {_samples_line(model)}",
              f"- field: {_field_line(model.field)}",
              f"- NeRF-W: appearance {model.use_appearance}, transient {model.use_transient}",
              f"- loss weights from masks: {train_cfg.use_masks} (floor {train_cfg.mask_weight_floor})",
              f"- photometric evidence (train.robust.mode): {_robust_mode(train_cfg)}",
              f"- batch {train_cfg.batch_rays} rays, {train_cfg.max_steps} steps, lr "
              f"{train_cfg.lr_init} -> {train_cfg.lr_final} (warm-up {train_cfg.warmup}), "
              f"clip {train_cfg.max_grad_norm}", ""]
    if figure_lines:
        lines += ["## Views (ground truth | render | depth)", ""] + figure_lines + [""]
    if extra_lines:
        lines += ["## Notes", ""] + list(extra_lines) + [""]
    path = run_dir / "report.md"
    io.atomic_write_bytes(path, "\n".join(lines).encode("utf-8"))
    return path
