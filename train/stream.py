"""Read tar shards (capture/pack.py) for training as a stream, in bounded memory, per rank.

Each epoch, every rank takes its own shards (a seeded permutation of the split's shards,
dealt round-robin) and reads them in order through a shuffle buffer of BUFFER samples: the
buffer holds where a sample lies (shard, offset, size), and a sample's bytes are read and
decoded only when it leaves the buffer, so memory stays a few batches whatever the
dataset's size. Every rank yields exactly len // world samples an epoch: a rank whose shards
hold fewer reads its shards again (resampled, in a new seeded order) and one whose shards
hold more stops early, so DDP ranks always take the same number of steps. The order is a
pure function of (seed, rank, world size, epoch), and skipping to a step reads tar headers
only, so a resumed run continues with the same samples. Items come from
SplitInfo.make_item, exactly as SampleSet makes them.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tarfile
import tempfile
import threading
import weakref
from collections import OrderedDict
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from rigspace.capture.dataset import DatasetError, DatasetManifest
from rigspace.capture.pack import FORMAT, FORMAT_VERSION, INDEX_FILE
from rigspace.sdk.exr import Maps, read_exr
from rigspace.train.data import Prefetcher, SampleSet, SplitInfo

BUFFER = 1000
"""Samples in the shuffle buffer (locations only: about 200 bytes each)."""
OPEN_FILES = 4
"""Shard files kept open at once (a buffer spans a few consecutive shards)."""
DECODE_THREADS = min(8, os.cpu_count() or 1)
"""Threads decoding a batch's samples (OpenImageIO and numpy release the GIL): a GPU rank
trains faster than one thread decodes 256x256 EXRs (docs/scale.md)."""


def is_shards(folder: str | Path) -> bool:
    """Whether `folder` is a shards folder (rigspace dataset pack) rather than a dataset."""
    return (Path(folder) / INDEX_FILE).is_file()


def read_index(folder: str | Path) -> dict[str, Any]:
    path = Path(folder) / INDEX_FILE
    try:
        index = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(
            f"{path} is not readable JSON ({exc}).",
            "pack the dataset again: `rigspace dataset pack DATASET --out SHARDS`.",
        ) from exc
    if (index.get("format"), index.get("format_version")) != (FORMAT, FORMAT_VERSION):
        raise DatasetError(
            f"{path} is not a {FORMAT} index of version {FORMAT_VERSION}.",
            "pack the dataset again with this version of rigspace.",
        )
    return index


@dataclass(frozen=True)
class Member:
    """Where one sample lies in its shard: per file extension (exr, npz), offset and size."""

    shard: int
    key: str
    parts: tuple[tuple[str, int, int], ...]


class ShardSet(SplitInfo):
    """One split of a shards folder: its shards, and reading a sample by location or index."""

    def __init__(self, folder: str | Path, split: str, resolution: int | None = None) -> None:
        self.folder = Path(folder)
        index = read_index(self.folder)
        manifest = DatasetManifest.from_json(index["manifest"], self.folder / INDEX_FILE)
        super().__init__(manifest, split, resolution)
        self.shards = [s for s in index["shards"] if s["split"] == split]
        self.starts = np.cumsum([0] + [s["count"] for s in self.shards])
        self._files: OrderedDict[int, BinaryIO] = OrderedDict()
        self._lock = threading.Lock()
        self._listed: tuple[int, list[Member]] | None = None
        shm = "/dev/shm" if os.access("/dev/shm", os.W_OK) else None
        self._scratch = Path(tempfile.mkdtemp(prefix="rigspace-exr-", dir=shm))
        weakref.finalize(self, shutil.rmtree, self._scratch, True)

    def __len__(self) -> int:
        return int(self.starts[-1])

    def _damaged(self, shard: int, what: str) -> DatasetError:
        path = self.folder / self.shards[shard]["file"]
        return DatasetError(
            f"Shard {path} is {what}.",
            f"pack the dataset again into a new folder (`rigspace dataset pack DATASET --out "
            f"{self.folder}.new`); index.json records each shard's sha256 to find damaged ones.",
        )

    def _file(self, shard: int) -> BinaryIO:
        if shard in self._files:
            self._files.move_to_end(shard)
            return self._files[shard]
        path = self.folder / self.shards[shard]["file"]
        try:
            handle = path.open("rb")
        except OSError as exc:
            raise self._damaged(shard, f"unreadable ({exc.strerror or exc})") from exc
        if os.fstat(handle.fileno()).st_size != self.shards[shard]["bytes"]:
            handle.close()
            raise self._damaged(shard, "not the size index.json records (truncated or replaced)")
        self._files[shard] = handle
        while len(self._files) > OPEN_FILES:
            self._files.popitem(last=False)[1].close()
        return handle

    def scan(self, shard: int) -> Iterator[Member]:
        """The shard's samples in file order, read from tar headers only (data is skipped)."""
        with self._lock:
            self._file(shard)  # checks the size
        path = self.folder / self.shards[shard]["file"]
        count = 0
        try:
            with tarfile.open(path, "r:") as tar:
                key, parts = None, []
                while (info := tar.next()) is not None:
                    tar.members.clear()  # type: ignore[attr-defined]  # keep no headers: bounded
                    name, ext = info.name.split(".", 1)
                    if key is not None and name != key:
                        yield Member(shard, key, tuple(parts))
                        count += 1
                        parts = []
                    key = name
                    parts.append((ext, info.offset_data, info.size))
                if key is not None:
                    yield Member(shard, key, tuple(parts))
                    count += 1
        except (tarfile.TarError, ValueError) as exc:
            raise self._damaged(shard, f"not a readable tar ({exc})") from exc
        if count != self.shards[shard]["count"]:
            raise self._damaged(
                shard, f"holding {count} samples, not {self.shards[shard]['count']}"
            )

    def read(self, member: Member) -> dict[str, np.ndarray]:
        """A sample's item: its bytes read at their offsets and decoded (SplitInfo.make_item)."""
        maps, row = self.decode(member)
        return self.make_item(maps, row)

    def decode(self, member: Member) -> tuple[Maps, dict[str, np.ndarray]]:
        """A sample's captured maps and its params row, read at their offsets."""
        data = {}
        with self._lock:
            handle = self._file(member.shard)
            for ext, offset, size in member.parts:
                handle.seek(offset)
                data[ext] = handle.read(size)
        if set(data) != {"exr", "npz"}:
            raise self._damaged(member.shard, f"missing a file of sample {member.key}")
        # OpenImageIO reads files, not bytes: the EXR goes through a scratch file in memory.
        scratch = self._scratch / f"{threading.get_ident()}.exr"
        scratch.write_bytes(data["exr"])
        maps = read_exr(scratch)
        with np.load(io.BytesIO(data["npz"]), allow_pickle=False) as row:
            return maps, {name: row[name] for name in row.files}

    def member(self, k: int) -> Member:
        """Where sample k of the split lies (its shard's headers are scanned once in a row)."""
        shard = int(np.searchsorted(self.starts, k, side="right") - 1)
        if self._listed is None or self._listed[0] != shard:
            self._listed = (shard, list(self.scan(shard)))
        return self._listed[1][k - int(self.starts[shard])]

    def item(self, k: int) -> dict[str, np.ndarray]:
        """Sample k of the split (random access: for previews, not for the training stream)."""
        return self.read(self.member(k))

    def maps(self, k: int) -> Maps:
        """Sample k's captured maps (random access: `rigspace eval` on a shards folder)."""
        return self.decode(self.member(k))[0]

    def batch(self, ks: np.ndarray) -> dict[str, np.ndarray]:
        return self.batch_of([self.item(int(k)) for k in ks])

    def close(self) -> None:
        for handle in self._files.values():
            handle.close()
        self._files.clear()
        shutil.rmtree(self._scratch, ignore_errors=True)


