"""The blocks of masking.py that decide what `mask` writes and says, against answers worked out
by hand: the out-of-domain rule at its exact boundaries (`domain_verdict`, `domain_line`), the
settings' ranges (`check_settings`, `check_classes`), `parse_classes`, and the `masked_share`
written per frame (the share of M after dilation, rounded to 4 places)."""

import os
import re

import numpy as np
import pytest

from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.masks import write as masking
from jaxnerf_grid.util import io

RULE = "out of domain when more than 50% of the frames have more than 40% of their pixels masked"


# --------------------------------------------------------------------------- domain_verdict


@pytest.mark.parametrize("shares, confidences, expect", [
    # 0.4 exactly is not "more than 40 %"; 2 of 4 frames is not "more than half"
    ([0.4, 0.41, 0.9, 0.0], [0.9, 0.8, 0.7, 0.61237],
     dict(out_of_domain=False, frames=4, frames_mostly_masked=2, median_share=0.405, mean_share=0.4275,
          mean_confidence=0.7531)),
    # 3 of 5 is
    ([0.4, 0.41, 0.9, 0.0, 0.5], None,
     dict(out_of_domain=True, frames=5, frames_mostly_masked=3, median_share=0.41, mean_share=0.442,
          mean_confidence=None)),
    # 2 of 3 is (more than 1.5); the median and mean rounded to 4 places
    ([0.123456, 0.654321, 0.9], [], dict(out_of_domain=True, frames=3, frames_mostly_masked=2, median_share=0.6543,
                                         mean_share=0.5593, mean_confidence=None)),
    # 1 of 3 is not; one frame: out exactly when it is mostly masked
    ([0.41, 0.0, 0.0], [1.0, 1.0, 1.0], dict(out_of_domain=False, frames=3, frames_mostly_masked=1, median_share=0.0,
                                             mean_share=0.1367, mean_confidence=1.0)),
    ([0.41], None, dict(out_of_domain=True, frames=1, frames_mostly_masked=1, median_share=0.41, mean_share=0.41,
                        mean_confidence=None)),
    ([0.4], None, dict(out_of_domain=False, frames=1, frames_mostly_masked=0, median_share=0.4, mean_share=0.4,
                       mean_confidence=None)),
])
def test_domain_verdict_at_its_boundaries_by_hand(shares, confidences, expect):
    assert masking.domain_verdict(shares, confidences) == {**expect, "rule": RULE}


def test_domain_verdict_of_no_frames_is_refused():
    with pytest.raises(ValueError, match="^domain_verdict: no frames$"):
        masking.domain_verdict([])


def test_domain_line_in_words():
    inside = {"out_of_domain": False, "frames": 4, "frames_mostly_masked": 1, "median_share": 0.25}
    assert masking.domain_line(inside) == ("jaxnerf-grid mask: the DPT looks in its domain: 1 of 4 frames have more "
                                           "than 40% of their pixels masked (median 25%)")
    out = {"out_of_domain": True, "frames": 5, "frames_mostly_masked": 3, "median_share": 0.5}
    assert masking.domain_line(out) == (
        "jaxnerf-grid mask: the DPT looks OUT OF ITS DOMAIN on these photos: 3 of 5 frames have more than 40% of "
        "their pixels masked (median 50%); do not trust these masks (`demo` trains with train.robust = robust "
        "instead; docs/MASKS.md)")


# --------------------------------------------------------------------------- settings


@pytest.mark.parametrize("settings", [
    (0.0, 0.0, 0, None, None), (1.0, 1.0, 0, 1, [0]), (0.5, 0.2, 3, 384, []), (0.5, 0.2, 3, 384, [0, 149]),
])
def test_check_settings_accepts_the_ends_of_each_range(settings):
    masking.check_settings(*settings)


@pytest.mark.parametrize("settings, key", [
    ((-0.01, 0.0, 0, None, None), "mask.threshold"), ((1.01, 0.0, 0, None, None), "mask.threshold"),
    (("0.5", 0.0, 0, None, None), "mask.threshold"),
    ((0.5, -0.01, 0, None, None), "mask.floor"), ((0.5, 1.01, 0, None, None), "mask.floor"),
    ((0.5, "0.5", 0, None, None), "mask.floor"),
    ((0.5, 0.0, -1, None, None), "mask.dilate"), ((0.5, 0.0, 1.5, None, None), "mask.dilate"),
    ((0.5, 0.0, 0, 0, None), "mask.max_side"), ((0.5, 0.0, 0, 2.5, None), "mask.max_side"),
    ((0.5, 0.0, 0, None, [0, -1]), "mask.classes"), ((0.5, 0.0, 0, None, [1.5]), "mask.classes"),
])
def test_check_settings_names_the_key_out_of_range(settings, key):
    with pytest.raises(ConfigError, match="^" + re.escape(key + " = ")):
        masking.check_settings(*settings)


