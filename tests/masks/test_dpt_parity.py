"""Parity of our JAX DPT with transformers' torch DPT on tiny random configs (CPU, no download).

Every weight is randomised (including BatchNorm running statistics and the CLS / position
embeddings that HF initialises to zero), the torch model is saved in the HF layout, loaded with
`dpt.load_pretrained`, and the outputs must match within 1e-4 at HF's raw resolution; `logits` /
`depth` (input resolution) are checked against torch's bilinear resize of HF's output.
"""

import sys

import numpy as np
import pytest

sys.modules.setdefault("torchvision", None)  # the installed torchvision is broken; HF must not import it
torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")

from jaxnerf_grid.masks import dpt  # noqa: E402

TOL = 1e-4


def _randomise(model, seed):
    """Fills every parameter and buffer so outputs are O(1) (std 0.5/sqrt(fan_in) for matrices)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            r = torch.randn(p.shape, generator=gen)
            if p.ndim >= 2 and "embeddings" not in name:
                fan_in = p[0].numel() if "resize" not in name else p.shape[0]
                p.copy_(0.5 * r / np.sqrt(fan_in))
            elif name.endswith("weight"):          # LayerNorm / BatchNorm scales
                p.copy_(1.0 + 0.2 * r)
            else:                                   # biases, CLS token, position embeddings
                p.copy_(0.2 * r if "embeddings" not in name else 0.5 * r)
        if hasattr(model.head, "head") and isinstance(model, transformers.DPTForDepthEstimation):
            model.head.head[4].bias.fill_(0.3)  # keep the final ReLU mostly active (else depth == 0)
        for name, b in model.named_buffers():
            if name.endswith("running_mean"):
                b.copy_(0.2 * torch.randn(b.shape, generator=gen))
            elif name.endswith("running_var"):
                b.copy_(0.5 + torch.rand(b.shape, generator=gen))


def _hf_config(readout, batch_norm, **kw):
    base = dict(hidden_size=32, num_hidden_layers=4, num_attention_heads=4, intermediate_size=64,
                image_size=32, patch_size=8, backbone_out_indices=[0, 1, 2, 3],
                neck_hidden_sizes=[8, 16, 24, 32], fusion_hidden_size=16, num_labels=5,
                readout_type=readout, use_batch_norm_in_fusion_residual=batch_norm)
    base.update(kw)
    return transformers.DPTConfig(**base)


def _save(model, tmp_path, name):
    folder = tmp_path / name
    model.save_pretrained(folder)
    return folder


def _torch_resize(x_nchw, size):
    return torch.nn.functional.interpolate(x_nchw, size=size, mode="bilinear", align_corners=False)


# 32 px = the trained grid (4x4); 40 px = 5x5 grid: interpolated position embeddings and an odd
# grid, so the fusion stage must resize a residual (HF's align_corners=False branch). One size
# per case keeps one XLA compile per case; every readout and task still sees both sizes.
def _size(batch_norm, task):
    return 40 if batch_norm == (task == "segmentation") else 32


def _raw_size(size, patch=8):
    """HF's raw output rows: the deepest map has ceil(g/2) rows (stride-2 conv, padding 1), four
    fusion stages and the head each double it."""
    return 32 * -(-(size // patch) // 2)


@pytest.mark.parametrize("readout", ["project", "add", "ignore"])
@pytest.mark.parametrize("batch_norm", [True, False])
@pytest.mark.parametrize("task", ["segmentation", "depth"])
def test_parity_with_transformers(tmp_path, readout, batch_norm, task):
    cls = transformers.DPTForSemanticSegmentation if task == "segmentation" else transformers.DPTForDepthEstimation
    ref = cls(_hf_config(readout, batch_norm)).eval()
    _randomise(ref, seed=["project", "add", "ignore"].index(readout) * 4 + 2 * batch_norm + (task == "depth"))
    model = dpt.load_pretrained(_save(ref, tmp_path, "hf"))
    assert model.config.heads == (task,)
    rng = np.random.default_rng(0)
    for size in (_size(batch_norm, task),):
        x = rng.uniform(-1, 1, size=(2, size, size, 3)).astype(np.float32)
        with torch.no_grad():
            out = ref(pixel_values=torch.from_numpy(x).permute(0, 3, 1, 2))
        got = dpt.apply(model, x)
        if task == "segmentation":
            raw = out.logits
            assert raw.std() > 1e-2
            # HF's raw logits are larger than the input for patch 8 (2x for an even grid)
            assert raw.shape[-2:] == (_raw_size(size),) * 2
            np.testing.assert_allclose(np.asarray(got["logits_raw"]), raw.permute(0, 2, 3, 1).numpy(),
                                       atol=TOL, rtol=0)
            full = _torch_resize(raw, (size, size)).permute(0, 2, 3, 1).numpy()
            np.testing.assert_allclose(np.asarray(got["logits"]), full, atol=TOL, rtol=0)
        else:
            raw = out.predicted_depth
            assert (raw > 0).float().mean() > 0.3 and raw.std() > 1e-2  # a reference that can catch errors
            assert raw.shape[-2:] == (_raw_size(size),) * 2
            np.testing.assert_allclose(np.asarray(got["depth_raw"]), raw.numpy(), atol=TOL, rtol=0)
            full = _torch_resize(raw[:, None], (size, size))[:, 0].numpy()
            np.testing.assert_allclose(np.asarray(got["depth"]), full, atol=TOL, rtol=0)
            assert np.all(np.asarray(got["depth"]) >= 0)


def test_auxiliary_head_and_patch16_resolution(tmp_path):
    """Patch 16 (as Intel/dpt-large-ade): HF's logits come out at the input size; the auxiliary
    head (not returned by HF's forward) is checked by calling HF's module on HF's own neck output."""
    cfg = _hf_config("project", False, patch_size=16, image_size=32, num_labels=3)
    ref = transformers.DPTForSemanticSegmentation(cfg).eval()
    _randomise(ref, seed=7)
    model = dpt.load_pretrained(_save(ref, tmp_path, "hf16"))
    # non-square inputs work here (HF's ViT neck reshapes tokens to a square and cannot run them)
    x = np.random.default_rng(1).uniform(-1, 1, size=(1, 64, 96, 3)).astype(np.float32)
    got = dpt.apply(model, x)
    assert got["logits"].shape == got["logits_raw"].shape == (1, 64, 96, 3)
    assert np.all(np.isfinite(np.asarray(got["logits"])))
    x_sq = x[:, :, :64]
    with torch.no_grad():
        xt = torch.from_numpy(x_sq).permute(0, 3, 1, 2)
        out = ref(pixel_values=xt, output_hidden_states=True)
        hidden = [h for i, h in enumerate(out.hidden_states[1:]) if i in cfg.backbone_out_indices]
        aux = ref.auxiliary_head(ref.neck(hidden)[-1])
    assert out.logits.shape[-2:] == (64, 64)
    got_sq = dpt.apply(model, x_sq, auxiliary=True)
    assert "aux_logits" not in dpt.apply(model, x_sq)  # skipped unless asked for
    np.testing.assert_allclose(np.asarray(got_sq["logits"]), out.logits.permute(0, 2, 3, 1).numpy(), atol=TOL, rtol=0)
    np.testing.assert_allclose(np.asarray(got_sq["aux_logits"]), aux.permute(0, 2, 3, 1).numpy(), atol=TOL, rtol=0)


def test_depth_head_with_projection(tmp_path):
    """`add_projection` (a 3x3 256 -> 256 conv + ReLU ahead of the depth head, as DPT-hybrid has):
    our head folds the fusion's last x2 into that conv instead of into conv1."""
    cfg = _hf_config("project", False, fusion_hidden_size=256, add_projection=True)
    ref = transformers.DPTForDepthEstimation(cfg).eval()
    _randomise(ref, seed=11)
    model = dpt.load_pretrained(_save(ref, tmp_path, "hfproj"))
    assert "projection" in model.params["depth"]
    x = np.random.default_rng(2).uniform(-1, 1, size=(1, 32, 32, 3)).astype(np.float32)
    with torch.no_grad():
        raw = ref(pixel_values=torch.from_numpy(x).permute(0, 3, 1, 2)).predicted_depth
    # the 256-wide projection averages a lot, so the map varies less than in the cases above;
    # its spread is still 50x the tolerance
    assert (raw > 0).float().mean() > 0.3 and raw.std() > 50 * TOL
    np.testing.assert_allclose(np.asarray(dpt.apply(model, x)["depth_raw"]), raw.numpy(), atol=TOL, rtol=0)
    # a head that skipped the projection would be caught
    without = dpt.Model(model.config, {**model.params, "depth": {k: v for k, v in model.params["depth"].items()
                                                                  if k != "projection"}})
    assert np.abs(np.asarray(dpt.apply(without, x)["depth_raw"]) - raw.numpy()).max() > 10 * TOL
