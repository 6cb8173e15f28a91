"""report.html (docs/REPORT_HTML.md): the helpers against brute force and closed forms,
the page of a tiny run (self-contained, the views, the measurements as measurements.json has
them) and its screenshot in headless Chromium (the 3-D view holds the model's pixels: those that
change when the model's traces are hidden, whatever the model's colours)."""

import base64
import html
import json
import os
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.report import html as report_html
from jaxnerf_grid.report import markdown as report_markdown
from jaxnerf_grid.util import io
from tests.train.test_loop import TINY_FIELD, tiny_dataset

CHROMIUM = Path("/usr/bin/chromium")
NORM = {"scale": 0.05, "translation": [3.0, -2.0, -15.0]}


# --------------------------------------------------------------------------- helpers


def test_decimate_points_keeps_a_subset_in_order_with_its_colours():
    rng = np.random.default_rng(1)
    p, c = rng.normal(size=(500, 3)), rng.uniform(size=(500, 3))
    q, d = report_html.decimate_points(p, c, limit=120)
    assert len(q) == len(d) == 120
    rows = [int(np.flatnonzero(np.all(p == x, axis=1))[0]) for x in q]   # where each kept point came from
    assert rows == sorted(rows) and len(set(rows)) == 120
    np.testing.assert_array_equal(d, c[rows])
    same, _ = report_html.decimate_points(p, None, limit=500)
    assert same is p


def test_cluster_mesh_matches_a_brute_force_grid_merge():
    # a 20 x 20 grid of vertices on a tilted plane, two triangles per square
    n = 20
    u, v = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    verts = np.stack([u.ravel() * 0.1, v.ravel() * 0.1, 0.03 * u.ravel()], -1)
    idx = np.arange(n * n).reshape(n, n)
    faces = np.concatenate([np.stack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()], -1),
                            np.stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()], -1)])
    colours = np.random.default_rng(0).uniform(size=(n * n, 3))
    cell = 0.25
    v2, f2, c2 = report_html.cluster_mesh(verts, faces, colours, cell)
    # brute force: a dict of cells, each vertex's cell by a loop
    groups = {}
    for k, x in enumerate(verts):
        groups.setdefault(tuple(int(np.floor(a / cell)) for a in x), []).append(k)
    assert len(v2) == len(groups)
    means = {tuple(np.round(verts[ks].mean(0), 9)): colours[ks].mean(0) for ks in groups.values()}
    for x, c in zip(v2, c2):
        np.testing.assert_allclose(means[tuple(np.round(x, 9))], c)
    cell_of = {k: key for key, ks in groups.items() for k in ks}
    tris = set()
    for a, b, c in faces:
        ka, kb, kc = cell_of[a], cell_of[b], cell_of[c]
        if len({ka, kb, kc}) == 3:
            tris.add(frozenset((ka, kb, kc)))
    keys = [tuple(int(np.floor(a / cell)) for a in x) for x in v2]   # a merged vertex stays in its cell
    assert {frozenset(keys[i] for i in f) for f in f2} == tris and len(f2) == len(tris)
    vd, fd, _ = report_html.decimate_mesh(verts, faces, colours, limit=100)
    assert 0 < len(fd) <= 100


def test_frustum_corners_project_to_the_image_corners():
    from jaxnerf_grid.nerf import rays

    c2w = np.asarray(rays.look_at([3.0, 1.0, 2.0], [0, 0, 0]), np.float64)
    fx, fy, cx, cy, w, h = 50.0, 55.0, 31.0, 22.0, 64, 48
    lines = report_html.frustum_lines(c2w, [fx, fy, cx, cy], w, h, depth=0.5)
    corners = lines[8:12]
    # world -> camera (the camera looks along -z, y up), then the pinhole
    cam = (corners - c2w[:3, 3]) @ c2w[:3, :3]
    u = fx * cam[:, 0] / -cam[:, 2] + cx
    v = -fy * cam[:, 1] / -cam[:, 2] + cy
    np.testing.assert_allclose(np.stack([u, v], -1), [[0, 0], [w, 0], [w, h], [0, h]], atol=1e-4)   # look_at is float32
    np.testing.assert_allclose(-cam[:, 2], 0.5, atol=1e-6)
    np.testing.assert_allclose(lines[0], c2w[:3, 3])