@pytest.mark.parametrize("text, expect", [
    (None, None), ("", None), ("12,20,127", [12, 20, 127]), (" 12 , ,20 ", [12, 20]), ("7", [7]), (",", []),
    ("0", [0]),
])
def test_parse_classes(text, expect):
    assert masking.parse_classes(text) == expect


@pytest.mark.parametrize("text, bad", [("12,x", "'x'"), ("1.5", "'1.5'"), (" 3, -", "'-'")])
def test_parse_classes_names_the_bad_entry(text, bad):
    with pytest.raises(ConfigError, match=re.escape(f"mask.classes: {bad} is not a class id (comma-separated "
                                                    "integers, e.g. 12,20)")):
        masking.parse_classes(text)


def test_check_classes_against_the_models_labels():
    masking.check_classes([0, 2], 3, "w")
    with pytest.raises(ConfigError, match=re.escape("mask.classes [3]: outside the 3 labels of w (0..2)")):
        masking.check_classes([3], 3, "w")
    with pytest.raises(ConfigError, match=re.escape("mask.classes [-1, 5]: outside the 3 labels of w (0..2)")):
        masking.check_classes([-1, 1, 5], 3, "w")
    with pytest.raises(ConfigError, match="^mask.classes: no class id given$"):
        masking.check_classes([], 3, "w")


# --------------------------------------------------------------------------- masked_share


def _gt_dataset(root, h: int, w: int, rects) -> None:
    """Frame i: a random photo h x w, its distractor mask the rectangle rects[i] (rows, cols; None
    for none) with bit 0 set, a depth map of ones."""
    import cv2

    rng = np.random.default_rng(0)
    (root / "distractor").mkdir(parents=True)
    frames = []
    for i, rect in enumerate(rects):
        io.write_png(root / f"images/f{i}.png", rng.uniform(size=(h, w, 3)))
        m = np.zeros((h, w), np.uint8)
        if rect is not None:
            m[rect] = 1
        cv2.imwrite(str(root / f"distractor/f{i}.png"), m)
        io.write_exr(root / f"depth/f{i}.exr", np.ones((h, w), np.float32))
        frames.append({"file_path": f"images/f{i}.png", "distractor_mask_path": f"distractor/f{i}.png",
                       "depth_file_path": f"depth/f{i}.exr"})
    io.write_json(root / "transforms.json", {"frames": frames})


@pytest.mark.parametrize("dilate", [0, 1])
def test_masked_share_is_the_written_masks_share_after_dilation_to_4_places(tmp_path, dilate):
    """17 x 21 = 357 pixels; frame 0 a 2 x 3 rectangle (6 pixels: 6 / 357 = 0.0168), dilated by
    one pixel with OpenCV's 3 x 3 ellipse (a cross) a 4 x 5 rectangle without its 4 corners (16:
    16 / 357 = 0.0448); frame 1 no distractor (0.0)."""
    rect = (slice(4, 6), slice(5, 8))
    _gt_dataset(tmp_path, 17, 21, [rect, None])
    masking.write_masks(tmp_path, source="gt", dilate=dilate, progress=False)
    meta = io.read_json(tmp_path / "transforms.json")
    expect = np.zeros((17, 21), np.float32)
    expect[rect] = 1
    if dilate:
        expect[3:7, 4:9] = 1
        expect[[3, 3, 6, 6], [4, 8, 4, 8]] = 0
    np.testing.assert_array_equal(io.read_mask(tmp_path / meta["frames"][0]["mask_path"]), expect)
    assert [f["masked_share"] for f in meta["frames"]] == [0.0448 if dilate else 0.0168, 0.0]


# --------------------------------------------------------------------------- files and folders


def test_frame_stem_and_image_path(tmp_path):
    assert masking._frame_stem({"file_path": "images/abc.def.png"}, 3) == "abc.def"
    assert masking._frame_stem({}, 7) == "frame_0007"
    assert masking._frame_stem({"file_path": ""}, 12) == "frame_0012"
    (tmp_path / "images").mkdir()
    (tmp_path / "images/b.JPG").write_bytes(b"")
    (tmp_path / "images/c.png").write_bytes(b"")
    (tmp_path / "images/c.jpg").write_bytes(b"")
    for name in ("d.jpg", "e.jpeg", "f.PNG"):
        (tmp_path / "images" / name).write_bytes(b"")
        assert masking._image_path(tmp_path, {"file_path": f"images/{name[0]}"}) == tmp_path / "images" / name
    assert masking._image_path(tmp_path, {"file_path": "images/b"}) == tmp_path / "images/b.JPG"
    assert masking._image_path(tmp_path, {"file_path": "images/c"}) == tmp_path / "images/c.png"   # .png first
    assert masking._image_path(tmp_path, {"file_path": "images/c.jpg"}) == tmp_path / "images/c.jpg"
    assert masking._image_path(tmp_path, {"file_path": "images/none"}) == tmp_path / "images/none"


