"""report.html: one self-contained page of a run that opens from disk with no network (docs/REPORT_HTML.md).

What it holds: above the 3-D view, a warning block with report.md's "tilt doubtful" and
"clearance doubtful" rows when there are any (`doubt_html`); the export's measurements and
report.md's per-span conductors' table (doubtful clearances marked); the metrics tables
(metrics.json), the test views beside the ground truth and the
depth (PNG, base64; each a thumbnail that opens full size on a click), and an interactive 3-D view
(plotly, its JavaScript embedded from the Python package, `include_plotlyjs=True`): the tower
cloud, the export's mesh where there is one, the training cameras as small frusta, the fitted
ground plane and the measurements (height, cross-arm spans where export measured them, the box).
The measurements also sit in the page as JSON (`<script type="application/json"
id="measurements">`) so that a reader (or a test) finds exactly the numbers the view draws.

The 3-D view is in the export's units when the run has an export (its PLY files, the cameras
moved by the dataset's normalisation undone), else in the normalised scene (the run's
tower_points.ply). Clouds are decimated to MAX_POINTS points, meshes to MAX_FACES faces.
"""

from __future__ import annotations

import base64
import html
import json
import os
import re
from pathlib import Path

import numpy as np

from jaxnerf_grid.data.normalize import apply_normalization_to_points, invert_normalization
from jaxnerf_grid.export import catenary
from jaxnerf_grid.report import markdown as report
from jaxnerf_grid.util import io

MAX_POINTS = 20000        # points of a cloud drawn in the 3-D view (a random subset, seeded)
MAX_FACES = 30000         # faces of a mesh drawn (vertex clustering on a coarser grid until it fits)
MAX_VIEWS = 8             # test views shown
VIEW_SIDE = 640           # longest side of an embedded view image (a larger one is shrunk)
FRUSTUM_SHARE = 0.04      # a camera frustum's depth, as a share of the scene's extent
PLOT_DIV = "scene3d"      # the id of the 3-D view's element (tests/report/test_html.py screenshots it)
METRIC_KEYS = ("psnr", "ssim", "ms_ssim", "lpips")


# --------------------------------------------------------------------------- geometry helpers


def decimate_points(points: np.ndarray, colours: np.ndarray | None, limit: int = MAX_POINTS, seed: int = 0):
    """At most `limit` of points [N, 3] (and their colours [N, 3]), a seeded random subset in
    the original order. Returns (points [M, 3], colours [M, 3] | None)."""
    points = np.asarray(points)
    if len(points) <= limit:
        return points, colours
    keep = np.sort(np.random.default_rng(seed).choice(len(points), limit, replace=False))
    return points[keep], None if colours is None else np.asarray(colours)[keep]


def cluster_mesh(verts: np.ndarray, faces: np.ndarray, colours: np.ndarray | None, cell: float):
    """Vertex clustering: vertices [V, 3] snapped to a grid of `cell`, each cell's vertices merged
    into their mean (colours averaged), faces [F, 3] that collapse or repeat dropped.
    Returns (verts [V', 3], faces [F', 3], colours [V', 3] | None)."""
    keys = np.floor(np.asarray(verts, np.float64) / cell).astype(np.int64)
    _, label, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    label = label.reshape(-1)
    merged = np.zeros((len(counts), 3))
    np.add.at(merged, label, verts)
    merged /= counts[:, None]
    new_colours = None
    if colours is not None:
        new_colours = np.zeros((len(counts), 3))
        np.add.at(new_colours, label, colours)
        new_colours /= counts[:, None]
    f = label[np.asarray(faces)]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(first)]
    return merged, f, new_colours


def decimate_mesh(verts: np.ndarray, faces: np.ndarray, colours: np.ndarray | None, limit: int = MAX_FACES):
    """A mesh (verts [V, 3], faces [F, 3], colours [V, 3] | None) with at most `limit` faces:
    `cluster_mesh` on a grid that coarsens by 1.5x from 1/512 of the extent until it fits."""
    if len(faces) <= limit:
        return verts, faces, colours
    extent = float(np.max(np.ptp(verts, axis=0))) or 1.0
    cell = extent / 512
    while True:
        v, f, c = cluster_mesh(verts, faces, colours, cell)
        if len(f) <= limit:
            return v, f, c
        cell *= 1.5


