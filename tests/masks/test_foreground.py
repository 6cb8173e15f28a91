"""Eq. 6-8 against hand-computed closed forms."""

import numpy as np
import pytest

from jaxnerf_grid.masks import foreground as fg


def test_probability_sums_softmax_over_classes():
    # logits log(1), log(2), log(3), log(4): softmax = [0.1, 0.2, 0.3, 0.4]
    logits = np.log(np.array([[[1.0, 2.0, 3.0, 4.0]]]))
    c = np.asarray(fg.foreground_probability(logits, [1, 3]))
    np.testing.assert_allclose(c, [[0.6]], atol=1e-6)
    np.testing.assert_allclose(np.asarray(fg.foreground_probability(logits, [2, 2])), [[0.3]], atol=1e-6)


def test_binary_mask_is_strict_threshold():
    prob = np.array([0.2, 0.5, 0.50001, 0.9])
    np.testing.assert_array_equal(np.asarray(fg.binary_mask(prob, 0.5)), [0, 0, 1, 1])


def test_depth_weighted_mask_eq7_exact_and_floor():
    mask = np.array([[1.0, 1.0], [0.0, 1.0]])
    depth = np.array([[1.0, 4.0], [2.0, 3.0]])  # Dmax = 4
    # Eq. 7: (4 - D) / 4 -> [[0.75, 0], [., 0.25]]
    np.testing.assert_allclose(np.asarray(fg.depth_weighted_mask(mask, depth)), [[0.75, 0.0], [0.0, 0.25]])
    # floor 0.5: max(0.5, w) on masked pixels only
    np.testing.assert_allclose(np.asarray(fg.depth_weighted_mask(mask, depth, floor=0.5)), [[0.75, 0.5], [0.0, 0.5]])
    # floor 1: every masked pixel fully excluded
    np.testing.assert_allclose(np.asarray(fg.depth_weighted_mask(mask, depth, floor=1.0)), mask)
    # explicit Dmax
    np.testing.assert_allclose(np.asarray(fg.depth_weighted_mask(mask, depth, dmax=8.0)),
                               [[7 / 8, 4 / 8], [0.0, 5 / 8]])
    with pytest.raises(ValueError, match="floor"):
        fg.depth_weighted_mask(mask, depth, floor=1.5)


def test_infinite_depth_is_the_farthest():
    mask = np.ones((1, 3))
    depth = np.array([[1.0, 4.0, np.inf]])
    np.testing.assert_allclose(np.asarray(fg.depth_weighted_mask(mask, depth)), [[0.75, 0.0, 0.0]])
    np.testing.assert_allclose(np.asarray(fg.depth_weighted_mask(mask, depth, floor=0.3)), [[0.75, 0.3, 0.3]])


def test_dmax_is_per_image_in_a_batch():
    mask = np.ones((2, 1, 2))
    depth = np.array([[[1.0, 2.0]], [[1.0, 10.0]]])
    np.testing.assert_allclose(np.asarray(fg.depth_weighted_mask(mask, depth)), [[[0.5, 0.0]], [[0.9, 0.0]]])


def test_eq7_with_depths_below_one_and_a_dmax_per_image():
    """DPT's relative depths 1 / r are far below 1 (r in the hundreds): Eq. 7 is scale-free, so
    the depths of the test above divided by 100 give the same M_w, an infinite depth included;
    and a dmax given per image ([2] for a batch of 2) is each image's own."""
    mask = np.ones((1, 4))
    depth = np.array([[0.01, 0.02, 0.04, np.inf]])        # Dmax = 0.04 (inf counts as it)
    np.testing.assert_allclose(np.asarray(fg.depth_weighted_mask(mask, depth)), [[0.75, 0.5, 0.0, 0.0]],
                               atol=1e-6)
    np.testing.assert_allclose(np.asarray(fg.depth_weighted_mask(mask, depth, dmax=0.08)),
                               [[7 / 8, 6 / 8, 4 / 8, 0.0]], atol=1e-6)
    batch = np.array([[[1.0, 2.0]], [[1.0, 2.0]]])
    got = np.asarray(fg.depth_weighted_mask(np.ones((2, 1, 2)), batch, dmax=np.array([4.0, 8.0])))
    np.testing.assert_allclose(got, [[[3 / 4, 2 / 4]], [[7 / 8, 6 / 8]]], atol=1e-6)


def test_filter_image_and_training_weights():
    img = np.full((1, 2, 3), 0.8)
    mw = np.array([[0.25, 1.0]])
    np.testing.assert_allclose(np.asarray(fg.filter_image(img, mw)), [[[0.6] * 3, [0.0] * 3]], atol=1e-6)
    np.testing.assert_allclose(np.asarray(fg.training_weights(mw)), [[0.75, 0.0]])