def test_recover_rolls_a_complete_set_forward_and_discards_an_incomplete_one(tmp_path):
    """Nothing: None. A staging folder without COMPLETE (and a retired folder): both removed,
    "discarded", the old set untouched. A retired folder alone: removed, "discarded". A complete
    staging folder: its masks/ and transforms.json replace the old, the old weights/ (not in the
    new set) goes, "rolled forward"."""
    root = tmp_path
    (root / "masks").mkdir()
    (root / "masks/old.png").write_text("old")
    (root / "weights").mkdir()
    (root / "transforms.json").write_text("old")
    assert masking.recover(root) is None
    stage, retired = root / masking.STAGING, root / masking.RETIRED
    (stage / "masks").mkdir(parents=True)
    retired.mkdir()
    assert masking.recover(root) == "discarded"
    assert not stage.exists() and not retired.exists() and (root / "masks/old.png").is_file()
    retired.mkdir()
    assert masking.recover(root) == "discarded" and not retired.exists()
    (stage / "masks").mkdir(parents=True)                      # no retired folder this time
    assert masking.recover(root) == "discarded" and not stage.exists()
    (stage / "masks").mkdir(parents=True)
    (stage / "masks/new.png").write_text("new")
    (stage / "transforms.json").write_text("new")
    (stage / masking.COMPLETE).write_text("masks\n")
    assert masking.recover(root) == "rolled forward"
    assert sorted(p.name for p in (root / "masks").iterdir()) == ["new.png"]
    assert (root / "transforms.json").read_text() == "new" and not (root / "weights").exists()
    assert not stage.exists() and not retired.exists()


def test_a_staging_folder_of_another_live_process_is_left_alone_and_a_second_mask_refused(tmp_path):
    """Two `mask` (or `demo`) runs on one dataset: the staging folder of a process still running
    (its OWNER a live pid of this host, here a `sleep`) is neither discarded by `recover` (which
    every dataset load calls) nor written into by a second `write_masks`, which is refused in
    one line naming the dataset and the pid; the old set stays. Once that process is gone, the
    same folder is discarded and masking runs. A staging folder owned by this very process (the
    error path of its own `write_masks`) is discarded as before."""
    import socket
    import subprocess
    import sys

    from jaxnerf_grid.util.io import DataError

    _gt_dataset(tmp_path, 9, 11, [(slice(2, 4), slice(3, 6))])
    masking.write_masks(tmp_path, source="gt", progress=False)    # a set already there: the refusal
    before = (tmp_path / "transforms.json").read_bytes()           # still names the other process
    stage = tmp_path / masking.STAGING
    (stage / "masks").mkdir(parents=True)
    (stage / "masks/half_done.png").write_text("theirs")
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (stage / "OWNER").write_text(f"{socket.gethostname()} {other.pid}\n")
        assert masking.recover(tmp_path) is None
        with pytest.raises(DataError) as err:
            masking.write_masks(tmp_path, source="gt", progress=False)
        message = str(err.value)
        assert "\n" not in message and str(tmp_path) in message and f"pid {other.pid}" in message
        assert (stage / "masks/half_done.png").read_text() == "theirs"
        assert (tmp_path / "transforms.json").read_bytes() == before
        assert io.read_mask(tmp_path / "masks/f0.png").sum() == 6
    finally:
        other.kill()
        other.wait()
    masking.write_masks(tmp_path, source="gt", overwrite=True, progress=False)  # owner gone: discarded
    assert not stage.exists() and io.read_mask(tmp_path / "masks/f0.png").sum() == 6
    (stage / "masks").mkdir(parents=True)
    (stage / "OWNER").write_text(f"{socket.gethostname()} {os.getpid()}\n")
    assert masking.recover(tmp_path) == "discarded" and not stage.exists()


def test_check_outputs_refuses_existing_masks_unless_overwrite(tmp_path):
    from jaxnerf_grid.util.io import DataError

    (tmp_path / "masks").mkdir()
    masking._check_outputs(tmp_path, {"frames": [{"file_path": "a.png"}]}, False)       # an empty folder
    masking._check_outputs(tmp_path, {}, False)                                          # no frames listed
    with pytest.raises(DataError, match=re.escape(f"{tmp_path / 'transforms.json'}: frames already have mask_path; "
                                                  "pass overwrite=True")):
        masking._check_outputs(tmp_path, {"frames": [{"file_path": "a.png"}, {"mask_path": "m.png"}]}, False)
    (tmp_path / "weights").mkdir()
    (tmp_path / "weights/a.exr").write_text("")
    with pytest.raises(DataError, match=re.escape(f"{tmp_path / 'weights'}: mask outputs already exist; pass "
                                                  "overwrite=True to replace them")):
        masking._check_outputs(tmp_path, {"frames": []}, False)
    masking._check_outputs(tmp_path, {"frames": [{"mask_path": "m.png"}]}, True)


