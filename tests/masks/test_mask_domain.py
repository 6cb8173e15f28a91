"""Knowing when the DPT is out of its domain (docs/MASKS.md): the per-frame
figures `mask` records (`masked_share`, `dpt_confidence`), the dataset-level rule
(`masking.domain_verdict`: out of domain when more than half of the frames have more than 40 %
of their pixels masked), and what `demo --masks` trains with (`demo.mask_plan`).

References are written here: the rule as a plain count over the frames, the confidence as a
NumPy softmax over the raw logits of `dpt.apply`. The built-in model is checked on photos unlike
its training data (scikit-image's sample photos, shipped with the package) and on small
synthetic tower scenes made here.
"""

import json

import numpy as np
import pytest

from jaxnerf_grid import demo
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.masks import dpt
from jaxnerf_grid.masks import foreground as fg
from jaxnerf_grid.masks import write as masking
from jaxnerf_grid.util import io


def _rule_by_hand(shares):
    """The rule as a count: frames with more than 40 % masked, against half the frames."""
    mostly = 0
    for s in shares:
        if s > 0.4:
            mostly += 1
    return mostly, mostly * 2 > len(shares)


@pytest.mark.parametrize("shares", [[0.5, 0.5, 0.1], [0.5, 0.1], [0.41, 0.41, 0.39, 0.39], [0.9] * 5,
                                    [0.0] * 3, [0.4, 0.4, 0.4], [0.41], [0.39]])
def test_domain_verdict_counts_mostly_masked_frames(shares):
    k, out = _rule_by_hand(shares)
    v = masking.domain_verdict(shares, [0.8] * len(shares))
    assert (v["frames_mostly_masked"], v["out_of_domain"], v["frames"]) == (k, out, len(shares))
    assert v["median_share"] == pytest.approx(float(np.median(shares)), abs=1e-4)
    assert v["mean_confidence"] == pytest.approx(0.8)
    assert ("OUT OF ITS DOMAIN" in masking.domain_line(v)) == out


def test_max_class_probability_against_numpy():
    logits = np.random.default_rng(0).normal(scale=3.0, size=(2, 5, 7, 9)).astype(np.float32)
    e = np.exp(logits.astype(np.float64) - logits.max(-1, keepdims=True))
    ref = (e / e.sum(-1, keepdims=True)).max(-1)
    np.testing.assert_allclose(np.asarray(fg.max_class_probability(logits)), ref, rtol=1e-5)


TINY_DPT = dict(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32, image_size=32,
                patch_size=16, backbone_out_indices=(0, 0, 1, 1), neck_hidden_sizes=(8, 8, 8, 8),
                fusion_hidden_size=8, num_labels=3, heads=("segmentation", "depth"))


@pytest.mark.parametrize("tiles", [1, 2])
def test_predict_maps_confidence_is_the_mean_max_probability_dpt_saw(tiles):
    """with_confidence adds the frame's mean largest-class probability over the pixels DPT saw
    (the working-size photo; every window when tiled), the maps unchanged."""
    model = dpt.init(0, dpt.DPTConfig(**TINY_DPT))
    photo = np.random.default_rng(1).uniform(size=(70, 100, 3)).astype(np.float32)
    (c, _, conf), = fg.predict_maps(model, model, [photo], classes=[1], max_side=64, batch_size=1, tiles=tiles,
                                      with_confidence=True)
    (c0, _), = fg.predict_maps(model, model, [photo], classes=[1], max_side=64, batch_size=1, tiles=tiles)
    np.testing.assert_array_equal(c, c0)
    if tiles == 1:
        x = fg.to_working_size(photo, 64, 32)[None]
    else:
        lay = fg.tile_layout(70, 100, 64, 32, tiles, 0.25)
        resized = fg.resize_map(photo, *lay.resized)
        x = np.stack([resized[y:y + lay.tile[0], s:s + lay.tile[1]] for y in lay.starts_y for s in lay.starts_x])
    logits = np.asarray(dpt.apply(model, dpt.normalize(x))["logits"], np.float64)
    e = np.exp(logits - logits.max(-1, keepdims=True))
    assert conf == pytest.approx(float((e / e.sum(-1, keepdims=True)).max(-1).mean()), rel=1e-5)


