"""Ranks under ``torchrun``: who am I, which device is mine, wait for the others.

Built on `torch.distributed` and the environment ``torchrun`` (``python -m torch.distributed.run``)
sets for every worker: ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR`` and
``MASTER_PORT``. Without them (a plain ``python`` run) everything here answers as for a
single process: rank 0 of 1, `barrier` does nothing, `init_process_group` starts nothing.

>>> from geofeat.runtime import distributed
>>> with distributed.process_group(device="auto") as device:   # cuda:<LOCAL_RANK>, or cpu
...     mine = distributed.shard(sorted(items))                 # items i with i % world == rank
...     ...
...     distributed.barrier()

The backend is NCCL when every rank of a node has a GPU of its own and gloo otherwise. Used by
`geofeat.apps.extract` (sharded feature extraction); the trainer uses it for DDP.
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TypeVar

import torch

from geofeat.errors import DistributedError
from geofeat.runtime.devices import resolve_device

log = logging.getLogger(__name__)

T = TypeVar("T")

#: Variables ``torchrun`` sets for every worker; all of them mean "started by torchrun".
TORCHRUN_VARIABLES = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


@dataclass(frozen=True)
class RankInfo:
    """Where this process stands among the workers.

    Attributes
    ----------
    rank : int
        Global rank, 0 to ``world_size - 1``.
    world_size : int
        Number of processes on all nodes.
    local_rank : int
        Rank on this node (picks the GPU).
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        """True on rank 0 (the one that merges, logs and writes shared files)."""
        return self.rank == 0


def launched_by_torchrun() -> bool:
    """True when the torchrun variables (`TORCHRUN_VARIABLES`) are all set."""
    return all(name in os.environ for name in TORCHRUN_VARIABLES)


def _env_int(name: str, default: int) -> int:
    text = os.environ.get(name)
    if text is None:
        return default
    try:
        return int(text)
    except ValueError:
        raise DistributedError(f"environment variable {name} must be an integer (set by torchrun); found {text!r}.") from None


def rank_info() -> RankInfo:
    """Rank, world size and local rank: from the process group when started, else the torchrun variables, else 0/1/0.

    Raises
    ------
    DistributedError
        The variables contradict each other (a rank outside ``[0, WORLD_SIZE)``).
    """
    local = _env_int("LOCAL_RANK", 0)
    if _group_started():
        return RankInfo(torch.distributed.get_rank(), torch.distributed.get_world_size(), local)
    info = RankInfo(_env_int("RANK", 0), _env_int("WORLD_SIZE", 1), local)
    if info.world_size < 1 or not 0 <= info.rank < info.world_size or info.local_rank < 0:
        raise DistributedError(
            f"inconsistent torchrun environment: RANK={info.rank}, WORLD_SIZE={info.world_size}, LOCAL_RANK={info.local_rank}; "
            "expected 0 <= RANK < WORLD_SIZE and LOCAL_RANK >= 0. Start the workers with torchrun, or unset these variables."
        )
    return info


def group_rank_info() -> RankInfo:
    """`rank_info` for work that needs the process group whenever there are several ranks.

    Raises
    ------
    DistributedError
        ``WORLD_SIZE`` above 1 in the environment but no process group (the rendezvous
        variables of torchrun are missing): each process would think it is one of several
        and do only its share.
    """
    info = rank_info()
    if info.world_size > 1 and not _group_started():
        raise DistributedError(
            f"WORLD_SIZE={info.world_size} is set but no process group could be started (found MASTER_ADDR="
            f"{os.environ.get('MASTER_ADDR')!r}, MASTER_PORT={os.environ.get('MASTER_PORT')!r}); launch with "
            "torchrun, which sets all of RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT, or unset WORLD_SIZE."
        )
    return info


def rank() -> int:
    """Global rank of this process (0 without torchrun)."""
    return rank_info().rank


def world_size() -> int:
    """Number of processes (1 without torchrun)."""
    return rank_info().world_size


def local_rank() -> int:
    """Rank on this node (0 without torchrun)."""
    return rank_info().local_rank


def is_main() -> bool:
    """True on rank 0."""
    return rank_info().is_main


def local_device(device: str | torch.device | None = "auto") -> torch.device:
    """The device of this rank.

    Parameters
    ----------
    device : str, torch.device or None
        ``"auto"`` (or None): the GPU ``LOCAL_RANK`` (modulo the GPUs visible) when CUDA is
        present, else the CPU. Anything else as for `geofeat.runtime.devices.resolve_device`; a bare
        ``"cuda"`` becomes ``cuda:<LOCAL_RANK>`` too.

    Returns
    -------
    torch.device
    """
    if device is None or (isinstance(device, str) and device == "auto"):
        if not torch.cuda.is_available():
            return torch.device("cpu")
        device = "cuda"
    resolved = resolve_device(device)
    if resolved.type == "cuda" and resolved.index is None:
        resolved = torch.device("cuda", local_rank() % torch.cuda.device_count())
    return resolved