def test_default_classes_from_the_folder_or_the_ade20k_labels(tmp_path):
    from types import SimpleNamespace

    from jaxnerf_grid.masks import foreground as fg
    from jaxnerf_grid.util.io import DataError

    def model(n):
        return SimpleNamespace(config=SimpleNamespace(num_labels=n))

    io.write_json(tmp_path / "a/config.json", {"extra": {"dynamic_classes": ["3", 5]}})
    assert masking.default_classes(model(150), str(tmp_path / "a")) == [3, 5]
    io.write_json(tmp_path / "b/config.json", {"extra": {}})
    assert masking.default_classes(model(150), str(tmp_path / "b")) == sorted(fg.ADE20K_DYNAMIC)
    io.write_json(tmp_path / "d/config.json", {"format": "no extra"})
    assert masking.default_classes(model(150), str(tmp_path / "d")) == sorted(fg.ADE20K_DYNAMIC)
    io.write_json(tmp_path / "c/config.json", ["not", "a", "dict"])
    assert masking.default_classes(model(150), str(tmp_path / "c")) == sorted(fg.ADE20K_DYNAMIC)
    with pytest.raises(DataError, match=re.escape(f"{tmp_path / 'b'}: 151-label model with no known dynamic "
                                                  "classes; give mask.classes ID,ID,...")):
        masking.default_classes(model(151), str(tmp_path / "b"))


def test_load_models_pairs_the_heads(tmp_path, monkeypatch):
    """A model with both heads is its own depth model; a segmentation-only one has none unless
    depth weights are given; a folder without the head asked of it is refused by name."""
    from jaxnerf_grid.masks import dpt
    from jaxnerf_grid.util.io import DataError

    def saved(name, heads):
        cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                            image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                            neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=3, heads=heads)
        dpt.save(dpt.init(0, cfg), tmp_path / name)
        return str(tmp_path / name)

    both, seg = saved("both", ("segmentation", "depth")), saved("seg", ("segmentation",))
    depth = saved("depth", ("depth",))
    s, d, w = masking.load_models(both, None)
    assert d is s and w == both and s.config.heads == ("segmentation", "depth")
    s, d, w = masking.load_models(seg, None)
    assert d is None and s.config.heads == ("segmentation",) and w == seg
    s, d, w = masking.load_models(seg, depth)
    assert d.config.heads == ("depth",) and s.config.heads == ("segmentation",)
    with pytest.raises(DataError, match=re.escape(f"{depth}: this DPT has no segmentation head (heads: ('depth',)); "
                                                  "mask.weights must be a segmentation model (e.g. "
                                                  "Intel/dpt-large-ade)")):
        masking.load_models(depth, None)
    with pytest.raises(DataError, match=re.escape(f"{seg}: this DPT has no depth head")):
        masking.load_models(both, seg)
    monkeypatch.setattr(masking, "BUILTIN", tmp_path / "none")
    with pytest.raises(DataError, match=re.escape(f"{tmp_path / 'none'}: no built-in DPT model is shipped in this "
                                                  "build; give mask.weights (a folder: a copy of "
                                                  "Intel/dpt-large-ade) or use mask.source gt on synthetic data")):
        masking.load_models(None, None)
    monkeypatch.setattr(masking, "BUILTIN", tmp_path / "seg")
    s, d, w = masking.load_models(None, None)
    assert w == seg and d is None


def test_model_max_side_reads_the_folders_extra_else_384(tmp_path):
    io.write_json(tmp_path / "a/config.json", {"extra": {"max_side": "256"}})
    assert masking.model_max_side(tmp_path / "a") == 256
    io.write_json(tmp_path / "b/config.json", {"extra": {"steps": 3}})
    assert masking.model_max_side(str(tmp_path / "b")) == 384
    io.write_json(tmp_path / "c/config.json", {})
    assert masking.model_max_side(tmp_path / "c") == 384


def test_recover_never_raises_over_a_leftover_it_cannot_remove(tmp_path):
    """A file where the staging or the retired folder would be (rmtree cannot remove it):
    recover still answers "discarded" (it runs before every dataset is read), the file stays."""
    (tmp_path / masking.STAGING).write_text("")
    assert masking.recover(tmp_path) == "discarded"
    (tmp_path / masking.STAGING).unlink()
    (tmp_path / masking.RETIRED).write_text("")
    assert masking.recover(tmp_path) == "discarded"
    (tmp_path / masking.STAGING).mkdir()
    assert masking.recover(tmp_path) == "discarded" and not (tmp_path / masking.STAGING).exists()


def test_ground_truth_source_names_the_frame_and_the_missing_key(tmp_path):
    from jaxnerf_grid.util.io import DataError

    _gt_dataset(tmp_path, 4, 5, [None, None])
    meta = io.read_json(tmp_path / "transforms.json")
    del meta["frames"][1]["depth_file_path"]
    io.write_json(tmp_path / "transforms.json", meta)
    with pytest.raises(DataError, match=re.escape(f"{tmp_path / 'transforms.json'}: frame 'images/f1.png' has no "
                                                  "'depth_file_path'; mask.source gt needs the synthetic ground "
                                                  "truth")):
        masking.write_masks(tmp_path, source="gt", progress=False)


