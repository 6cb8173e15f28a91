"""The conductors found in the photos against the generator's truth (docs/EXPORT.md "Conductors").

Usage:
  python -m benchmarks.conductors --data SCENE [--data SCENE2 ...] [--export EXPORT_DIR ...]
      [--span-length M] [--arm-seeds] [--detect-threshold K] [--no-refine] [--no-shared-azimuth]
      [--no-shared-span] [--no-shared-curvature] [--no-next-tower] [--no-shared-sag] [--no-settle]
      [--no-top-window]
      [--out benchmarks/results/conductors.json]

For each generated scene (`jaxnerf-grid synth`; its transforms.json says preset, seed and whether
it has conductors) the wires are found with the TRUE cameras (`export.conductors`: detection in
the training photos, the spans fitted from the true tower's axis and line direction) and scored
against the scene's own cables (`data.synthetic.scene.conductor_spans`); with `--export`, an
export's measurements.json (its `conductors` record, from the trained chain) is scored against
the scene of the same position in --data. Per span in view (the two spans at the main tower:
6 phase conductors and 2 earth wires on each side): found or not, the RMS distance of the fitted
curve to the true one over the true span (metres), the azimuth's error (radians), the sag
error (the true sag: the lowest point below the attachments) and that error in the sag's stated
1-sigma, the lowest point's height error, the lowest point's clearance above the true ground
(z = 0) against the truth; and the spans found that match no cable (invented).

An export of photos posed by `poses` from their GPS (a scene `synth --gps-origin` wrote, its
gps_truth.json beside it) is in the CRS's local frame: its spans are moved into the generator's
world by the translation between the two (`gps_shift`), so the GPS's own error stays in the
figures (`--match-radius` widens the attachments' match for it); the clearance is over the
export's own ground and needs no move.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from jaxnerf_grid.export import catenary

MATCH_RADIUS = 1.0      # m: a fitted span matches a cable when their attachments lie this close


def true_spans(attach: np.ndarray) -> list[dict]:
    """The spans in view (at the main tower, y = 0) as the export sees them: side +1 goes to +y
    (the generator's span k = 0), side -1 to -y (k = -1). Each {"wire", "earth", "side",
    "attachment" [3], "far" [3], "sag" (the true lowest point below the attachment), "points"
    [K, 3] (dense)}."""
    from jaxnerf_grid.data.synthetic import scene as sc

    out = []
    for span in sc.conductor_spans(attach):
        if span["k"] not in (-1, 0):
            continue
        side = 1 if span["k"] == 0 else -1
        pts = sc.catenary(span["p0"], span["p1"], span["sag"], 4000)
        near, far = (span["p0"], span["p1"]) if side == 1 else (span["p1"], span["p0"])
        out.append({"wire": span["wire"], "earth": span["earth"], "side": side, "attachment": near, "far": far,
                    "sag": float(near[2] - pts[:, 2].min()), "lowest_z": float(pts[:, 2].min()), "points": pts})
    return out


def curve_rms(fitted: np.ndarray, truth: np.ndarray) -> float:
    """RMS over the true curve's points [K, 3] of their distance to the fitted polyline's
    points [M, 3] (sampled finely: nearest point, `scipy.spatial.cKDTree`)."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(fitted).query(truth[::10])
    return float(np.sqrt(np.mean(d ** 2)))


def goes_along(record: dict, t: dict) -> bool:
    """Whether a fitted span runs from its attachment the way the true span t does: its far
    attachment ahead along t's horizontal direction. A record's own "side" counts along the line
    direction its export chose (the cross-arms' axis turned a quarter, of either sign), so it is
    used only when the far attachment is unknown."""
    far = (record.get("far_attachment") or {}).get("value")
    if far is None:
        return record["side"] == t["side"]
    ahead = np.asarray(far, np.float64) - np.asarray(record["attachment"]["value"], np.float64)
    return float(ahead[:2] @ (t["far"] - t["attachment"])[:2]) > 0.0


