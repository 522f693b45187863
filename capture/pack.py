"""Pack a dataset folder into streamable tar shards with an index (`rigspace dataset pack`).

Layout of a shards folder:
    index.json              format, the dataset's manifest, and per shard: file, split,
                            count, sample ids (as [first, stop) ranges), bytes, sha256
    shards/<split>-<n>.tar  WebDataset-style: per sample <id>.exr (the captured EXR, byte for
                            byte) then <id>.npz (its params.npz row, every column)
    manifest.json, params.npz, capsules.json, contact_sheet.png    copied from the dataset

A sample's id is its row in params.npz (9 digits); a shard holds consecutive samples of one
split. Tar headers carry no time, owner or mode of the host, so packing the same dataset
twice gives the same bytes (and sha256). Shards are written atomically and index.json last:
a folder without index.json is an unfinished pack, which packing again replaces. Training
reads a shards folder as a stream (train/stream.py) wherever it reads a dataset folder; the
copied manifest and parameter table keep export and `rigspace eval` able to read the rig
rows without the images.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import sys
import tarfile
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from rigspace.capture import dataset as ds
from rigspace.capture.ring import SPLITS
from rigspace.sdk.files import replacing, write_atomic

INDEX_FILE = "index.json"
SHARDS_FOLDER = "shards"
FORMAT = "rigspace.shards"
FORMAT_VERSION = 1
SAMPLES_PER_SHARD = 1000
"""Default: about 170 MB per shard at the paper's 256x256 (170 KB a sample), within the
100 MB - 1 GB that object stores and sequential readers handle best."""
COPIED = (ds.MANIFEST_FILE, ds.PARAMS_FILE, "capsules.json", ds.CONTACT_SHEET, ds.CHARTS_FILE)
KEY_DIGITS = 9


def sample_key(row: int) -> str:
    return f"{row:0{KEY_DIGITS}d}"


def ranges(rows: np.ndarray) -> list[list[int]]:
    """Sorted ids as [first, stop) runs: compact for the consecutive rows a shard holds."""
    if len(rows) == 0:
        return []
    breaks = np.flatnonzero(np.diff(rows) != 1) + 1
    return [[int(run[0]), int(run[-1]) + 1] for run in np.split(rows, breaks)]


def _member(name: str, data: bytes) -> tuple[tarfile.TarInfo, io.BytesIO]:
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode = len(data), 0, 0o644
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    return info, io.BytesIO(data)


def write_shard(
    path: Path,
    folder: Path,
    table: dict[str, np.ndarray],
    rows: np.ndarray,
    bar: tqdm | None = None,
) -> dict[str, Any]:
    """One shard of `rows` (atomically), each sample's EXR checked against its recorded sha256."""
    with replacing(path) as tmp:
        with tarfile.open(tmp, "w", format=tarfile.USTAR_FORMAT) as tar:
            for row in rows:
                relative = str(table["path"][row])
                try:
                    exr = (folder / relative).read_bytes()
                except OSError as exc:
                    raise ds.DatasetError(
                        f"Sample {folder / relative} cannot be read ({exc.strerror or exc}).",
                        f"re-render it with `{ds.resume_command(folder)}`, then pack again.",
                    ) from exc
                if hashlib.sha256(exr).hexdigest() != str(table["sha256"][row]):
                    raise ds.DatasetError(
                        f"Sample {folder / relative} differs from its recorded checksum (damaged).",
                        f"repair the dataset with `{ds.resume_command(folder)}`, then pack again.",
                    )
                key = sample_key(int(row))
                tar.addfile(*_member(f"{key}.exr", exr))
                columns = {name: column[row] for name, column in table.items()}
                tar.addfile(*_member(f"{key}.npz", ds.npz_bytes(columns)))
                if bar is not None:
                    bar.update(1)
        digest = hashlib.sha256()
        with tmp.open("rb") as stream:
            while chunk := stream.read(1 << 20):
                digest.update(chunk)
        size = tmp.stat().st_size
    return {"bytes": size, "sha256": digest.hexdigest()}


def _check_out(out: Path, manifest: ds.DatasetManifest, samples_per_shard: int) -> dict | None:
    """The index of an identical finished pack in `out` (then nothing to do), else None once
    `out` is known to be new, empty, or an unfinished pack (which is replaced)."""
    if out.exists() and not out.is_dir():
        raise ds.DatasetError(f"--out {out} is a file.", "choose a folder for the shards.")
    if not out.is_dir() or not any(out.iterdir()):
        return None
    index_path = out / INDEX_FILE
    if index_path.is_file():
        index = json.loads(index_path.read_text())
        same = (
            index.get("manifest", {}).get("checksum") == manifest.checksum
            and index.get("samples_per_shard") == samples_per_shard
        )
        if same:
            return index
        raise ds.DatasetError(
            f"--out {out} holds shards of another dataset or shard size.",
            "choose a new folder for the shards.",
        )
    ours = {SHARDS_FOLDER, *COPIED}
    others = sorted(p.name for p in out.iterdir() if p.name not in ours)
    if others:
        raise ds.DatasetError(
            f"--out {out} is not empty and holds no shards ({', '.join(others[:3])}).",
            "choose a new or empty folder for the shards.",
        )
    return None


def pack(
    dataset: str | Path,
    out: str | Path,
    samples_per_shard: int = SAMPLES_PER_SHARD,
    progress: bool = False,
) -> dict[str, Any]:
    """Pack a finished dataset folder into shards in `out` (see the module doc); the index.
    `progress` shows a bar on stderr (samples, rate, ETA)."""
    folder, out = Path(dataset), Path(out)
    if samples_per_shard < 1:
        raise ds.DatasetError(
            f"--samples-per-shard {samples_per_shard} is below 1.", "pass a positive count."
        )
    manifest = ds.read_manifest(folder)
    existing = _check_out(out, manifest, samples_per_shard)
    if existing is not None:
        return existing
    with np.load(folder / ds.PARAMS_FILE, allow_pickle=False) as data:
        table = {name: data[name] for name in data.files}
    shutil.rmtree(out / SHARDS_FOLDER, ignore_errors=True)  # an unfinished pack's shards
    (out / SHARDS_FOLDER).mkdir(parents=True, exist_ok=True)
    shards = []
    bar = tqdm(
        total=len(table["split"]),
        unit="sample",
        disable=not progress,
        file=sys.stderr,
        dynamic_ncols=True,
    )
    with bar:
        for split_index, split in enumerate(SPLITS):
            rows = np.flatnonzero(table["split"] == split_index)
            for n, start in enumerate(range(0, len(rows), samples_per_shard)):
                chunk = rows[start : start + samples_per_shard]
                name = f"{SHARDS_FOLDER}/{split}-{n:05d}.tar"
                written = write_shard(out / name, folder, table, chunk, bar)
                shards.append(
                    {"file": name, "split": split, "count": len(chunk), "samples": ranges(chunk)}
                    | written
                )
    for name in COPIED:
        if (folder / name).is_file():
            with replacing(out / name) as tmp:  # a pack made again over this one
                shutil.copyfile(folder / name, tmp)
    index = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "samples_per_shard": samples_per_shard,
        "counts": {s: sum(x["count"] for x in shards if x["split"] == s) for s in SPLITS},
        "bytes": sum(x["bytes"] for x in shards),
        "shards": shards,
        "manifest": manifest.to_json(),
    }
    write_atomic(out / INDEX_FILE, json.dumps(index, indent=1) + "\n")
    return index
