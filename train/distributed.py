"""Training on several processes with torch.distributed: torchrun, DDP, rank 0 writes.

    torchrun --standalone --nproc-per-node 2 -m rigspace.apps.train DATASET --out MODEL ...
    rigspace train DATASET --out MODEL --nproc 2 ...        (the same, torchrun spawned)

Under torchrun (WORLD_SIZE > 1 in the environment) `context()` joins the process group:
gloo on CPU, nccl with one GPU per rank on CUDA. The model is wrapped in
DistributedDataParallel; --batch stays the global batch and each rank reads batch / world of
it (train.stream.prefetcher), so a step trains on the same samples whatever the world size
and `--resume` continues a run on another world size. Rank 0 alone writes run.json, the log,
previews, checkpoints and the bundle; decisions that depend on the clock (--minutes) are
rank 0's, shared, so every rank takes the same steps. Without torchrun the context is one
process and training behaves exactly as it always has.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

from rigspace.sdk.errors import RigspaceError

if TYPE_CHECKING:
    import torch

T = TypeVar("T")
N = TypeVar("N", bool, int)


def under_torchrun() -> bool:
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


@dataclass
class Context:
    """This process's place in the run: rank, world size, device."""

    rank: int = 0
    world: int = 1
    device: torch.device = field(default_factory=lambda: _torch().device("cpu"))

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def wrap(self, model: torch.nn.Module) -> torch.nn.Module:
        """The module the training step calls: DDP over `model` (moved to the device)."""
        if self.world == 1:
            return model
        from torch.nn.parallel import DistributedDataParallel

        # Progressive training leaves the blocks above the current level without gradients.
        ids = [self.device.index] if self.device.type == "cuda" else None
        return DistributedDataParallel(model, device_ids=ids, find_unused_parameters=True)

    def to_device(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The batch on this rank's device; to a GPU through page-locked memory, so the copy
        runs asynchronously (non_blocking only overlaps from pinned memory)."""
        if self.device.type == "cpu":
            return batch
        pin = self.device.type == "cuda"
        return {
            k: (v.pin_memory() if pin else v).to(self.device, non_blocking=True)
            for k, v in batch.items()
        }

    def on_cpu(self, model: torch.nn.Module) -> torch.nn.Module:
        """`model`, or a CPU copy of it (previews read numpy batches on the CPU)."""
        return model if self.device.type == "cpu" else copy.deepcopy(model).cpu()

    def share(self, make: Callable[[], T]) -> T:
        """Rank 0's `make()` on every rank; a RigspaceError it raises is raised on every rank."""
        if self.world == 1:
            return make()
        import torch.distributed as dist

        if self.is_main:
            try:
                value = make()
            except RigspaceError as exc:
                dist.broadcast_object_list([("error", type(exc), exc.what, exc.fix)], src=0)
                raise
            dist.broadcast_object_list([("ok", value)], src=0)
            return value
        box: list[Any] = [None]
        dist.broadcast_object_list(box, src=0)
        if box[0][0] == "error":
            _, kind, what, fix = box[0]
            raise kind(what, fix)
        return box[0][1]

    def agree(self, value: N) -> N:
        """Rank 0's value (a bool or an int) on every rank: decisions taken on the clock."""
        if self.world == 1:
            return value
        import torch
        import torch.distributed as dist

        tensor = torch.tensor([int(value)], dtype=torch.int64, device=self._comm_device)
        dist.broadcast(tensor, src=0)
        return type(value)(int(tensor.item()))

    def mean(
        self, loss: torch.Tensor, terms: dict[str, torch.Tensor]
    ) -> tuple[float, dict[str, float]]:
        """The step's loss and terms averaged over the ranks (what a log line shows), read
        from the device in one transfer."""
        import torch

        values = torch.stack([loss.detach(), *terms.values()]).to(torch.float64)
        if self.world == 1:
            read = values.tolist()
            return read[0], dict(zip(terms, read[1:], strict=True))
        import torch.distributed as dist

        values = values.to(self._comm_device)
        dist.all_reduce(values)
        values = (values / self.world).cpu()
        return float(values[0]), dict(zip(terms, values[1:].tolist(), strict=True))

    def barrier(self) -> None:
        if self.world > 1:
            import torch.distributed as dist

            dist.barrier()

    @property
    def _comm_device(self) -> torch.device:
        import torch.distributed as dist

        return self.device if dist.get_backend() == "nccl" else _torch().device("cpu")


def _torch() -> Any:
    import torch  # here, not at the top: `rigspace train --nproc` launches without it

    return torch


_context: Context | None = None


DEVICES = "auto, cpu, cuda or cuda:N"


def resolve_device(spec: str | None) -> torch.device:
    """The torch device a `--device` value names: `auto` (CUDA when torch sees a GPU, else
    the CPU), `cpu`, `cuda` (the current GPU) or `cuda:N`. None is `cpu` (the library's
    default, as before). A GPU that is not there is an error naming what torch sees."""
    torch = _torch()
    text = (spec or "cpu").strip().lower()
    if text == "auto":
        text = "cuda" if torch.cuda.is_available() else "cpu"
    if text == "cpu":
        return torch.device("cpu")
    kind, _, index = text.partition(":")
    if kind != "cuda" or (index and not index.isdigit()):
        raise RigspaceError(f"Unknown device {spec!r}.", f"pass --device {DEVICES}.")
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    wanted = int(index) if index else 0
    if wanted >= count:
        built = getattr(torch.version, "cuda", None)
        seen = (
            f"torch sees {count} GPU{'s' if count != 1 else ''}"
            if built
            else f"this torch ({torch.__version__}) is a CPU build"
        )
        raise RigspaceError(
            f"Device {spec!r} is not available: {seen}.",
            "pass --device cpu (or auto), or install a CUDA build of torch on a machine with "
            "an NVIDIA GPU (README, 'GPU').",
        )
    return torch.device("cuda", wanted) if index else torch.device("cuda")


def context(device: str | None = None) -> Context:
    """This process's Context; under torchrun the first call joins the process group.

    `device` (a --device value, resolve_device) picks one process's device; None keeps the
    context already made (the CPU on the first call). Under torchrun each rank takes the GPU
    of its LOCAL_RANK when torch sees GPUs, unless `device` is `cpu`."""
    global _context
    if not under_torchrun():
        if device is not None or _context is None:
            _context = Context(device=resolve_device(device))
        return _context
    if _context is not None:
        return _context
    import torch
    import torch.distributed as dist

    rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))
    if torch.cuda.is_available() and (device or "auto").strip().lower() != "cpu":
        chosen = torch.device("cuda", local_rank)
        torch.cuda.set_device(chosen)
        backend = "nccl"
    else:
        chosen, backend = torch.device("cpu"), "gloo"
        # The ranks of a node share its cores: one process's default would oversubscribe.
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // local_world))
    if not dist.is_initialized():
        dist.init_process_group(backend)
    _context = Context(rank, world, chosen)
    return _context


def close() -> None:
    """Leave the process group (the end of a torchrun process's training)."""
    global _context
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()
    _context = None
