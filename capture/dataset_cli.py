"""`rigspace dataset pack`: turn a dataset folder into streamable tar shards (capture/pack.py)."""

from __future__ import annotations

import argparse
import sys

from rigspace.sdk.cli import CommandSpec

DESCRIPTION = """\
Work on finished capture datasets. `pack` writes a dataset folder as WebDataset-style tar
shards (per sample its EXR and its parameter row, keyed by sample id) with index.json, for
datasets larger than memory and for training on many nodes: `rigspace train SHARDS ...`
reads them as a stream (docs/scale.md).
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    pack = actions.add_parser(
        "pack", help="write a dataset folder as tar shards with an index", description=DESCRIPTION
    )
    pack.add_argument("dataset", help="a finished dataset folder written by `rigspace capture`")
    pack.add_argument("--out", required=True, help="folder for the shards (new or empty)")
    pack.add_argument(
        "--samples-per-shard",
        type=int,
        default=1000,
        help="samples per tar shard (default 1000: about 170 MB at 256x256)",
    )


def run(args: argparse.Namespace) -> int:
    from rigspace.capture.pack import pack

    index = pack(args.dataset, args.out, args.samples_per_shard, progress=True)
    counts = ", ".join(f"{split} {n}" for split, n in index["counts"].items())
    print(
        f"packed {sum(index['counts'].values())} samples ({counts}) into "
        f"{len(index['shards'])} shards, {index['bytes'] / 2**20:.1f} MiB, in {args.out}",
        file=sys.stdout,
    )
    return 0


COMMAND = CommandSpec(
    name="dataset",
    help="pack a capture dataset into streamable tar shards",
    description=DESCRIPTION,
    add_arguments=add_arguments,
    run=run,
)