def _photo_dataset(folder, images):
    """A bare dataset: the photos as PNGs and a transforms.json listing them (no poses needed by `mask`)."""
    (folder / "images").mkdir(parents=True)
    frames = []
    for i, img in enumerate(images):
        io.write_png(folder / "images" / f"p{i}.png", img)
        frames.append({"file_path": f"images/p{i}.png"})
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": 1.0, "frames": frames}))
    return folder


needs_builtin = pytest.mark.skipif(not masking.BUILTIN.exists(), reason="no built-in DPT model in this build")


@needs_builtin
def test_builtin_model_stays_quiet_on_everyday_photos_without_transients(tmp_path, capsys):
    """scikit-image's sample photos of a coffee cup and a cat (no person, vehicle or bird): far
    from the synthetic tower scenes, but the built-in DPT was also trained on static real photos
    with empty masks, so `mask` masks little of them, records the figures per frame and says in
    one line that the model is in its domain (the rule's firing on a model that masks every
    pixel: tests/masks/test_write.py)."""
    skdata = pytest.importorskip("skimage.data")
    photos = [np.asarray(getattr(skdata, n)(), np.float32)[..., :3] / 255.0 for n in ("coffee", "chelsea", "cat")]
    data = _photo_dataset(tmp_path / "photos", photos)
    out = masking.write_masks(data, progress=False)
    line = capsys.readouterr().out
    meta = io.read_json(data / "transforms.json")
    shares = [f["masked_share"] for f in meta["frames"]]
    for f in meta["frames"]:  # the recorded share is the written mask's
        m = io.read_mask(data / f["mask_path"])
        assert f["masked_share"] == pytest.approx(float(np.mean(m > 0.5)), abs=1e-4)
        assert 1 / 9 <= f["dpt_confidence"] <= 1.0
    assert max(shares) < masking.OOD_FRAME_SHARE / 2
    assert _rule_by_hand(shares)[1] is False
    assert meta["mask_domain"]["out_of_domain"] is False and out["domain"] == meta["mask_domain"]
    assert "in its domain" in line and "OUT OF ITS DOMAIN" not in line
    assert demo.mask_plan("auto", meta["mask_domain"])["mode"] == "dpt"


@needs_builtin
@pytest.mark.parametrize("clutter", ["medium", "high"])
def test_rule_stays_quiet_on_the_synthetic_scenes(tmp_path, capsys, clutter):
    """The synthetic tower scenes the built-in model was made for, at the high clutter level too
    (22-32 % of each training view covered by distractors): in its domain."""
    from jaxnerf_grid.data.synthetic.generate import generate_scene

    generate_scene("tower-small", tmp_path / "s", seed=5, distractors=clutter, progress=False,
                   num_train=6, num_test=1, supersample=1)
    masking.write_masks(tmp_path / "s", progress=False)
    meta = io.read_json(tmp_path / "s/transforms.json")
    shares = [f["masked_share"] for f in meta["frames"]]
    assert _rule_by_hand(shares)[1] is False
    assert meta["mask_domain"]["out_of_domain"] is False
    assert "in its domain" in capsys.readouterr().out
    assert demo.mask_plan("auto", meta["mask_domain"])["mode"] == "dpt"


def test_ground_truth_masks_record_shares_but_no_verdict(tmp_path):
    from jaxnerf_grid.data.synthetic.generate import generate_scene

    generate_scene("tower-small", tmp_path / "s", seed=2, progress=False, width=40, height=30, num_train=3,
                   num_test=1, supersample=1, buildings=4, trees=0.3)
    out = masking.write_masks(tmp_path / "s", source="gt", progress=False)
    meta = io.read_json(tmp_path / "s/transforms.json")
    assert out["domain"] is None and "mask_domain" not in meta
    for f in meta["frames"]:
        ref = (io.read_distractor_mask(tmp_path / "s" / f["distractor_mask_path"])
               if "distractor_mask_path" in f else None)
        if ref is not None:
            assert f["masked_share"] == pytest.approx(float(np.mean(ref)), abs=1e-4)
        assert "dpt_confidence" not in f