def score(records: list[dict], truth: list[dict], match_radius: float = MATCH_RADIUS) -> dict:
    """Matches fitted spans (measurements.json's `conductors.spans` records) to the true ones by
    direction (`goes_along`) and attachment (within match_radius, m) and scores each (module
    docstring); "invented_spans": each record matching no cable, with its nearest cable."""

    rows, used = [], set()
    for t in truth:
        best, best_d = None, match_radius
        for i, r in enumerate(records):
            a = np.asarray(r["attachment"]["value"], np.float64)
            d = float(np.linalg.norm(a - t["attachment"]))
            if goes_along(r, t) and d < best_d and i not in used:
                best, best_d = i, d
        row = {"wire": t["wire"], "earth": bool(t["earth"]), "side": t["side"], "found": best is not None,
               "true_sag": t["sag"], "true_lowest_z": t["lowest_z"]}
        if best is not None:
            used.add(best)
            r = records[best]
            length = float(np.linalg.norm((t["far"] - t["attachment"])[:2]))
            fitted = catenary.curve_points(r["theta"], r.get("centre", [0.0, 0.0, 0.0]),
                                       np.linspace(0.0, length, 8000), r.get("up", [0.0, 0.0, 1.0]))
            sag, low = r["sag"]["value"], r["lowest_point"]["value"]
            true_psi = math.atan2(*(t["far"] - t["attachment"])[1::-1])      # the line's azimuth from x, about z
            psi_error = (float(r["theta"][2]) - true_psi + math.pi) % (2 * math.pi) - math.pi
            row.update({"attachment_error": best_d, "rms": curve_rms(fitted, t["points"]), "azimuth_error": psi_error,
                        "sag": sag, "sag_sigma": r["sag"]["sigma"],
                        "sag_error_rel": None if sag is None else (sag - t["sag"]) / t["sag"],
                        "sag_error_sigmas": None if sag is None or not r["sag"]["sigma"] else
                        (sag - t["sag"]) / r["sag"]["sigma"],
                        "lowest_z": None if low is None else low[2],
                        "lowest_z_error": None if low is None else low[2] - t["lowest_z"],
                        "clearance": (r.get("clearance") or {}).get("ground"),
                        "inlier_share": r["inlier_share"], "observed_stations": r["observed_stations"],
                        "span_length_shared": r.get("span_length_shared"),
                        "curvature_across": r.get("curvature_across"), "curvature_own": r.get("curvature_own"),
                        "next_tower": r.get("next_tower")})
            g = row["clearance"]
            row["clearance_error"] = None if g is None else g - t["lowest_z"]
        rows.append(row)
    found = [r for r in rows if r["found"]]

    def worst(key):
        vals = [abs(r[key]) for r in found if r.get(key) is not None]
        return max(vals) if vals else None

    invented = []
    for i, r in enumerate(records):
        if i in used:
            continue
        a = np.asarray(r["attachment"]["value"], np.float64)
        near = min(truth, key=lambda t: float(np.linalg.norm(a - t["attachment"])), default=None)
        invented.append({"side": r.get("side"), "attachment": [float(v) for v in a],
                         "sag": r["sag"]["value"], "inlier_share": r.get("inlier_share"),
                         "nearest_cable": None if near is None else
                         {"wire": near["wire"], "side": near["side"],
                          "distance": float(np.linalg.norm(a - near["attachment"]))}})
    return {"spans": rows, "found": len(found), "existing": len(truth), "invented": len(records) - len(used),
            "invented_spans": invented,
            "worst_rms": worst("rms"), "worst_sag_error_rel": worst("sag_error_rel"),
            "worst_lowest_z_error": worst("lowest_z_error"), "worst_clearance_error": worst("clearance_error"),
            "worst_sag_error_sigmas": worst("sag_error_sigmas")}


def gps_shift(measurements: dict, data: Path) -> np.ndarray | None:
    """The translation [3] from an export's frame to the generator's world, for a scene written by
    `synth --gps-origin` (its gps_truth.json: x_crs = x_world + tower_base_crs) and an export in a
    CRS (measurements.json survey.base_centre: crs = local + the dataset's origin): origin -
    tower_base_crs. None when either is missing (the export is in the generator's frame)."""
    truth_file = Path(data) / "gps_truth.json"
    base = ((measurements.get("survey") or {}).get("base_centre")) or {}
    if not truth_file.is_file() or base.get("crs") is None:
        return None
    truth = json.loads(truth_file.read_text())
    origin = np.asarray(base["crs"], np.float64) - np.asarray(base["local"], np.float64)
    return origin - np.asarray(truth["tower_base_crs"], np.float64)


