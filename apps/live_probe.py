"""Print what a live source sends: `python -m rigspace.apps.live_probe URL [--seconds S]`."""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from rigspace.apps.tools import run_tool
from rigspace.runtime.live.buffer import LiveBuffer
from rigspace.runtime.live.sources import open_source

POLL = 0.02
"""Seconds between looks at the frame count while waiting for --frames."""


def probe(
    url: str, seconds: float, every: float = 1.0, out=None, frames: int | None = None
) -> dict:
    """Listen on `url` for `seconds`, or until `frames` frames have arrived, printing one JSON
    line of status every `every` seconds and when it stops; returns the last one: status,
    counters, sample rate, and the bones seen so far."""
    out = out or sys.stdout  # looked up per call: a redirected stdout is honoured
    source = open_source(url, "probe")
    buffer = LiveBuffer(source.bones)
    source.start(buffer)
    report: dict = {}
    try:
        start = last_time = time.monotonic()
        last_samples = 0
        while True:
            line_due = min(last_time + every, start + seconds)
            while time.monotonic() < line_due and not _enough(source, frames):
                time.sleep(max(0.0, min(POLL, line_due - time.monotonic())))
            now = time.monotonic()
            counters = source.counters(now).as_dict()
            pose = buffer.pose(now)
            seen = [b for b, ok in zip(source.bones, pose.valid, strict=True) if ok]
            rate = (counters["samples"] - last_samples) / max(now - last_time, 1e-9)
            report = {
                "url": url,
                "seconds": round(now - start, 2),
                **counters,
                "frames": source.decoder.counters.frames,
                "samples_per_second": round(rate, 1),
                "bones_seen": len(seen),
                "bones": seen[:12] + (["..."] if len(seen) > 12 else []),
                "root": None
                if pose.root_position is None
                else np.round(pose.root_position, 3).tolist(),
                "transport": source.error,
            }
            print(json.dumps(report), file=out, flush=True)
            last_time, last_samples = now, counters["samples"]
            if now - start >= seconds or _enough(source, frames):
                return report
    finally:
        source.stop()


def _enough(source, frames: int | None) -> bool:
    """Whether `frames` frames have arrived (never, without a count)."""
    return frames is not None and source.decoder.counters.frames >= frames


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog=prog or "python -m rigspace.apps.live_probe", description=__doc__
    )
    parser.add_argument("url", help="a live-source URL, such as vmc://127.0.0.1:39539")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long to listen")
    parser.add_argument(
        "--frames", type=int, metavar="N", help="stop once N frames have arrived (within --seconds)"
    )
    args = parser.parse_args(argv)
    return run_tool(parser.prog, lambda: probe(args.url, args.seconds, frames=args.frames))


if __name__ == "__main__":
    raise SystemExit(main())