# --------------------------------------------------------------------------- write_masks


def test_ground_truth_masks_with_the_defaults_and_a_threshold_for_dpt_only(tmp_path):
    """Depth 1 everywhere: Eq. 7's (Dmax - D) / Dmax is 0, so with the default floor 0 M_w = 0 and
    the weights are 1 everywhere; the threshold is DPT's (C > T), a ground-truth mask is taken
    as it is even at T = 1; the params recorded; a second run without overwrite refused."""
    from jaxnerf_grid.util.io import DataError

    rect = (slice(4, 6), slice(5, 8))
    _gt_dataset(tmp_path, 17, 21, [rect])
    masking.write_masks(tmp_path, source="gt", threshold=1.0, progress=False)
    meta = io.read_json(tmp_path / "transforms.json")
    f = meta["frames"][0]
    assert f["masked_share"] == 0.0168 and io.read_mask(tmp_path / f["mask_path"]).sum() == 6
    np.testing.assert_array_equal(io.read_exr(tmp_path / f["weight_path"]), np.ones((17, 21), np.float32))
    assert meta["mask_params"] == {"threshold": 1.0, "floor": 0.0, "dilate": 0}
    with pytest.raises(DataError, match="pass overwrite=True"):
        masking.write_masks(tmp_path, source="gt", progress=False)


@pytest.mark.parametrize("kwargs, message", [
    ({"batch_size": 0}, "mask.batch_size must be an integer >= 1, got 0"),
    ({"max_side": 0}, "mask.max_side = 0: must be an integer >= 1"),
    ({"classes": [-1]}, "mask.classes = -1: must be an integer >= 0"),
    ({"source": "x"}, "mask.source = 'x': must be dpt or gt"),
])
def test_write_masks_refuses_a_bad_setting_before_reading_the_data(tmp_path, kwargs, message):
    with pytest.raises(ConfigError, match="^" + re.escape(message) + "$"):
        masking.write_masks(tmp_path / "no such folder", **{"source": "gt", **kwargs})


def test_write_masks_names_what_is_wrong_with_the_data(tmp_path, monkeypatch):
    from jaxnerf_grid.util.io import DataError

    missing = tmp_path / "missing"
    with pytest.raises(DataError, match="^" + re.escape(f"{missing}: mask.data is not a folder") + "$"):
        masking.write_masks(missing, source="gt")
    for meta in ([], {"frames": []}):
        io.write_json(tmp_path / "transforms.json", meta)
        with pytest.raises(DataError, match="^" + re.escape(f"{tmp_path / 'transforms.json'}: no frames") + "$"):
            masking.write_masks(tmp_path, source="gt")
    io.write_json(tmp_path / "transforms.json", {"frames": [{"file_path": "images/gone.png"}]})
    with pytest.raises(DataError, match="^" + re.escape(f"{tmp_path / 'images/gone.png'}: image file not found "
                                                        f"(listed in {tmp_path / 'transforms.json'})") + "$"):
        masking.write_masks(tmp_path, source="gt")
    monkeypatch.setattr(masking.folders.os, "access", lambda *a, **k: False)   # a read-only dataset folder
    with pytest.raises(DataError, match=re.escape(f"{tmp_path}: mask.data is not writable by this user")):
        masking.write_masks(tmp_path, source="gt")


def test_a_ground_truth_mask_of_another_size_is_named(tmp_path):
    from jaxnerf_grid.util.io import DataError

    _gt_dataset(tmp_path, 4, 5, [None])
    io.write_png(tmp_path / "images/f0.png", np.zeros((6, 5, 3), np.float32))
    with pytest.raises(DataError, match="^" + re.escape(f"{tmp_path / 'images/f0.png'}: mask is (4, 5), image is "
                                                        "(6, 5)") + "$"):
        masking.write_masks(tmp_path, source="gt", progress=False)


