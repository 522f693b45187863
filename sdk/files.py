"""Files replaced in one step: a reader sees the old file or the new one, never a part of either.

    write_atomic(path, data)              bytes or text (UTF-8)
    with replacing(path) as tmp: ...      for writers that need a path (torch.save, OpenImageIO,
                                          tarfile): write `tmp`, and on leaving it replaces `path`

The new content goes to a temporary file beside the target (the same folder, so the same file
system: os.replace is then one rename), is flushed to the disk (fsync), and renamed over the
target. The temporary name is hidden and unique per process and call (".NAME.PID.N.tmp"), so
two processes or threads writing the same file never write into each other's temporary, and
a killed writer leaves only a ".*.tmp*" file (capture.dataset.clean_temporaries removes them).
Every writer of the project's own artefacts (manifests, capture.json, run.json, reports,
capsules, a bundle's graphs rewritten in place) goes through here; apps/recipe.py keeps its own
copy because it runs with the standard library only.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_calls = itertools.count()
"""Numbers the temporaries of one process (next() on a count is atomic under the GIL)."""


def temporary_beside(path: str | Path, suffix: str = "") -> Path:
    """A hidden temporary name beside `path`, unique to this process and call; `suffix` ends
    it (".exr": OpenImageIO chooses the format by the extension)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}.{next(_calls)}.tmp{suffix}")


@contextmanager
def replacing(path: str | Path, suffix: str = "", *, durable: bool = True) -> Iterator[Path]:
    """A temporary path beside `path` to write; when the block ends without an exception, the
    temporary (flushed to the disk first when `durable`) replaces `path`. On an exception the
    temporary is removed and `path` is left as it was.

    `durable=False` skips the fsync, for many files whose loss a later record catches (a
    capture's sample EXRs: each work item's record holds their sha256, and a resumed capture
    re-renders any that do not match)."""
    path = Path(path)
    tmp = temporary_beside(path, suffix)
    try:
        yield tmp
        if durable:
            _fsync(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_atomic(path: str | Path, data: bytes | str, *, durable: bool = True) -> Path:
    """Write `data` (text as UTF-8) to `path` in one step (replacing); returns the path."""
    path = Path(path)
    with replacing(path, durable=durable) as tmp, open(tmp, "wb") as stream:
        stream.write(data.encode() if isinstance(data, str) else data)
    return path


def _fsync(path: Path) -> None:
    """Flush a written file's data to the disk (a rename can reach the disk before the data)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
