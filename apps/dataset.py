"""`rigspace dataset pack | cache`: tar shards of a dataset folder (capture/pack.py), or its
samples decoded once into memory-mapped arrays (capture/cache.py)."""

from __future__ import annotations

import argparse
import sys

from rigspace.sdk.cli import CommandSpec

DESCRIPTION = """\
Work on finished capture datasets. `pack` writes a dataset folder as WebDataset-style tar
shards (per sample its EXR and its parameter row, keyed by sample id) with index.json, for
datasets larger than memory and for training on many nodes: `rigspace train SHARDS ...`
reads them as a stream (docs/scale.md). `cache` decodes every sample once into DATASET/cache
(the EXRs' own precisions, cropped to the character; `rigspace train` does this itself
unless --no-cache), so training and evaluation read arrays instead of decoding EXRs.
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
    cache = actions.add_parser(
        "cache",
        help="decode every sample once into DATASET/cache (rebuilt when the samples change)",
        description=DESCRIPTION,
    )
    cache.add_argument("dataset", help="a finished dataset folder written by `rigspace capture`")
    cache.add_argument(
        "--workers", type=int, default=0, help="decoding processes (default: one per core)"
    )
    cache.add_argument("--force", action="store_true", help="rebuild even if it is up to date")


def run_cache(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    import numpy as np

    from rigspace.capture.cache import build_cache, stale_reason
    from rigspace.capture.dataset import read_manifest

    folder = Path(args.dataset)
    manifest = read_manifest(folder)
    why = stale_reason(folder, manifest)
    if why is None and not args.force:
        print(f"the decoded cache of {folder} is up to date")
        return 0
    with np.load(folder / "params.npz", allow_pickle=False) as table:
        paths = [str(p) for p in table["path"]]
    start = time.monotonic()
    cache = build_cache(folder, manifest, paths, workers=args.workers)
    seconds = time.monotonic() - start
    print(
        f"decoded {len(cache)} samples in {seconds:.1f} s ({len(cache) / seconds:.0f} samples/s) "
        f"into {cache.root}: {cache.info['bytes'] / 2**30:.2f} GiB, "
        f"{cache.info['stored_pixels'] / (len(cache) * cache.size**2):.0%} of the pixels"
    )
    return 0


def run(args: argparse.Namespace) -> int:
    if args.action == "cache":
        return run_cache(args)
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
    help="pack a capture dataset into streamable tar shards, or decode it once into a cache",
    description=DESCRIPTION,
    add_arguments=add_arguments,
    run=run,
)
