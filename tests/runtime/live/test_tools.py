"""The send and probe tools (the cores of `rigspace live send` and `rigspace live probe`)."""

from __future__ import annotations

import io
import json
import threading
import time

import pytest

from rigspace.apps import live_probe as probe
from rigspace.apps import live_send as send
from tests.conftest import free_port
from tests.runtime.live.conftest import CMU_CLIP, started_source, wait_for


@pytest.mark.slow
def test_probe_reports_a_vmc_sender():
    """The sender streams (looping) before and after the probe, which listens until 400 frames
    arrived (a timed window before, which a busy machine could leave empty)."""
    from rigspace.runtime.live.decoders.bvh import read_bvh

    port = free_port()
    skeleton, motion, frame_time = read_bvh(CMU_CLIP)
    clip = send.humanoid_clip(skeleton, *skeleton.pose(motion), frame_time)
    stop = threading.Event()
    sender = threading.Thread(
        target=send.send_vmc, args=(f"vmc://127.0.0.1:{port}", clip, 4.0, True, stop), daemon=True
    )
    sender.start()
    out = io.StringIO()
    try:
        result = probe.probe(f"vmc://127.0.0.1:{port}", 120.0, 0.25, out, frames=400)
    finally:
        stop.set()
        sender.join()
    lines = [json.loads(line) for line in out.getvalue().splitlines()]
    assert result == lines[-1] and result["frames"] >= 400
    seen = max(lines, key=lambda r: r["bones_seen"])
    assert seen["bones_seen"] == 23  # the 22 mapped humanoid bones and Root
    assert any(r["samples_per_second"] > 0 and r["status"] == "connected" for r in lines)
    assert result["malformed"] == 0


def test_send_serves_bvh_tcp_clients(free_tcp_port):
    url = f"bvh+tcp://127.0.0.1:{free_tcp_port}"
    codes = []
    # The client first: it connects the moment the server listens.
    source, _ = started_source(f"{url}?skeleton={CMU_CLIP}&retry=0.05", "neuron")
    assert wait_for(lambda: source.error is not None)
    server = threading.Thread(
        target=lambda: codes.append(
            send.main([url, "--bvh", str(CMU_CLIP), "--speed", "8", "--seconds", "1.5"])
        )
    )
    server.start()
    try:
        assert wait_for(lambda: source.decoder.counters.frames >= 20)
    finally:
        source.stop()
        server.join()
    assert codes == [0] and source.decoder.counters.malformed == 0


def test_tool_errors_are_one_line(capsys):
    assert send.main(["osc://127.0.0.1:1", "--bvh", str(CMU_CLIP)]) == 2
    assert "not a URL this sender speaks" in capsys.readouterr().err
    assert send.main(["vmc://127.0.0.1:1", "--bvh", "missing.bvh"]) == 2
    assert "missing.bvh cannot be read" in capsys.readouterr().err
    assert probe.main(["nope://x", "--seconds", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "no live source handles the scheme 'nope'" in err and "Traceback" not in err


def test_send_seconds_count_from_the_first_frame(monkeypatch, capsys):
    """A slow preparation (the clip re-expressed on HumanBodyBones, slow on a loaded machine)
    must not eat --seconds, nor may a busy machine: the sender sends the frames of the time
    asked (0.3 s at 120 Hz: 36), catching up when held back."""
    prepare = send.humanoid_clip

    def slow(*args, **kwargs):
        time.sleep(0.5)
        return prepare(*args, **kwargs)

    monkeypatch.setattr(send, "humanoid_clip", slow)
    url = f"vmc://127.0.0.1:{free_port()}"
    assert send.main([url, "--bvh", str(CMU_CLIP), "--seconds", "0.3"]) == 0
    sent = int(capsys.readouterr().out.split()[1])
    assert sent == 36