def frustum_lines(c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int, depth: float) -> np.ndarray:
    """The edges of a camera's frustum (the convention of `rays`: the camera looks along -z, y up)
    as a polyline with NaN breaks: [16, 3]. c2w [3|4, 4]; intrinsics [4] (fx, fy, cx, cy)."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    rot, centre = np.asarray(c2w, np.float64)[:3, :3], np.asarray(c2w, np.float64)[:3, 3]
    corners = [centre + depth * rot @ np.array([(u - cx) / fx, -(v - cy) / fy, -1.0])
               for u, v in ((0, 0), (width, 0), (width, height), (0, height))]
    gap = np.full(3, np.nan)
    a, b, c, d = corners
    return np.stack([centre, a, b, centre, c, d, centre, gap, a, b, c, d, a, gap, gap, gap])


def box_lines(lo, hi) -> np.ndarray:
    """The 12 edges of the axis-aligned box [lo, hi] as a polyline with NaN breaks: [36, 3]."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    corner = lambda i: np.where(np.array([i & 1, i >> 1 & 1, i >> 2 & 1], bool), hi, lo)  # noqa: E731
    edges = [(a, b) for a in range(8) for b in range(8) if a < b and bin(a ^ b).count("1") == 1]
    out = []
    for a, b in edges:
        out += [corner(a), corner(b), np.full(3, np.nan)]
    return np.stack(out)


