"""Capture throughput per renderer and resolution, with the time split per sample.

    python -m rigspace.apps.capture_rates [--scene S] [--character P] [--frames A:B] [--json F]

The captures run in rigspace.capture.rates (the bench's capture part runs them too).
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

from rigspace.capture.rates import DEFAULT_CHARACTER, DEFAULT_SCENE, run
from rigspace.sdk.files import write_atomic
from rigspace.sdk.render import renderer_plugins


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--character", default=DEFAULT_CHARACTER)
    parser.add_argument("--frames", default="0:47", help="time codes A:B")
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--renderers", nargs="+", default=["gl", "embree"])
    parser.add_argument("--json", type=Path, help="also write the raw numbers here")
    args = parser.parse_args(argv)
    first, last = (float(x) for x in args.frames.split(":"))
    usable = [r for r in args.renderers if r in renderer_plugins()]
    print(
        f"# capture throughput: {args.scene.name} {args.character}, frames {args.frames}, "
        f"{args.views} views, {platform.processor() or platform.machine()}"
    )
    print(
        "| renderer | size | samples/s | pose ms | render ms | draw ms | read-back ms | "
        "write ms | KiB/sample |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    rows = run(args.scene, args.character, (first, last), args.views, args.sizes, usable)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(
            args.json,
            json.dumps(
                {"command": "python -m rigspace.apps.capture_rates", "rows": rows}, indent=2
            ),
        )


if __name__ == "__main__":
    main()
