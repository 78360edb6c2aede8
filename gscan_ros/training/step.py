"""One training update, shared by the trainer, bench/train.py and the overfit test, so
what is timed and tested is what trains: batch -> forward -> finite check -> backward ->
clip -> Adam -> schedule."""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from gscan_ros.errors import GscanError
from gscan_ros.training import distributed
from gscan_ros.training.batches import EpisodeStore


class TrainingDiverged(GscanError):
    """The loss became NaN or infinite; the update that saw it was not applied."""


def teacher_batch(model: torch.nn.Module, store: EpisodeStore, ids: Sequence[int]):
    """The teacher-forcing input of episodes `ids` in the form `model` takes."""
    if model.kind == "compositional":
        return store.batch(ids, model.table, model.active_rows_multiple)
    return model.make_batch(store, ids)


class TrainStep:
    """Updates `model` on one global batch of episode ids per call; returns the batch's loss.

    Under several ranks (`ranks.distributed`) the model is wrapped in
    DistributedDataParallel here, each rank runs its shard of the batch
    (`distributed.shard_batch`), and the returned loss and the finite check cover the
    whole batch, so every rank stops at the same update.
    """

    def __init__(self, model: torch.nn.Module, optimizer: torch.optim.Optimizer, store: EpisodeStore,
                 scheduler: torch.optim.lr_scheduler.LRScheduler | None = None, grad_clip: float = 0.0,
                 ranks: distributed.Ranks = distributed.Ranks()):
        self.model, self.optimizer, self.store = model, optimizer, store
        self.scheduler, self.grad_clip, self.ranks = scheduler, grad_clip, ranks
        self.net = model
        if ranks.distributed:
            # Some parameters never get a gradient (att_out_b, cancelled by the softmax; att_state_*
            # unless attention_state='add'). The model moves its batch itself (device_ids None).
            self.net = torch.nn.parallel.DistributedDataParallel(model, find_unused_parameters=True)

    def __call__(self, ids: np.ndarray) -> float:
        """Train on episodes `ids`; TrainingDiverged (weights untouched) on a non-finite loss."""
        self.model.train()
        shard, weight = distributed.shard_batch(ids, self.store.lengths, self.ranks)
        loss = self.net(teacher_batch(self.model, self.store, shard)).loss
        if weight != 1.0:
            loss = loss * weight
        batch_loss, finite = self._whole_batch(loss)
        if not finite:
            raise TrainingDiverged(f"the loss became {batch_loss}")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.grad_clip:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.grad_clip)
        self.optimizer.step()
        if self.scheduler is not None:
            self.scheduler.step()
        return batch_loss

    def _whole_batch(self, loss: torch.Tensor) -> tuple[float, bool]:
        """The whole batch's loss (DDP's average of the shards') and whether every rank's is finite."""
        if not self.ranks.distributed:
            return float(loss.detach()), bool(torch.isfinite(loss))
        stats = self.ranks.reduce_sum(torch.stack([loss.detach() / self.ranks.world_size,
                                                   (~torch.isfinite(loss)).float()]))
        return float(stats[0]), not bool(stats[1])