def test_box_lines_are_the_twelve_edges():
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 3.0, 2.5])
    pts = report_html.box_lines(lo, hi).reshape(12, 3, 3)
    assert np.all(np.isnan(pts[:, 2]))
    edges = {frozenset(map(tuple, e[:2])) for e in pts}
    corners = [np.array([x, y, z]) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    want = {frozenset((tuple(a), tuple(b))) for i, a in enumerate(corners) for b in corners[i + 1:]
            if np.sum(a != b) == 1}
    assert edges == want and len(want) == 12


def test_ground_patch_lies_on_the_plane_and_is_centred():
    n = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    q = report_html.ground_patch(n, -0.7, [2.0, 3.0, 9.0], 1.5)
    np.testing.assert_allclose(q @ n - 0.7, 0, atol=1e-12)
    foot = np.array([2.0, 3.0, 9.0]) - (n @ [2.0, 3.0, 9.0] - 0.7) * n
    np.testing.assert_allclose(q.mean(0), foot, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q[1] - q[0]), 3.0)


def test_the_first_view_is_a_cube_around_the_model():
    verts = np.array([[0.0, 0.0, 0.0], [2.0, 1.0, 10.0]])
    scene = {"mesh": (verts, np.zeros((0, 3), int), None), "measurements": None, "points": None}
    ranges = report_html.tower_ranges(scene, margin=0.1)
    # a cube of side 10 * 1.2 centred on (1, 0.5, 5)
    np.testing.assert_allclose(ranges, [[1 - 6, 1 + 6], [0.5 - 6, 0.5 + 6], [5 - 6, 5 + 6]])
    assert report_html.tower_ranges({"mesh": None, "measurements": None, "points": None}) is None


# --------------------------------------------------------------------------- the measurements drawn


# cross-arm 1 from x = -2 to 10 m (off the box's vertical axis, x = 0) at 20 m above the plane
# 0.6 y + 0.8 z + 1.5 = 0: y = 0, z = 23.125
ARM_ENDS = [[-2.0, 0.0, 23.125], [10.0, 0.0, 23.125]]


def _export_folder(folder: Path) -> dict:
    """An export folder with a known measurements.json, a small mesh and a cloud (metres)."""
    n = np.array([0.0, 0.6, 0.8])
    meas = {"units": "metres", "height": 30.0, "box": {"min": [-5.0, -5.0, -2.0], "max": [5.0, 5.0, 30.0]},
            "ground": {"normal": n.tolist(), "offset": 1.5},
            "footprint": {"width_a": 6.0, "width_b": 4.0, "axis_a": [1.0, 0.0, 0.0], "axis_b": [0.0, 0.8, -0.6]},
            "cross_arms": {"levels": [{"height": 20.0, "span": 12.0, "axis": "a", "ends": ARM_ENDS},
                                      {"height": 26.0, "span": 8.0, "axis": "b"}]}}   # written before "ends"
    folder.mkdir(parents=True)
    io.write_json(folder / "measurements.json", meas)
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32) * 10
    io.write_ply(folder / "tower_mesh.ply", verts, np.eye(4)[:, :3], np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3],
                                                                                 [1, 2, 3]]))
    io.write_ply(folder / "tower_points.ply", verts, np.eye(4)[:, :3])
    return meas