def shifted(record: dict, shift: np.ndarray) -> dict:
    """A span record moved by shift [3]: its points, and its curve (the horizontal part of the
    shift on "centre", the part along "up" on the attachment height theta[1])."""
    shift = np.asarray(shift, np.float64)
    up = np.asarray(record.get("up", [0.0, 0.0, 1.0]), np.float64)
    up = up / np.linalg.norm(up)
    out = dict(record)
    for key in ("attachment", "far_attachment", "lowest_point"):
        fig = record.get(key) or {}
        if fig.get("value") is not None:
            out[key] = {**fig, "value": [float(v) for v in np.asarray(fig["value"], np.float64) + shift]}
    vertical = float(shift @ up)
    out["centre"] = [float(v) for v in np.asarray(record.get("centre", [0.0, 0.0, 0.0]), np.float64)
                     + shift - vertical * up]
    theta = [float(v) for v in record["theta"]]
    theta[1] += vertical
    out["theta"] = theta
    return out


def scene_meta(data: Path, size: tuple[int, int] | None = None) -> dict:
    """transforms.json of a generated scene; with `size` (W, H) and no transforms.json yet (synth
    still rendering), the same record rebuilt from the generator (tower-small, seed 0: its camera
    path, `data.synthetic.cameras.camera_path`) for the training photos already written."""
    from jaxnerf_grid.util import io

    if (data / "transforms.json").is_file() or size is None:
        return io.read_json(data / "transforms.json")
    from jaxnerf_grid.data.synthetic import NORMALIZATION, cameras
    from jaxnerf_grid.data.synthetic.generate import make_config

    cfg = make_config("tower-small", 0, width=size[0], height=size[1])
    c2w, split = cameras.camera_path(cfg.num_train, cfg.num_test, cfg.orbits, cfg.low_pass,
                                     np.random.default_rng([cfg.seed, 1]))
    intr = cameras.intrinsics(size[0], size[1], cfg.fov_deg)
    frames, counts = [], {"train": 0, "test": 0}
    for pose, sp in zip(c2w, split):
        name = f"images/{sp}_{counts[sp]:03d}.png"
        counts[sp] += 1
        if sp == "train" and (data / name).is_file():
            frames.append({"file_path": name, "split": sp, "transform_matrix":
                           cameras.normalise_pose(pose, NORMALIZATION["scale"], NORMALIZATION["translation"]).tolist()})
    return {**intr, "frames": frames, "generator": {"preset": "tower-small", "seed": 0, "conductors": True,
                                                    "partial": f"{len(frames)} of {cfg.num_train} training photos"}}


def true_camera_views(data: Path, size: tuple[int, int] | None = None, threshold: float | None = None):
    """(images [N, H, W, 3], Views in metres) of a generated scene's training photos, TRUE cameras;
    threshold: the detections' (`export.conductors.detections`; None: its default)."""
    from jaxnerf_grid.data.synthetic import NORMALIZATION
    from jaxnerf_grid.export import conductors as cond
    from jaxnerf_grid.util import io

    meta = scene_meta(data, size)
    frames = [f for f in meta["frames"] if f.get("split", "train") == "train"]
    images = np.stack([io.read_image(data / f["file_path"])[..., :3] for f in frames])
    c2w = cond.metric_cameras(np.stack([np.asarray(f["transform_matrix"], np.float64) for f in frames]),
                              NORMALIZATION)
    intr = np.tile([meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]], (len(frames), 1))
    responses = [cond.ridge_map(im) for im in images]
    kw = {} if threshold is None else {"threshold": float(threshold)}
    masks = np.stack([cond.detections(r, **kw) for r in responses])
    return images, cond.Views(c2w, intr, masks, responses)


def true_arm_seeds() -> list[tuple[float, float]]:
    """The main tower's cross-arm tips as `find_spans` seeds (across offset along side +1's
    e_across = -x, height), as the export measures them (`export.run.arm_seeds`)."""
    from jaxnerf_grid.data.synthetic import scene as sc

    return [(-s * (sc.half_width(z) + length), z) for z, length in zip(sc.ARM_LEVELS, sc.ARM_LENGTHS) for s in (-1, 1)]