def test_dpt_masks_record_the_verdict_the_confidence_and_no_depth_without_a_depth_head(tmp_path):
    """A tiny DPT whose classifier favours class 2 by 50 everywhere (C ~ 1 with classes [2]):
    every pixel masked, so each frame's share is 1.0, both frames are mostly masked and the
    verdict is out of domain; each frame's confidence (one frame's mean largest probability,
    rounded to 4 places) is recorded and their mean is the verdict's. A segmentation-only model:
    no depth written, no dpt_depth_path, the weights 1 - M (M_w = M) = 0."""
    from jaxnerf_grid.masks import dpt

    _gt_dataset(tmp_path / "data", 32, 48, [None, None])
    for heads in (("segmentation", "depth"), ("segmentation",)):
        cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                            image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                            neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=3, heads=heads)
        model = dpt.init(0, cfg)
        model.params["segmentation"]["cls"]["b"] = np.array([0.0, 0.0, 50.0], np.float32)
        dpt.save(model, tmp_path / "w", extra={"dynamic_classes": [2]})
        out = masking.write_masks(tmp_path / "data", weights=str(tmp_path / "w"), max_side=64, overwrite=True,
                                  progress=False)
        meta = io.read_json(tmp_path / "data/transforms.json")
        frames = meta["frames"]
        assert [f["masked_share"] for f in frames] == [1.0, 1.0]
        conf = [f["dpt_confidence"] for f in frames]
        assert all(0.99 <= c <= 1.0 for c in conf)
        assert meta["mask_domain"] == out["domain"] == {
            "out_of_domain": True, "frames": 2, "frames_mostly_masked": 2, "median_share": 1.0, "mean_share": 1.0,
            "mean_confidence": round(float(np.mean(conf)), 4), "rule": RULE}
        has_depth = "depth" in heads
        assert (tmp_path / "data/dpt_depth").is_dir() == has_depth
        assert all(("dpt_depth_path" in f) == has_depth for f in frames)
        if not has_depth:
            np.testing.assert_array_equal(io.read_exr(tmp_path / "data" / frames[0]["weight_path"]),
                                          np.zeros((32, 48), np.float32))


# --------------------------------------------------------------------------- masking again

E = float(np.e)


def _flat_dpt(folder, heads, seed=0):
    """A tiny DPT saved (float32) into `folder` whose classifier is its bias alone: weights 0, bias
    [0, 0, 1], so every pixel's logits are [0, 0, 1] and its softmax [1, 1, e] / (e + 2): C of
    class 2 is e / (e + 2) = 0.576117 everywhere (> 0.5: every pixel masked), and so is the largest
    class probability, the frame's confidence. With a depth head, its last bias raised by 0.1 so
    the relative inverse depth is positive and varies (tests/joins/test_join_foreground.py's model)."""
    from jaxnerf_grid.masks import dpt

    cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                        image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                        neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=3, heads=heads)
    model = dpt.init(seed, cfg)
    if "segmentation" in heads:
        cls = model.params["segmentation"]["cls"]
        cls["w"] = np.zeros_like(np.asarray(cls["w"]))
        cls["b"] = np.array([0.0, 0.0, 1.0], np.float32)
    if "depth" in heads:
        model.params["depth"]["conv3"]["b"] = np.asarray(model.params["depth"]["conv3"]["b"]) + 0.1
    dpt.save(model, folder, dtype="float32", extra={"dynamic_classes": [2]})
    return str(folder)


def test_masking_from_the_dpt_then_from_the_ground_truth_keeps_no_dpt_record(tmp_path, capsys):
    """A fresh dataset masked by a segmentation-only DPT (no depth head: no dpt_depth_path to pop),
    then again from the ground truth with overwrite: the second transforms.json must hold nothing
    of the DPT run (a user reading `dpt_confidence` or `mask_domain` would judge ground-truth
    masks by a model that no longer made them): no `dpt_confidence` per frame, no `mask_domain`,
    the params of the ground truth alone, no verdict returned or printed; each frame's
    `dpt_depth_path` is now the ground-truth depth. Confidences by hand: round(e / (e + 2), 4) =
    0.5761 (5 places would be 0.57612)."""
    data = tmp_path / "data"
    rect = (slice(4, 6), slice(5, 8))
    _gt_dataset(data, 32, 48, [rect, None])
    weights = _flat_dpt(tmp_path / "seg", ("segmentation",))
    conf = round(E / (E + 2), 4)
    assert conf == 0.5761 and round(E / (E + 2), 5) == 0.57612
    out = masking.write_masks(data, weights=weights, max_side=64, progress=False)
    meta = io.read_json(data / "transforms.json")
    verdict = {"out_of_domain": True, "frames": 2, "frames_mostly_masked": 2, "median_share": 1.0,
               "mean_share": 1.0, "mean_confidence": conf, "rule": RULE}
    params = {"threshold": 0.5, "floor": 0.0, "dilate": 0, "weights": weights, "depth_weights": None,
              "classes": [2], "max_side": 64, "depth": None}
    assert out == {"root": data, "source": "dpt", "frames": 2, "params": params, "domain": verdict}
    assert meta["mask_source"] == "dpt" and meta["mask_params"] == params and meta["mask_domain"] == verdict
    assert [f["dpt_confidence"] for f in meta["frames"]] == [conf, conf]
    assert [f["masked_share"] for f in meta["frames"]] == [1.0, 1.0]
    assert not any("dpt_depth_path" in f for f in meta["frames"]) and not (data / "dpt_depth").exists()
    assert capsys.readouterr().out == ("jaxnerf-grid mask: no depth head available; using M_w = M (pass "
                                       "--depth-weights for Eq. 7)\n" + masking.domain_line(verdict) + "\n")

    out = masking.write_masks(data, source="gt", overwrite=True, progress=False)
    meta = io.read_json(data / "transforms.json")
    params = {"threshold": 0.5, "floor": 0.0, "dilate": 0}
    assert out == {"root": data, "source": "ground-truth", "frames": 2, "params": params, "domain": None}
    assert meta["mask_source"] == "ground-truth" and meta["mask_params"] == params
    assert "mask_domain" not in meta
    assert not any("dpt_confidence" in f for f in meta["frames"])
    assert [f["masked_share"] for f in meta["frames"]] == [0.0039, 0.0]          # 6 / (32 * 48)
    assert [f["dpt_depth_path"] for f in meta["frames"]] == ["dpt_depth/f0.exr", "dpt_depth/f1.exr"]
    np.testing.assert_array_equal(io.read_exr(data / "dpt_depth/f0.exr"), np.ones((32, 48), np.float32))
    assert capsys.readouterr().out == ""                                            # no verdict to print


