"""Peak resident memory of the runtime rendering N characters, measured in a fresh process.

    peak_rss(8, size=256)          # runs `measure` in a child, returns its JSON
    python -m rigspace.apps.memory --characters 8 --size 256 --precision fp32 --frames 4

The child renders the previs sample scene (N - 1 more heroes referenced from /World/Hero
into a temporary layer) and prints one JSON line: peak resident set size (KiB; VmHWM, see
_max_rss_kib) at start, after importing the runtime, after creating the Engine, and after
the frames, plus the median milliseconds per frame. A fresh process per measurement,
because a peak only ever grows: it cannot be reset between runs in one process.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any


def _max_rss_kib() -> int:
    """This process's peak resident set size in KiB.

    Linux's VmHWM, not ru_maxrss: exec keeps the parent's high-water mark in ru_maxrss, so a
    child of a large process (pytest with torch loaded: about 290 MiB, measured) would read
    the parent's peak from its first line. VmHWM belongs to the new address space alone.
    ru_maxrss (KiB on Linux) is the fallback where /proc is missing.
    """
    status = Path("/proc/self/status")
    if status.is_file():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def measure(characters: int, size: int, precision: str, frames: int) -> dict[str, Any]:
    """The child's measurement (run it in a fresh process: see the module doc)."""
    rss = {"start": _max_rss_kib()}
    import numpy as np

    from rigspace.bench.frame_stages import TIMES
    from rigspace.bench.scenes import PREVIS, crowd_scene
    from rigspace.runtime.engine import Engine, EngineSettings

    rss["imports"] = _max_rss_kib()
    with tempfile.TemporaryDirectory() as tmp:
        scene = PREVIS if characters == 1 else crowd_scene(Path(tmp), characters)
        engine = Engine(scene, EngineSettings(width=size, height=size, precision=precision))
        rss["engine"] = _max_rss_kib()
        try:
            engine.render(float(TIMES[0]))  # warm-up: sessions, renderer buffers
            reports = [engine.render(float(t)).report.to_json() for t in TIMES[1 : frames + 1]]
        finally:
            engine.close()
        rss["frames"] = _max_rss_kib()
    evaluated = [
        sum(c["decision"] in ("evaluated", "reused") for c in r["characters"]) for r in reports
    ]
    return {
        "characters": characters,
        "size": size,
        "precision": precision,
        "frames": len(reports),
        "peak_rss_kib": rss,
        "rss_source": "VmHWM" if Path("/proc/self/status").is_file() else "ru_maxrss",
        "peak_rss_mib": {k: v / 1024 for k, v in rss.items()},
        "ms_per_frame": 1e3 * float(np.median([r["seconds"]["total"] for r in reports])),
        "characters_drawn": min(evaluated),
    }


CHILD = (
    "import json, sys; from rigspace.bench.memory import measure; a = sys.argv; "
    "print(json.dumps(measure(int(a[1]), int(a[2]), a[3], int(a[4]))), flush=True)"
)
"""The child process's program: `measure` with peak_rss's arguments, its JSON on one line."""


def peak_rss(
    characters: int, size: int = 256, precision: str = "fp32", frames: int = 4
) -> dict[str, Any]:
    """Run `measure` in a fresh Python process and return its result."""
    command = [sys.executable, "-c", CHILD, str(characters), str(size), precision, str(frames)]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(
            f"{' '.join(command)} exited with {done.returncode}:\n{done.stderr[-2000:]}"
        )
    return json.loads(done.stdout.strip().splitlines()[-1])
