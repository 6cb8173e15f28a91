"""Checkpoints of a training-state pytree: atomic writes, the last k kept, exact resume.

A checkpoint is `run_dir/checkpoints/ckpt_{step:08d}.npz`: one array per pytree leaf
(`leaf_00000`, ...) plus `__manifest__`, a JSON description (format version, step, and per
leaf its key path from `jax.tree_util.keystr`, dtype, shape and kind). Restoring goes into
the structure of a template pytree (the real state, or `jax.eval_shape` of its constructor),
matched by key path, so parameters, optimiser state, PRNG keys (raw uint32 ones and typed
`jax.random.key` ones, stored as `jax.random.key_data`) and the step come back bit-for-bit.

Writes go to a temporary file in the same folder (named `.ckpt_....tmp`, never matching
`ckpt_*.npz`; `io.atomic_path(..., durable=True)`), fsync-ed, then `os.replace`-d into place: a crash leaves
either the old set of checkpoints or the new one, never a half-written `ckpt_*.npz`.
A checkpoint that is nevertheless unreadable (truncated copy, disk fault) is skipped by
`restore_latest` with a warning, falling back to the previous one.

Typical use in a trainer (state = {"params": ..., "opt_state": ..., "key": ..., "step": ...}):

    restored = restore_latest(run_dir, template=state)
    if restored is not None:
        state, step = restored
    ...
    save_checkpoint(run_dir, step, state, keep=3)

Under pmap, save the unreplicated state (`tree_map(lambda x: x[0], replicated)`).
"""

from __future__ import annotations

import io
import json
import os
import re
import warnings
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.util.io import DataError, atomic_path, load_error_reason

FORMAT = "jaxnerf-grid-checkpoint"
VERSION = 1
CHECKPOINT_DIR = "checkpoints"
_NAME = re.compile(r"^ckpt_(\d+)\.npz$")
_MANIFEST = "__manifest__"

__all__ = [
    "CheckpointError",
    "CorruptCheckpointError",
    "checkpoint_path",
    "list_checkpoints",
    "latest_checkpoint",
    "load_checkpoint",
    "restore_latest",
    "save_checkpoint",
]


class CheckpointError(DataError):
    """A checkpoint does not match the expected state (structure, shape, dtype)."""


class CorruptCheckpointError(CheckpointError):
    """A checkpoint file cannot be read (truncated, garbage, bad manifest)."""


# --------------------------------------------------------------------------- naming


def checkpoint_path(run_dir: str | os.PathLike, step: int) -> Path:
    """`run_dir/checkpoints/ckpt_{step:08d}.npz`."""
    return Path(run_dir) / CHECKPOINT_DIR / f"ckpt_{int(step):08d}.npz"


def list_checkpoints(run_dir: str | os.PathLike) -> list[tuple[int, Path]]:
    """All `(step, path)` of `run_dir/checkpoints/ckpt_*.npz`, oldest step first."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    if not folder.is_dir():
        return []
    found = []
    for path in folder.iterdir():
        match = _NAME.match(path.name)
        if match and path.is_file():
            found.append((int(match.group(1)), path))
    return sorted(found)


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """Path of the checkpoint with the highest step, or None when there is none."""
    found = list_checkpoints(run_dir)
    return found[-1][1] if found else None


# --------------------------------------------------------------------------- leaves


def _is_typed_key(dtype) -> bool:
    return jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key)


def _leaf_dtype(leaf):
    """dtype of a leaf (array, ShapeDtypeStruct, Python or NumPy scalar)."""
    if hasattr(leaf, "dtype"):
        return leaf.dtype
    return np.asarray(leaf).dtype


def _encode(leaf) -> tuple[np.ndarray, dict]:
    """Leaf -> (array to store, manifest entry without key)."""
    dtype = _leaf_dtype(leaf)
    if _is_typed_key(dtype):
        data = np.asarray(jax.device_get(jax.random.key_data(leaf)))
        return data, {"kind": "key", "impl": str(jax.random.key_impl(leaf)),
                      "shape": list(np.shape(leaf)), "dtype": str(data.dtype)}
    data = np.asarray(jax.device_get(leaf))
    entry = {"kind": "array", "shape": list(data.shape), "dtype": str(data.dtype)}
    if data.dtype.isbuiltin != 1:  # ml_dtypes (bfloat16, float8...): store the raw bits
        data = data.view(np.dtype(f"u{data.dtype.itemsize}"))
    return data, entry


def _decode(data: np.ndarray, entry: dict, template_leaf):
    """Stored array -> leaf of the template's kind (jax array, numpy array or Python scalar)."""
    if entry["kind"] == "key":
        return jax.random.wrap_key_data(jnp.asarray(data), impl=entry["impl"])
    dtype = jnp.dtype(entry["dtype"])
    if data.dtype != dtype:
        data = data.view(dtype)
    if isinstance(template_leaf, (bool, int, float, complex)):
        return type(template_leaf)(data.item())
    if isinstance(template_leaf, np.generic):
        return data[()]
    if isinstance(template_leaf, np.ndarray):
        return data
    return jnp.asarray(data, dtype=dtype)


