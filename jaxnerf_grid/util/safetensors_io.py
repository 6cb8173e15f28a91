"""A tiny numpy reader / writer of the safetensors format (no `safetensors` package needed).

Layout: 8-byte little-endian unsigned header length N, N bytes of JSON header
`{name: {"dtype", "shape", "data_offsets": [begin, end]}, "__metadata__"?: {str: str}}`,
then the raw little-endian tensor bytes (offsets relative to the end of the header).
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import numpy as np

from jaxnerf_grid.util.io import DataError, atomic_write_bytes

_DTYPES: dict[str, np.dtype] = {
    "F64": np.dtype("<f8"), "F32": np.dtype("<f4"), "F16": np.dtype("<f2"),
    "I64": np.dtype("<i8"), "I32": np.dtype("<i4"), "I16": np.dtype("<i2"), "I8": np.dtype("i1"),
    "U64": np.dtype("<u8"), "U32": np.dtype("<u4"), "U16": np.dtype("<u2"), "U8": np.dtype("u1"),
    "BOOL": np.dtype("?"),
}
_NAMES = {v: k for k, v in _DTYPES.items()}


def read_header(path: str | os.PathLike) -> tuple[dict, int]:
    """Returns (header dict, byte offset of the data section)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: safetensors file not found")
    with open(path, "rb") as handle:
        raw = handle.read(8)
        if len(raw) < 8:
            raise DataError(f"{path}: too short to be a safetensors file")
        (n,) = struct.unpack("<Q", raw)
        if n > 100_000_000:
            raise DataError(f"{path}: implausible safetensors header length {n}")
        try:
            header = json.loads(handle.read(n).decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            raise DataError(f"{path}: corrupt safetensors header ({err})") from None
    return header, 8 + n


def load(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict]:
    """Reads every tensor. Returns ({name: array}, metadata). BF16 is widened to float32."""
    path = Path(path)
    header, start = read_header(path)
    metadata = header.pop("__metadata__", {}) or {}
    data = np.memmap(path, dtype=np.uint8, mode="r")
    tensors = {}
    for name, info in header.items():
        begin, end = info["data_offsets"]
        shape = tuple(info["shape"])
        raw = data[start + begin: start + end]
        if info["dtype"] == "BF16":
            bits = np.frombuffer(raw.tobytes(), dtype="<u2").astype(np.uint32) << 16
            arr = bits.view(np.float32)
        elif info["dtype"] in _DTYPES:
            arr = np.frombuffer(raw.tobytes(), dtype=_DTYPES[info["dtype"]])
        else:
            raise DataError(f"{path}: tensor {name!r} has unsupported dtype {info['dtype']}")
        if arr.size != int(np.prod(shape, dtype=np.int64)):
            raise DataError(f"{path}: tensor {name!r} has {arr.size} values for shape {shape}")
        tensors[name] = arr.reshape(shape)
    return tensors, metadata


def save(path: str | os.PathLike, tensors: dict[str, np.ndarray], metadata: dict | None = None) -> None:
    """Writes {name: array} (atomic). Supported dtypes: float16/32/64, (u)int8-64, bool."""
    header, chunks, offset = {}, [], 0
    for name in sorted(tensors):
        arr = np.ascontiguousarray(np.asarray(tensors[name]))
        dt = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
        key = _NAMES.get(np.dtype(dt).newbyteorder("<") if dt.itemsize > 1 else np.dtype(dt))
        if key is None:
            raise DataError(f"{path}: cannot store tensor {name!r} of dtype {arr.dtype}")
        blob = arr.astype(_DTYPES[key]).tobytes()
        header[name] = {"dtype": key, "shape": list(arr.shape), "data_offsets": [offset, offset + len(blob)]}
        chunks.append(blob)
        offset += len(blob)
    if metadata:
        header["__metadata__"] = {str(k): str(v) for k, v in metadata.items()}
    text = json.dumps(header, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 8)  # align the data section to 8 bytes
    atomic_write_bytes(path, struct.pack("<Q", len(text)) + text + b"".join(chunks))