def ground_patch(normal, offset: float, centre, half: float) -> np.ndarray:
    """The four corners [4, 3] of a square of side 2 * half on the plane n . x + offset = 0,
    centred on the projection of `centre`."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    foot = np.asarray(centre, np.float64) - (n @ centre + offset) * n
    helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return np.stack([foot + half * (s * e1 + t * e2) for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1))])


def measurement_lines(meas: dict) -> list[dict]:
    """What the 3-D view draws of measurements.json: [{"name", "value", "points" [2, 3]}] with
    "height" (from the box centre's foot on the ground along the normal) and one "cross-arm N"
    per level: between its recorded end points ("ends", `export.measure.cross_arms`); a file
    written before export recorded them: its span along the footprint's axis, centred on that
    vertical line at the level's height. Empty without a ground plane."""
    g = meas.get("ground")
    if not g or meas.get("height") is None:
        return []
    n = np.asarray(g["normal"], np.float64)
    centre = 0.5 * (np.asarray(meas["box"]["min"], np.float64) + np.asarray(meas["box"]["max"], np.float64))
    foot = centre - (n @ centre + g["offset"]) * n
    out = [{"name": "height", "value": float(meas["height"]), "points": np.stack([foot, foot + meas["height"] * n])}]
    fp = meas.get("footprint") or {}
    for k, level in enumerate((meas.get("cross_arms") or {}).get("levels") or []):
        axis = np.asarray(fp.get("axis_a" if level["axis"] == "a" else "axis_b", [1.0, 0, 0]), np.float64)
        mid = foot + level["height"] * n
        ends = level.get("ends") or [mid - 0.5 * level["span"] * axis, mid + 0.5 * level["span"] * axis]
        out.append({"name": f"cross-arm {k + 1}", "value": float(level["span"]), "height": float(level["height"]),
                    "points": np.asarray(ends, np.float64)})
    return out


def embedded_measurements(meas: dict | None) -> dict:
    """The JSON the page carries (id "measurements"): {"units", "height", "cross_arms" [{"height",
    "span", "ends" (the end points [2, 3] drawn, when measurements.json has them)}], "box" {"min",
    "max"}, "footprint" {"width_a", "width_b"}}; {} without an export."""
    if not meas:
        return {}
    fp = meas.get("footprint") or {}
    return {"units": meas.get("units"), "height": meas.get("height"),
            "cross_arms": [{"height": a["height"], "span": a["span"], **({"ends": a["ends"]} if "ends" in a else {})}
                           for a in (meas.get("cross_arms") or {}).get("levels") or []],
            "box": {"min": meas["box"]["min"], "max": meas["box"]["max"]},
            "footprint": {"width_a": fp.get("width_a"), "width_b": fp.get("width_b")} if fp else None}


# --------------------------------------------------------------------------- the scene


def _to_export_units(points: np.ndarray, normalization: dict | None) -> np.ndarray:
    """Normalised scene points [..., 3] -> the export's units (the dataset's normalisation undone)."""
    if not normalization:
        return np.asarray(points, np.float64)
    record = {"scale": float(normalization.get("scale", 1.0)),
              "translation": normalization.get("translation", [0.0, 0.0, 0.0])}
    if normalization.get("rotation") is not None:
        record["rotation"] = normalization["rotation"]
    return apply_normalization_to_points(points, invert_normalization(record))


def read_mesh(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A triangle mesh written by `io.write_ply` (binary little-endian, uchar-counted int faces):
    (verts [V, 3], faces [F, 3] int64, colours [V, 3] in [0, 1] | None). DataError naming the file
    when it has no triangle faces."""
    path = Path(path)
    vertex = io.read_ply(path)
    verts = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=-1).astype(np.float64)
    colours = (np.stack([vertex["red"], vertex["green"], vertex["blue"]], -1) / 255.0
               if "red" in vertex else None)
    raw = path.read_bytes()
    body = raw.find(b"\n", raw.find(b"end_header")) + 1
    header = raw[:body].decode("ascii", "replace")
    count = next((int(line.split()[2]) for line in header.splitlines() if line.startswith("element face")), 0)
    if count == 0 or "binary_little_endian" not in header:
        raise io.DataError(f"{path}: no binary little-endian triangle faces to draw")
    row = np.dtype([("n", "u1"), ("v", "<i4", (3,))])
    faces = np.frombuffer(raw, row, count=count, offset=len(raw) - count * row.itemsize)
    if np.any(faces["n"] != 3):
        raise io.DataError(f"{path}: faces that are not triangles")
    return verts, faces["v"].astype(np.int64), colours


def scene_of_run(run_dir, ds, export_dir=None) -> dict:
    """What the 3-D view draws: {"units", "points" ([N, 3], colours [N, 3] | None) | None, "mesh"
    (verts, faces, colours) | None, "cameras" [[16, 3] polylines], "measurements" (measurements.json)
    | None, "counts" {what was read and drawn}}. With an export (`export_dir` holding
    measurements.json) everything is in its units, else in the normalised scene."""
    run_dir = Path(run_dir)
    meas = None
    if export_dir is not None and (Path(export_dir) / "measurements.json").is_file():
        meas = io.read_json(Path(export_dir) / "measurements.json")
    move = (lambda p: _to_export_units(p, ds.normalization)) if meas else (lambda p: np.asarray(p, np.float64))
    cloud_path = Path(export_dir) / "tower_points.ply" if meas else run_dir / "tower_points.ply"
    counts, points, mesh = {}, None, None
    if cloud_path.is_file():
        vertex = io.read_ply(cloud_path)
        p = np.stack([vertex["x"], vertex["y"], vertex["z"]], -1).astype(np.float64)
        c = np.stack([vertex["red"], vertex["green"], vertex["blue"]], -1) / 255.0 if "red" in vertex else None
        points = decimate_points(p, c)
        counts["points"] = [int(len(p)), int(len(points[0]))]
    if meas and (Path(export_dir) / "tower_mesh.ply").is_file():
        v, f, c = read_mesh(Path(export_dir) / "tower_mesh.ply")
        mesh = decimate_mesh(v, f, c)
        counts["faces"] = [int(len(f)), int(len(mesh[1]))]
    train_ids = np.asarray(ds.split["train"]) if len(ds.split["train"]) else np.arange(ds.num_frames)
    centres = move(np.asarray(ds.c2w)[train_ids, :3, 3])
    extent = [np.ptp(centres, axis=0).max()] + ([np.ptp(points[0], axis=0).max()] if points and len(points[0]) else [])
    depth_norm = FRUSTUM_SHARE * float(max(extent) or 1.0)
    cameras = []
    for i in train_ids:
        # the frustum drawn in the normalised scene, then moved (a rotation and a scale keep its shape)
        scale = float((ds.normalization or {}).get("scale", 1.0)) if meas else 1.0
        lines = frustum_lines(ds.c2w[i], ds.intrinsics[i], ds.width, ds.height, depth_norm * scale)
        ok = np.isfinite(lines[:, 0])
        moved = np.full_like(lines, np.nan)
        moved[ok] = move(lines[ok])
        cameras.append(moved)
    return {"units": (meas or {}).get("units", "normalised scene units") if meas else "normalised scene units",
            "points": points, "mesh": mesh, "cameras": cameras, "measurements": meas, "counts": counts,
            "conductors": conductor_lines(meas)}


def conductor_lines(meas: dict | None, spacing: float = 1.0) -> list[np.ndarray]:
    """The fitted spans of measurements.json's `conductor_spans` as polylines [K, 3] in the export's
    units (`export.catenary.sample_span`, a point every `spacing` horizontally); [] without."""
    spans = ((meas or {}).get("conductor_spans") or {}).get("spans") or []
    lines = [catenary.sample_span(r["theta"], r["centre"], spacing, r["up"]) for r in spans]
    return [line for line in lines if len(line) > 1]


# --------------------------------------------------------------------------- the page


def _rgb_strings(colours: np.ndarray) -> list[str]:
    c = np.round(np.clip(np.asarray(colours, np.float64), 0, 1) * 255).astype(int)
    return [f"rgb({r},{g},{b})" for r, g, b in c]


def _polyline(parts: list[np.ndarray]) -> tuple[list, list, list]:
    """Polylines [K, 3] (NaN breaks) -> plotly's x, y, z lists with None breaks between them."""
    xs, ys, zs = [], [], []
    for part in parts:
        for x, y, z in part:
            ok = np.isfinite(x)
            xs.append(float(x) if ok else None)
            ys.append(float(y) if ok else None)
            zs.append(float(z) if ok else None)
        xs.append(None)
        ys.append(None)
        zs.append(None)
    return xs, ys, zs


def figure(scene: dict):
    """The plotly Figure of a `scene_of_run` dict."""
    import plotly.graph_objects as go

    traces = []
    if scene["mesh"] is not None:
        v, f, c = scene["mesh"]
        traces.append(go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2],
                                vertexcolor=None if c is None else _rgb_strings(c), color="#8a8a8a" if c is None
                                else None, flatshading=True, name="mesh", showlegend=True))
    if scene["points"] is not None:
        p, c = scene["points"]
        traces.append(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="markers", name="tower points",
                                   marker={"size": 2, "color": "#c04020" if c is None else _rgb_strings(c)}))
    xs, ys, zs = _polyline(scene["cameras"])
    traces.append(go.Scatter3d(x=xs, y=ys, z=zs, mode="lines", name="training cameras",
                               line={"color": "#1f4fbf", "width": 2}, hoverinfo="skip"))
    if scene.get("conductors"):
        cx, cy, cz = _polyline(scene["conductors"])
        traces.append(go.Scatter3d(x=cx, y=cy, z=cz, mode="lines", name="conductors (fitted catenaries)",
                                   line={"color": "#ff7f00", "width": 3}))
    meas = scene["measurements"]
    if meas:
        unit = "m" if meas.get("units") == "metres" else "units"
        bx, by, bz = _polyline([box_lines(meas["box"]["min"], meas["box"]["max"])])
        traces.append(go.Scatter3d(x=bx, y=by, z=bz, mode="lines",
                                   name="box", line={"color": "#444444", "width": 2, "dash": "dash"}))
        g = meas.get("ground")
        if g:
            lo, hi = np.asarray(meas["box"]["min"]), np.asarray(meas["box"]["max"])
            q = ground_patch(g["normal"], g["offset"], 0.5 * (lo + hi), 0.75 * float(np.max(hi - lo)))
            traces.append(go.Mesh3d(x=q[:, 0], y=q[:, 1], z=q[:, 2], i=[0, 0], j=[1, 2], k=[2, 3], opacity=0.35,
                                    color="#5a8f3a", name="ground plane", showlegend=True, hoverinfo="name"))
        for line in measurement_lines(meas):
            text = f"{line['name']}: {line['value']:.2f} {unit}"
            p = line["points"]
            traces.append(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="lines+markers+text",
                                       text=["", text], name=text, textposition="top center",
                                       line={"color": "#e0a000" if line["name"] == "height" else "#d02090",
                                             "width": 6}, marker={"size": 3}))
    fig = go.Figure(traces)
    ranges = tower_ranges(scene)
    whole = {f"scene.{a}axis.autorange": True for a in "xyz"}
    near = {f"scene.{a}axis.range": r for a, r in zip("xyz", ranges)} if ranges else whole
    fig.update_layout(scene={"aspectmode": "cube" if ranges else "data", "xaxis_title": "x", "yaxis_title": "y",
                             "zaxis_title": "z", **({f"{a}axis": {"range": r} for a, r in zip("xyz", ranges)}
                                                    if ranges else {})},
                      margin={"l": 0, "r": 0, "t": 30, "b": 0}, height=640,
                      title=f"Tower model ({scene['units']}); drag to rotate, scroll to zoom, right-drag to pan",
                      legend={"x": 0.01, "y": 0.98},
                      updatemenus=[{"type": "buttons", "direction": "left", "x": 0.99, "xanchor": "right", "y": 0.02,
                                    "buttons": [{"label": "the tower", "method": "relayout",
                                                 "args": [{**near, "scene.aspectmode": "cube" if ranges else "data"}]},
                                                {"label": "the tower and the cameras", "method": "relayout",
                                                 "args": [{**whole, "scene.aspectmode": "data"}]}]}])
    return fig