def test_inverse_depth_to_depth():
    inv = np.array([[4.0, 2.0], [1.0, 0.0]])
    d = np.asarray(fg.inverse_depth_to_depth(inv, eps=0.01))
    # 1/r, and r = 0 clamped to eps * max(r) = 0.04 -> 25
    np.testing.assert_allclose(d, [[0.25, 0.5], [1.0, 25.0]], rtol=1e-6)


def test_inverse_depth_to_depth_per_image_of_a_batch():
    """[B, H, W]: the clamp eps * max(r) is each image's own (found by mutation testing: a
    maximum over the whole batch, or over the wrong axes, passed every single-image test)."""
    inv = np.array([[[4.0, 0.0], [1.0, 2.0]], [[0.5, 0.25], [0.0, 1.0]]], np.float32)
    d = np.asarray(fg.inverse_depth_to_depth(inv, eps=0.1))
    expect = [[[0.25, 1 / 0.4], [1.0, 0.5]], [[2.0, 4.0], [1 / 0.1, 1.0]]]
    np.testing.assert_allclose(d, expect, rtol=1e-6)


def test_dilate_matches_disc_max_filter():
    m = np.zeros((9, 9), np.float32)
    m[4, 4] = 0.7
    out = fg.dilate(m, 2)
    # max filter of a single spike = the structuring element stamped at the spike (a 5x5 disc:
    # the centre row and column fully, the corners never)
    assert out[4, 2] == out[2, 4] == out[4, 6] == out[6, 4] == out[3, 3] == np.float32(0.7)
    assert out[2, 2] == out[6, 6] == out[0, 0] == 0 and out[4, 1] == 0
    assert np.count_nonzero(out) < 25 and out.max() == np.float32(0.7)


def test_working_size_keeps_aspect_and_multiple():
    for h, w in [(2160, 3840), (3648, 5472), (100, 60)]:
        wh, ww = fg.working_size(h, w, 384, 32)
        assert wh % 32 == 0 and ww % 32 == 0 and max(wh, ww) <= 400
        assert abs(wh / ww - h / w) < 0.1
    assert fg.working_size(2160, 3840, 384, 32) == (224, 384)


def test_predict_maps_on_large_photo_bounded_and_full_resolution():
    """A 3840x2160 photo through a tiny random DPT with both heads: outputs at full size, and one
    compiled working shape for two photos of the same size."""
    import jax

    from jaxnerf_grid.masks import dpt
    cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                        image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                        neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=3,
                        heads=("segmentation", "depth"))
    model = dpt.init(jax.random.PRNGKey(0), cfg)
    ramp = np.linspace(0, 1, 3840, dtype=np.float32)
    photo = np.broadcast_to(ramp[None, :, None], (2160, 3840, 3))
    outs = list(fg.predict_maps(model, model, [photo, photo], classes=[1], max_side=128, batch_size=2))
    assert len(outs) == 2
    c, inv = outs[0]
    assert c.shape == inv.shape == (2160, 3840)
    assert 0.0 <= c.min() and c.max() <= 1.0 and inv.min() >= 0
    np.testing.assert_array_equal(outs[0][0], outs[1][0])


