"""JAX LPIPS against the `lpips` package (v0.1, 'alex') built with a random AlexNet trunk.

The reference model is `lpips.LPIPS(net='alex', pretrained=True, pnet_rand=True)`: linear layers
from the package's own weights/v0.1/alex.pth, trunk random (torchvision stand-in from
conftest.py). It is converted with the same code path as scripts/convert_lpips_weights.py, saved
as .npz, loaded with `load_lpips`, and the distances compared on random and real image pairs.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from jaxnerf_grid.eval import lpips as jl
from jaxnerf_grid.eval import metrics
from jaxnerf_grid.util.io import DataError

torch = pytest.importorskip("torch")

SIZES = ((64, 64), (96, 128))


def _converter():
    path = Path(__file__).resolve().parents[2] / "scripts" / "convert_lpips_weights.py"
    spec = importlib.util.spec_from_file_location("convert_lpips_weights", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def torch_model(lpips_module):
    torch.manual_seed(0)
    return lpips_module.LPIPS(net="alex", version="0.1", pretrained=True, pnet_rand=True, verbose=False)


@pytest.fixture(scope="module")
def weights_file(torch_model, tmp_path_factory):
    path = tmp_path_factory.mktemp("lpips") / "alex_random_trunk.npz"
    jl.save_lpips(path, _converter().arrays_from_torch_lpips(torch_model))
    return path


@pytest.fixture(scope="module")
def params(weights_file):
    return jl.load_lpips(weights_file)


def _torch_lpips(model, a, b):
    """a, b: [N, H, W, 3] in [0, 1] -> [N]."""
    ta = torch.from_numpy(np.ascontiguousarray(a)).permute(0, 3, 1, 2)
    tb = torch.from_numpy(np.ascontiguousarray(b)).permute(0, 3, 1, 2)
    with torch.no_grad():
        return model(ta, tb, normalize=True).reshape(-1).numpy().astype(np.float64)


def _real_pairs(real_images, h, w, seed):
    """Real photographs resized to h x w; preds: noisy and blurred versions. -> [2, h, w, 3] x 2."""
    from skimage.filters import gaussian
    from skimage.transform import resize

    rng = np.random.default_rng(seed)
    astro = resize(real_images["astronaut"], (h, w), anti_aliasing=True).astype(np.float32)
    cat = resize(real_images["chelsea"], (h, w), anti_aliasing=True).astype(np.float32)
    noisy = np.clip(astro + 0.08 * rng.standard_normal(astro.shape), 0, 1).astype(np.float32)
    blurred = gaussian(cat, sigma=1.2, channel_axis=-1, preserve_range=True).astype(np.float32)
    return np.stack([noisy, blurred]), np.stack([astro, cat])


def test_linear_layers_come_from_the_lpips_wheel(lpips_module, weights_file):
    pth = Path(lpips_module.__file__).parent / "weights" / "v0.1" / "alex.pth"
    assert pth.exists(), "lpips wheel should ship weights/v0.1/alex.pth"
    state = torch.load(pth, map_location="cpu")
    with np.load(weights_file) as z:
        for l in range(5):
            np.testing.assert_array_equal(z[f"lin{l}.weight"], state[f"lin{l}.model.1.weight"].numpy())
        assert str(z["format"]) == jl.FORMAT


@pytest.mark.parametrize("h,w", SIZES)
def test_matches_torch_lpips_random_and_real(torch_model, params, real_images, h, w):
    rng = np.random.default_rng(h)
    a = rng.random((2, h, w, 3), dtype=np.float32)
    b = np.clip(a + 0.15 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    c = rng.random((2, h, w, 3), dtype=np.float32)  # unrelated images: a large distance
    pred_r, tgt_r = _real_pairs(real_images, h, w, seed=w)
    preds = np.concatenate([b, c, pred_r])
    tgts = np.concatenate([a, a, tgt_r])
    ref = _torch_lpips(torch_model, preds, tgts)
    got = np.asarray(jl.lpips_jit(params, preds, tgts), np.float64)  # batch [6, h, w, 3] -> [6]
    assert got.shape == (6,)
    assert np.all(ref > 0) and np.ptp(ref) > 0.1 * ref.max()  # the reference is not degenerate
    np.testing.assert_allclose(got, ref, rtol=1e-4)
    # single image [h, w, 3] -> scalar, via the metrics entry point
    out = metrics.evaluate_image(pred_r[0], tgt_r[0], lpips_params=params)
    assert out["lpips"] == pytest.approx(ref[4], rel=1e-4)
    assert float(jl.lpips_jit(params, tgt_r[0], tgt_r[0])) == pytest.approx(0.0, abs=1e-7)


def test_absent_weights_mean_unavailable(tmp_path):
    assert jl.load_lpips(None) is None
    with pytest.warns(UserWarning, match="not found"):
        assert jl.load_lpips(tmp_path / "missing.npz") is None
    rng = np.random.default_rng(0)
    img = rng.random((40, 40, 3), dtype=np.float32)
    assert metrics.evaluate_image(img, img * 0.5)["lpips"] is None


def test_bad_weights_file_is_a_clear_error(tmp_path, weights_file):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file")
    with pytest.raises(DataError, match="junk.npz"):
        jl.load_lpips(junk)
    with np.load(weights_file) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["conv3.weight"] = arrays["conv3.weight"][:, :10]
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(DataError, match=r"bad\.npz.*conv3\.weight.*shape"):
        jl.load_lpips(bad)
    del arrays["lin2.weight"]
    np.savez(bad, **{k: v for k, v in arrays.items() if k != "conv3.weight"})
    with pytest.raises(DataError, match="lack key"):
        jl.load_lpips(bad)


def test_too_small_image_rejected(params):
    img = np.zeros((30, 64, 3), np.float32)
    with pytest.raises(ValueError, match="too small"):
        jl.lpips(params, img, img)


def test_torchvision_stand_in_layout(lpips_module):
    import sys

    tv = sys.modules["torchvision"]
    if not getattr(tv, "__jaxnerf_grid_stub__", False):
        pytest.skip("a real torchvision is in use")
    from torch import nn

    feats = tv.models.alexnet(pretrained=False).features
    convs = [(m.in_channels, m.out_channels, m.kernel_size, m.stride, m.padding)
             for m in feats if isinstance(m, nn.Conv2d)]
    assert convs == [(3, 64, (11, 11), (4, 4), (2, 2)), (64, 192, (5, 5), (1, 1), (2, 2)),
                     (192, 384, (3, 3), (1, 1), (1, 1)), (384, 256, (3, 3), (1, 1), (1, 1)),
                     (256, 256, (3, 3), (1, 1), (1, 1))]
    assert [type(m).__name__ for m in feats] == [
        "Conv2d", "ReLU", "MaxPool2d", "Conv2d", "ReLU", "MaxPool2d",
        "Conv2d", "ReLU", "Conv2d", "ReLU", "Conv2d", "ReLU", "MaxPool2d"]
    with pytest.raises(RuntimeError, match="no pretrained"):
        tv.models.alexnet(pretrained=True)