def test_the_page_carries_and_draws_the_measurements_of_measurements_json(tmp_path):
    ds = tiny_dataset()
    ds.normalization = NORM
    meas = _export_folder(tmp_path / "run" / "export")
    path = report_html.write_report_html(tmp_path / "report.html", tmp_path / "run", ds,
                                         export_dir=tmp_path / "run" / "export")
    text = path.read_text()
    block = re.search(r'<script type="application/json" id="measurements">(.*?)</script>', text, re.S).group(1)
    shown = json.loads(block)["measurements"]
    saved = io.read_json(tmp_path / "run" / "export" / "measurements.json")
    assert shown["height"] == saved["height"] == 30.0 and shown["units"] == "metres"
    assert shown["box"] == {"min": saved["box"]["min"], "max": saved["box"]["max"]}
    assert [(a["height"], a["span"]) for a in shown["cross_arms"]] == [(20.0, 12.0), (26.0, 8.0)]
    assert shown["cross_arms"][0]["ends"] == ARM_ENDS and "ends" not in shown["cross_arms"][1]
    assert "height: 30.00 m" in text and "cross-arm 1: 12.00 m" in text
    # the lines drawn: the height from the ground along the normal, the spans at their heights
    n, d = np.array(meas["ground"]["normal"]), meas["ground"]["offset"]
    lines = {x["name"]: x for x in report_html.measurement_lines(meas)}
    foot, top = lines["height"]["points"]
    assert foot @ n + d == pytest.approx(0, abs=1e-12) and top @ n + d == pytest.approx(30.0)
    for name, (h, span, axis) in {"cross-arm 1": (20, 12, [1, 0, 0]), "cross-arm 2": (26, 8, [0, 0.8, -0.6])}.items():
        a, b = lines[name]["points"]
        assert np.linalg.norm(b - a) == pytest.approx(span)
        np.testing.assert_allclose([a @ n + d, b @ n + d], [h, h], atol=1e-9)
        np.testing.assert_allclose(np.cross(b - a, axis), 0, atol=1e-9)
    # cross-arm 1 between its recorded ends; cross-arm 2 (no ends) centred on the box's vertical line
    np.testing.assert_allclose(lines["cross-arm 1"]["points"], ARM_ENDS)
    np.testing.assert_allclose(np.mean(lines["cross-arm 2"]["points"], axis=0), foot + 26.0 * n, atol=1e-9)


