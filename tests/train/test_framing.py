"""How much of the frame the character fills (python -m rigspace.apps.framing)."""

from __future__ import annotations

import numpy as np

from rigspace.apps import framing


def test_centred_extent_is_the_square_around_the_frame_centre_holding_the_mask():
    mask = np.zeros((8, 8), np.float32)
    assert framing.centred_extent(mask) is None
    mask[3:5, 3:5] = 1  # the central 2x2 pixels: a quarter of the side
    assert framing.centred_extent(mask) == 0.25
    mask[0, 4] = 1  # one pixel on the top edge: the square must reach the whole frame
    assert framing.centred_extent(mask) == 1.0
    mask[:] = 0
    mask[2, 6] = 0.4  # below the coverage threshold: not the character
    mask[5, 5] = 1  # 1.5 pixels from the centre (3.5, 3.5): a 4-pixel square
    assert framing.centred_extent(mask) == 0.5


def test_measure_reads_every_split_of_a_capture(tiny_dataset, capsys):
    m = framing.measure(str(tiny_dataset), samples=16)
    assert m["samples"] == 16 and 0 < m["median"] <= m["p95"] <= m["max"] <= 1
    assert framing.main([str(tiny_dataset), "--samples", "8"]) == 0
    assert "linear resolution before it crops the widest pose" in capsys.readouterr().out