def tower_ranges(scene: dict, margin: float = 0.15) -> list[list[float]] | None:
    """The axis ranges [[lo, hi]] * 3 of the first view: a cube around the model (the mesh, else
    the box, else the middle 98 % of the points) widened by `margin` of its side on each side;
    None without a model."""
    if scene["mesh"] is not None and len(scene["mesh"][0]):
        lo, hi = scene["mesh"][0].min(0), scene["mesh"][0].max(0)
    elif scene["measurements"]:
        lo, hi = np.asarray(scene["measurements"]["box"]["min"]), np.asarray(scene["measurements"]["box"]["max"])
    elif scene["points"] is not None and len(scene["points"][0]) >= 10:
        lo, hi = np.percentile(scene["points"][0], 1, axis=0), np.percentile(scene["points"][0], 99, axis=0)
    else:
        return None
    centre, half = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) * (1 + 2 * margin)
    return [[float(c - half), float(c + half)] for c in centre]


def _png_data(image: np.ndarray) -> str:
    """An image [H, W, 3] in [0, 1] -> a data: URL of its PNG, the longest side shrunk to VIEW_SIDE."""
    import cv2

    image = np.clip(np.asarray(image, np.float32), 0, 1)
    side = max(image.shape[:2])
    if side > VIEW_SIDE:
        image = io.resize(image, (round(image.shape[1] * VIEW_SIDE / side), round(image.shape[0] * VIEW_SIDE / side)))
    ok, buf = cv2.imencode(".png", np.round(image[..., ::-1] * 255).astype(np.uint8))
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def _fmt(v, digits=3) -> str:
    return html.escape(report._fmt(v, digits))