def test_separate_depth_weights_give_the_depth_of_the_depth_model(tmp_path):
    """A segmentation-only DPT for the masks and a depth-only DPT passed as `depth_weights`: the
    depth written is Eq. 7's D = 1 / max(r, 1e-3 max r) from the depth model's own inverse depth r
    on the photo as written (32 x 64 = the working size at max_side 64: no resizing), computed
    here in NumPy from `dpt.apply`; the params name both folders."""
    from jaxnerf_grid.masks import dpt

    data = tmp_path / "data"
    _gt_dataset(data, 32, 64, [None])
    weights = _flat_dpt(tmp_path / "seg", ("segmentation",))
    depth_weights = _flat_dpt(tmp_path / "depth", ("depth",), seed=1)
    out = masking.write_masks(data, weights=weights, depth_weights=depth_weights, max_side=64, progress=False)
    meta = io.read_json(data / "transforms.json")
    assert out["params"] == meta["mask_params"] == {
        "threshold": 0.5, "floor": 0.0, "dilate": 0, "weights": weights, "depth_weights": depth_weights,
        "classes": [2], "max_side": 64, "depth": "relative (1 / DPT inverse depth)"}
    photo = io.read_image(data / "images/f0.png")
    r = np.maximum(np.asarray(dpt.apply(dpt.load_pretrained(depth_weights), dpt.normalize(photo[None]))["depth"][0],
                              np.float64), 0.0)
    assert r.shape == (32, 64) and np.std(r) > 1e-3
    expect = 1.0 / np.maximum(r, 1e-3 * r.max())
    frame = meta["frames"][0]
    assert frame["dpt_depth_path"] == "dpt_depth/f0.exr" and frame["dpt_confidence"] == round(E / (E + 2), 4)
    np.testing.assert_allclose(io.read_exr(data / "dpt_depth/f0.exr"), expect, rtol=1e-4)
    # every pixel masked (C = 0.5761 > 0.5), floor 0: the weights are 1 - (Dmax - D) / Dmax = D / Dmax
    np.testing.assert_allclose(io.read_exr(data / frame["weight_path"]), expect / expect.max(), atol=1e-5)


