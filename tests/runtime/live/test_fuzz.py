"""The fuzz command: random and mutated bytes through every decoder, nothing escapes."""

from __future__ import annotations

import logging

import pytest

from rigspace.apps.live_fuzz import fuzz, main
from rigspace.runtime.live.decoders.vmc import VmcDecoder


@pytest.mark.parametrize("name", ["vmc", "bvh", "ximu3", "evdev"])
def test_fuzz_decoder(name):
    result = fuzz(name, 60_000, seed=11)
    assert result["failures"] == []
    assert result["bytes"] >= 60_000
    assert result["malformed"] > 0 and result["frames"] > 0  # both paths were exercised


def test_fuzz_command_prints_counts(capsys):
    assert main(["--bytes", "20000", "--decoder", "ximu3"]) == 0
    out = capsys.readouterr().out
    assert "decoder=ximu3" in out and "failures=0" in out and "peak RSS" in out


def test_garbage_does_not_flood_the_log(caplog):
    with caplog.at_level(logging.DEBUG):
        decoder = VmcDecoder()
        for _ in range(20):
            decoder.feed(b"#bundle\x00" + b"\x00" * 8 + b"\x00\x00\x00\x08garbage!", 0.0)
    assert decoder.counters.packets == 20
    assert not [r for r in caplog.records if "pythonosc" in r.pathname]
