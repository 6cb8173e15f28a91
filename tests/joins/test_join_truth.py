"""The joins of geometry scoring, export's score, export's field, the loss weights and
the proposal sampler held to answers computed independently (hand counts, per-pixel loops,
closed forms, NumPy), each test written against a one-line mistake that the rest of the suite would miss."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data.normalize import apply_normalization_to_points
from jaxnerf_grid.eval import evaluate, geometry
from jaxnerf_grid.eval import export_score as score_lib
from jaxnerf_grid.nerf import fields
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError
from tests.support import analytic_field as af
from tests.train.test_loop import TINY_FIELD, tiny_config, tiny_dataset

# --------------------------------------------------------------------------- planted clouds


def _lattice(lo, hi, step):
    """The points of a regular lattice in the box [lo, hi] ([3] each), `step` apart. [M, 3]."""
    axes = [np.arange(a, b + 1e-9, step) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _half_of(ref, shrink=0.0):
    """The reference points with x below the middle of their x range: half of them exactly,
    drawn `shrink` of the way to the reference's centre (inside its box whatever the float
    rounding of the normalisations, within far less than a threshold of their twins)."""
    xs = np.unique(ref[:, 0])
    keep = ref[:, 0] < xs[len(xs) // 2]
    assert keep.sum() * 2 == len(ref)
    centre = 0.5 * (ref.min(0) + ref.max(0))
    return centre + (1.0 - shrink) * (ref[keep] - centre)


def test_a_cloud_covering_half_the_reference_has_recall_half_and_precision_one():
    ref = _lattice([0, 0, 0], [0.7, 0.3, 0.9], 0.1)               # 8 x 4 x 10 points
    pred = _half_of(ref)
    # no ground strip: every point is scored; by hand, all pred points sit on ref points (P = 1),
    # half of ref has a pred point within 0.01 (R = 0.5)
    out = geometry.score_points(pred, ref, (0.01,), ground_strip=0.0)
    assert out["thresholds"]["0.01"]["precision"] == 1.0
    assert out["thresholds"]["0.01"]["recall"] == 0.5
    assert out["num_pred"] == len(ref) // 2 and out["num_ref"] == len(ref)
    # the box is the reference's, not the prediction's: a pred point beyond the reference's x
    # range is cropped, so it counts for nothing
    out = geometry.score_points(np.vstack([pred, [[5.0, 0.1, 0.5]]]), ref, (0.01,), ground_strip=0.0)
    assert out["num_pred"] == len(ref) // 2 and out["thresholds"]["0.01"]["precision"] == 1.0


def test_eval_geometry_score_is_precision_one_recall_half_on_a_planted_half_cloud(tmp_path):
    """`evaluate.score_geometry` -> `geometry.score_against_ply`: the exported cloud is the
    prediction, the dataset's tower.ply the reference, through both normalisation records."""
    metric_ref = _lattice([10, 20, 0], [17, 23, 9], 1.0) * [1, 1, 1.5] + [0, 0, 30]  # 8 x 4 x 10, z 30..43.5
    file_norm = {"scale": 0.1, "translation": [-10.0, -20.0, -30.0]}
    scene_norm = {"scale": 0.05, "translation": [-13.0, -21.0, -35.0], "rotation": af.TURN_Z.tolist()}
    io.write_ply(tmp_path / "tower.ply", apply_normalization_to_points(metric_ref, file_norm))
    ds = tiny_dataset()
    ds.root, ds.normalization = tmp_path, scene_norm
    ds.meta = {"tower_ply": "tower.ply", "scene_normalization": file_norm}
    # the rotation turns about z: the up axis stays z, so the lowest layer is the ground strip
    # (0.05 normalised units = 1 m: the layer at z = 30 m, 32 of the 320 points, is cropped)
    pred = apply_normalization_to_points(_half_of(metric_ref, 1e-3), scene_norm)
    out = evaluate.score_geometry(ds, [(pred, np.zeros_like(pred))])
    tau = out["thresholds"]["0.01"]
    assert (tau["precision"], tau["recall"]) == (1.0, 0.5)
    assert out["num_ref"] == 320 - 32 and out["num_pred"] == 160 - 16