# --------------------------------------------------------------------------- a tiny run's page


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny run (a ball, 2 x 32 MLP, 40 steps) evaluated and exported with the CLI."""
    from jaxnerf_grid.data.formats import save_transforms_json
    from jaxnerf_grid.train import runs

    root = tmp_path_factory.mktemp("report_html")
    ds = tiny_dataset(width=24, height=18, frames=7)
    ds.frame_paths = [f"images/frame_{i:03d}.png" for i in range(ds.num_frames)]
    save_transforms_json(ds, root / "data")
    meta = io.read_json(root / "data" / "transforms.json")
    io.write_json(root / "data" / "transforms.json", {**meta, "scene_normalization": NORM})
    overrides = {"model": {"field": TINY_FIELD, "num_coarse": 8, "num_fine": 8},
                 "train": {"batch_rays": 128, "max_steps": 40, "checkpoint_every": 40, "log_every": 20, "warmup": 5,
                           "lr_init": 5e-3, "lr_final": 1e-3, "chunk": 512, "num_devices": 1}}
    run, _, _ = runs.train_run(str(root / "data"), "ours", root / "run", overrides, progress=False)
    assert cli.main(["eval", "--run", str(run), "--quiet", "--distractor-views", "0"]) == 0
    return run


def test_eval_and_export_write_a_self_contained_page(tiny_run):
    page = tiny_run / "report.html"
    assert page.is_file()
    text = page.read_text()
    # nothing fetched: no script or stylesheet by address (plotly.js names its CDN only for geo maps' topojson)
    assert not re.search(r"<script[^>]*\bsrc=", text) and "<link" not in text
    assert "Plotly.newPlot" in text and len(text) > 3_000_000            # plotly.js itself is in the page
    # the first view's ground truth is the dataset's test photo (8-bit)
    src = re.search(r'<img class="view" src="data:image/png;base64,([^"]+)"', text).group(1)
    import cv2
    gt = cv2.imdecode(np.frombuffer(base64.b64decode(src), np.uint8), cv2.IMREAD_COLOR)[..., ::-1] / 255.0
    photo = io.read_image(next((tiny_run.parent / "data" / "images").glob("*frame_006.png")))
    np.testing.assert_allclose(gt, photo, atol=1 / 255 + 1e-6)
    assert text.count('class="view"') == 3                              # gt | render | depth of the one test view
    assert cli.main(["export", "--run", str(tiny_run), "--box=-21,-18,-3,15,22,33", "--resolution", "24",
                     "--threshold", "0.02", "--views", "4", "--quiet"]) == 0
    text = page.read_text()
    shown = json.loads(re.search(r'id="measurements">(.*?)</script>', text, re.S).group(1))
    saved = io.read_json(tiny_run / "export" / "measurements.json")
    assert shown["units"] == "metres" and shown["measurements"]["box"]["min"] == saved["box"]["min"]
    assert shown["counts"]["faces"][0] == saved["mesh"]["faces"] and 'class="view"' in text


def _screenshot(page: Path, out: Path, size=(1200, 900)) -> np.ndarray:
    cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
           "--use-angle=swiftshader", "--hide-scrollbars", "--virtual-time-budget=15000",
           f"--window-size={size[0]},{size[1]}", f"--screenshot={out}", page.resolve().as_uri()]
    subprocess.run(cmd, check=True, capture_output=True, timeout=180)
    return io.read_image(out)


def _require_chromium():
    if not CHROMIUM.exists():
        why = ("/usr/bin/chromium is missing: install Debian's `chromium` (bash scripts/setup.sh --test does) "
               "to screenshot report.html")
        if os.environ.get("JAXNERF_GRID_REQUIRE_CHROMIUM") == "1":   # where the browser must be (CI)
            pytest.fail(why)
        pytest.skip(why)


MODEL_TRACES = ("mesh", "tower points")   # the names report_html.figure gives the model's traces

# Appended to a copy of the page: once plotly has drawn, hide the legend (its entries grey out when
# a trace is hidden) and the traces named in HIDE.
HIDING_SCRIPT = """<script>window.addEventListener("load", function () { setTimeout(function () {
  var gd = document.getElementById("%s"), hide = %s, idx = [];
  gd.data.forEach(function (t, i) { if (hide.indexOf(t.name) >= 0) { idx.push(i); } });
  Plotly.relayout(gd, {showlegend: false});
  if (idx.length) { Plotly.restyle(gd, {visible: false}, idx); }
}, 200); });</script>"""


def model_pixels(page: Path, folder: Path, hide=MODEL_TRACES) -> tuple[np.ndarray, np.ndarray]:
    """The pixels the model adds to the page's screenshot: two copies of `page`, both with the
    legend hidden, the second with the traces named `hide` hidden too, screenshotted in headless
    Chromium; a pixel is the model's where the two differ (by more than 0.1 in a channel), so the
    criterion holds for a model of any colour. Returns (mask [H, W], the first screenshot)."""
    text = page.read_text()
    shots = []
    for name, names in (("shown", []), ("hidden", list(hide))):
        copy = folder / f"{page.stem}_{name}.html"
        script = HIDING_SCRIPT % (report_html.PLOT_DIV, json.dumps(names))
        copy.write_text(text.replace("</body>", script + "</body>"))
        shots.append(_screenshot(copy, folder / f"{page.stem}_{name}.png"))
    return np.max(np.abs(shots[0] - shots[1]), axis=-1) > 0.1, shots[0]


def test_the_page_shows_the_model_in_headless_chromium(tiny_run, tmp_path):
    _require_chromium()
    if not (tiny_run / "export" / "measurements.json").is_file():
        assert cli.main(["export", "--run", str(tiny_run), "--box=-21,-18,-3,15,22,33", "--resolution", "24",
                         "--threshold", "0.02", "--views", "4", "--quiet"]) == 0
    model, shot = model_pixels(tiny_run / "report.html", tmp_path)
    io.write_png(tiny_run / "report_screenshot.png", shot)
    # the 3-D view: below the title, 640 px high; the model's pixels are inside it
    rows, cols = np.nonzero(model)
    assert model.mean() > 0.01, f"only {int(model.sum())} pixels of the screenshot are the model's"
    assert rows.min() > 60 and rows.max() < 760, "the model's pixels are not in the 3-D view"


def test_a_grey_model_is_found_in_the_screenshot(tmp_path):
    """A grey mesh and grey points (a real tower's colours, close to plotly's greys): their pixels
    are found all the same; hiding nothing finds none (the screenshots are repeatable)."""
    _require_chromium()
    ds = tiny_dataset()
    ds.normalization = NORM
    export = tmp_path / "run" / "export"
    _export_folder(export)
    verts, faces = report_html.read_mesh(export / "tower_mesh.ply")[:2]
    grey = np.full((len(verts), 3), 0.55)
    io.write_ply(export / "tower_mesh.ply", verts, grey, faces)
    io.write_ply(export / "tower_points.ply", verts, grey)
    page = report_html.write_report_html(tmp_path / "report.html", tmp_path / "run", ds, export_dir=export)
    model, shot = model_pixels(page, tmp_path)
    assert model.mean() > 0.01, f"only {int(model.sum())} pixels of the screenshot are the grey model's"
    saturation = shot.max(-1) - shot.min(-1)
    assert np.mean(saturation[model] > 0.2) < 0.05            # grey: the saturation rule found none of them
    (tmp_path / "nothing").mkdir()
    nothing, _ = model_pixels(page, tmp_path / "nothing", hide=())
    assert not nothing.any()


# --------------------------------------------------------------------------- progress.html


def test_svg_curve_places_the_points_linearly():
    from jaxnerf_grid.report.progress_page import svg_curve

    svg = svg_curve([(0, 1.0), (10, 3.0), (20, 2.0), (30, float("nan"))], "loss", width=100, height=80)
    pts = np.array([[float(v) for v in p.split(",")] for p in re.search(r'points="([^"]+)"', svg).group(1).split()])
    # 30 px margins: steps 0..20 over x 30..70, the values 1..3 over y 50..30 (up); the NaN left out
    np.testing.assert_allclose(pts, [[30, 50], [50, 30], [70, 40]], atol=0.05)


def test_train_progress_page_is_rewritten_while_training(tmp_path):
    from jaxnerf_grid.data.formats import save_transforms_json
    from jaxnerf_grid.train import runs

    ds = tiny_dataset()
    save_transforms_json(ds, tmp_path / "data")
    overrides = {"model": {"field": TINY_FIELD, "num_coarse": 8, "num_fine": 8},
                 "train": {"batch_rays": 64, "max_steps": 25, "checkpoint_every": 10, "log_every": 5, "warmup": 5,
                           "lr_init": 5e-3, "lr_final": 1e-3, "chunk": 256, "num_devices": 1}}
    seen = []
    from jaxnerf_grid.report import progress_page

    original = progress_page.write_progress_page

    def spy(run_dir, records, step, view, seconds):
        seen.append((step, len(records), None if view is None else view["step"]))
        return original(run_dir, records, step, view, seconds)

    progress_page.write_progress_page = spy
    try:
        run, _, _ = runs.train_run(str(tmp_path / "data"), "ours", tmp_path / "run", overrides, progress=False,
                                   progress_page=10)
    finally:
        progress_page.write_progress_page = original
    # every 10 steps and at the end: the log so far, that step's checkpoint
    assert seen == [(10, 2, 10), (20, 4, 20), (25, 5, 25)]
    text = (run / "progress.html").read_text()
    assert "step 25" in text and 'http-equiv="refresh"' in text and text.count("<polyline") == 2
    assert text.count('class="view"') == 3
    with pytest.raises(Exception, match="run.progress_page"):
        runs.train_run(str(tmp_path / "data"), "ours", tmp_path / "run2", overrides, progress=False, progress_page=-1)


def test_every_layer_of_the_3d_view_lies_in_the_export_frame_at_hand_worked_positions(tmp_path):
    """The cloud, the mesh, the cameras, the measurement lines and the conductors of one page, all in
    metres: each checked at a position worked out by hand from NORM (x = x_norm / 0.05 - t)."""
    import math

    ds = tiny_dataset()
    ds.normalization = NORM
    meas = _export_folder(tmp_path / "run" / "export")
    a, xv = 1600.0, 160.0
    theta = [-7.6, 14.9, math.pi / 2, -math.sinh(xv / a), 1.0 / a]    # x = 7.6, along +y, lowest at y = 160
    meas["conductor_spans"] = {"spans": [{"theta": theta, "centre": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0]}]}
    io.write_json(tmp_path / "run" / "export" / "measurements.json", meas)
    scene = report_html.scene_of_run(tmp_path / "run", ds, export_dir=tmp_path / "run" / "export")
    fig = report_html.figure(scene)
    traces = {t.name: t for t in fig.data}

    def xyz(trace):
        return np.array([[x, y, z] for x, y, z in zip(trace.x, trace.y, trace.z) if x is not None], np.float64)

    # the conductors: the attachment (7.6, 0, 14.9), the lowest point a (cosh(x_v / a) - 1) below it at y = 160
    wire = xyz(traces["conductors (fitted catenaries)"])
    np.testing.assert_allclose(wire[0], [7.6, 0.0, 14.9], atol=1e-9)
    low = wire[np.argmin(wire[:, 2])]
    np.testing.assert_allclose(low, [7.6, 160.0, 14.9 - a * (math.cosh(xv / a) - 1.0)], atol=1e-3)
    np.testing.assert_allclose(wire[-1], [7.6, 320.0, 14.9], atol=1e-6)
    # the cloud and the mesh: the file's metres as written (the tetrahedron 0..10 m)
    np.testing.assert_allclose(np.sort(xyz(traces["tower points"]), axis=0),
                               np.sort(np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10.0]]), axis=0), atol=1e-5)
    mesh = traces["mesh"]
    np.testing.assert_allclose(sorted(mesh.x), [0, 0, 0, 10], atol=1e-5)
    # the cameras: each frustum's apex is the camera's centre, x_norm / 0.05 - (3, -2, -15)
    apex = np.asarray(ds.c2w[0])[:3, 3] / 0.05 - np.array([3.0, -2.0, -15.0])
    cams = xyz(traces["training cameras"])
    assert np.min(np.linalg.norm(cams - apex, axis=1)) < 1e-6
    # the measurement lines: the height line's foot on the ground, its top 30 m up the normal
    height = next(t for n, t in traces.items() if n.startswith("height"))
    foot, top = xyz(height)
    n, d = np.array([0.0, 0.6, 0.8]), 1.5
    assert foot @ n + d == pytest.approx(0.0, abs=1e-9) and top @ n + d == pytest.approx(30.0, abs=1e-9)
    # the box: its corners are measurements.json's, in metres
    box = xyz(traces["box"])
    np.testing.assert_allclose(box.min(axis=0), [-5.0, -5.0, -2.0]) and np.testing.assert_allclose(
        box.max(axis=0), [5.0, 5.0, 30.0])


# --------------------------------------------------------------------------- the doubtful findings

NOT_SEEN = {"radius": 16.0, "count": 3, "min_count": 10, "median_height": 0.05, "tolerance": 0.2, "doubtful": True,
            "reason": "too few ground points"}
SOUND = {**NOT_SEEN, "count": 812, "median_height": 0.0, "doubtful": False, "reason": None}
NOT_SEEN_WORDS = ("only 3 ground points of the cloud within 16.00 m of the point beneath the lowest point (at least 10 "
                  "needed): the ground there is not seen, and the clearance over the ground is the fitted plane's "
                  "extrapolation")
TILT_725 = ("the tower's axis leans 7.25 deg from vertical: a standing lattice tower leans under 2 degrees in every "
            "export measured here: either this one leans, or the model's tower is incomplete or misplaced (look at "
            "report_views.png), and its height, cross-arm levels and the conductors' clearance are doubtful")


def _span(seen: dict | None, side: int = 1) -> dict:
    """A fitted span's record: a 320 m level span along +y at x = 7.6 (as above), its lowest point
    6.90 +- 0.01 above the ground, the ground beneath as `seen` says."""
    fig = {"value": 1.0, "sigma": 0.1}
    theta = [-7.6, 14.9, np.pi / 2, -np.sinh(0.1), 1.0 / 1600.0]
    return {"theta": theta, "centre": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0], "side": side,
            "attachment": {"value": [0.0, 0.0, 14.9], "sigma": [0.0, 0.0, 0.01]}, "sag": fig,
            "catenary_parameter": fig, "clearance": {"ground": 6.9, "ground_sigma": 0.01, "ground_seen": seen}}


def _page_of(tmp_path, extra: dict) -> str:
    """The text of the page of an export whose measurements.json is `_export_folder`'s with `extra`."""
    ds = tiny_dataset()
    ds.normalization = NORM
    meas = {**_export_folder(tmp_path / "run" / "export"), **extra}
    io.write_json(tmp_path / "run" / "export" / "measurements.json", meas)
    return report_html.write_report_html(tmp_path / "report.html", tmp_path / "run", ds,
                                         export_dir=tmp_path / "run" / "export").read_text()