def metrics_html(metrics: dict | None) -> str:
    """The metrics tables (mean, per view, geometry) of metrics.json as HTML."""
    if not metrics:
        return "<p>No metrics yet (run <code>jaxnerf-grid eval</code>).</p>"
    mean = metrics.get("mean") or {}
    rows = [(k.upper().replace("_", "-"), _fmt(mean.get(k), 2 if k == "psnr" else 4)) for k in METRIC_KEYS]
    for name, value in (metrics.get("regions_mean") or {}).items():
        rows.append((f"PSNR, {name.replace('_', ' ')}", _fmt(value, 2)))
    if metrics.get("distractor_psnr") is not None:
        rows.append(("PSNR inside distractors", _fmt(metrics["distractor_psnr"], 2)))
    out = [f"<h2>Metrics (mean over {metrics.get('num_views', '?')} test views, step {metrics.get('step', '?')})</h2>",
           "<table><tr><th>metric</th><th>value</th></tr>"]
    out += [f"<tr><td>{html.escape(k)}</td><td>{v}</td></tr>" for k, v in rows]
    out.append(f"</table><p>{html.escape(str(metrics.get('protocol', '')))}</p>")
    per_view = metrics.get("per_view") or []
    if per_view:
        out.append("<h3>Per view</h3><table><tr><th>view</th><th>PSNR</th><th>SSIM</th></tr>")
        out += [f"<tr><td>{html.escape(str(r['name']))}</td><td>{_fmt(r.get('psnr'), 2)}</td>"
                f"<td>{_fmt(r.get('ssim'), 4)}</td></tr>" for r in per_view]
        out.append("</table>")
    geo = metrics.get("geometry")
    if geo:
        out.append("<h3>Tower geometry (normalised units)</h3><table><tr><th>threshold</th><th>precision</th>"
                   "<th>recall</th><th>F-score</th></tr>")
        out += [f"<tr><td>{html.escape(t)}</td><td>{_fmt(r.get('precision'), 4)}</td><td>{_fmt(r.get('recall'), 4)}"
                f"</td><td>{_fmt(r.get('fscore'), 4)}</td></tr>" for t, r in geo.get("thresholds", {}).items()]
        out.append(f"</table><p>Chamfer distance {_fmt(geo.get('chamfer'), 4)}</p>")
    return "\n".join(out)