def _export_folder(folder, mesh_points, fused_points, height):
    folder.mkdir(parents=True, exist_ok=True)
    io.write_ply(folder / "tower_mesh.ply", mesh_points, faces=np.zeros((0, 3), int))
    io.write_ply(folder / "tower_points.ply", fused_points)
    io.write_json(folder / "measurements.json", {"units": "metres", "height": height})


def test_export_score_in_metres_crops_a_one_metre_strip_and_keeps_precision_and_recall_apart(tmp_path):
    """`score.score_export` and `evaluate.export_section`: in metres, the ground strip is
    DEFAULT_GROUND_STRIP normalised units / scale (1 m at scale 0.05), and the export is the
    prediction."""
    ref = _lattice([0, 0, 0], [7, 3, 9], 1.0) * [1, 1, 1.5]        # metres, 8 x 4 x 10 (z = 0 .. 13.5)
    half = _half_of(ref, 1e-3)
    _export_folder(tmp_path / "run" / "export", half, ref, 13.5)
    out = score_lib.score_export(tmp_path / "run" / "export", ref, 0.05)
    assert out["ground_strip"] == pytest.approx(1.0)
    # by hand: the strip (the box's bottom at z = 1 m) drops the layer z = 0: 9 of the 10 layers
    # are scored
    assert out["mesh"]["num_ref"] == 32 * 9 and out["mesh"]["num_pred"] == 16 * 9
    tau = out["mesh"]["thresholds"]["0.2"]
    assert (tau["precision"], tau["recall"]) == (1.0, 0.5)
    tau = out["points"]["thresholds"]["0.2"]
    assert (tau["precision"], tau["recall"]) == (1.0, 1.0)
    assert out["height"] == {"export": 13.5, "reference": 13.5, "error": 0.0, "error_percent": 0.0}
    assert out["units"] == "metres" and out["reference_points"] == len(ref)
    # the height error in percent of a short reference, and of a flat one (none)
    flat = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]])
    assert score_lib.height_error(0.8, flat + [[0, 0, 0], [0, 0, 0.5]]) == {
        "export": 0.8, "reference": 0.5, "error": pytest.approx(0.3), "error_percent": pytest.approx(60.0)}
    assert score_lib.height_error(0.8, flat)["error_percent"] is None

    # the same through eval: the dataset's record (scale 0.05) sets the strip
    norm = {"scale": 0.05, "translation": [-3.5, -1.5, -6.75], "rotation": af.TURN_Z.tolist()}
    io.write_ply(tmp_path / "tower.ply", apply_normalization_to_points(ref, norm))
    ds = tiny_dataset()
    ds.root, ds.normalization = tmp_path, norm
    ds.meta = {"tower_ply": "tower.ply", "scene_normalization": norm}
    info = evaluate.export_section(ds, tmp_path / "run")
    assert info["score"]["ground_strip"] == pytest.approx(1.0)
    assert info["score"]["mesh"]["num_ref"] == 32 * 9
    tau = info["score"]["mesh"]["thresholds"]["0.2"]
    assert (tau["precision"], tau["recall"]) == (1.0, 0.5)