def _doubt_block(text: str) -> list[tuple[str, str]] | None:
    """The (label, words) rows of the page's warning block, unescaped; None when it has none."""
    found = re.search(r'<div class="doubt" id="doubt">(.*?)</div>', text, re.S)
    if found is None:
        return None
    return [(html.unescape(a), html.unescape(b)) for a, b in
            re.findall(r"<tr><th>(.*?)</th><td>(.*?)</td></tr>", found.group(1), re.S)]


def test_the_page_warns_at_its_top_of_a_leaning_tower_and_doubtful_spans_in_report_mds_words(tmp_path):
    """A tower leaning 7.25 deg, spans 1 and 3 doubtful (too few ground points beneath), span 2
    sound, the conductors' lowest reconstructed point's ground not seen: the page's warning block,
    before the 3-D view, holds report.md's bold rows word for word, each written out here."""
    lowest = {**NOT_SEEN, "radius": 2.5, "count": 0, "median_height": None}
    text = _page_of(tmp_path, {"survey": {"tilt_degrees": {"value": 7.25, "sigma": 0.4},
                                          "conductor_clearance": {"value": 11.0, "sigma": 0.5}},
                               "conductors": {"reconstructed": True, "ground_seen": lowest},
                               "conductor_spans": {"found": 3, "photos": 40,
                                                   "spans": [_span(NOT_SEEN), _span(SOUND, -1), _span(NOT_SEEN)]}})
    rows = _doubt_block(text)
    assert rows == [
        ("tilt doubtful", TILT_725),
        ("clearance doubtful", "2 spans (1, 3): " + NOT_SEEN_WORDS),
        ("clearance doubtful", "the conductors' lowest reconstructed point: only 0 ground points of the cloud "
                               "within 2.50 m of the point beneath the lowest point (at least 10 needed): the ground "
                               "there is not seen, and the clearance over the ground is the fitted plane's "
                               "extrapolation")]
    assert text.index('id="doubt"') < text.index(f'id="{report_html.PLOT_DIV}"')
    # report.md's rows of the same measurements: the same words
    md = report_markdown.export_lines({"measurements": io.read_json(tmp_path / "run" / "export" /
                                                                    "measurements.json")})
    assert [line for line in md if line.startswith("| **")] == [f"| **{a}** | {b} |" for a, b in rows]


