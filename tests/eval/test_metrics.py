"""PSNR / SSIM / MS-SSIM against scikit-image and pytorch_msssim (independent references)."""

import math

import jax
import numpy as np
import pytest

from jaxnerf_grid.eval import metrics

torch = pytest.importorskip("torch")
pm = pytest.importorskip("pytorch_msssim")
skm = pytest.importorskip("skimage.metrics")


def _noisy(img, sigma, seed):
    rng = np.random.default_rng(seed)
    return np.clip(img + sigma * rng.standard_normal(img.shape), 0, 1).astype(np.float32)


def _blurred(img, sigma):
    from skimage.filters import gaussian

    return gaussian(img, sigma=sigma, channel_axis=-1, preserve_range=True).astype(np.float32)


def _nchw(x):
    return torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None]


def _torch_ssim(a, b):
    return pm.ssim(_nchw(a), _nchw(b), data_range=1.0, win_size=11, win_sigma=1.5).item()


def _skimage_ssim(a, b):
    return skm.structural_similarity(a.astype(np.float64), b.astype(np.float64), gaussian_weights=True,
                                     sigma=1.5, use_sample_covariance=False, data_range=1.0,
                                     channel_axis=-1)


def _torch_ms_ssim_loop(a, b, weights):
    """MS-SSIM with pytorch_msssim's own per-scale SSIM (`_ssim`) and torch's avg_pool2d, for
    sizes where `pytorch_msssim.ms_ssim` refuses (it asserts min side > 160 whatever the
    number of weights)."""
    import torch.nn.functional as F
    from pytorch_msssim.ssim import _fspecial_gauss_1d, _ssim

    x, y = _nchw(a).double(), _nchw(b).double()
    win = _fspecial_gauss_1d(11, 1.5).repeat([3, 1, 1, 1])
    vals = []
    for i in range(len(weights)):
        s, cs = _ssim(x, y, data_range=1.0, win=win)
        if i < len(weights) - 1:
            vals.append(torch.relu(cs))
            pad = [d % 2 for d in x.shape[2:]]
            x, y = F.avg_pool2d(x, kernel_size=2, padding=pad), F.avg_pool2d(y, kernel_size=2, padding=pad)
        else:
            vals.append(torch.relu(s))
    w = torch.tensor(weights, dtype=torch.float64).view(-1, 1, 1)
    return torch.prod(torch.stack(vals) ** w, dim=0).mean().item()


@pytest.fixture(scope="module")
def pairs(real_images):
    """(name, pred, target) float32 HWC pairs: random (odd sizes) and real with noise / blur."""
    rng = np.random.default_rng(0)
    rand = rng.random((300, 451, 3), dtype=np.float32)  # chelsea's shape: shares compiles
    astro = real_images["astronaut"]
    chelsea = real_images["chelsea"]
    return [
        ("random_noise", _noisy(rand, 0.1, 1), rand),
        ("astronaut_noise", _noisy(astro, 0.05, 2), astro),
        ("chelsea_blur", _blurred(chelsea, 1.5), chelsea),
    ]


def test_psnr_matches_skimage_and_batches(pairs):
    for _, pred, target in pairs[:2]:
        ref = skm.peak_signal_noise_ratio(target.astype(np.float64), pred.astype(np.float64), data_range=1.0)
        assert float(metrics.psnr(pred, target)) == pytest.approx(ref, abs=1e-3)
    # batch [B, H, W, 3] -> [B]
    _, pred, target = pairs[1]
    b_pred = np.stack([pred, target])
    b_tgt = np.stack([target, _noisy(target, 0.2, 5)])
    got = np.asarray(metrics.psnr(b_pred, b_tgt))
    assert got.shape == (2,)
    for i in range(2):
        ref = skm.peak_signal_noise_ratio(b_tgt[i].astype(np.float64), b_pred[i].astype(np.float64), data_range=1.0)
        assert got[i] == pytest.approx(ref, abs=1e-3)
    assert math.isinf(float(metrics.psnr(target, target)))


def test_psnr_mask_is_region_psnr():
    rng = np.random.default_rng(3)
    pred = rng.random((20, 30, 3), dtype=np.float32)
    target = rng.random((20, 30, 3), dtype=np.float32)
    pred[:10] = target[:10] + 0.01  # a near-perfect top half
    mask = np.zeros((20, 30), np.float32)
    mask[:10] = 1.0
    ref = skm.peak_signal_noise_ratio(target[:10].astype(np.float64), pred[:10].astype(np.float64), data_range=1.0)
    assert float(metrics.psnr(pred, target, mask)) == pytest.approx(ref, abs=1e-3)
    # soft weights: brute-force weighted mean over pixels
    w = rng.random((20, 30))
    mse = sum(w[i, j] * np.mean((pred[i, j].astype(np.float64) - target[i, j]) ** 2)
              for i in range(20) for j in range(30)) / w.sum()
    assert float(metrics.psnr(pred, target, w)) == pytest.approx(-10 * np.log10(mse), abs=1e-3)