def test_tile_starts_fewest_windows_that_cover_with_overlap():
    """Brute force: every pixel covered, neighbours share >= overlap, first at 0 and last flush with
    the end, and no smaller count of windows could do it."""
    for length in range(1, 90, 7):
        for tile in (8, 16, 33):
            for overlap in (0, 3, tile // 2, tile - 1):
                starts = fg.tile_starts(length, tile, overlap)
                covered = np.zeros(length, bool)
                for s in starts:
                    covered[s:s + tile] = True
                assert covered.all() and starts[0] == 0
                if tile < length:
                    assert starts[-1] == length - tile
                    assert all(a + tile - b >= overlap for a, b in zip(starts, starts[1:]))
                    n = len(starts) - 1  # n windows at the widest legal spacing fall short of the end
                    assert n == 0 or tile + (n - 1) * (tile - overlap) < length
                else:
                    assert starts == [0]
    with pytest.raises(ValueError, match="overlap"):
        fg.tile_starts(100, 16, 16)


def test_tile_layout_one_tile_is_the_working_size():
    for h, w in [(2160, 3840), (3648, 5472), (120, 160)]:
        lay = fg.tile_layout(h, w, 384, 32, 1, 0.25)
        assert lay.resized == fg.working_size(h, w, 384, 32) == lay.tile
        assert lay.starts_y == lay.starts_x == [0]
    lay = fg.tile_layout(3648, 5472, 384, 32, 3, 0.25)
    assert lay.tile == (384, 384) and lay.resized == (640, 960) and lay.overlap == 96
    assert lay.starts_x == [0, 288, 576] and lay.starts_y == [0, 256]
    lay = fg.tile_layout(100, 1000, 64, 32, 4, 0.25)   # a strip: one window, narrower, on the short side
    assert lay.resized == (32, 64 + 3 * 48)                # 21 rows would be too few for one window
    assert lay.tile == (32, 64) and lay.starts_y == [0] and len(lay.starts_x) == 4


def test_blend_tiles_against_per_pixel_loop():
    """Each pixel: the ramp-weighted mean of the windows that cover it (a loop over pixels)."""
    lay = fg.tile_layout(70, 100, 32, 16, 3, 0.3)
    th, tw = lay.tile
    wins = [(y, x) for y in lay.starts_y for x in lay.starts_x]
    values = np.random.default_rng(0).uniform(size=(len(wins), th, tw)).astype(np.float32)
    out = fg.blend_tiles(values, lay)

    def ramp(i, size):
        return min(1.0, min(i + 1, size - i) / (lay.overlap + 1))

    for py in range(lay.resized[0]):
        for px in range(lay.resized[1]):
            num = den = 0.0
            for k, (y, x) in enumerate(wins):
                if y <= py < y + th and x <= px < x + tw:
                    wgt = ramp(py - y, th) * ramp(px - x, tw)
                    num += wgt * values[k, py - y, px - x]
                    den += wgt
            assert abs(out[py, px] - num / den) < 1e-5
    # a constant map stays constant (the weights are normalised everywhere, borders included)
    np.testing.assert_allclose(fg.blend_tiles(np.full_like(values, 0.3), lay), 0.3, atol=1e-6)


def test_predict_maps_tiled_against_per_window_reference():
    """tiles=2: C equals DPT run on each window alone (batch of one), blended, resized; depth equals
    the untiled whole-photo depth."""
    from jaxnerf_grid.masks import dpt
    cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                        image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                        neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=3,
                        heads=("segmentation", "depth"))
    model = dpt.init(5, cfg)
    photo = np.random.default_rng(1).uniform(size=(150, 230, 3)).astype(np.float32)
    (c, inv), = fg.predict_maps(model, model, [photo], classes=[1, 2], max_side=64, batch_size=3, tiles=2)
    (c1, inv1), = fg.predict_maps(model, model, [photo], classes=[1, 2], max_side=64, batch_size=3)
    lay = fg.tile_layout(150, 230, 64, 32, 2, 0.25)
    assert lay.tile == (64, 64) and lay.starts_x == [0, 48] and lay.starts_y == [0, 9]
    fine = fg.resize_map(photo, *lay.resized)
    th, tw = lay.tile
    per_window = []
    for y in lay.starts_y:
        for x in lay.starts_x:
            logits = dpt.apply(model, dpt.normalize(fine[None, y:y + th, x:x + tw]))["logits"]
            per_window.append(np.asarray(fg.foreground_probability(logits, [1, 2]))[0])
    expect = fg.resize_map(fg.blend_tiles(np.stack(per_window), lay), 150, 230)
    assert c.shape == (150, 230) and np.std(c) > 1e-3
    np.testing.assert_allclose(c, expect, atol=1e-5)
    np.testing.assert_allclose(inv, inv1, atol=1e-6)
    assert np.abs(c - c1).max() > 1e-3  # the windows do see something else than the whole photo
    with pytest.raises(ValueError, match="tile_overlap"):
        next(fg.predict_maps(model, model, [photo], classes=[1], tiles=2, tile_overlap=0.9))


def test_class_probabilities_sum_to_predict_maps_c():
    """class_probabilities (every class, full resolution) summed over Eq. 6's classes is the C that
    predict_maps gives for the same photo: the two share the working size and the upsampling, so
    a study of other class rules (experiments/mask_tower_overlap.py) sees what `mask` sees."""
    from jaxnerf_grid.masks import dpt
    cfg = dpt.DPTConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32,
                        image_size=32, patch_size=16, backbone_out_indices=(0, 0, 1, 1),
                        neck_hidden_sizes=(8, 8, 8, 8), fusion_hidden_size=8, num_labels=3)
    model = dpt.init(7, cfg)
    photo = np.random.default_rng(2).uniform(size=(90, 170, 3)).astype(np.float32)
    (c, _), = fg.predict_maps(model, None, [photo], classes=[1, 2], max_side=64, batch_size=1)
    prob = fg.class_probabilities(model, photo, max_side=64)
    assert prob.shape == (90, 170, 3)
    np.testing.assert_allclose(prob.sum(-1), 1.0, atol=1e-5)
    assert np.std(c) > 1e-3
    np.testing.assert_allclose(prob[..., 1] + prob[..., 2], c, atol=1e-5)