def test_export_section_reads_the_files_record_the_users_reference_and_a_record_without_scale(tmp_path):
    """`evaluate.export_section` (metrics.json["export"]): the measurements and the picture handed
    on as written; the dataset's tower stored in another record than the dataset's (scale 0.1,
    its own translation) is mapped through that record; a user's reference in the dataset's
    units replaces a missing tower; a dataset record without a scale scores in its own units
    (strip = DEFAULT_GROUND_STRIP). Each time the counts by hand of the test above: 9 of 10
    layers, P = 1, R = 0.5."""
    ref = _lattice([0, 0, 0], [7, 3, 9], 1.0) * [1, 1, 1.5]
    _export_folder(tmp_path / "run" / "export", _half_of(ref, 1e-3), ref, 13.5)
    norm = {"scale": 0.05, "translation": [-3.5, -1.5, -6.75], "rotation": af.TURN_Z.tolist()}
    file_norm = {"scale": 0.1, "translation": [1.0, 2.0, 3.0]}
    io.write_ply(tmp_path / "tower.ply", apply_normalization_to_points(ref, file_norm))
    io.write_ply(tmp_path / "user.ply", apply_normalization_to_points(ref, norm))
    io.write_ply(tmp_path / "plain.ply", ref)
    ds = tiny_dataset()
    ds.root, ds.normalization = tmp_path, norm
    ds.meta = {"tower_ply": "tower.ply", "scene_normalization": file_norm}
    runs = [evaluate.export_section(ds, tmp_path / "run")]
    assert runs[0]["measurements"] == {"units": "metres", "height": 13.5}
    assert runs[0]["image"] == "export/export_views.png"
    ds.meta = None                                   # a dataset without a meta record: no tower
    assert evaluate.reference_cloud(ds) is None
    runs.append(evaluate.export_section(ds, tmp_path / "run", reference_ply=tmp_path / "user.ply"))
    ds.normalization = {}
    runs.append(evaluate.export_section(ds, tmp_path / "run", reference_ply=tmp_path / "plain.ply"))
    for info, strip in zip(runs, (1.0, 1.0, geometry.DEFAULT_GROUND_STRIP)):
        assert info["score"]["ground_strip"] == pytest.approx(strip)
        assert info["score"]["mesh"]["num_ref"] == 32 * 9
        tau = info["score"]["mesh"]["thresholds"]["0.2"]
        assert (tau["precision"], tau["recall"]) == (1.0, 0.5)


# --------------------------------------------------------------------------- export's field


@pytest.fixture
def analytic(monkeypatch):
    """The analytic tower (tests/support/analytic_field.py) in place of `fields.apply`."""
    af.clear_compiled()
    monkeypatch.setattr(fields, "apply", af.apply)
    yield
    monkeypatch.undo()
    af.clear_compiled()


def analytic_config(contract_radius=2.5):
    """The "ours" model (contraction, encoding scale = contract_radius) with 48 + 48 samples."""
    return train.make_config("ours", {"model": {"field": TINY_FIELD, "contract_radius": contract_radius,
                                                "sampler": {"kind": "hierarchical", "samples": [48, 48]}},
                                      "train": {"num_devices": 1, "chunk": 2048}})


def test_export_field_is_the_analytic_tower_at_its_metric_place(analytic):
    """`export.field.evaluate` feeds the field the model's own input map: the density it returns
    at metric points (normalised with the record) is the analytic tower's, in and out."""
    from jaxnerf_grid.export import field

    cfg = analytic_config()
    params = af.params(cfg.model)
    rng = np.random.default_rng(3)
    lo, hi = af.boxes()[0]
    inside = rng.uniform(lo + 0.2, hi - 0.2, (200, 3))
    outside = np.column_stack([rng.uniform(lo[0] - 8, lo[0] - 2.5, 100), rng.uniform(lo[1], hi[1], 100),
                               rng.uniform(af.GROUND_Z + 1, af.GROUND_Z + 19, 100)])
    tower = np.vstack([inside, outside])                          # the tower's frame
    scene = apply_normalization_to_points(af.to_metric_frame(tower), af.NORMALIZATION)
    sigma = field.evaluate(params, cfg.model, scene)["sigma"]
    np.testing.assert_array_equal(sigma, np.where(af.inside_tower(tower), af.SIGMA, 0.0))
    assert np.sum(sigma > 0) == 200


class _Counter:
    def __init__(self):
        self.steps = []

    def update(self, n):
        self.steps.append(n)


def _analytic_sigma(scene):
    """The analytic scene's density at normalised points [N, 3], from the record in closed form."""
    metric = af.to_tower_frame((scene @ np.asarray(af.ROTATION)) / af.NORMALIZATION["scale"]
                               - np.asarray(af.NORMALIZATION["translation"]))
    ground = (metric[:, 2] <= af.GROUND_Z) & (metric[:, 2] >= af.GROUND_Z - 2.0)
    return np.where(af.inside_tower(metric) | ground, af.SIGMA, 0.0), af.inside_tower(metric)


