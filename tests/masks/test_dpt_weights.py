"""Checkpoint I/O: the safetensors reader/writer against the `safetensors` package, the native
round trip, clear errors on bad checkpoints, and the layer primitives against torch."""

import json
import sys

import numpy as np
import pytest

from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.masks import dpt
from jaxnerf_grid.masks.dpt import ops as layers
from jaxnerf_grid.masks.dpt.weights import params_to_hf
from jaxnerf_grid.util import safetensors_io
from jaxnerf_grid.util.io import DataError

TINY = dict(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32, image_size=32,
            patch_size=16, backbone_out_indices=(0, 0, 1, 1), neck_hidden_sizes=(8, 8, 8, 8),
            fusion_hidden_size=8, num_labels=3)


def test_safetensors_roundtrip_against_reference_package(tmp_path):
    st = pytest.importorskip("safetensors.numpy")
    tensors = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.array(7, np.int64),
               "c": np.ones((2, 2), np.float16), "d": np.array([True, False])}
    safetensors_io.save(tmp_path / "ours.safetensors", tensors, {"k": "v"})
    theirs = st.load_file(str(tmp_path / "ours.safetensors"))
    for k, v in tensors.items():
        np.testing.assert_array_equal(theirs[k], v)
        assert theirs[k].dtype == v.dtype
    st.save_file(tensors, str(tmp_path / "theirs.safetensors"), metadata={"x": "y"})
    back, meta = safetensors_io.load(tmp_path / "theirs.safetensors")
    assert meta == {"x": "y"}
    for k, v in tensors.items():
        np.testing.assert_array_equal(back[k], v)


def test_native_roundtrip_float16(tmp_path):
    model = dpt.init(3, dpt.DPTConfig(**TINY, heads=("segmentation", "depth")))
    dpt.save(model, tmp_path / "m", dtype="float16")
    back = dpt.load_pretrained(tmp_path / "m")
    assert back.config == model.config
    a = np.asarray(model.params["vit"]["blocks"][1]["fc1"]["w"])
    np.testing.assert_allclose(np.asarray(back.params["vit"]["blocks"][1]["fc1"]["w"]), a, rtol=1e-3, atol=1e-4)


def _hf_folder(tmp_path, model, arch="DPTForSemanticSegmentation", **cfg_over):
    cfg = {"model_type": "dpt", "architectures": [arch], "hidden_act": "gelu",
           **{k: list(v) if isinstance(v, tuple) else v for k, v in TINY.items()},
           "id2label": {str(i): f"c{i}" for i in range(TINY["num_labels"])}}
    cfg.update(cfg_over)
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "config.json").write_text(json.dumps(cfg))
    tensors = params_to_hf(model)
    tensors["head.head.1.num_batches_tracked"] = np.array(5, np.int64)
    return tmp_path, tensors


def test_hf_errors_name_the_key(tmp_path):
    model = dpt.init(0, dpt.DPTConfig(**TINY))
    folder, tensors = _hf_folder(tmp_path / "ok", model)
    safetensors_io.save(folder / "model.safetensors", tensors)
    loaded = dpt.load_pretrained(folder)  # the HF export round-trips
    np.testing.assert_array_equal(loaded.params["reassemble"]["resample"][0]["w"],
                                  model.params["reassemble"]["resample"][0]["w"])
    assert loaded.config.id2label == ("c0", "c1", "c2")

    bad = dict(tensors)
    del bad["neck.convs.2.weight"]
    safetensors_io.save(folder / "model.safetensors", bad)
    with pytest.raises(DataError, match="missing key 'neck.convs.2.weight'"):
        dpt.load_pretrained(folder)

    bad = dict(tensors, **{"dpt.encoder.layer.2.output.dense.bias": np.zeros(16, np.float32)})
    safetensors_io.save(folder / "model.safetensors", bad)
    with pytest.raises(DataError, match="unexpected key 'dpt.encoder.layer.2.output.dense.bias'"):
        dpt.load_pretrained(folder)

    bad = dict(tensors, **{"head.head.4.weight": np.zeros((4, 8, 1, 1), np.float32)})
    safetensors_io.save(folder / "model.safetensors", bad)
    with pytest.raises(DataError, match=r"'head.head.4.weight' has shape \(4, 8, 1, 1\)"):
        dpt.load_pretrained(folder)

    # a config that does not match the weights (hidden size)
    safetensors_io.save(folder / "model.safetensors", tensors)
    cfg = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps(dict(cfg, hidden_size=32, intermediate_size=32)))
    with pytest.raises(DataError, match="dpt.embeddings.cls_token"):
        dpt.load_pretrained(folder)

    (folder / "config.json").write_text(json.dumps(dict(cfg, is_hybrid=True)))
    with pytest.raises(ConfigError, match="Hybrid"):
        dpt.load_pretrained(folder)
    (folder / "config.json").write_text(json.dumps(dict(cfg, architectures=["DPTModel"])))
    with pytest.raises(ConfigError, match="architectures"):
        dpt.load_pretrained(folder)