@pytest.mark.parametrize("choice, domain, mode, train", [
    ("auto", {"out_of_domain": True, "frames": 4, "frames_mostly_masked": 4, "median_share": 0.7}, "robust",
     {"use_masks": False, "robust": {"mode": "robust"}}),
    ("auto", {"out_of_domain": False, "frames": 4, "frames_mostly_masked": 1, "median_share": 0.1}, "dpt",
     {"use_masks": True}),
    ("auto", None, "dpt", {"use_masks": True}),
    ("dpt", {"out_of_domain": True, "frames": 4, "frames_mostly_masked": 4, "median_share": 0.7}, "dpt",
     {"use_masks": True}),
    ("robust", None, "robust", {"use_masks": False, "robust": {"mode": "robust"}}),
    ("dpt+robust", None, "dpt+robust", {"use_masks": True, "robust": {"mode": "dpt+robust"}}),
    ("none", None, "none", {"use_masks": False}),
])
def test_mask_plan(choice, domain, mode, train):
    plan = demo.mask_plan(choice, domain)
    assert plan["mode"] == mode and plan["overrides"] == {"train": train}
    note = demo._mask_note("dpt", plan)
    assert plan["why"] in note
    assert ("none used" in note) == (mode in ("robust", "none"))
    if choice == "auto" and domain and domain["out_of_domain"]:
        assert "out of its domain" in note and "4 of 4 frames" in note


@pytest.mark.parametrize("domain, mode", [
    ({"out_of_domain": False, "frames": 4, "frames_mostly_masked": 0, "median_share": 0.0}, "dpt"),
    ({"out_of_domain": True, "frames": 4, "frames_mostly_masked": 4, "median_share": 0.7}, "robust"),
    (None, "dpt"),
])
def test_auto_trains_a_real_capture_on_the_dpt_masks_without_the_photometric_evidence(domain, mode):
    """On a capture, auto is the DPT's masks alone where they are in their domain (the evidence
    takes a tower's thin members for outliers), the evidence alone where they are not; the
    report's sentence says why the evidence is left out; a forced choice stays the user's."""
    plan = demo.mask_plan("auto", domain, capture=True)
    assert plan["mode"] == mode
    assert plan["overrides"]["train"]["use_masks"] == (mode == "dpt")
    assert plan["overrides"]["train"].get("robust") == (None if mode == "dpt" else {"mode": "robust"})
    assert ("thin members" in plan["why"]) == (mode == "dpt")
    assert demo.mask_plan("dpt+robust", domain, capture=True)["mode"] == "dpt+robust"
    assert "thin members" not in demo.mask_plan("auto", domain)["why"]


def test_a_dataset_is_a_capture_when_poses_registered_it(tmp_path):
    made = tmp_path / "made"
    made.mkdir()
    (made / "transforms.json").write_text(json.dumps({"frames": [], "poses": {"photos": 3, "registered": 3}}))
    generated = tmp_path / "generated"
    generated.mkdir()
    (generated / "transforms.json").write_text(json.dumps({"frames": []}))
    assert demo.is_capture(made)
    assert not demo.is_capture(generated)
    assert not demo.is_capture(tmp_path / "missing")


def test_a_capture_trains_appearance_and_the_depth_prior_when_its_sparse_model_is_there(tmp_path):
    from jaxnerf_grid.data.formats import colmap_model

    made = tmp_path / "made"
    (made / "sparse" / "0").mkdir(parents=True)
    appearance = {"use_appearance": True}
    assert demo.capture_defaults(True, made) == {"model": appearance, "train": {"appearance_steps": 0}}  # no depth yet
    colmap_model.write_model(made / "sparse" / "0", {}, {}, {})
    assert demo.capture_defaults(True, made) == {
        "model": appearance, "train": {"appearance_steps": 0, "depth": {"weight": demo.DEPTH_WEIGHT}}}
    assert demo.capture_defaults(False, made) == {}  # a generated scene keeps the recipe


def cameras_on_an_arc(degrees: float, count: int = 12) -> list[dict]:
    """Frames whose cameras stand on a circle of radius 10, 5 up, over `degrees` of azimuth, each
    looking at the origin (OpenGL c2w, z up)."""
    frames = []
    for a in np.radians(np.linspace(0.0, degrees, count, endpoint=degrees < 360)):
        centre = np.array([10 * np.cos(a), 10 * np.sin(a), 5.0])
        back = centre / np.linalg.norm(centre)  # the camera looks down -z: z points away from the target
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        c2w[:3, 3] = centre
        frames.append({"file_path": f"images/{len(frames):03d}.png", "transform_matrix": c2w.tolist()})
    return frames