class ShardStream:
    """The sample order of one rank: epochs of `epoch_length` members (see the module doc)."""

    def __init__(
        self, samples: ShardSet, seed: int, rank: int = 0, world: int = 1, buffer: int = BUFFER
    ) -> None:
        if len(samples) < world:
            raise DatasetError(
                f"{samples.folder} has {len(samples)} {samples.split} samples, fewer than the "
                f"{world} ranks.",
                "train on fewer ranks or on a larger dataset.",
            )
        self.samples, self.seed, self.rank, self.world = samples, seed, rank, world
        self.buffer = max(1, buffer)
        self.epoch_length = len(samples) // world

    def shards_of(self, epoch: int) -> list[int]:
        """This rank's shards in an epoch: a permutation shared by all ranks, dealt out."""
        count = len(self.samples.shards)
        order = np.random.default_rng([self.seed, epoch]).permutation(count)
        mine = order[self.rank :: self.world].tolist()
        return mine or [int(order[self.rank % count])]  # fewer shards than ranks: share

    def epoch(self, epoch: int) -> Iterator[Member]:
        """Exactly epoch_length members, shuffled through the buffer."""
        rng = np.random.default_rng([self.seed, epoch, self.rank, self.world])
        mine = self.shards_of(epoch)
        own = sum(self.samples.shards[s]["count"] for s in mine)

        def locations() -> Iterator[Member]:
            order = mine
            while True:  # passes after the first resample this rank's shards in a new order
                for shard in order:
                    yield from self.samples.scan(shard)
                order = rng.permutation(mine).tolist()

        source = locations()
        buffer: list[Member] = []
        taken = produced = 0
        while produced < self.epoch_length:
            # Fill from the rank's own samples, then only as far as the epoch still needs.
            while len(buffer) < self.buffer and (
                taken < own or produced + len(buffer) < self.epoch_length
            ):
                buffer.append(next(source))
                taken += 1
            j = int(rng.integers(len(buffer)))
            buffer[j], buffer[-1] = buffer[-1], buffer[j]
            yield buffer.pop()
            produced += 1

    def members_from(self, position: int) -> Iterator[Member]:
        """The members from `position` (samples since the start of training) on, forever."""
        epoch, offset = divmod(position, self.epoch_length)
        yield from islice(self.epoch(epoch), offset, None)
        while True:
            epoch += 1
            yield from self.epoch(epoch)