def measurements_html(meas: dict | None) -> str:
    """The export's measurements as an HTML table (none without an export); the conductors' lowest
    reconstructed point's clearance marked "(doubtful)" as report.md marks it."""
    if not meas:
        return ""
    unit = "m" if meas.get("units") == "metres" else "units (unknown scale)"
    rows = [("height above the fitted ground", f"{_fmt(meas.get('height'), 2)} {unit}")]
    fp = meas.get("footprint") or {}
    if fp:
        rows.append(("base footprint", f"{_fmt(fp.get('width_a'), 2)} x {_fmt(fp.get('width_b'), 2)} {unit}"))
    for k, a in enumerate((meas.get("cross_arms") or {}).get("levels") or []):
        rows.append((f"cross-arm {k + 1} at {_fmt(a['height'], 1)}", f"span {_fmt(a['span'], 2)} {unit}"))
    if (meas.get("conductors") or {}).get("reconstructed"):
        doubt = report.lowest_point_doubtful(meas, unit) is not None
        rows.append(("conductors' lowest reconstructed point above the ground",
                     report._pm((meas.get("survey") or {}).get("conductor_clearance"), unit)
                     + (" (doubtful)" if doubt else "")))
    box = meas.get("box") or {}
    rows.append(("box", f"{[round(v, 2) for v in box.get('min', [])]} - {[round(v, 2) for v in box.get('max', [])]}"))
    body = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in rows)
    return f"<h2>Measurements (export)</h2><table><tr><th>measurement</th><th>value</th></tr>{body}</table>"


def inline_markdown(text: str) -> str:
    """One line of report.md as HTML: escaped, **bold** as <b>, `code` as <code>."""
    out = html.escape(text, quote=False)
    out = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", out)
    return re.sub(r"`(.+?)`", r"<code>\1</code>", out)