def true_camera_fit(data: Path, picture: Path | None = None, size=None,
                    span_length: float | None = None, arm_seeds: bool = False,
                    threshold: float | None = None, refine: bool = True,
                    shared_azimuth: bool = True, shared_span: bool = True,
                    shared_sag: bool = True, settle: bool = True, top_window: bool = True,
                    shared_curvature: bool = True, next_tower: bool = True) -> tuple[list[dict], dict]:
    """The spans found with the true cameras and the true tower (axis at the origin, line along y,
    30.4 m tall, box 4.5 m either side); span_length: the towers' spacing given to the fit (a level
    span of that length), None: the catenary parameter free; arm_seeds: the cross-arm tips as
    seeds, each searched in the export's window below it (`export.run.SEED_WINDOW`); refine,
    shared_azimuth, shared_span, shared_sag: `find_spans`' (the track's curves refined on the
    sub-pixel detections, the side's wires sharing one azimuth, one span length when none is
    given, and the wires hung from the arms one sag); settle: last, each wire's attachment scanned
    for more support); top_window: with arm_seeds, the earth wires' window above the arms searched at
    the track's support (`export.conductors.earth_window`); shared_curvature: without span_length,
    the phase wires' curvature pooled across the tower and each side's span from its slope
    (`export.conductors.phase_curvature`); next_tower: with it, each side's span measured at the
    next tower where the photos see it (`export.next_tower`, the true ground at z = 0).
    Returns (records, timings)."""
    from jaxnerf_grid.export import conductors as cond
    from jaxnerf_grid.export import next_tower as nt
    from jaxnerf_grid.util import io

    t0 = time.perf_counter()
    images, views = true_camera_views(data, size, threshold)
    t1 = time.perf_counter()
    f = float(np.median(views.intrinsics[:, 0]))
    dist = float(np.median(np.linalg.norm(views.c2w[:, :3, 3], axis=1)))
    step = dist / f
    centre = np.zeros(3)
    kw = {}
    if arm_seeds:
        from jaxnerf_grid.export.run import SEED_WINDOW

        kw = {"seeds": true_arm_seeds(), "seed_window": tuple(v * 30.4 for v in SEED_WINDOW)}
    if next_tower and span_length is None:   # searched only without a span length (find_spans)
        half_width = max(abs(c) for c, _ in true_arm_seeds())
        kw["next_tower"] = functools.partial(nt.next_tower, nt.grey_high_passed(images), views.c2w,
                                             views.intrinsics, centre, (0.0, 0.0, 1.0), 0.0, 30.4, half_width)
    spans = cond.find_spans(views, centre, math.pi / 2, 4.5, (7.5, 33.0), 18.0, step, 30.4, span_length=span_length,
                            refine=refine, shared_azimuth=shared_azimuth, shared_span=shared_span,
                            shared_sag=shared_sag, settle=settle, top_window=top_window,
                            shared_curvature=shared_curvature, **kw)
    t2 = time.perf_counter()
    if picture is not None:
        io.write_png(picture, cond.views_picture(images, views, spans, centre))
    records = []
    for s in spans:
        rec = cond.span_record(s, centre)
        rec["clearance"] = {"ground": rec["lowest_point"]["value"][2] if rec["lowest_point"]["value"] else None}
        records.append(rec)
    return records, {"detect_s": t1 - t0, "fit_s": t2 - t1, "views": int(len(images)),
                     "size": [int(images.shape[2]), int(images.shape[1])]}


