"""Where DPT joins the masks: `foreground.predict_maps` (untiled) and `masking.write_masks` (the
`mask` command's DPT source), each against a reference written here from the model's raw
outputs (`dpt.apply`) with OpenCV and NumPy, so a wiring bug (a map flipped or rotated, inverse
depth fed to Eq. 7 as depth, the wrong image's map) shows as a value difference.

The equations are those of docs (paper Eq. 6-8; `jaxnerf_grid/masks/foreground.py`'s docstring):
  Eq. 6  C = sum_{k in classes} softmax(logits)_k,  M = [C > T]
  Eq. 7  M_w = M * max(floor, (Dmax - D) / Dmax), D = 1 / max(r, 1e-3 * max(r)) from DPT's
         relative inverse depth r, Dmax the per-image maximum
  weight = 1 - M_w
"""

import cv2
import numpy as np
import pytest

from jaxnerf_grid.masks import dpt
from jaxnerf_grid.util import io

TINY_DPT = dict(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32, image_size=32,
                patch_size=16, backbone_out_indices=(0, 0, 1, 1), neck_hidden_sizes=(8, 8, 8, 8),
                fusion_hidden_size=8, num_labels=3, heads=("segmentation", "depth"))


def _model(seed=0):
    """A tiny random DPT with both heads; the depth head's last bias raised so the relative
    inverse depth is positive and varies over the image (instead of mostly clipped to 0)."""
    model = dpt.init(seed, dpt.DPTConfig(**TINY_DPT))
    model.params["depth"]["conv3"]["b"] = np.asarray(model.params["depth"]["conv3"]["b"]) + 0.1
    return model


def _photo(h, w, seed):
    """A photo with no symmetry: a diagonal ramp, a bright block in one corner, noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([xx / w, yy / h, 0.5 * (xx / w + yy / h)], -1)
    img[: h // 3, : w // 4] = [1.0, 0.9, 0.1]
    return np.clip(img + rng.normal(scale=0.15, size=img.shape), 0, 1).astype(np.float32)


def _softmax(x):
    e = np.exp(x - x.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)


def _reference_maps(model, photo, classes, work_hw):
    """C and r at full resolution, by hand: the photo shrunk to the working size with OpenCV's
    area filter, DPT on it alone (batch of one), Eq. 6 in NumPy, both maps enlarged back with
    OpenCV's bilinear filter, r clipped at 0. (Photos here are larger than the working size on
    both sides.)"""
    h, w = photo.shape[:2]
    small = cv2.resize(photo, (work_hw[1], work_hw[0]), interpolation=cv2.INTER_AREA)
    out = dpt.apply(model, dpt.normalize(small[None]))
    prob = _softmax(np.asarray(out["logits"][0], np.float64))[..., list(classes)].sum(-1).astype(np.float32)
    inv = np.asarray(out["depth"][0], np.float32)
    up = lambda m: cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR)  # noqa: E731
    return up(prob), np.maximum(up(inv), 0.0)


def test_predict_maps_untiled_against_dpt_on_the_resized_photo():
    """Two different photos in one batch: each one's C and inverse depth equal DPT on that photo
    resized to the working size, resized back (a rotated, flipped or swapped map fails)."""
    from jaxnerf_grid.masks import foreground as fg

    model = _model()
    photos = [_photo(150, 230, 1), _photo(150, 230, 2)]
    outs = list(fg.predict_maps(model, model, photos, classes=[1, 2], max_side=64, batch_size=2))
    # working size by hand: longest side 230 -> 64, 150 * 64 / 230 = 41.7 -> the nearest multiple of 32
    work = (32, 64)
    assert len(outs) == 2
    for photo, (c, inv) in zip(photos, outs):
        ref_c, ref_inv = _reference_maps(model, photo, [1, 2], work)
        assert c.shape == inv.shape == (150, 230)
        assert np.std(ref_c) > 1e-3 and np.std(ref_inv) > 1e-3      # the maps do vary over the image
        np.testing.assert_allclose(c, ref_c, atol=2e-5)
        np.testing.assert_allclose(inv, ref_inv, rtol=1e-4, atol=1e-5)
        # a 180-degree rotation (or a flip) of either map is far off
        assert np.abs(c[::-1, ::-1] - ref_c).max() > 50 * 2e-5
        assert np.abs(inv[::-1, ::-1] - ref_inv).max() > 1e-3
    # the batch kept each photo's own map
    assert np.abs(outs[0][0] - outs[1][0]).max() > 1e-3
    # a separate depth model: the depth comes from it, C still from the segmentation model
    other = _model(seed=3)
    (c2, inv2), = fg.predict_maps(model, other, photos[:1], classes=[1, 2], max_side=64, batch_size=1)
    np.testing.assert_allclose(c2, _reference_maps(model, photos[0], [1, 2], work)[0], atol=2e-5)
    np.testing.assert_allclose(inv2, _reference_maps(other, photos[0], [1, 2], work)[1], rtol=1e-4, atol=1e-5)
    # no depth model (an HF segmentation checkpoint without --depth-weights): C alone, depth None
    (c3, inv3), = fg.predict_maps(model, None, photos[1:], classes=[1, 2], max_side=64, batch_size=1)
    assert inv3 is None
    np.testing.assert_allclose(c3, _reference_maps(model, photos[1], [1, 2], work)[0], atol=2e-5)


def _dataset(root, photos):
    frames = []
    for i, photo in enumerate(photos):
        io.write_png(root / f"images/f{i}.png", photo)
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": np.eye(4).tolist(), "split": "train"})
    io.write_json(root / "transforms.json", {"fl_x": 40.0, "w": photos[0].shape[1], "h": photos[0].shape[0],
                                             "frames": frames})


def _eq6_to_8(c, inv, threshold, floor):
    """M, D, weight 1 - M_w from C and DPT's inverse depth r, per Eq. 6-8 (see the module docstring)."""
    m = (c > threshold).astype(np.float32)
    d = 1.0 / np.maximum(inv, 1e-3 * inv.max())
    dmax = d.max()
    mw = m * np.maximum(floor, (dmax - d) / dmax)
    return m, d, 1.0 - mw


