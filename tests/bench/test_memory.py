"""bench/memory.py: peak RSS of the runtime in a fresh process, 1 and 8 characters."""

from __future__ import annotations

import pytest

from rigspace.bench.memory import peak_rss

MIB = 1024
"""ru_maxrss is in KiB on Linux."""
PER_CHARACTER_KIB = 32 * MIB
"""Extra heroes share the bundle's sessions; each adds its rig and layer buffers (about 13
MiB each at 64x64 when measured), far below a bundle's own load."""


@pytest.mark.slow
def test_peak_rss_grows_mildly_with_characters():
    one = peak_rss(1, size=64, frames=2)
    eight = peak_rss(8, size=64, frames=2)
    for result, n in ((one, 1), (eight, 8)):
        rss = result["peak_rss_kib"]
        # start < imports: the child's own peak, not the parent's (ru_maxrss survives exec)
        assert 0 < rss["start"] < rss["imports"] <= rss["engine"] <= rss["frames"]
        assert result["characters_drawn"] == n  # every hero in view, so each ran its network
        assert result["ms_per_frame"] > 0 and result["frames"] == 2
    grown = eight["peak_rss_kib"]["frames"] - one["peak_rss_kib"]["frames"]
    assert -8 * MIB < grown < 7 * PER_CHARACTER_KIB
