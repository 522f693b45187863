"""`python -m rigspace.apps.quantize MODEL DATASET [--check-only]`: re-quantise a bundle's int8
graphs from its fp32 graphs and re-check them, or only re-check them (rigspace.train.quantize),
and print the per-level table."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rigspace.train.quantize import format_level_table, recheck_bundle, requantize_bundle


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=requantize_bundle.__doc__)
    parser.add_argument("bundle", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument(
        "--check-only", action="store_true", help="re-check the int8 graphs, do not re-quantise"
    )
    args = parser.parse_args(argv)
    if args.check_only:
        result = recheck_bundle(args.bundle, args.dataset)
    else:
        result = requantize_bundle(args.bundle, args.dataset)
    print(format_level_table({int(r): e for r, e in result["levels"].items()}))
    print(json.dumps({"offered_levels": result["offered_levels"]}))
    for name, graph in result["graphs"].items():
        print(
            name,
            "ok" if graph["ok"] else "FAILED",
            "offered" if graph["offered"] else "",
            graph["not_offered"],
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
