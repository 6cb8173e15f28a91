"""Checkpoint import / export.

`load_pretrained(folder)` reads either
  * a Hugging Face folder (`config.json` + `model.safetensors`) of DPTForSemanticSegmentation or
    DPTForDepthEstimation with a plain ViT backbone (e.g. copies of Intel/dpt-large-ade,
    Intel/dpt-large), or
  * a native folder written by `save(model, folder)` (`config.json` with
    "format": "jaxnerf_grid.masks.dpt" + `params.safetensors` keyed by '/'-joined pytree paths).
Every HF tensor is mapped to one leaf of our pytree (torch Linear [out, in] -> [in, out], Conv
OIHW -> HWIO, ConvTranspose [in, out, k, k] -> [in, k, k, out]). Missing keys, unexpected keys
and wrong shapes are errors naming the key. Ignored on purpose: BatchNorm `num_batches_tracked`
and `dpt.pooler.*` (unused by either task model). Hybrid (BiT) backbones are refused.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxnerf_grid.config.schema import ConfigError, from_dict, to_dict
from jaxnerf_grid.masks.dpt.dpt_config import DPTConfig
from jaxnerf_grid.masks.dpt.model import Model, param_shapes
from jaxnerf_grid.util import safetensors_io
from jaxnerf_grid.util.io import DataError, atomic_write_bytes, read_json

NATIVE_FORMAT = "jaxnerf_grid.masks.dpt"
_ARCHS = {"DPTForSemanticSegmentation": ("segmentation",), "DPTForDepthEstimation": ("depth",)}

# (our array) = transform(hf array); shapes permute the same way.
_TO_OURS = {
    "linear": lambda a: a.T,
    "conv": lambda a: np.transpose(a, (2, 3, 1, 0)),
    "convT": lambda a: np.transpose(a, (0, 2, 3, 1)),
    "vec": lambda a: a,
    "token": lambda a: a.reshape(a.shape[-1]),
    "pos": lambda a: a.reshape(a.shape[-2], a.shape[-1]),
}
_TO_HF = {
    "linear": lambda a: a.T,
    "conv": lambda a: np.transpose(a, (3, 2, 0, 1)),
    "convT": lambda a: np.transpose(a, (0, 3, 1, 2)),
    "vec": lambda a: a,
    "token": lambda a: a.reshape(1, 1, -1),
    "pos": lambda a: a.reshape(1, *a.shape),
}


# ----------------------------------------------------------------- config
def config_from_hf(hf: dict, where: str = "config.json") -> DPTConfig:
    """Our DPTConfig from an HF DPT config dict (raises ConfigError on unsupported variants)."""
    if hf.get("model_type", "dpt") != "dpt":
        raise ConfigError(f"{where}: model_type {hf.get('model_type')!r} is not 'dpt'")
    if hf.get("is_hybrid"):
        raise ConfigError(f"{where}: DPT-Hybrid (BiT backbone) checkpoints are not supported; "
                          "use a plain-ViT DPT such as Intel/dpt-large-ade or Intel/dpt-large")
    if hf.get("backbone_config") or hf.get("backbone"):
        raise ConfigError(f"{where}: DPT with an external backbone ({hf.get('backbone') or 'backbone_config'}) "
                          "is not supported; only the ViT encoder is implemented")
    archs = [a for a in hf.get("architectures") or [] if a in _ARCHS]
    if not archs:
        raise ConfigError(f"{where}: architectures {hf.get('architectures')} contain neither "
                          f"{' nor '.join(_ARCHS)}")
    if hf.get("hidden_act", "gelu") != "gelu":
        raise ConfigError(f"{where}: hidden_act {hf.get('hidden_act')!r} unsupported (only exact 'gelu')")
    heads = _ARCHS[archs[0]]
    id2label = hf.get("id2label") or {}
    num_labels = len(id2label) if id2label else int(hf.get("num_labels", 1) or 1)
    labels = tuple(str(id2label.get(str(i), id2label.get(i, f"LABEL_{i}"))) for i in range(num_labels)) \
        if id2label else ()

    def size(name, default):
        v = hf.get(name, default)
        if isinstance(v, (list, tuple)):
            if len(set(v)) != 1:
                raise ConfigError(f"{where}: non-square {name} {v} unsupported")
            v = v[0]
        return int(v)

    fields = {f.name for f in dataclasses.fields(DPTConfig)}
    kw: dict[str, Any] = {k: hf[k] for k in (
        "hidden_size", "num_hidden_layers", "num_attention_heads", "intermediate_size", "layer_norm_eps", "qkv_bias",
        "readout_type", "fusion_hidden_size", "head_in_index", "use_batch_norm_in_fusion_residual",
        "use_bias_in_fusion_residual", "add_projection", "num_channels") if k in hf and k in fields}
    for k in ("backbone_out_indices", "reassemble_factors", "neck_hidden_sizes"):
        if k in hf:
            kw[k] = tuple(hf[k])
    kw["reassemble_factors"] = tuple(int(f) if float(f).is_integer() else float(f)
                                     for f in kw.get("reassemble_factors", DPTConfig.reassemble_factors))
    kw["image_size"] = size("image_size", 384)
    kw["patch_size"] = size("patch_size", 16)
    kw["use_auxiliary_head"] = bool(hf.get("use_auxiliary_head", True))
    kw["num_labels"] = num_labels
    kw["heads"] = heads
    kw["id2label"] = labels
    try:
        return DPTConfig(**kw)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None


# ----------------------------------------------------------------- key mapping
def hf_key_map(cfg: DPTConfig) -> list[tuple[str, tuple, str]]:
    """[(hf_key, path in our params pytree, transform kind)] for a single-head HF model."""
    m: list[tuple[str, tuple, str]] = []
    e = "dpt.embeddings."
    m += [(e + "cls_token", ("vit", "cls"), "token"), (e + "position_embeddings", ("vit", "pos"), "pos"),
          (e + "patch_embeddings.projection.weight", ("vit", "patch", "w"), "conv"),
          (e + "patch_embeddings.projection.bias", ("vit", "patch", "b"), "vec")]
    lin = lambda hf, path, bias=True: [(hf + ".weight", path + ("w",), "linear")] + (  # noqa: E731
        [(hf + ".bias", path + ("b",), "vec")] if bias else [])
    norm = lambda hf, path: [(hf + ".weight", path + ("scale",), "vec"), (hf + ".bias", path + ("bias",), "vec")]  # noqa: E731
    bn = lambda hf, path: norm(hf, path) + [(hf + ".running_mean", path + ("mean",), "vec"),  # noqa: E731
                                            (hf + ".running_var", path + ("var",), "vec")]
    conv = lambda hf, path, bias=True: [(hf + ".weight", path + ("w",), "conv")] + (  # noqa: E731
        [(hf + ".bias", path + ("b",), "vec")] if bias else [])
    for i in range(cfg.num_hidden_layers):
        L = f"dpt.encoder.layer.{i}."
        P: tuple = ("vit", "blocks", i)  # a path in the params pytree
        for name in ("query", "key", "value"):
            m += lin(L + "attention.attention." + name, P + (name[0],), cfg.qkv_bias)
        m += lin(L + "attention.output.dense", P + ("o",))
        m += lin(L + "intermediate.dense", P + ("fc1",)) + lin(L + "output.dense", P + ("fc2",))
        m += norm(L + "layernorm_before", P + ("ln1",)) + norm(L + "layernorm_after", P + ("ln2",))
    m += norm("dpt.layernorm", ("vit", "ln_final"))
    R = "neck.reassemble_stage."
    for i, f in enumerate(cfg.reassemble_factors):
        if cfg.readout_type == "project":
            m += lin(R + f"readout_projects.{i}.0", ("reassemble", "readout", i))
        m += conv(R + f"layers.{i}.projection", ("reassemble", "proj", i))
        if f > 1:
            m += [(R + f"layers.{i}.resize.weight", ("reassemble", "resample", i, "w"), "convT"),
                  (R + f"layers.{i}.resize.bias", ("reassemble", "resample", i, "b"), "vec")]
        elif f < 1:
            m += conv(R + f"layers.{i}.resize", ("reassemble", "resample", i))
        m += conv(f"neck.convs.{i}", ("reassemble", "convs", i), bias=False)
    for i in range(len(cfg.neck_hidden_sizes)):
        F, P = f"neck.fusion_stage.layers.{i}.", ("fusion", i)
        m += conv(F + "projection", P + ("proj",))
        for r in (1, 2):
            for c in (1, 2):
                m += conv(F + f"residual_layer{r}.convolution{c}", P + (f"rcu{r}", f"conv{c}"), cfg.fusion_bias)
                if cfg.use_batch_norm_in_fusion_residual:
                    m += bn(F + f"residual_layer{r}.batch_norm{c}", P + (f"rcu{r}", f"bn{c}"))
    if "segmentation" in cfg.heads:
        for hf, ours in (("head.head.", "segmentation"), ("auxiliary_head.head.", "auxiliary")):
            if ours == "auxiliary" and not cfg.use_auxiliary_head:
                continue
            m += conv(hf + "0", (ours, "conv"), bias=False) + bn(hf + "1", (ours, "bn"))
            m += conv(hf + "4", (ours, "cls"))
    if "depth" in cfg.heads:
        if cfg.add_projection:
            m += conv("head.projection", ("depth", "projection"))
        m += conv("head.head.0", ("depth", "conv1")) + conv("head.head.2", ("depth", "conv2"))
        m += conv("head.head.4", ("depth", "conv3"))
    return m


def _ignorable(key: str) -> bool:
    return key.endswith(".num_batches_tracked") or key.startswith("dpt.pooler.")


def _get(tree, path):
    for p in path:
        tree = tree[p]
    return tree


def _set(tree, path, value):
    for p in path[:-1]:
        tree = tree[p]
    tree[path[-1]] = value


def params_from_hf(cfg: DPTConfig, tensors: dict, where: str = "model.safetensors") -> dict:
    """Maps HF tensors to our params pytree; errors name the offending key."""
    mapping = hf_key_map(cfg)
    expected = {k for k, _, _ in mapping}
    missing = [k for k in expected if k not in tensors]
    if missing:
        raise DataError(f"{where}: missing key {sorted(missing)[0]!r} ({len(missing)} missing in all) "
                        "-- does config.json match these weights?")
    unexpected = sorted(k for k in tensors if k not in expected and not _ignorable(k))
    if unexpected:
        raise DataError(f"{where}: unexpected key {unexpected[0]!r} ({len(unexpected)} unexpected in all) "
                        "-- does config.json match these weights?")
    template = param_shapes(cfg)
    params = jax.tree_util.tree_map(lambda s: None, template)
    for key, path, kind in mapping:
        want = tuple(_get(template, path).shape)
        arr = np.asarray(tensors[key], dtype=np.float32)
        want_hf = _TO_HF[kind](np.empty(want, np.float32)).shape
        if arr.shape != want_hf:
            raise DataError(f"{where}: key {key!r} has shape {tuple(arr.shape)}, config.json implies {tuple(want_hf)}")
        _set(params, path, np.ascontiguousarray(_TO_OURS[kind](arr)))
    return jax.tree_util.tree_map(np.asarray, params)


def params_to_hf(model: Model) -> dict:
    """Inverse of `params_from_hf` for a single-head model (HF key -> numpy array)."""
    if len(model.config.heads) != 1:
        raise ConfigError("params_to_hf: an HF model has exactly one head (segmentation or depth)")
    return {k: np.ascontiguousarray(_TO_HF[kind](np.asarray(_get(model.params, path), np.float32)))
            for k, path, kind in hf_key_map(model.config)}


# ----------------------------------------------------------------- native format
def _flatten(tree, prefix=()):
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from _flatten(v, prefix + (str(k),))
    elif isinstance(tree, (list, tuple)):
        for i, v in enumerate(tree):
            yield from _flatten(v, prefix + (str(i),))
    else:
        yield "/".join(prefix), tree


def save(model: Model, folder, dtype: str = "float32", extra: dict | None = None) -> None:
    """Writes the native format: folder/config.json + folder/params.safetensors (float16 or float32)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    np_dtype = {"float32": np.float32, "float16": np.float16}[dtype]
    tensors = {k: np.asarray(v).astype(np_dtype) for k, v in _flatten(model.params)}
    safetensors_io.save(folder / "params.safetensors", tensors, {"format": NATIVE_FORMAT})
    meta = {"format": NATIVE_FORMAT, "version": 1, "config": to_dict(model.config)}
    if extra:
        meta["extra"] = extra
    atomic_write_bytes(folder / "config.json", (json.dumps(meta, indent=2) + "\n").encode())