def conductors_html(meas: dict | None) -> str:
    """report.md's "Conductors" section (`report.markdown.conductor_lines`: one row per span fitted
    in the photos, its clearance marked "(doubtful)" where the ground beneath is not seen) as HTML,
    its text and table row for row; "" without fitted spans' record. The photos' picture is left out."""
    lines = report.conductor_lines(meas, "m" if meas.get("units") == "metres" else "units") if meas else []
    if not lines:
        return ""
    cells = [[c.strip() for c in line.strip().strip("|").split(" | ")] for line in lines
             if line.startswith("|") and not line.startswith("|---")]
    text = "".join(f"<p>{inline_markdown(line)}</p>" for line in lines
                   if line and not line.startswith(("|", "#", "![")))
    table = ""
    if cells:
        head = "".join(f"<th>{inline_markdown(c)}</th>" for c in cells[0])
        body = "".join("<tr>" + "".join(f"<td>{inline_markdown(c)}</td>" for c in row) + "</tr>" for row in cells[1:])
        table = f'<table id="{CONDUCTORS_ID}"><tr>{head}</tr>{body}</table>'
    return f"<h2>Conductors</h2>{text}{table}"


CONDUCTORS_ID = "conductors"   # the id of the per-span conductors' table
DOUBT_ID = "doubt"         # the id of the warning block (tests/report/test_html.py reads it)


def doubt_html(meas: dict | None) -> str:
    """The warning block at the top of the page: report.md's bold "tilt doubtful" and "clearance
    doubtful" rows (`report.markdown.doubt_rows`, the same words) as a table; "" when the export is
    sound or there is none."""
    rows = report.doubt_rows(meas, "m" if meas.get("units") == "metres" else "units") if meas else []
    if not rows:
        return ""
    body = "".join(f"<tr><th>{html.escape(label)}</th><td>{html.escape(words, quote=False)}</td></tr>"
                   for label, words in rows)
    return (f'<div class="doubt" id="{DOUBT_ID}"><h2>Doubtful measurements</h2><table>{body}</table>'
            "<p>The figures these rows name are in the measurements below and in report.md, marked "
            "(doubtful) where they are.</p></div>")


def views_html(views: list[dict]) -> str:
    """The test views: one row per view of ground truth | render | depth thumbnails, each opening
    full size on a click. views: [{"name", "gt" [H, W, 3], "rgb" [H, W, 3], "depth" [H, W]}]."""
    if not views:
        return ""
    out = ["<h2>Test views (ground truth | render | depth); click an image for full size</h2>"]
    for v in views[:MAX_VIEWS]:
        cells = [(v["gt"], "ground truth"), (v["rgb"], "render"), (report.colourise_depth(v["depth"]), "depth")]
        imgs = "".join(f'<figure><img class="view" src="{_png_data(a)}" alt="{html.escape(v["name"])} {what}" '
                       f'onclick="zoom(this)"><figcaption>{html.escape(what)}</figcaption></figure>'
                       for a, what in cells)
        out.append(f'<div class="row"><div class="name">{html.escape(v["name"])}</div>{imgs}</div>')
    return "\n".join(out)


def videos_html(page_dir, run_dir) -> str:
    """The run's fly-around videos (RUN/videos/*.mp4, docs/VIDEOS.md) as links relative to the
    page's folder `page_dir`; "" when there are none. Links, not players: the videos are mp4v,
    which browsers generally do not play, and they stay beside the page rather than inside it."""
    folder = Path(run_dir) / "videos"
    found = sorted(p for p in folder.glob("*.mp4") if not p.name.startswith(".")) if folder.is_dir() else []
    if not found:
        return ""
    items = "".join(f'<li><a href="{html.escape(Path(os.path.relpath(p, page_dir)).as_posix())}">'
                    f"{html.escape(p.name)}</a></li>" for p in found)
    return ("<h2>Fly-around videos</h2><p>Beside this page, in the run's videos/ folder (MP4, codec mp4v: open "
            f"them with a video player):</p><ul>{items}</ul>")


