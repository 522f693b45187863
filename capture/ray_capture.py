"""Capture on a Ray cluster: the work items of capture/pipeline.py as Ray tasks with retries.

    capture_on_ray(scene, character, out, overrides, address="auto")

The driver resolves the settings, checks the output folder and lists the work items exactly
as `rigspace capture` does; each unfinished item becomes one Ray task that renders it with
the pipeline's ItemWorker (one per worker process, reused across its tasks) and commits it
with its atomic record. A task whose worker process dies is re-run by Ray (max_retries), and
so is one that fails with a transient I/O error (retry_exceptions): an item is rendered from
scratch and written whole, so a re-run gives the same bytes. The driver writes the manifest,
params.npz, contact sheet and capsules once, at the end. Every node must see `out` at the
same path (a shared folder: NFS, an S3 fuse mount); docs/scale.md says how to run it.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

from rigspace.capture import dataset as ds
from rigspace.capture.pipeline import CaptureResult, ItemDone, ItemWorker, capture
from rigspace.capture.settings import (
    CaptureError,
    CaptureOverrides,
    CaptureSettings,
    Warn,
    print_warning,
)

LOCAL = "local"
"""`--ray` without an address: start a local Ray cluster for this capture (ray.init's name)."""
MAX_RETRIES = 3
"""Re-runs of an item whose worker died or that hit a transient I/O error."""
TRANSIENT = [OSError]
"""Errors a task retries: a shared folder's hiccup (NFS stale handle, fuse timeout)."""
DIE_ONCE = "RIGSPACE_TEST_RAY_DIE_ONCE"
"""Tests only: a file path; the first task that finds the file there renames it away, leaves
its item half-written (samples on disk, one truncated, no record) and kills its own worker
process, as a node lost mid-item would."""

_workers: dict[tuple[str, str], ItemWorker] = {}
"""Per Ray worker process: the ItemWorker of each (settings, folder), reused across tasks."""


def _die_mid_item(folder: Path, item: ds.WorkItem) -> None:
    armed = os.environ.get(DIE_ONCE)
    if not armed:
        return
    try:
        os.rename(armed, armed + ".fired")  # atomic: exactly one task of the run dies
    except FileNotFoundError:
        return
    ds.record_path(folder, item).unlink()
    first = folder / ds.sample_path(item.clip, item.times[0], item.views[0])
    first.write_bytes(first.read_bytes()[:100])
    os._exit(1)


def render_item(settings_json: dict[str, Any], folder: str, item: ds.WorkItem) -> ItemDone:
    """One work item, rendered and committed in a Ray worker process (the Ray task body)."""
    key = (repr(sorted(settings_json.items())), folder)
    if key not in _workers:
        _workers[key] = ItemWorker(CaptureSettings.from_json(settings_json), Path(folder))
    done = _workers[key].run(item)
    _die_mid_item(Path(folder), item)
    return done


def connect(address: str, workers: int | None) -> bool:
    """Join (or, for LOCAL, start) the Ray cluster; True when this call started Ray."""
    import ray

    if ray.is_initialized():
        return False
    options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
    if address == LOCAL:
        options["num_cpus"] = workers or os.cpu_count() or 1
    try:
        ray.init(address=address, **options)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise CaptureError(
            f"--ray {address}: cannot reach a Ray cluster ({str(exc).splitlines()[0]}).",
            "start one with `ray start --head` (then pass --ray auto or its address), or pass "
            "--ray with no address for a local cluster.",
        ) from exc
    return True


def ray_items(
    address: str,
    settings: CaptureSettings,
    folder: Path,
    mine: list[ds.WorkItem],
    workers: int | None,
    stack: contextlib.ExitStack,
) -> Iterator[ItemDone]:
    """pipeline.Runner on Ray: joins (or starts) the cluster now, then yields the items as
    their tasks finish, at most `workers` in flight; a task that failed after its retries
    is a CaptureError naming the resume command."""
    import ray

    if connect(address, workers):
        stack.callback(ray.shutdown)
    # retry_exceptions takes a list of exception types (Ray's stubs say bool only).
    options: dict[str, Any] = {"max_retries": MAX_RETRIES, "retry_exceptions": TRANSIENT}
    task = ray.remote(num_cpus=1, **options)(render_item)
    settings_ref = ray.put(settings.to_json())
    shared = str(folder.absolute())  # the tasks run elsewhere: the path every node sees
    queue = list(reversed(mine))
    pending: list[Any] = []
    stack.callback(lambda: [ray.cancel(r, force=True) for r in pending])
    limit = workers or len(mine)
    resume = f"{ds.resume_command(folder)} --ray {address}"

    def finished() -> Iterator[ItemDone]:
        while queue or pending:
            while queue and len(pending) < limit:
                pending.append(task.remote(settings_ref, shared, queue.pop()))
            ready, rest = ray.wait(pending, num_returns=1)
            pending[:] = rest
            try:
                yield ray.get(ready[0])
            except ray.exceptions.RayTaskError as exc:
                if isinstance(exc.cause, CaptureError):  # the task's own, unwrapped
                    raise exc.cause from None
                raise CaptureError(
                    f"A capture task failed on the Ray cluster after {MAX_RETRIES} "
                    f"retries: {str(exc).strip().splitlines()[-1]}.",
                    f"fix the cause, then resume with `{resume}` (finished items are kept).",
                ) from exc
            except ray.exceptions.WorkerCrashedError as exc:
                raise CaptureError(
                    f"A capture task's worker process died {MAX_RETRIES + 1} times: {exc}.",
                    "check the nodes' memory and logs (`ray logs`), then resume the "
                    f"capture: `{resume}`.",
                ) from exc

    return finished()


def capture_on_ray(
    scene: str | Path,
    character: str,
    out: str | Path,
    overrides: CaptureOverrides | None = None,
    *,
    address: str = LOCAL,
    shard: tuple[int, int] = (0, 1),
    resume: bool = False,
    workers: int | None = None,
    progress: bool = True,
    warn: Warn = print_warning,
) -> CaptureResult:
    """pipeline.capture, with the work items as Ray tasks (see the module doc).

    `workers` caps the tasks in flight (default: as many as the cluster schedules); with a
    local cluster it is also the cluster's CPU count.
    """
    return capture(
        scene,
        character,
        out,
        overrides,
        shard=shard,
        resume=resume,
        workers=workers,
        progress=progress,
        warn=warn,
        runner=partial(ray_items, address),
    )