def _load_native(folder: Path, meta: dict) -> Model:
    cfg = from_dict(DPTConfig, meta["config"], f"{folder / 'config.json'}: config")
    tensors, _ = safetensors_io.load(folder / "params.safetensors")
    template = param_shapes(cfg)
    where = folder / "params.safetensors"
    expected = dict(_flatten(template))
    for k in expected:
        if k not in tensors:
            raise DataError(f"{where}: missing key {k!r}")
    for k in tensors:
        if k not in expected:
            raise DataError(f"{where}: unexpected key {k!r}")
    params = jax.tree_util.tree_map(lambda s: None, template)
    for k, shape in expected.items():
        arr = tensors[k]
        if tuple(arr.shape) != tuple(shape.shape):
            raise DataError(f"{where}: key {k!r} has shape {tuple(arr.shape)}, expected {tuple(shape.shape)}")
        path = tuple(int(p) if p.isdigit() else p for p in k.split("/"))
        _set(params, path, np.asarray(arr, np.float32))
    return Model(cfg, jax.device_put(params))


def load_pretrained(folder) -> Model:
    """A Model from an HF-layout folder or a native folder (see module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: not a folder (expected config.json + model.safetensors)")
    meta = read_json(folder / "config.json")
    if isinstance(meta, dict) and meta.get("format") == NATIVE_FORMAT:
        return _load_native(folder, meta)
    cfg = config_from_hf(meta, str(folder / "config.json"))
    st = folder / "model.safetensors"
    if not st.is_file():
        extra = " (only pytorch_model.bin found: convert it to safetensors first)" \
            if (folder / "pytorch_model.bin").is_file() else ""
        raise DataError(f"{st}: file not found{extra}")
    tensors, _ = safetensors_io.load(st)
    # on the device once: numpy leaves would be copied on every `apply` (0.2 s per call for
    # DPT-base on CPU, 1.3 GB per call for DPT-large)
    return Model(cfg, jax.device_put(params_from_hf(cfg, tensors, str(st))))