def test_ssim_matches_pytorch_msssim_and_skimage(pairs):
    for name, pred, target in pairs:
        got = float(metrics.ssim(pred, target))
        ref_t = _torch_ssim(pred, target)
        ref_s = _skimage_ssim(pred, target)
        # skimage reflect-pads then crops 5 px per border: the same valid positions as torch
        assert ref_t == pytest.approx(ref_s, abs=2e-5), name
        assert got == pytest.approx(ref_t, abs=2e-5), name
        assert got == pytest.approx(ref_s, abs=2e-5), name
    assert float(metrics.ssim(pairs[0][2], pairs[0][2])) == pytest.approx(1.0, abs=1e-6)


def test_ssim_batch_and_jit():
    rng = np.random.default_rng(4)
    target = rng.random((2, 32, 40, 3), dtype=np.float32)
    pred = np.clip(target + 0.1 * rng.standard_normal(target.shape), 0, 1).astype(np.float32)
    got = np.asarray(jax.jit(metrics.ssim)(pred, target))
    assert got.shape == (2,)
    for i in range(2):
        assert got[i] == pytest.approx(_skimage_ssim(pred[i], target[i]), abs=2e-5)
    with pytest.raises(ValueError, match="smaller than"):
        metrics.ssim(pred[:, :10], target[:, :10])


def test_ms_ssim_five_scales_matches_pytorch_msssim(pairs):
    for name, pred, target in pairs:
        assert metrics.ms_ssim_scales(*pred.shape[:2]) == 5
        ref = pm.ms_ssim(_nchw(pred), _nchw(target), data_range=1.0, win_size=11, win_sigma=1.5).item()
        assert float(metrics.ms_ssim(pred, target)) == pytest.approx(ref, abs=3e-5), name


def test_ms_ssim_truncated_weights_match_pytorch_msssim(pairs):
    _, pred, target = pairs[0]  # 300 x 451: pytorch_msssim accepts it, so pass truncated weights
    w3 = list(metrics.ms_ssim_weights(3))
    assert sum(w3) == pytest.approx(1.0)
    assert w3[1] / w3[0] == pytest.approx(0.2856 / 0.0448)
    ref = pm.ms_ssim(_nchw(pred), _nchw(target), data_range=1.0, weights=w3).item()
    assert float(metrics.ms_ssim(pred, target, num_scales=3)) == pytest.approx(ref, abs=3e-5)


@pytest.mark.parametrize("shape,scales", [((150, 97), 4), ((45, 60), 3), ((23, 21), 2)])
def test_ms_ssim_small_images_fewer_scales(real_images, shape, scales):
    target = real_images["chelsea"][100:100 + shape[0], 150:150 + shape[1]]
    pred = _noisy(target, 0.05, 6)
    assert metrics.ms_ssim_scales(*shape) == scales
    ref = _torch_ms_ssim_loop(pred, target, list(metrics.ms_ssim_weights(scales)))
    assert float(metrics.ms_ssim(pred, target)) == pytest.approx(ref, abs=3e-5)
    with pytest.raises(ValueError, match="at most"):
        metrics.ms_ssim(pred, target, num_scales=scales + 1)


def test_ms_ssim_scales_rule():
    def brute(h, w):  # largest n whose coarsest scale (n-1 ceil-halvings) still holds 11 px
        n, side = 0, min(h, w)
        while n < 5 and side >= 11:
            n += 1
            side = -(-side // 2)
        return n

    for side in range(11, 400, 7):
        assert metrics.ms_ssim_scales(side, side + 3) == brute(side, side + 3), side
    assert metrics.ms_ssim_scales(161, 500) == 5 and metrics.ms_ssim_scales(160, 500) == 4
    with pytest.raises(ValueError):
        metrics.ms_ssim_scales(10, 100)


def test_evaluate_image_without_lpips(pairs):
    _, pred, target = pairs[0]
    out = metrics.evaluate_image(pred, target)
    assert set(out) == {"psnr", "ssim", "ms_ssim", "ms_ssim_scales", "lpips"}
    assert out["lpips"] is None  # unavailable, never a number
    assert out["ms_ssim_scales"] == 5
    assert out["ssim"] == pytest.approx(_torch_ssim(pred, target), abs=2e-5)
    small = metrics.evaluate_image(pred[:41, :50], target[:41, :50], mask=np.ones((41, 50)))
    assert small["ms_ssim_scales"] == 3
    assert small["psnr_masked"] == pytest.approx(small["psnr"], abs=1e-4)