class StreamPrefetcher:
    """Prefetcher's interface over a ShardStream: reads step s + 1 while step s trains."""

    def __init__(self, stream: ShardStream, batch: int) -> None:
        self.stream, self.batch = stream, batch
        self._pool = ThreadPoolExecutor(max_workers=1)
        self._decode = ThreadPoolExecutor(max_workers=DECODE_THREADS)
        self._members: Iterator[Member] | None = None
        self._pending: tuple[int, Future] | None = None

    def _read(self) -> dict[str, np.ndarray]:
        assert self._members is not None
        members = list(islice(self._members, self.batch))
        return self.stream.samples.batch_of(
            list(self._decode.map(self.stream.samples.read, members))
        )

    def get(self, step: int) -> dict[str, np.ndarray]:
        if self._pending is None or self._pending[0] != step:  # a start, resume or skip
            if self._pending is not None and not self._pending[1].cancel():
                self._pending[1].exception()  # running: let it finish with the old iterator
            self._members = self.stream.members_from(step * self.batch)
            self._pending = (step, self._pool.submit(self._read))
        result = self._pending[1].result()
        self._pending = (step + 1, self._pool.submit(self._read))
        return result

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._decode.shutdown(wait=True, cancel_futures=True)


def open_split(folder: str | Path, split: str, resolution: int | None) -> SampleSet | ShardSet:
    """A split of a dataset folder (SampleSet) or of a shards folder (ShardSet)."""
    return (ShardSet if is_shards(folder) else SampleSet)(folder, split, resolution)


def prefetcher(
    samples: SampleSet | ShardSet,
    batch: int,
    seed: int,
    rank: int = 0,
    world: int = 1,
    oversample: float = 0.0,
) -> Prefetcher | StreamPrefetcher:
    """The batches of a training run: `batch` is the global batch; rank `rank` of `world`
    gets batch // world of them (a slice of the global batch from a dataset folder, its own
    stream from shards). `oversample` > 0 draws rare poses more often (dataset folders only:
    a stream reads its shards in order and cannot pick samples by weight)."""
    if world > 1 and batch % world:
        raise DatasetError(
            f"--batch {batch} does not split evenly over {world} ranks.",
            f"pass a multiple of {world} (the global batch; each rank takes batch / {world}).",
        )
    if isinstance(samples, ShardSet):
        if oversample:
            raise DatasetError(
                f"--oversample {oversample:g} needs a dataset folder, but {samples.folder} is "
                "a shards folder, read as a stream in shard order (no sample is picked by "
                "weight).",
                "train on the dataset folder the shards were packed from, or pass --oversample 0.",
            )
        return StreamPrefetcher(ShardStream(samples, seed, rank, world), batch // world)
    return Prefetcher(samples, batch, seed, rank, world, oversample)