def _check_leaf(key: str, entry: dict, template_leaf, path: Path) -> None:
    """Raises CheckpointError when the stored leaf cannot go where the template has one."""
    t_dtype = _leaf_dtype(template_leaf)
    t_shape = list(np.shape(template_leaf))
    if _is_typed_key(t_dtype):
        if entry["kind"] != "key":
            raise CheckpointError(f"{path}: leaf {key} is a plain {entry['dtype']} array in the file, "
                                  f"but a typed PRNG key ({t_dtype}) in the template")
        impl = str(jax.random.key_impl(template_leaf)) if not isinstance(
            template_leaf, jax.ShapeDtypeStruct) else entry["impl"]
        if impl != entry["impl"]:
            raise CheckpointError(f"{path}: leaf {key} is a {entry['impl']} key in the file, {impl} in the template")
    elif entry["kind"] == "key":
        raise CheckpointError(f"{path}: leaf {key} is a typed PRNG key in the file, "
                              f"but a {t_dtype} array in the template")
    if entry["shape"] != t_shape:
        raise CheckpointError(f"{path}: leaf {key} has shape {tuple(entry['shape'])} in the file, "
                              f"{tuple(t_shape)} in the template")
    if entry["kind"] == "array" and entry["dtype"] != str(np.dtype(t_dtype)):
        if not (isinstance(template_leaf, (bool, int, float, complex))
                and np.dtype(entry["dtype"]).kind == np.dtype(t_dtype).kind):
            raise CheckpointError(f"{path}: leaf {key} has dtype {entry['dtype']} in the file, "
                                  f"{np.dtype(t_dtype)} in the template")


# --------------------------------------------------------------------------- save


def _write_npz(handle, arrays: dict[str, Any]) -> None:
    """Writes the arrays as an uncompressed .npz to an open binary file (a test seam)."""
    np.savez(handle, **arrays)


def save_checkpoint(run_dir: str | os.PathLike, step: int, state: Any, keep: int | None = 3) -> Path:
    """Writes `state` (any pytree of arrays / PRNG keys / scalars) as the checkpoint of `step`.

    Atomic (temporary file in the same folder + flush + fsync + os.replace + fsync of the
    folder); temporary files left by an earlier writer that was killed are removed first
    (one writer per run directory is assumed). Afterwards deletes the oldest `ckpt_*.npz` so that
    `keep` remain (never the one just written); keep=None keeps all. Returns the checkpoint's path.
    """
    if int(step) < 0:
        raise ValueError(f"save_checkpoint: step must be >= 0, got {step}")
    if keep is not None and keep < 1:
        raise ValueError(f"save_checkpoint: keep must be >= 1 or None, got {keep}")
    path = checkpoint_path(run_dir, step)
    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True)

    leaves, _ = jax.tree_util.tree_flatten_with_path(state)
    arrays: dict[str, np.ndarray] = {}
    entries = []
    for index, (key_path, leaf) in enumerate(leaves):
        data, entry = _encode(leaf)
        name = f"leaf_{index:05d}"
        arrays[name] = data
        entries.append({"key": jax.tree_util.keystr(key_path), "name": name, **entry})
    manifest = {"format": FORMAT, "version": VERSION, "step": int(step), "leaves": entries}
    arrays[_MANIFEST] = np.frombuffer(json.dumps(manifest).encode("utf-8"), dtype=np.uint8)

    for stale in folder.glob(".ckpt_*.tmp"):  # left by a writer killed outright (SIGKILL)
        try:
            stale.unlink()
        except OSError:
            pass
    with atomic_path(path, durable=True) as tmp:
        with open(tmp, "wb") as handle:
            _write_npz(handle, arrays)

    if keep is not None:
        others = [p for _, p in list_checkpoints(run_dir) if p != path]
        excess = len(others) + 1 - keep
        for old in others[:max(excess, 0)]:
            try:
                old.unlink()
            except FileNotFoundError:
                pass
    return path