def test_export_field_in_chunks_with_directions_is_the_analytic_tower_point_by_point(analytic):
    """300 points in chunks of 7 (the last padded): each point's density and colour are the
    analytic tower's at that point, in order; the progress bar counts the points once; no point
    gives empty arrays of the documented shapes."""
    from jaxnerf_grid.export import field

    cfg = analytic_config()
    params = af.params(cfg.model)
    rng = np.random.default_rng(4)
    scene = rng.uniform([-0.2, -0.2, -0.65], [0.2, 0.2, 0.55], (300, 3))
    sigma_ref, tower = _analytic_sigma(scene)
    assert 30 < np.sum(sigma_ref > 0) < 270                     # both kinds of points, interleaved
    dirs = rng.normal(size=(300, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    bar = _Counter()
    out = field.evaluate(params, cfg.model, scene, dirs, chunk=7, progress=bar)
    np.testing.assert_array_equal(out["sigma"], sigma_ref)
    np.testing.assert_allclose(out["rgb"], np.where(tower[:, None], af.TOWER_RGB, af.GROUND_RGB), atol=1e-6)
    assert out["sigma"].dtype == np.float32 and out["rgb"].dtype == np.float32
    assert sum(bar.steps) == 300 and max(bar.steps) == 7 and bar.steps[-1] == 300 % 7
    empty = field.evaluate(params, cfg.model, np.zeros((0, 3)), np.zeros((0, 3)), chunk=7)
    assert empty["sigma"].shape == (0,) and empty["rgb"].shape == (0, 3)
    assert empty["sigma"].dtype == np.float32 and empty["rgb"].dtype == np.float32
    density_only = field.evaluate(params, cfg.model, np.zeros((0, 3)))
    assert list(density_only) == ["sigma"] and density_only["sigma"].shape == (0,)
    assert density_only["sigma"].dtype == np.float32


@pytest.mark.parametrize("chunk", [13, 1 << 16])
def test_export_density_grid_nodes_are_origin_plus_h_times_ijk(analytic, chunk):
    """density_grid's node (i, j, k) is origin + h (i, j, k): against the analytic density there,
    on a grid of 7 x 6 x 12 nodes across the tower's edge and the ground (slabs of one x-plane
    with chunk 13, the whole grid in one with the default)."""
    from jaxnerf_grid.export import field

    cfg = analytic_config()
    origin, h, shape = np.array([-0.3031, -0.2517, -0.6093]), 0.0977, (7, 6, 12)
    bar = _Counter()
    grid = field.density_grid(af.params(cfg.model), cfg.model, origin, h, shape, chunk=chunk, progress=bar)
    assert sum(bar.steps) == 7 * 6 * 12                         # the bar counts every node once
    i, j, k = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    nodes = origin + h * np.stack([i, j, k], axis=-1).reshape(-1, 3)
    assert grid.shape == shape and grid.dtype == np.float32
    reference = _analytic_sigma(nodes)[0].reshape(shape)
    assert 0 < np.sum(reference > 0) < reference.size
    np.testing.assert_array_equal(grid, reference)


def test_export_colours_are_the_mean_seen_from_the_k_nearest_cameras(analytic, monkeypatch):
    """colours_from_cameras with a field whose colour is 0.5 + 0.5 x the viewing direction: each
    point's colour is the mean over its k nearest camera centres of 0.5 + 0.5 (p - c) / |p - c|
    (brute force); k larger than the cameras means all of them; k = 1 the nearest; one point is
    coloured, none gives [0, 3] float32."""
    from jaxnerf_grid.export import field

    def seen_from(field_params, field_cfg, x, viewdirs=None, appearance=None, transient=None):
        return {"sigma": af.apply(field_params, field_cfg, x)["sigma"], "rgb": 0.5 + 0.5 * viewdirs}

    af.clear_compiled()
    monkeypatch.setattr(fields, "apply", seen_from)
    cfg = analytic_config()
    rng = np.random.default_rng(5)
    points, centres = rng.uniform(-0.5, 0.5, (20, 3)), rng.uniform(-2.0, 2.0, (5, 3))
    for k, pts in ((3, points), (9, points), (1, points), (3, points[:1])):
        colours = field.colours_from_cameras(af.params(cfg.model), cfg.model, pts, centres, k=k, chunk=8)
        expected = []
        for p in pts:
            nearest = centres[np.argsort(np.linalg.norm(centres - p, axis=1))[:min(k, 5)]]
            d = (p - nearest) / np.linalg.norm(p - nearest, axis=1, keepdims=True)
            expected.append(np.mean(0.5 + 0.5 * d, axis=0))
        np.testing.assert_allclose(colours, expected, atol=1e-6)
        assert colours.dtype == np.float32
    none = field.colours_from_cameras(af.params(cfg.model), cfg.model, np.zeros((0, 3)), centres)
    assert none.shape == (0, 3) and none.dtype == np.float32


def test_export_colours_of_an_appearance_model_use_the_mean_embedding(analytic, monkeypatch):
    """A model with per-image appearance embeddings (NeRF-W's): the exported colour is the field's
    at the mean of the embedding table over the images (a field whose colour is the embedding's
    first three numbers, so the mean is read off); without a table, the zero embedding."""
    from jaxnerf_grid.export import field

    def tinted(field_params, field_cfg, x, viewdirs=None, appearance=None, transient=None):
        return {"sigma": af.apply(field_params, field_cfg, x)["sigma"], "rgb": appearance[..., :3]}

    af.clear_compiled()
    monkeypatch.setattr(fields, "apply", tinted)
    cfg = train.make_config("ours", {"model": {"field": TINY_FIELD, "contract_radius": 2.5, "use_appearance": True,
                                               "appearance_dim": 4,
                                               "sampler": {"kind": "hierarchical", "samples": [48, 48]}},
                                     "train": {"num_devices": 1, "chunk": 2048}})
    table = np.array([[0.1, 0.2, 0.3, 0.9], [0.5, 0.0, 0.7, 0.1], [0.3, 0.4, 0.2, 0.5]], np.float32)  # [images, 4]
    points = np.random.default_rng(6).uniform(-0.3, 0.3, (10, 3))
    dirs = np.tile([0.0, 0.0, 1.0], (10, 1))
    out = field.evaluate({**af.params(cfg.model), "appearance": jnp.asarray(table)}, cfg.model, points, dirs)
    np.testing.assert_allclose(out["rgb"], np.tile([0.3, 0.2, 0.4], (10, 1)), atol=1e-6)
    np.testing.assert_array_equal(field.evaluate(af.params(cfg.model), cfg.model, points, dirs)["rgb"], 0.0)


# --------------------------------------------------------------------------- the loss weights


@pytest.mark.parametrize("floor", [0.2, 0.7])
def test_loss_weights_cap_masked_pixels_at_one_minus_the_floor(floor):
    ds = tiny_dataset()
    rng = np.random.default_rng(5)
    ds.weights = rng.uniform(-0.2, 1.2, ds.weights.shape).astype(np.float32)
    ds.masks = (rng.uniform(size=ds.weights.shape) > 0.5).astype(np.float32)
    got = train.loss_weights(ds, tiny_config(mask_weight_floor=floor).train)
    want = np.empty_like(got)
    for idx in np.ndindex(*ds.weights.shape):                        # per pixel, by the rule
        w = min(max(float(ds.weights[idx]), 0.0), 1.0)
        want[idx] = min(w, 1.0 - floor) if ds.masks[idx] > 0.5 else w
    np.testing.assert_allclose(got, want, atol=1e-7)
    assert got.dtype == np.float32                                   # the docstring's dtype
    off = train.loss_weights(ds, tiny_config(use_masks=False).train)
    assert off.dtype == np.float32 and off.shape == ds.weights.shape and np.all(off == 1.0)


@pytest.mark.parametrize("mode", ["robust", "dpt+robust"])
def test_prior_weights_are_ones_or_the_capped_weights_whatever_use_masks_says(mode):
    """train.robust's prior: ones in mode robust; in dpt+robust the dataset's weights clipped to
    [0, 1] and capped at 1 - floor under the mask, even with train.use_masks off."""
    ds = tiny_dataset()
    rng = np.random.default_rng(6)
    ds.weights = rng.uniform(-0.2, 1.2, ds.weights.shape).astype(np.float32)
    ds.masks = (rng.uniform(size=ds.weights.shape) > 0.5).astype(np.float32)
    got = train.prior_weights(ds, tiny_config(robust=mode, robust_patch=4, use_masks=False,
                                              mask_weight_floor=0.3).train)
    want = np.ones(ds.weights.shape, np.float32)
    if mode == "dpt+robust":
        for idx in np.ndindex(*ds.weights.shape):
            w = min(max(float(ds.weights[idx]), 0.0), 1.0)
            want[idx] = min(w, 0.7) if ds.masks[idx] > 0.5 else w
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=1e-7)


def test_loss_weights_without_masks_ignore_the_floor_and_prior_weights_check_the_data_not_the_batch():
    """Weights without masks (a dataset's own weights files) are only clipped, whatever the floor;
    prior_weights refuses dpt+robust without weights (DataError) and a patch larger than the
    frames (ConfigError), but not a batch that is no multiple of the patch, nor one
    with scattered rays."""
    ds = tiny_dataset()
    ds.weights = np.linspace(-0.5, 1.5, ds.weights.size, dtype=np.float32).reshape(ds.weights.shape)
    ds.masks = None
    got = train.loss_weights(ds, tiny_config(mask_weight_floor=0.4).train)
    np.testing.assert_array_equal(got, np.clip(ds.weights, 0.0, 1.0))
    robust = tiny_config(robust="robust", robust_patch=4).train
    assert np.all(train.prior_weights(ds, dataclasses.replace(robust, batch_rays=50)) == 1.0)
    # a quarter of the batch scattered (64 = 16 scattered + 3 patches of 16): the prior checks one
    # patch without them (4 of its 16 rays scattered would leave 12, no whole patch)
    quarter = dataclasses.replace(robust, batch_rays=64, robust=dataclasses.replace(robust.robust, scattered=0.25))
    assert np.all(train.prior_weights(ds, quarter) == 1.0)
    with pytest.raises(ConfigError, match="robust.patch"):                 # 13 > the 16 x 12 frames
        train.prior_weights(ds, dataclasses.replace(robust, robust=dataclasses.replace(robust.robust, patch=13)))
    with pytest.raises(ConfigError, match="robust.patch_stride = 4: spans 13 px"):  # (4 - 1) 4 + 1 > 12
        train.prior_weights(ds, dataclasses.replace(robust, robust=dataclasses.replace(robust.robust, patch_stride=4)))
    assert np.all(train.prior_weights(ds, dataclasses.replace(robust, batch_rays=16, robust=dataclasses.replace(
        robust.robust, patch_stride=3))) == 1.0)
    ds.weights = None
    with pytest.raises(DataError, match="dpt\\+robust"):
        train.prior_weights(ds, tiny_config(robust="dpt+robust", robust_patch=4).train)


def test_grown_masks_of_no_growth_skip_opencv_and_the_grown_prior_is_float32_or_refused_word_for_word(monkeypatch):
    """grown_masks masks where > 0.5 (0.5 itself is not masked, 0.5 + 2^-20 is) and, with no
    growth (0 or fewer pixels), returns that without loading OpenCV (`io.opencv` made to fail
    here). prior_weights with train.robust.prior_grow: float32 like its other branches; without
    binary masks a DataError whose whole message names the dataset and what writes the masks."""
    masks = np.zeros((2, 3, 4), np.float32)
    masks[0, 1, 2], masks[1, 0, 0], masks[1, 2, 3] = 0.5, 0.5 + 2.0 ** -20, 1.0
    want = np.zeros((2, 3, 4), bool)
    want[1, 0, 0] = want[1, 2, 3] = True

    def no_opencv():
        raise AssertionError("OpenCV loaded for no growth")

    with monkeypatch.context() as m:
        m.setattr(io, "opencv", no_opencv)
        for pixels in (0, -1):
            got = train.grown_masks(masks, pixels)
            assert got.dtype == bool
            np.testing.assert_array_equal(got, want)
    ds = tiny_dataset()
    ds.masks = np.zeros(ds.images.shape[:3], np.float32)
    ds.masks[0, 5, 7] = 1.0
    grown = train.prior_weights(ds, tiny_config(robust="dpt+robust", robust_patch=4, robust_prior_grow=1).train)
    assert grown.dtype == np.float32 and grown[0, 5, 7] == 0.0
    ds.masks = None
    with pytest.raises(DataError) as err:
        train.prior_weights(ds, tiny_config(robust="dpt+robust", robust_patch=4, robust_prior_grow=1).train)
    assert str(err.value) == (f"{ds.root}: train.robust.prior_grow needs the dataset's binary masks "
                              "(mask_path, written by jaxnerf-grid mask)")


# --------------------------------------------------------------------------- proposal resampling


def test_proposal_main_samples_share_one_jitter_per_ray_with_the_padding(monkeypatch):
    """With single_jitter, the main field's samples are the inverse CDF (the last round's weights
    plus `padding` times their mean) at u_j = (j + c) / n with one c per ray: recovered here
    with NumPy from the returned levels and edges. The proposal field is a closed-form bump."""
    from jaxnerf_grid.nerf import samplers

    cfg = samplers.proposal.Config(samples=(16,), main_samples=8, padding=0.2)
    monkeypatch.setattr(fields.proposal, "density",
                        lambda params, fcfg, x: 30.0 * jnp.exp(-jnp.sum((x - params["centre"]) ** 2, -1) / 0.1))
    rays = 6
    origins = jnp.asarray(np.random.default_rng(1).normal(0, 0.3, (rays, 3)), jnp.float32)
    directions = jnp.asarray(np.tile([0.0, 0.6, 0.8], (rays, 1)), jnp.float32)

    def points(t_edges):
        t_mid = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
        return origins[:, None] + t_mid[..., None] * directions[:, None]

    passes = samplers.passes.Passes(batch_shape=(rays,), single_jitter=True, far_bin=lambda s: s,
                                    s_to_t=lambda s: 0.2 + 2.0 * s, points=points, shade=None)
    params = {"proposal": [{"centre": jnp.asarray([0.0, 0.6, 0.8])}]}
    levels, s_main = samplers.proposal.rounds(params, cfg, passes, jax.random.PRNGKey(7))
    edges, w = np.asarray(levels[-1]["s_edges"], np.float64), np.asarray(levels[-1]["weights"], np.float64)
    assert np.ptp(w, axis=-1).min() > 1e-3                          # the weights are not uniform
    mass = np.maximum(w, 0) + 0.2 * w.mean(-1, keepdims=True) + 1e-12
    cdf = np.concatenate([np.zeros((rays, 1)), np.cumsum(mass / mass.sum(-1, keepdims=True), -1)], -1)
    n = s_main.shape[-1]
    assert n == 9
    u = np.stack([np.interp(np.asarray(s_main[r], np.float64), edges[r], cdf[r]) for r in range(rays)])
    jitter = u * n - np.arange(n)                                    # [rays, n]: one value per ray
    np.testing.assert_allclose(jitter, np.broadcast_to(jitter[:, :1], jitter.shape), atol=2e-3)
    assert np.all((jitter >= -1e-3) & (jitter <= 1 + 1e-3)) and np.ptp(jitter[:, 0]) > 0.05


# --------------------------------------------------------------------------- geometry's edges
# (the survivors of mutmut on geometry.py that change a value or a message: docs/TESTING.md)


def test_score_points_reports_its_crop_and_chamfer_by_hand():
    ref = _lattice([0, 0, 0], [0.7, 0.3, 0.9], 0.1)
    pred = _half_of(ref) + [0.0, 0.0, 0.03]                          # 0.03 above each twin
    out = geometry.score_points(pred, ref, (0.03, 0.5), ground_strip=0.15)
    lo, hi = ref.min(0), ref.max(0)
    lo[2] += 0.15                                                   # layers z >= 0.2 are scored
    assert out["box"] == {"min": pytest.approx(lo.tolist()), "max": pytest.approx(hi.tolist())}
    assert out["ground_strip"] == 0.15 and out["up_axis"] == 2
    r = ref[ref[:, 2] >= 0.2 - 1e-9]
    p = pred[(pred[:, 2] >= 0.2 - 1e-9) & (pred[:, 2] <= 0.9 + 1e-9)]
    assert (out["num_ref"], out["num_pred"]) == (len(r), len(p))
    d_pred = np.linalg.norm(p[:, None] - r[None], axis=-1).min(1)  # brute force
    d_ref = np.linalg.norm(r[:, None] - p[None], axis=-1).min(1)
    assert out["chamfer"] == pytest.approx(0.5 * (d_pred.mean() + d_ref.mean()))
    # a distance exactly at the threshold counts (<=): 0.5 is exact in binary
    got = geometry.prf_from_distances(np.array([0.5, 0.75]), np.array([0.5]), (0.5,))[0.5]
    assert (got["precision"], got["recall"]) == (0.5, 1.0)
    got = geometry.prf_from_distances(np.array([0.25]), np.zeros(0), (0.5,))[0.5]
    assert (got["precision"], got["recall"]) == (1.0, 0.0)          # a share of nothing is 0
    # another up axis: the strip is cut along it
    out = geometry.score_points(ref, ref, (0.01,), ground_strip=0.15, up_axis=0)
    assert out["num_ref"] == np.sum(ref[:, 0] >= 0.15 - 1e-9) and out["up_axis"] == 0
    # a strip as tall as the reference leaves its top layer
    assert geometry.score_points(ref, ref, (0.01,), ground_strip=0.9)["num_ref"] == 32


def test_nearest_distances_and_chamfer_with_one_point_and_none():
    one = np.array([[1.0, 2.0, 2.0]])
    cloud = np.array([[1.0, 2.0, 0.0], [4.0, 6.0, 2.0]])
    np.testing.assert_allclose(geometry.nearest_distances(cloud, one), [2.0, 5.0])
    np.testing.assert_allclose(geometry.nearest_distances(one, cloud), [2.0])
    assert geometry.chamfer(cloud, one) == pytest.approx(0.5 * (3.5 + 2.0))
    assert geometry.nearest_distances([], cloud).shape == (0,)
    out = geometry.score_points([], cloud, (1.0,), ground_strip=0.0)
    assert out["num_pred"] == 0 and out["chamfer"] is None
    with pytest.raises(ValueError, match=r"points must be \[N, 3\], got \(2, 2\)"):
        geometry.nearest_distances(np.zeros((2, 2)), cloud)
    with pytest.raises(ValueError, match="tower_box: the reference cloud is empty"):
        geometry.tower_box(np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"tower_box: ground_strip 2.0 is taller than the reference \(1 units\)"):
        geometry.tower_box(np.array([[0.0, 0.0, 5.0], [1.0, 1.0, 6.0]]), 2.0)


def test_reference_to_scene_between_records_that_share_a_scale_or_a_translation():
    p = np.array([[0.1, -0.2, 0.3], [0.5, 0.4, -0.1]])
    for file_norm, scene_norm in (({"scale": 0.1, "translation": [1.0, 2.0, 3.0]},
                                   {"scale": 0.1, "translation": [0.0, 2.0, 3.0]}),
                                  ({"scale": 0.1, "translation": [1.0, 2.0, 3.0]},
                                   {"scale": 0.05, "translation": [1.0, 2.0, 3.0]})):
        metric = p / file_norm["scale"] - np.asarray(file_norm["translation"])       # by hand
        want = scene_norm["scale"] * (metric + np.asarray(scene_norm["translation"]))
        np.testing.assert_allclose(geometry.reference_to_scene(p, file_norm, scene_norm), want, atol=1e-12)


def test_score_against_ply_takes_the_strip_and_refuses_an_empty_reference(tmp_path):
    ref = _lattice([0, 0, 0], [0.7, 0.3, 0.9], 0.1)
    io.write_ply(tmp_path / "tower.ply", ref)
    out = geometry.score_against_ply([(ref, ref)], tmp_path / "tower.ply", thresholds=(0.01,), ground_strip=0.0)
    assert out["num_ref"] == len(ref) and out["units"] == "normalised scene units"
    io.write_ply(tmp_path / "one.ply", ref[:1])
    assert geometry.score_against_ply([(ref, ref)], tmp_path / "one.ply", ground_strip=0.0)["num_ref"] == 1
    io.write_ply(tmp_path / "empty.ply", np.zeros((0, 3)))
    with pytest.raises(io.DataError, match="empty.ply: the reference point cloud is empty"):
        geometry.score_against_ply([(ref, ref)], tmp_path / "empty.ply")