def test_apply_rejects_bad_input_shape():
    model = dpt.init(0, dpt.DPTConfig(**TINY))
    with pytest.raises(ValueError, match="multiple of the patch size"):
        dpt.apply(model, np.zeros((1, 40, 32, 3), np.float32))


def test_primitives_against_torch():
    sys.modules.setdefault("torchvision", None)
    torch = pytest.importorskip("torch")
    x = np.random.default_rng(0).normal(size=(2, 5, 7, 3)).astype(np.float32)
    xt = torch.from_numpy(x).permute(0, 3, 1, 2)
    for size, ac in [((10, 14), True), ((9, 4), False), ((3, 3), False), ((5, 7), True)]:
        ref = torch.nn.functional.interpolate(xt, size=size, mode="bilinear", align_corners=ac)
        np.testing.assert_allclose(np.asarray(layers.resize_bilinear(x, *size, align_corners=ac)),
                                   ref.permute(0, 2, 3, 1).numpy(), atol=1e-5)
    np.testing.assert_allclose(np.asarray(layers.gelu(x)), torch.nn.functional.gelu(torch.from_numpy(x)).numpy(),
                               atol=1e-6)
    conv = torch.nn.Conv2d(3, 4, 3, stride=2, padding=1)
    p = {"w": conv.weight.detach().numpy().transpose(2, 3, 1, 0), "b": conv.bias.detach().numpy()}
    np.testing.assert_allclose(np.asarray(layers.conv2d(p, x, stride=2, padding=1)),
                               conv(xt).detach().permute(0, 2, 3, 1).numpy(), atol=1e-5)
    convt = torch.nn.ConvTranspose2d(3, 4, 4, stride=4)
    p = {"w": convt.weight.detach().numpy().transpose(0, 2, 3, 1), "b": convt.bias.detach().numpy()}
    np.testing.assert_allclose(np.asarray(layers.conv_transpose_nonoverlap(p, x)),
                               convt(xt).detach().permute(0, 2, 3, 1).numpy(), atol=1e-5)


def test_conv_of_upsampled_map_against_torch():
    """`layers.conv2d_upsampled` (taps mixed at low resolution, then interpolated) against torch's
    interpolate + Conv2d, for x2 and non-integer scales, 1x1 / 3x3 / 5x5 kernels, and sizes where
    the zero padding and the interpolation's clamped last sample meet."""
    sys.modules.setdefault("torchvision", None)
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(3)
    for (h, w), (oh, ow), k in [((5, 7), (10, 14), 3), ((4, 3), (9, 5), 3), ((6, 6), (12, 12), 5),
                                ((3, 4), (6, 8), 1), ((1, 2), (2, 4), 3)]:
        x = rng.normal(size=(2, h, w, 3)).astype(np.float32)
        conv = torch.nn.Conv2d(3, 4, k, padding=k // 2)
        with torch.no_grad():
            ref = conv(torch.nn.functional.interpolate(torch.from_numpy(x).permute(0, 3, 1, 2), size=(oh, ow),
                                                       mode="bilinear", align_corners=True))
        p = {"w": conv.weight.detach().numpy().transpose(2, 3, 1, 0), "b": conv.bias.detach().numpy()}
        np.testing.assert_allclose(np.asarray(layers.conv2d_upsampled(p, x, oh, ow, padding=k // 2)),
                                   ref.permute(0, 2, 3, 1).numpy(), atol=1e-5)


def test_forward_is_vmap_and_jit_safe():
    import jax
    model = dpt.init(1, dpt.DPTConfig(**TINY, heads=("segmentation", "depth")))
    xs = np.random.default_rng(2).uniform(-1, 1, (3, 32, 48, 3)).astype(np.float32)
    batched = dpt.apply(model, xs)
    per_example = jax.jit(jax.vmap(lambda x: dpt.forward(model.params, model.config, x[None])["logits"][0]))(xs)
    assert np.std(np.asarray(batched["logits"])) > 1e-3
    np.testing.assert_allclose(np.asarray(per_example), np.asarray(batched["logits"]), atol=1e-5)
