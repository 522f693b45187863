"""Read and write safetensors files with numpy alone: the bundle's network weights.

The format (https://huggingface.co/docs/safetensors, "Format"): an 8-byte little-endian
header length N, N bytes of JSON (`{name: {"dtype", "shape", "data_offsets": [begin, end]},
"__metadata__": {str: str}}`, offsets relative to the byte after the header), then the raw
little-endian tensor bytes. It holds no code, so reading one cannot run any (unlike a
pickle); a damaged file is a WeightsError naming what is wrong. numpy alone, so a runtime
without torch or the `safetensors` package reads it (tested against that package).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.files import replacing

DTYPES: dict[str, np.dtype] = {
    "F32": np.dtype("<f4"),
    "F16": np.dtype("<f2"),
    "F64": np.dtype("<f8"),
    "I64": np.dtype("<i8"),
    "I32": np.dtype("<i4"),
    "U8": np.dtype("u1"),
}
MAX_HEADER = 100 * 2**20
"""The safetensors reference refuses headers over 100 MB (a damaged length field)."""


class WeightsError(RigspaceError):
    """A weights file that cannot be read."""


def write_safetensors(
    path: str | Path, tensors: dict[str, np.ndarray], metadata: dict[str, str] | None = None
) -> None:
    """Write `tensors` (name -> array) to `path`, atomically (a temporary file, then rename)."""
    path = Path(path)
    names = {dtype: name for name, dtype in DTYPES.items()}
    header: dict[str, object] = {"__metadata__": dict(metadata)} if metadata else {}
    blobs, offset = [], 0
    for name in sorted(tensors):
        array = np.asarray(tensors[name])
        dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
        if dtype not in names:
            raise ValueError(f"tensor {name!r} has dtype {array.dtype}; write one of {DTYPES}")
        blob = np.ascontiguousarray(array, dtype=dtype).tobytes()
        header[name] = {
            "dtype": names[dtype],
            "shape": list(array.shape),
            "data_offsets": [offset, offset + len(blob)],
        }
        blobs.append(blob)
        offset += len(blob)
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # the data starts 8-byte aligned, as the reference writes
    with replacing(path) as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<Q", len(text)))
        f.write(text)
        for blob in blobs:
            f.write(blob)


def read_safetensors(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """(name -> array, metadata) of a safetensors file; a WeightsError for a damaged one."""
    path = Path(path)
    fix = "re-export the model bundle with `rigspace train`, or restore the file."
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise WeightsError(f"Weights file {path} cannot be read ({exc}).", fix) from exc
    if len(data) < 8:
        raise WeightsError(f"Weights file {path} is truncated ({len(data)} bytes).", fix)
    (size,) = struct.unpack("<Q", data[:8])
    if size > MAX_HEADER or 8 + size > len(data):
        raise WeightsError(
            f"Weights file {path} is damaged: its header says {size} bytes, the file has "
            f"{len(data) - 8} after the length.",
            fix,
        )
    try:
        header = json.loads(data[8 : 8 + size])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise WeightsError(f"Weights file {path} has a damaged header ({exc}).", fix) from exc
    if not isinstance(header, dict):
        raise WeightsError(f"Weights file {path} has a damaged header (not an object).", fix)
    metadata = header.pop("__metadata__", None) or {}
    body = memoryview(data)[8 + size :]
    tensors: dict[str, np.ndarray] = {}
    for name, entry in header.items():
        try:
            dtype = DTYPES[entry["dtype"]]
            shape = tuple(int(s) for s in entry["shape"])
            begin, end = (int(o) for o in entry["data_offsets"])
        except (KeyError, TypeError, ValueError) as exc:
            raise WeightsError(
                f"Weights file {path}: tensor {name!r} has a damaged entry {entry!r} "
                f"({type(exc).__name__}: {exc}).",
                fix,
            ) from exc
        count = int(np.prod(shape, dtype=np.int64))
        if not 0 <= begin <= end <= len(body) or end - begin != count * dtype.itemsize:
            raise WeightsError(
                f"Weights file {path}: tensor {name!r} ({entry['dtype']} {list(shape)}) has "
                f"byte range {begin}..{end} in a body of {len(body)} bytes.",
                fix,
            )
        tensors[name] = np.frombuffer(body[begin:end], dtype=dtype).reshape(shape).copy()
    return tensors, {str(k): str(v) for k, v in metadata.items()}