def scene_attachments():
    from jaxnerf_grid.data.synthetic import scene as sc

    return sc.tower_members(np.random.default_rng(0))[3]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", nargs="+", required=True, type=Path, help="generated scene folders")
    p.add_argument("--export", nargs="*", default=[], type=Path,
                   help="export folders (measurements.json), one per --data in order, from the trained chain")
    p.add_argument("--pictures", type=Path, default=None, help="folder for each scene's conductors_views.png")
    p.add_argument("--no-true-cameras", action="store_true", help="score the --export folders only")
    p.add_argument("--partial", default=None, metavar="W,H",
                   help="a tower-small scene (seed 0) of this size still being rendered: the training photos "
                        "written so far, with the generator's cameras")
    p.add_argument("--span-length", type=float, default=None, metavar="M",
                   help="the towers' spacing given to the fit (the generator's is 320 m): each span level and "
                        "this long; without it the catenary parameter is fitted from the photos alone")
    p.add_argument("--arm-seeds", action="store_true",
                   help="the cross-arm tips as seeds (as the export passes the ones it measures)")
    p.add_argument("--detect-threshold", type=float, default=None, metavar="K",
                   help="the detections' hysteresis threshold in robust scales (export.conductors.detections; "
                        "default its own)")
    p.add_argument("--no-refine", action="store_true",
                   help="the track's curves as they are (find_spans refine=False: no sub-pixel refinement, no shared "
                        "azimuth)")
    p.add_argument("--no-shared-azimuth", action="store_true",
                   help="each wire keeps its own refined azimuth (find_spans shared_azimuth=False)")
    p.add_argument("--no-shared-span", action="store_true",
                   help="without --span-length, each wire keeps its own curvature (find_spans shared_span=False)")
    p.add_argument("--no-shared-curvature", action="store_true",
                   help="without --span-length, each side's span the median of its wires' own, not from its slope "
                        "and the phase wires' curvature pooled across the tower (find_spans shared_curvature=False)")
    p.add_argument("--no-next-tower", action="store_true",
                   help="without --span-length, the spans from the wires' slopes and curvature only, the next towers "
                        "not searched in the photos (find_spans next_tower=None)")
    p.add_argument("--no-shared-sag", action="store_true",
                   help="each wire hung from a cross-arm keeps its own sag (find_spans shared_sag=False)")
    p.add_argument("--no-settle", action="store_true",
                   help="no last scan of each wire's attachment for more support (find_spans settle=False)")
    p.add_argument("--no-top-window", action="store_true",
                   help="with --arm-seeds, the earth wires' peaks in the open plane only, at the plane's support "
                        "(find_spans top_window=False; default: their window above the arms at the track's)")
    p.add_argument("--match-radius", type=float, default=MATCH_RADIUS, metavar="M",
                   help=f"a fitted span matches a cable when their attachments lie this close "
                        f"(default {MATCH_RADIUS} m; an export georeferenced by GPS is off by the GPS's error)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/conductors.json"))
    args = p.parse_args(argv)
    from jaxnerf_grid.util import io

    truth_all = true_spans(scene_attachments())
    # find_spans' steps: every one after the refinement goes with it
    steps = {"refine": not args.no_refine,
             **{key: not (args.no_refine or getattr(args, f"no_{key}"))
                for key in ("shared_azimuth", "shared_span", "shared_curvature", "next_tower", "shared_sag", "settle")}}
    results = []
    for i, data in enumerate(args.data):
        size = tuple(int(v) for v in args.partial.split(",")) if args.partial else None
        meta = scene_meta(data, size)
        gen = meta.get("generator", {})
        truth = truth_all if gen.get("conductors", True) else []
        picture = None
        if args.pictures is not None:
            args.pictures.mkdir(parents=True, exist_ok=True)
            picture = args.pictures / f"{data.name}_conductors_views.png"
        entry = {"data": data.name, "preset": gen.get("preset"), "seed": gen.get("seed"),
                 "distractors": gen.get("distractors"), "conductors": gen.get("conductors", True),
                 "size": [meta["w"], meta["h"]], "partial": gen.get("partial"), "span_length": args.span_length,
                 "arm_seeds": bool(args.arm_seeds), "detect_threshold": args.detect_threshold,
                 "top_window": not args.no_top_window,
                 **steps}
        if not args.no_true_cameras:
            records, timings = true_camera_fit(data, picture, size, args.span_length, args.arm_seeds,
                                               args.detect_threshold, **steps, top_window=not args.no_top_window)
            entry["true_cameras"] = {**score(records, truth), "timings": timings}
            print(json.dumps({k: v for k, v in entry["true_cameras"].items() if k != "spans"}), file=sys.stderr)
        if i < len(args.export):
            m = io.read_json(args.export[i] / "measurements.json")
            spans = ((m.get("conductor_spans") or {}).get("spans")) or []
            shift = gps_shift(m, data)
            if shift is not None:
                spans = [shifted(r, shift) for r in spans]
            timings = m.get("timings") or {}
            entry["export"] = {"folder": str(args.export[i]),
                               "shift_to_world": None if shift is None else [float(v) for v in shift],
                               **score(spans, truth, args.match_radius),
                               "export_seconds": m.get("seconds"), "conductor_seconds": timings.get("conductors")}
            print(json.dumps({k: v for k, v in entry["export"].items() if k != "spans"}), file=sys.stderr)
        results.append(entry)
    out = {"benchmark": "conductors", "load_avg": os.getloadavg(), "results": results}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