def test_tiled_masks_record_the_tiling_and_use_its_overlap(tmp_path, monkeypatch):
    """tiles = 2 with tile_overlap = 0.5 (not the default 0.25) on a 32 x 96 photo at max_side 32:
    the params record both; the mask is M = [C > T] for C of `foreground.predict_maps` with these
    settings (predict_maps is held to a per-window reference of its own in test_foreground), T the
    median of that C; `mask.batch_size` handed on (a user short of accelerator memory sets it).
    The windows by hand: side 32, overlap 16 px, the photo resized to 32 x 48,
    windows at x = 0 and 16; with 0.25: 32 x 56, windows at 0 and 24, so C differs."""
    from jaxnerf_grid.masks import dpt
    from jaxnerf_grid.masks import foreground as fg

    data = tmp_path / "data"
    _gt_dataset(data, 32, 96, [None])
    cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                        image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                        neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=3, heads=("segmentation",))
    dpt.save(dpt.init(0, cfg), tmp_path / "w", dtype="float32", extra={"dynamic_classes": [1, 2]})
    model = dpt.load_pretrained(str(tmp_path / "w"))
    photo = io.read_image(data / "images/f0.png")
    assert fg.tile_layout(32, 96, 32, 32, 2, 0.5) == ((32, 48), (32, 32), [0], [0, 16], 16)
    assert fg.tile_layout(32, 96, 32, 32, 2, 0.25) == ((32, 56), (32, 32), [0], [0, 24], 8)
    (c, _, conf), = fg.predict_maps(model, None, [photo], [1, 2], max_side=32, tiles=2, tile_overlap=0.5,
                                    with_confidence=True)
    (c_default, _), = fg.predict_maps(model, None, [photo], [1, 2], max_side=32, tiles=2)
    threshold = float(np.median(c))
    sure = np.abs(c - threshold) > 1e-4
    assert sure.mean() > 0.9 and np.mean((c > threshold) != (c_default > threshold)) > 0.02
    passed = []
    real = fg.predict_maps

    def spy(*args, **kwargs):
        passed.append(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(masking.fg, "predict_maps", spy)
    out = masking.write_masks(data, weights=str(tmp_path / "w"), threshold=threshold, max_side=32, tiles=2,
                              tile_overlap=0.5, batch_size=2, progress=False)
    assert passed == [{"max_side": 32, "batch_size": 2, "tiles": 2, "tile_overlap": 0.5, "with_confidence": True}]
    meta = io.read_json(data / "transforms.json")
    assert out["params"] == meta["mask_params"] == {
        "threshold": threshold, "floor": 0.0, "dilate": 0, "weights": str(tmp_path / "w"), "depth_weights": None,
        "classes": [1, 2], "max_side": 32, "depth": None, "tiles": 2, "tile_overlap": 0.5}
    got = io.read_mask(data / meta["frames"][0]["mask_path"])
    np.testing.assert_array_equal(got[sure], (c > threshold)[sure])
    assert meta["frames"][0]["dpt_confidence"] == round(conf, 4)


def test_dpt_classes_refused_by_the_model_folder_and_by_its_labels(tmp_path):
    """A 3-label DPT saved without `dynamic_classes` and no classes given: refused, naming the
    folder (no known dynamic classes for 3 labels); a class id past its labels: refused, naming
    the folder and its range. Nothing is written either way."""
    from jaxnerf_grid.masks import dpt
    from jaxnerf_grid.util.io import DataError

    data = tmp_path / "data"
    _gt_dataset(data, 32, 32, [None])
    cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                        image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                        neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=3, heads=("segmentation",))
    weights = tmp_path / "w"
    dpt.save(dpt.init(0, cfg), weights, dtype="float32")
    with pytest.raises(DataError, match="^" + re.escape(f"{weights}: 3-label model with no known dynamic classes; "
                                                        "give mask.classes ID,ID,...") + "$"):
        masking.write_masks(data, weights=str(weights), progress=False)
    with pytest.raises(ConfigError, match="^" + re.escape(f"mask.classes [3]: outside the 3 labels of {weights} "
                                                          "(0..2)") + "$"):
        masking.write_masks(data, weights=str(weights), classes=[1, 3], progress=False)
    assert sorted(p.name for p in data.iterdir()) == ["depth", "distractor", "images", "transforms.json"]
    assert "mask_path" not in io.read_json(data / "transforms.json")["frames"][0]


# --------------------------------------------------------------------------- what is shown


def test_overlays_are_scaled_to_the_preview_size_and_the_progress_is_shown_by_default(tmp_path, monkeypatch,
                                                                                        capsys):
    """With OVERLAY_MAX_SIDE 8: a 24 x 16 photo's overlay panels are 8 x 5 (scale 8 / 24, 16 / 3 =
    5.33 rounds to 5) and a 100 x 2 photo's 8 x 1 (0.16 rounds to 0: at least one pixel; a 2 x 100
    photo's 1 x 8), all by hand; a 6 x 4 photo is not enlarged (the overlay is two panels side by side). By default
    write_masks shows its progress, stderr's one line "mask: 4/4 frames (100%), 0.0 s" (not a
    terminal here; the bars' clock is stopped in tests, so no throttled line comes before it), and
    ends with its stdout line; quiet, it prints neither."""
    import cv2

    monkeypatch.setattr(masking, "OVERLAY_MAX_SIDE", 8)
    _gt_dataset(tmp_path, 16, 24, [(slice(2, 4), slice(3, 6)), None, None, None])
    meta = io.read_json(tmp_path / "transforms.json")
    for i, (h, w) in ((1, (2, 100)), (2, (4, 6)), (3, (100, 2))):
        io.write_png(tmp_path / f"images/f{i}.png", np.full((h, w, 3), 0.5))
        io.write_exr(tmp_path / f"depth/f{i}.exr", np.ones((h, w), np.float32))
        cv2.imwrite(str(tmp_path / f"distractor/f{i}.png"), np.zeros((h, w), np.uint8))
    io.write_json(tmp_path / "transforms.json", meta)
    capsys.readouterr()
    masking.write_masks(tmp_path, source="gt")
    out = capsys.readouterr()
    assert out.err == "mask: 4/4 frames (100%), 0.0 s\n"    # the bar's clock is stopped (conftest)
    assert out.out.splitlines()[-1] == f"wrote masks for 4 frames (ground-truth) into {tmp_path}"
    frames = io.read_json(tmp_path / "transforms.json")["frames"]
    sizes = [io.read_image(tmp_path / f["overlay_path"]).shape[:2] for f in frames]
    assert sizes == [(5, 2 * 8), (1, 2 * 8), (4, 2 * 6), (8, 2 * 1)]    # two panels side by side
    masking.write_masks(tmp_path, source="gt", overwrite=True, progress=False)
    out = capsys.readouterr()
    assert out.err == "" and "wrote masks" not in out.out