# --------------------------------------------------------------------------- load


def _read(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """Reads manifest and arrays, raising CorruptCheckpointError on any damage."""
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        raw = path.read_bytes()
        with np.load(io.BytesIO(raw), allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}  # reading checks each member's CRC
        manifest = json.loads(arrays.pop(_MANIFEST).tobytes().decode("utf-8"))
    except Exception as err:  # noqa: BLE001 - any failure to parse the file means damage
        # (seen: BadZipFile incl. bad CRC, NotImplementedError for a flipped compression
        # field, ValueError / KeyError / EOFError / UnicodeDecodeError / JSONDecodeError)
        raise CorruptCheckpointError(f"{path}: unreadable checkpoint ({type(err).__name__}: "
                                     f"{load_error_reason(err)})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise CorruptCheckpointError(f"{path}: not a {FORMAT} file (bad manifest)")
    if manifest.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {manifest.get('version')}, "
                              f"this code reads version {VERSION}")
    for entry in manifest["leaves"]:
        if entry["name"] not in arrays:
            raise CorruptCheckpointError(f"{path}: leaf {entry['key']} ({entry['name']}) missing from the file")
    return manifest, arrays


def _load(path: Path, template: Any) -> tuple[Any, int]:
    manifest, arrays = _read(path)
    stored = {entry["key"]: entry for entry in manifest["leaves"]}
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    wanted = [jax.tree_util.keystr(key_path) for key_path, _ in leaves]
    missing = [k for k in wanted if k not in stored]
    extra = [k for k in stored if k not in set(wanted)]
    if missing or extra:
        parts = []
        if missing:
            parts.append(f"missing from the file: {', '.join(missing[:8])}" + (" ..." if len(missing) > 8 else ""))
        if extra:
            parts.append(f"not in the template: {', '.join(extra[:8])}" + (" ..." if len(extra) > 8 else ""))
        raise CheckpointError(f"{path}: state structure does not match the template ({'; '.join(parts)})")
    restored = []
    for key, (_, template_leaf) in zip(wanted, leaves):
        entry = stored[key]
        _check_leaf(key, entry, template_leaf, path)
        restored.append(_decode(arrays[entry["name"]], entry, template_leaf))
    return jax.tree_util.tree_unflatten(treedef, restored), int(manifest["step"])


def load_checkpoint(path: str | os.PathLike, template: Any) -> Any:
    """Loads a checkpoint into the structure of `template` (a pytree whose leaves are arrays,
    `jax.ShapeDtypeStruct`s, PRNG keys or scalars). Leaves come back as the template's kind
    (jax array, numpy array, Python scalar) with the stored bits.

    Raises CorruptCheckpointError for an unreadable file, CheckpointError (naming the key and
    the file) when structure, shape, dtype or key kind differ from the template.
    """
    return _load(Path(path), template)[0]


def restore_latest(run_dir: str | os.PathLike, template: Any) -> tuple[Any, int] | None:
    """(state, step) from the newest readable checkpoint of `run_dir`, or None when there is
    no checkpoint. An unreadable newest checkpoint is skipped with a RuntimeWarning and the
    previous one is tried; if every one is unreadable, raises CorruptCheckpointError. A
    structure mismatch with the template raises CheckpointError at once (an older checkpoint
    of the same run would not fit either).
    """
    found = list_checkpoints(run_dir)
    if not found:
        return None
    failures = []
    for step, path in reversed(found):
        try:
            state, stored_step = _load(path, template)
        except CorruptCheckpointError as err:
            warnings.warn(f"{err}; falling back to an older checkpoint", RuntimeWarning, stacklevel=2)
            failures.append(str(err))
            continue
        if stored_step != step:
            warnings.warn(f"{path}: file name says step {step}, manifest says {stored_step}; "
                          f"using {stored_step}", RuntimeWarning, stacklevel=2)
        return state, stored_step
    raise CorruptCheckpointError(f"{Path(run_dir) / CHECKPOINT_DIR}: no readable checkpoint among "
                                 f"{len(found)} ({failures[0]})")