def test_the_page_has_no_warning_when_the_tower_stands_and_the_ground_is_seen(tmp_path):
    """A tower leaning 1.74 deg (the most a sound export measured), its spans and its lowest
    reconstructed point over a seen ground: no warning block; nor without an export's survey."""
    text = _page_of(tmp_path, {"survey": {"tilt_degrees": {"value": 1.74, "sigma": 0.4}},
                               "conductors": {"reconstructed": True, "ground_seen": SOUND},
                               "conductor_spans": {"found": 2, "photos": 40, "spans": [_span(SOUND), _span(None)]}})
    assert _doubt_block(text) is None and "doubtful" not in text.split(f'id="{report_html.PLOT_DIV}"')[0]
    assert report_html.doubt_html(None) == "" and report_html.doubt_html({"units": "metres"}) == ""


def test_the_pages_conductor_tables_mark_the_doubtful_clearances(tmp_path):
    """The per-span conductors' table: span 1's clearance over the ground "6.90 +- 0.01 (doubtful)",
    span 2's (ground seen) unmarked; the measurements table: the conductors' lowest reconstructed
    point "11.00 m +- 0.50 m (doubtful)"."""
    text = _page_of(tmp_path, {"survey": {"conductor_clearance": {"value": 11.0, "sigma": 0.5}},
                               "conductors": {"reconstructed": True, "ground_seen": NOT_SEEN},
                               "conductor_spans": {"found": 2, "photos": 40,
                                                   "spans": [_span(NOT_SEEN), _span(SOUND, -1)]}})
    table = re.search(r'<table id="conductors">(.*?)</table>', text, re.S).group(1)
    head = re.findall(r"<th>(.*?)</th>", table)
    column = head.index("lowest point above the ground (m)")
    cells = [re.findall(r"<td>(.*?)</td>", row) for row in re.findall(r"<tr>(.*?)</tr>", table)[1:]]
    assert [(row[0], row[1], row[column]) for row in cells] == [("1", "+", "6.90 +- 0.01 (doubtful)"),
                                                               ("2", "-", "6.90 +- 0.01")]
    assert ("<tr><td>conductors&#x27; lowest reconstructed point above the ground</td>"
            "<td>11.00 m +- 0.50 m (doubtful)</td></tr>") in text
    sound = _page_of(tmp_path / "sound", {"survey": {"conductor_clearance": {"value": 11.0, "sigma": 0.5}},
                                          "conductors": {"reconstructed": True, "ground_seen": SOUND}})
    assert "<td>11.00 m +- 0.50 m</td>" in sound and 'id="conductors"' not in sound
