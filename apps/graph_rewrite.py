"""`python -m rigspace.apps.graph_rewrite BUNDLE [--check]`: rewrite an exported bundle's graphs
into the faster form the current export writes (rigspace.train.graph_rewrite says why)."""

from __future__ import annotations

import argparse
import sys

from rigspace.sdk.bundle import BundleError
from rigspace.train.graph_rewrite import rewrite_bundle

DESCRIPTION = "Rewrite an exported bundle's graphs into the faster form the current export writes."


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.graph_rewrite", description=DESCRIPTION
    )
    parser.add_argument("bundle", help="a model bundle folder (rigspace train --out)")
    parser.add_argument(
        "--check", action="store_true", help="only list the graphs it would rewrite"
    )
    args = parser.parse_args(argv)
    try:
        changed = rewrite_bundle(args.bundle, dry_run=args.check)
    except BundleError as exc:  # a manifest a reader refuses: said, and nothing rewritten
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 1
    verb = "would rewrite" if args.check else "rewrote"
    print(
        f"{args.bundle}: {verb} {len(changed)} graphs"
        + (f": {', '.join(changed)}" if changed else "")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