STYLE = """body{font-family:sans-serif;margin:1em;color:#222}table{border-collapse:collapse;margin:.5em 0}
td,th{border:1px solid #bbb;padding:2px 8px;text-align:left}figure{display:inline-block;margin:4px}
img.view{width:220px;image-rendering:pixelated;cursor:zoom-in;border:1px solid #ccc}
.row{margin:6px 0}.name{font-weight:bold}#overlay{display:none;position:fixed;inset:0;
background:rgba(0,0,0,.85);align-items:center;justify-content:center;cursor:zoom-out}
#overlay img{max-width:95vw;max-height:95vh;image-rendering:pixelated;min-width:50vw}
.doubt{border:2px solid #b00000;background:#fff0f0;padding:0 1em;margin:.5em 0}.doubt th{color:#b00000}"""
SCRIPT = ("function zoom(img){var o=document.getElementById('overlay');o.firstChild.src=img.src;"
          "o.style.display='flex';}")


def page(title: str, plot_div: str, sections: list[str], embedded: dict, warning: str = "") -> str:
    """The whole HTML page: the title, `warning` (`doubt_html`), the 3-D view, the sections."""
    data = json.dumps(embedded, indent=1).replace("</", "<\\/")
    return "\n".join([
        "<!DOCTYPE html>", "<html><head><meta charset=\"utf-8\">", f"<title>{html.escape(title)}</title>",
        f"<style>{STYLE}</style>", f"<script>{SCRIPT}</script></head><body>",
        f"<h1>{html.escape(title)}</h1>", warning, plot_div, *sections,
        f'<script type="application/json" id="measurements">{data}</script>',
        '<div id="overlay" onclick="this.style.display=\'none\'"><img alt="full size"></div>', "</body></html>"])


def write_report_html(path, run_dir, ds, metrics: dict | None = None, views: list[dict] | None = None,
                      export_dir=None) -> Path:
    """Writes `path` (report.html, atomic): the run's metrics (`metrics`, else RUN/metrics.json when
    it exists), the test views (`views` as in `views_html`, else read back from RUN/renders/ and
    depth/ beside the dataset's targets for metrics["per_view"]) and the 3-D view of
    `scene_of_run(run_dir, ds, export_dir)`, then links to the run's videos (`videos_html`). Returns
    the path."""
    run_dir, path = Path(run_dir), Path(path)
    if metrics is None and (run_dir / "metrics.json").is_file():
        metrics = io.read_json(run_dir / "metrics.json")
    if views is None:
        views = _views_from_files(run_dir, ds, (metrics or {}).get("per_view") or [])
    scene = scene_of_run(run_dir, ds, export_dir)
    import plotly.io as pio

    plot = pio.to_html(figure(scene), include_plotlyjs=True, full_html=False, div_id=PLOT_DIV,
                       config={"displaylogo": False})
    counts = scene["counts"]
    notes = []
    if "points" in counts:
        notes.append(f"points drawn: {counts['points'][1]} of {counts['points'][0]}")
    if "faces" in counts:
        notes.append(f"mesh faces drawn: {counts['faces'][1]} of {counts['faces'][0]}")
    notes.append(f"{len(scene['cameras'])} training cameras")
    sections = [f"<p>{html.escape('; '.join(notes))}.</p>", measurements_html(scene["measurements"]),
                conductors_html(scene["measurements"]),
                metrics_html(metrics), views_html(views), videos_html(path.parent, run_dir)]
    title = f"Run report: {run_dir.name}"
    text = page(title, plot, sections, {"measurements": embedded_measurements(scene["measurements"]),
                                        "units": scene["units"], "counts": counts},
                doubt_html(scene["measurements"]))
    with io.naming_path(path):
        io.atomic_write_bytes(path, text.encode("utf-8"))
    return path


def _views_from_files(run_dir: Path, ds, per_view: list[dict]) -> list[dict]:
    """The views of metrics["per_view"] whose render and depth are in the run folder."""
    targets = ds.clean_images if ds.clean_images is not None else ds.images
    out = []
    for r in per_view[:MAX_VIEWS]:
        rgb, depth = run_dir / "renders" / f"{r['name']}.png", run_dir / "depth" / f"{r['name']}.exr"
        if rgb.is_file() and depth.is_file() and 0 <= int(r["index"]) < len(targets):
            out.append({"name": r["name"], "gt": np.asarray(targets[int(r["index"])], np.float32),
                        "rgb": io.read_image(rgb), "depth": io.read_exr(depth)})
    return out