@pytest.mark.parametrize("degrees, late", [(360, True), (250, True), (230, False), (100, False)])
def test_the_depth_prior_starts_late_only_where_the_cameras_surround_the_scene(tmp_path, degrees, late):
    from jaxnerf_grid.data.formats import colmap_model

    (tmp_path / "sparse" / "0").mkdir(parents=True)
    colmap_model.write_model(tmp_path / "sparse" / "0", {}, {}, {})
    # 12 cameras over `degrees`: the arc covered is degrees (less one step where they close the circle)
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": cameras_on_an_arc(degrees)}))
    depth = demo.capture_defaults(True, tmp_path)["train"]["depth"]
    assert depth == ({"weight": demo.DEPTH_WEIGHT, "start": demo.SURROUNDING_DEPTH_START} if late
                     else {"weight": demo.DEPTH_WEIGHT})


def test_mask_plan_refuses_an_unknown_choice():
    with pytest.raises(ConfigError, match="demo.masks"):
        demo.mask_plan("sometimes", None)


def test_dataset_domain_judges_dpt_masks_made_before_the_rule(tmp_path):
    """A dataset masked by DPT before `mask` recorded mask_domain: the verdict comes from its
    masks/ (2 of 3 frames over 40 % here); ground-truth masks are not judged."""
    frames = []
    for i, share in enumerate([0.5, 0.75, 0.25]):
        m = np.zeros((4, 8), np.float32)
        m.reshape(-1)[: int(share * 32)] = 1.0
        io.write_png(tmp_path / "masks" / f"f{i}.png", m)
        frames.append({"file_path": f"images/f{i}.png", "mask_path": f"masks/f{i}.png"})
    (tmp_path / "transforms.json").write_text(json.dumps({"mask_source": "dpt", "frames": frames}))
    v = demo.dataset_domain(tmp_path)
    assert v["out_of_domain"] is True and v["frames_mostly_masked"] == 2 and v["median_share"] == 0.5
    (tmp_path / "transforms.json").write_text(json.dumps({"mask_source": "ground-truth", "frames": frames}))
    assert demo.dataset_domain(tmp_path) is None


@pytest.mark.parametrize("domain,asked,settled", [
    ({"out_of_domain": True}, None, False),    # judged out of domain: either test re-admits
    ({"out_of_domain": False}, None, True),    # in its domain: strict re-admission
    (None, None, True),                        # not judged (ground-truth or the user's masks): strict
    ({"out_of_domain": False}, False, False),  # what the user set is kept
    ({"out_of_domain": True}, True, True),
])
def test_strict_readmission_follows_the_masks_domain_verdict(tmp_path, domain, asked, settled):
    """train.robust.strict_readmit None is settled on the dataset's transforms.json: the
    `mask_domain` that `mask` wrote reaches the loaded dataset and `config.resolve`, with and
    without the ray bounds (what a run's config.json stores)."""

    from jaxnerf_grid.config import schema as config
    from jaxnerf_grid.config.run_config import make_config
    from jaxnerf_grid.data import formats
    from tests.data.test_formats import _write_transforms

    _, top = _write_transforms(tmp_path)
    if domain is not None:
        top["mask_source"], top["mask_domain"] = "dpt", dict(domain, frames=3)
        io.write_json(tmp_path / "transforms.json", top)
    ds = formats.load_dataset(tmp_path)
    cfg = make_config("ours", {"train": {"robust": "dpt+robust", "robust_strict_readmit": asked}})
    assert cfg.train.robust.strict_readmit is asked
    for bounds in (True, False):
        assert config.resolve(cfg, ds, bounds=bounds).train.robust.strict_readmit is settled


def test_the_report_says_how_flagged_pixels_were_readmitted():
    """evaluate.strict_note: the report's sentence for dpt+robust with strict re-admission on /
    off, nothing for other modes or a run whose config predates the key."""
    from types import SimpleNamespace

    from jaxnerf_grid.eval import evaluate

    def note(robust, strict):
        return evaluate.strict_note(SimpleNamespace(robust=SimpleNamespace(mode=robust, strict_readmit=strict)))

    assert "only when its residual was an inlier and a neighbouring photo confirmed it" in note("dpt+robust", True)
    assert "when its residual was an inlier or a neighbouring photo confirmed it" in note("dpt+robust", False)
    assert note("robust", True) == note("off", False) == note("dpt+robust", None) == ""