def shard(items: Sequence[T], info: RankInfo | None = None) -> list[T]:
    """The items of this rank: those at positions ``i`` with ``i % world_size == rank``.

    Deterministic: every rank must pass the same sequence in the same order (sort it first).
    """
    info = rank_info() if info is None else info
    return [item for i, item in enumerate(items) if i % info.world_size == info.rank]


def init_process_group(device: torch.device | str | None = "auto", timeout_minutes: float = 30.0) -> bool:
    """Start the default process group when running under torchrun; returns True when this call started it.

    Parameters
    ----------
    device : torch.device, str or None
        This rank's device (see `local_device`; a GPU is made the current CUDA device).
        The backend is NCCL when every rank of the node has a GPU of its own, gloo
        otherwise (see `_backend`).
    timeout_minutes : float
        How long collective calls (`barrier`) wait for the slowest rank before failing.

    Returns
    -------
    bool
        False when not under torchrun or when a group is already started (left as it is).
    """
    if not launched_by_torchrun() or not torch.distributed.is_available() or _group_started():
        return False
    device = local_device(device)
    backend = _backend(device)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    info = rank_info()
    try:
        torch.distributed.init_process_group(
            backend=backend,
            rank=info.rank,
            world_size=info.world_size,
            timeout=datetime.timedelta(minutes=timeout_minutes),
        )
    except (RuntimeError, ValueError) as err:
        raise DistributedError(
            f"could not start the {backend} process group as rank {info.rank} of {info.world_size} "
            f"(MASTER_ADDR={os.environ.get('MASTER_ADDR')}, MASTER_PORT={os.environ.get('MASTER_PORT')}): {err}. "
            "Check that every node uses the same rendezvous address and port and that the port is free."
        ) from err
    log.info("rank %d of %d: %s process group started on %s", info.rank, info.world_size, backend, device)
    return True


def _backend(device: torch.device) -> str:
    """NCCL when every local rank has a GPU of its own, else gloo.

    NCCL refuses two ranks on one GPU ("Duplicate GPU detected"), which happens when a node
    starts more ranks than it has GPUs (seen on a one-GPU machine with 2 ranks); gloo then
    coordinates them, CUDA tensors included, more slowly.
    """
    if device.type != "cuda":
        return "gloo"
    local_ranks = _env_int("LOCAL_WORLD_SIZE", 1)
    if local_ranks > torch.cuda.device_count():
        log.warning(
            "%d ranks on this node share %d GPU(s): NCCL needs one GPU per rank, using gloo",
            local_ranks,
            torch.cuda.device_count(),
        )
        return "gloo"
    return "nccl"


def barrier() -> None:
    """Wait until every rank gets here; does nothing without a process group."""
    if not _group_started():
        return
    if torch.distributed.get_backend() == "nccl":
        torch.distributed.barrier(device_ids=[torch.cuda.current_device()])
    else:
        torch.distributed.barrier()


def gather_to_main(obj: T) -> list[T]:
    """Every rank's ``obj`` (picklable), in rank order, on rank 0; ``[]`` on the other ranks, ``[obj]`` without a group."""
    if not _group_started():
        return [obj]
    info = rank_info()
    gathered: list[T] | None = [None] * info.world_size if info.is_main else None  # type: ignore[list-item]
    torch.distributed.gather_object(obj, gathered, dst=0)
    return gathered if gathered is not None else []


def _group_started() -> bool:
    """True when a default process group is running in this process."""
    return torch.distributed.is_available() and torch.distributed.is_initialized()


def broadcast_from_main(obj: T) -> T:
    """Rank 0's ``obj`` (picklable; tensors in it on the CPU) on every rank; ``obj`` itself without a group."""
    if not _group_started():
        return obj
    box = [obj]
    torch.distributed.broadcast_object_list(box, src=0)
    return box[0]


def broadcast_tensor_from_main(tensor: torch.Tensor) -> torch.Tensor:
    """Overwrite ``tensor`` (any shape, on this rank's device) with rank 0's, in place; returns it."""
    if _group_started():
        torch.distributed.broadcast(tensor, src=0)
    return tensor


def all_reduce_sum(tensor: torch.Tensor) -> torch.Tensor:
    """Replace ``tensor`` (any shape, on this rank's device) by its sum over the ranks, in place; returns it."""
    if _group_started():
        torch.distributed.all_reduce(tensor, op=torch.distributed.ReduceOp.SUM)
    return tensor


def destroy_process_group() -> None:
    """End the default process group, if one is started."""
    if _group_started():
        torch.distributed.destroy_process_group()


@contextlib.contextmanager
def process_group(device: str | torch.device | None = "auto", timeout_minutes: float = 30.0) -> Iterator[torch.device]:
    """Start the process group under torchrun for the block and end it afterwards; yields this rank's device.

    A group started by someone else is used and left running; without torchrun the block
    runs as a single process.
    """
    resolved = local_device(device)
    started = init_process_group(resolved, timeout_minutes=timeout_minutes)
    try:
        yield resolved
    finally:
        if started:
            destroy_process_group()
