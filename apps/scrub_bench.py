"""`python -m rigspace.apps.scrub_bench SCENE`: scrub-to-paint in a real browser, and server ms.

Serves the scene as `rigspace view` does, opens the page in headless Chromium (Debian's
/usr/bin/chromium through playwright), scrubs the timeline to `--scrubs` seeded random times
one after another, and reports, measured in the page from the input event to the frame
painted (after requestAnimationFrame): the first paint (the scrub preview, or the cached
full frame) and the full-quality paint, p50 and p95; then the same times again (cached).
The server's ms per frame come from the frames' headers (render + encode).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from rigspace.apps.view import build, in_background
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.files import write_atomic

CHROMIUM = "/usr/bin/chromium"
SCRUB = """t => { const s = document.getElementById('scrub'); s.value = t;
  s.dispatchEvent(new Event('input')); }"""
PAINTED = """t => { const h = window.rigspaceView.viewport.last;
  return h && h.time === t && h.quality === 'full'; }"""


def _stats(values: list[float]) -> str:
    if not values:
        return "n/a"
    a = np.asarray(values)
    return f"p50 {np.percentile(a, 50):6.1f} ms  p95 {np.percentile(a, 95):6.1f} ms  (n={a.size})"


def measure(scene: str, scrubs: int, seed: int, resolution: tuple[int, int]) -> dict:
    from playwright.sync_api import sync_playwright

    viewer = build(scene, resolution=resolution)
    if viewer.frames.error:
        raise RigspaceError(f"No frames to measure: {viewer.frames.error}", "pick a valid scene.")
    server, url = in_background(viewer)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1600, "height": 950})
            page.goto(url)
            start = viewer.scene.stage.GetStartTimeCode()
            end = viewer.scene.stage.GetEndTimeCode()
            page.wait_for_function(PAINTED, arg=start, timeout=120_000)
            rng = np.random.default_rng(seed)
            times = [float(t) for t in rng.choice(np.arange(start + 1, end + 1), scrubs, False)]
            for t in times:
                page.evaluate(SCRUB, t)
                page.wait_for_function(PAINTED, arg=t, timeout=60_000)
            fresh = page.evaluate("window.rigspaceView.paints.slice()")
            for t in times[: max(scrubs // 2, 1)]:  # the same times again: the cache answers
                page.evaluate(SCRUB, t)
                page.wait_for_function(PAINTED, arg=t, timeout=60_000)
            again = page.evaluate("window.rigspaceView.paints")[len(fresh) :]
            browser.close()
    finally:
        server.should_exit = True
        viewer.close()
    first: dict[float, float] = {}
    full, server_preview, server_full = [], [], []
    for paint in fresh:
        if paint["time"] == start:
            continue
        first.setdefault(paint["time"], paint["ms"])  # the first frame painted for that time
        if paint["cached"]:
            continue
        if paint["quality"] == "preview":
            server_preview.append(paint["server_ms"])
        else:
            full.append(paint["ms"])
            server_full.append(paint["server_ms"])
    cached = [p["ms"] for p in again if p["cached"] and p["quality"] == "full"]
    first_ms = list(first.values())
    return {
        "scene": scene,
        "resolution": list(resolution),
        "scrubs": scrubs,
        "first_paint_ms": first_ms,
        "full_paint_ms": full,
        "cached_paint_ms": cached,
        "server_preview_ms": server_preview,
        "server_full_ms": server_full,
        "load_average": os.getloadavg()[0],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rigspace.apps.scrub_bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("scene")
    parser.add_argument("--scrubs", type=int, default=30, help="random times to scrub to")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="also write the raw numbers here")
    args = parser.parse_args(argv)
    try:
        result = measure(args.scene, args.scrubs, args.seed, (640, 360))
    except RigspaceError as exc:
        print(f"view bench: error: {exc}", file=sys.stderr)
        return 2
    load = os.getloadavg()[0]
    print(
        f"scrub-to-paint in Chromium, {args.scene} at 640x360, {args.scrubs} scrubs "
        f"({os.cpu_count()} CPUs, load average {load:.1f} at the end):"
    )
    print(f"  first paint (320x180 preview)  {_stats(result['first_paint_ms'])}")
    print(f"  full paint (640x360)           {_stats(result['full_paint_ms'])}")
    print(f"  cached full frame again        {_stats(result['cached_paint_ms'])}")
    print("server ms per frame (render + JPEG):")
    print(f"  preview 320x180                {_stats(result['server_preview_ms'])}")
    print(f"  full 640x360                   {_stats(result['server_full_ms'])}")
    if args.json:
        write_atomic(args.json, json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
