"""`python -m rigspace.apps.memory [--characters N] [--size S] [--precision P] [--frames F]`:
peak resident memory of the runtime rendering N characters, in this process
(rigspace.bench.memory.measure; the bench runs it in a fresh process per measurement)."""

from __future__ import annotations

import argparse
import json

from rigspace.bench.memory import measure

DESCRIPTION = (
    "Peak resident memory of the runtime rendering N characters, measured in a fresh process."
)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=DESCRIPTION)
    parser.add_argument("--characters", type=int, default=1)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--precision", choices=("fp32", "int8"), default="fp32")
    parser.add_argument("--frames", type=int, default=4)
    args = parser.parse_args(argv)
    if args.characters < 1 or args.frames < 1:
        parser.error("--characters and --frames must be at least 1")
    result = measure(args.characters, args.size, args.precision, args.frames)
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
