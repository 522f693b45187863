"""The numpy safetensors reader and writer: round trip, the reference library, damaged files."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from rigspace.sdk.weights import WeightsError, read_safetensors, write_safetensors

TENSORS = {
    "b.weight": np.arange(24, dtype=np.float32).reshape(2, 3, 4),
    "a.bias": np.array([1.5, -2.0], np.float16),
    "count": np.array(7, np.int64),
    "empty": np.zeros((0, 3), np.float32),
}


def test_round_trip_keeps_names_dtypes_shapes_values_and_metadata(tmp_path):
    path = tmp_path / "w.safetensors"
    write_safetensors(path, TENSORS, {"step": "12"})
    tensors, metadata = read_safetensors(path)
    assert metadata == {"step": "12"}
    assert sorted(tensors) == sorted(TENSORS)
    for name, value in TENSORS.items():
        assert tensors[name].dtype == value.dtype and tensors[name].shape == value.shape
        np.testing.assert_array_equal(tensors[name], value)
    (size,) = struct.unpack("<Q", path.read_bytes()[:8])
    assert size % 8 == 0  # the data starts aligned, as the reference writes it


def test_the_reference_library_reads_ours_and_we_read_its(tmp_path):
    numpy_io = pytest.importorskip("safetensors.numpy")
    ours = tmp_path / "ours.safetensors"
    write_safetensors(ours, TENSORS, {"k": "v"})
    loaded = numpy_io.load_file(str(ours))
    for name, value in TENSORS.items():
        np.testing.assert_array_equal(loaded[name], value)
    theirs = tmp_path / "theirs.safetensors"
    numpy_io.save_file({k: np.ascontiguousarray(v) for k, v in TENSORS.items()}, str(theirs))
    tensors, _ = read_safetensors(theirs)
    for name, value in TENSORS.items():
        np.testing.assert_array_equal(tensors[name], value)


def _header_file(tmp_path, header: dict, body: bytes) -> object:
    text = json.dumps(header).encode()
    path = tmp_path / "bad.safetensors"
    path.write_bytes(struct.pack("<Q", len(text)) + text + body)
    return path


@pytest.mark.parametrize(
    "damage",
    [
        "truncated",
        "length past the end",
        "not json",
        "offsets past the body",
        "size does not match the shape",
        "unknown dtype",
    ],
)
def test_a_damaged_file_is_an_error_naming_it(tmp_path, damage):
    good = tmp_path / "good.safetensors"
    write_safetensors(good, {"w": np.ones((2, 2), np.float32)})
    data = good.read_bytes()
    entry = {"dtype": "F32", "shape": [2, 2], "data_offsets": [0, 16]}
    path = tmp_path / "bad.safetensors"
    if damage == "truncated":
        path.write_bytes(data[:5])
    elif damage == "length past the end":
        path.write_bytes(struct.pack("<Q", 10**6) + data[8:])
    elif damage == "not json":
        path.write_bytes(struct.pack("<Q", 4) + b"{{{{" + bytes(16))
    elif damage == "offsets past the body":
        path = _header_file(tmp_path, {"w": {**entry, "data_offsets": [0, 64]}}, bytes(16))
    elif damage == "size does not match the shape":
        path = _header_file(tmp_path, {"w": {**entry, "shape": [3, 3]}}, bytes(16))
    else:
        path = _header_file(tmp_path, {"w": {**entry, "dtype": "Q99"}}, bytes(16))
    with pytest.raises(WeightsError) as info:
        read_safetensors(path)
    assert str(path) in str(info.value) and "Fix:" in str(info.value)