@pytest.mark.parametrize("floor", [0.0, 0.3])
def test_mask_command_dpt_source_against_eq6_to_8(tmp_path, floor):
    """`masking.write_masks` with a DPT whose classes and depth both vary over the image: masks,
    depth and weights on disk equal Eq. 6-8 computed by hand from the model's outputs on the
    photos as written (8-bit), with the threshold at the median of C so half the pixels are
    foreground and Eq. 7's depth term matters (inverse depth taken as depth fails)."""
    from jaxnerf_grid.masks import write as masking

    model = _model()
    dpt.save(model, tmp_path / "w", dtype="float32", extra={"dynamic_classes": [1, 2]})
    loaded = dpt.load_pretrained(str(tmp_path / "w"))
    h, w = 50, 70     # both sides shrink to the working size and grow back (area, then bilinear)
    _dataset(tmp_path / "data", [_photo(h, w, 4), _photo(h, w, 5)])
    work = (32, 64)   # longest side 70 -> 64; 50 * 64 / 70 = 45.7 -> 32
    refs = [_reference_maps(loaded, io.read_image(tmp_path / f"data/images/f{i}.png"), [1, 2], work) for i in range(2)]
    threshold = float(np.median(refs[0][0]))
    masking.write_masks(tmp_path / "data", weights=str(tmp_path / "w"), threshold=threshold, floor=floor,
                        max_side=64, batch_size=1, progress=False)
    meta = io.read_json(tmp_path / "data/transforms.json")
    assert meta["mask_source"] == "dpt" and meta["mask_params"]["classes"] == [1, 2]
    assert meta["mask_params"]["weights"] == str(tmp_path / "w") and meta["mask_params"]["max_side"] == 64
    assert meta["mask_params"]["depth"] == "relative (1 / DPT inverse depth)"
    for i, (c, inv) in enumerate(refs):
        m, d, weight = _eq6_to_8(c, inv, threshold, floor)
        frame = meta["frames"][i]
        got_m = io.read_mask(tmp_path / "data" / frame["mask_path"])
        got_d = io.read_exr(tmp_path / "data" / frame["dpt_depth_path"])
        got_w = io.read_exr(tmp_path / "data" / frame["weight_path"])
        # pixels whose C sits within float noise of T may fall either way
        sure = np.abs(c - threshold) > 1e-4
        assert 0.2 < m.mean() < 0.8 and sure.mean() > 0.95
        np.testing.assert_array_equal(got_m[sure], m[sure])
        np.testing.assert_allclose(got_d, d, rtol=1e-3)
        np.testing.assert_allclose(got_w[sure], weight[sure], atol=1e-3)
        masked = m.astype(bool) & sure
        # Eq. 7 does vary the weights of the masked pixels (not all 0 as with floor 1)
        assert np.std(weight[masked]) > 0.02


def test_mask_command_takes_the_working_size_from_the_model(tmp_path):
    """Without max_side, `write_masks` uses the model's own (config.json "extra": "max_side"),
    else 384; the maps are then DPT's at that working size (found by mutation testing: that
    branch was never taken)."""
    from jaxnerf_grid.masks import write as masking

    model = _model()
    dpt.save(model, tmp_path / "w32", dtype="float32", extra={"dynamic_classes": [1, 2], "max_side": 32})
    dpt.save(model, tmp_path / "plain", dtype="float32")          # no "extra" at all
    _dataset(tmp_path / "data", [_photo(50, 70, 6)])
    loaded = dpt.load_pretrained(str(tmp_path / "w32"))
    c, inv = _reference_maps(loaded, io.read_image(tmp_path / "data/images/f0.png"), [1, 2], (32, 32))
    threshold = float(np.median(c))
    masking.write_masks(tmp_path / "data", weights=str(tmp_path / "w32"), threshold=threshold, progress=False)
    meta = io.read_json(tmp_path / "data/transforms.json")
    assert meta["mask_params"]["max_side"] == 32
    sure = np.abs(c - threshold) > 1e-4
    _, _, weight = _eq6_to_8(c, inv, threshold, 0.0)
    np.testing.assert_allclose(io.read_exr(tmp_path / "data/weights/f0.exr")[sure], weight[sure], atol=1e-3)
    masking.write_masks(tmp_path / "data", weights=str(tmp_path / "plain"), classes=[1], overwrite=True,
                        progress=False)
    assert io.read_json(tmp_path / "data/transforms.json")["mask_params"]["max_side"] == 384
