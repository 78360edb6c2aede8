"""torch.distributed for training and evaluation: joining a `torchrun` job, and the few
collectives the loops need besides DistributedDataParallel's own.

`torchrun` starts one process per rank with RANK, LOCAL_RANK, WORLD_SIZE, MASTER_ADDR and
MASTER_PORT in the environment; `joined` reads them, picks the device (GPU `LOCAL_RANK`
with 'cuda') and the backend (nccl on CUDA, gloo on the CPU), and leaves the group at the
end. Without torchrun (or with one process) nothing is joined and every helper here is
the identity, so the single-process path is the one it always was.
"""
from __future__ import annotations

import gc
import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Callable, Iterator, Sequence, TypeVar

import numpy as np
import torch
import torch.distributed as dist

from gscan_ros.runtime import resolve_device

T = TypeVar("T")

# Rank 0 validates while the others wait in their next collective: long enough for a
# validation on a whole dev split, short enough that a hung job ends the same day.
TIMEOUT = timedelta(hours=2)


@dataclass(frozen=True)
class Ranks:
    """This process's place in the job (rank 0 of 1 without torchrun) and its device."""

    rank: int = 0
    world_size: int = 1
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    def from_main(self, fn: Callable[[], T]) -> T:
        """fn() run on rank 0 only; its result, or the exception it raised, reaches every
        rank (so a refusal on rank 0 stops all ranks with the same error)."""
        if not self.distributed:
            return fn()
        box: list = [None]
        if self.is_main:
            try:
                box = [(True, fn())]
            except Exception as exc:  # re-raised below, on every rank
                box = [(False, exc)]
        dist.broadcast_object_list(box, src=0)
        ok, value = box[0]
        if not ok:
            raise value
        return value

    def reduce_sum(self, values: torch.Tensor) -> torch.Tensor:
        """The element-wise sum of `values` over the ranks."""
        if self.distributed:
            values = values.clone()
            dist.all_reduce(values)
        return values

    def gather_to_main(self, obj: T) -> list[T] | None:
        """Every rank's `obj`, in rank order, on rank 0; None on the others."""
        if not self.distributed:
            return [obj]
        out = [None] * self.world_size if self.is_main else None
        dist.gather_object(obj, out, dst=0)
        return out


def launched_ranks() -> int:
    """WORLD_SIZE of the torchrun job this process belongs to (1 without torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


@contextmanager
def joined(device: str | torch.device = "cpu", backend: str | None = None) -> Iterator[Ranks]:
    """This process's `Ranks`: it joins the torchrun job when started by one with several
    ranks (backend: nccl on CUDA, gloo on the CPU, unless given) and leaves it at the end.
    Inside a group that is already up, the group is used and left alone."""
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    dev = resolve_device(device, local_rank)
    if dist.is_available() and dist.is_initialized():
        yield Ranks(dist.get_rank(), dist.get_world_size(), dev)
        return
    if launched_ranks() <= 1:
        yield Ranks(device=dev)
        return
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    dist.init_process_group(backend or ("nccl" if dev.type == "cuda" else "gloo"), timeout=TIMEOUT)
    try:
        yield Ranks(dist.get_rank(), dist.get_world_size(), dev)
        # No rank tears its connections down while another still has a message in flight
        # to it (not on an error: the other ranks may never get here).
        dist.barrier()
    finally:
        # A DistributedDataParallel wrapper sits in reference cycles and keeps the group
        # alive; left to interpreter exit, its gloo threads abort the process
        # now and then ("terminate called without an active exception").
        gc.collect()
        dist.destroy_process_group()


def shard_batch(ids: np.ndarray, lengths: np.ndarray, ranks: Ranks) -> tuple[np.ndarray, float]:
    """This rank's part of a global batch `ids` and the weight of its (mean) loss.

    The rows are sorted by length and dealt round-robin, so every rank gets long and short
    episodes alike. The weight n_r * W / B makes DDP's average of the W ranks' gradients
    the gradient of the whole batch's mean loss, also for unequal shards (a last batch
    that does not divide). A rank left with no row (a batch smaller than W) runs one row
    at weight 0: every rank must run forward and backward for DDP's all-reduce.
    """
    if not ranks.distributed:
        return ids, 1.0
    by_length = np.asarray(ids)[np.argsort(-lengths[ids], kind="stable")]
    shard = by_length[ranks.rank :: ranks.world_size]
    if not len(shard):
        return by_length[:1], 0.0
    return shard, len(shard) * ranks.world_size / len(ids)


def shard_of(items: Sequence[T], ranks: Ranks) -> Sequence[T]:
    """Every world_size-th item, starting at this rank's."""
    return items[ranks.rank :: ranks.world_size]
