"""sdk.files: a file replaced in one step, through a hidden temporary unique per call."""

from __future__ import annotations

import threading

import pytest

from rigspace.capture.dataset import clean_temporaries
from rigspace.sdk.files import replacing, temporary_beside, write_atomic


def test_write_atomic_writes_bytes_and_text_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "report.json"
    assert write_atomic(path, "{}\n") == path
    assert path.read_bytes() == b"{}\n"
    write_atomic(path, b"\x00\x01")
    assert path.read_bytes() == b"\x00\x01"
    write_atomic(path, "é")  # text is UTF-8
    assert path.read_bytes() == "é".encode()
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]


def test_the_temporary_is_hidden_beside_the_target_and_unique_per_call(tmp_path):
    names = [temporary_beside(tmp_path / "manifest.json") for _ in range(3)]
    assert len(set(names)) == 3
    for name in names:
        assert name.parent == tmp_path and name.name.startswith(".manifest.json.")
        assert name.match(".*.tmp*")  # what capture's clean_temporaries removes
    assert temporary_beside(tmp_path / "a.exr", ".exr").name.endswith(".tmp.exr")


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "capsules.json"
    path.write_text("old")
    with pytest.raises(RuntimeError), replacing(path) as tmp:
        tmp.write_text("half of the new")
        raise RuntimeError("the writer failed")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["capsules.json"]


def test_replacing_hands_a_path_with_the_suffix_a_writer_needs(tmp_path):
    path = tmp_path / "graph.onnx"
    with replacing(path, ".onnx", durable=False) as tmp:
        assert tmp.suffix == ".onnx" and tmp != path
        tmp.write_bytes(b"graph")
    assert path.read_bytes() == b"graph"


def test_threads_writing_one_file_never_share_a_temporary(tmp_path):
    """A temporary named by the process alone (".NAME.PID.tmp") is shared by two threads of one
    process: one renames it away under the other. Every write here must succeed whole."""
    path = tmp_path / "run.json"
    errors: list[BaseException] = []

    def writer(k: int) -> None:
        try:
            for _ in range(25):
                write_atomic(path, str(k) * 1000)
        except BaseException as exc:  # collected and asserted below
            errors.append(exc)

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    text = path.read_text()
    assert len(set(text)) == 1 and len(text) == 1000  # one writer's content, whole
    assert [p.name for p in tmp_path.iterdir()] == ["run.json"]


def test_what_a_killed_writer_leaves_is_cleaned_by_capture(tmp_path):
    left = temporary_beside(tmp_path / "items" / "00_walk.npz")
    left.parent.mkdir()
    left.write_bytes(b"half")
    assert clean_temporaries(tmp_path) == 1 and not left.exists()
