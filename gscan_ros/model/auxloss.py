"""AuxLoss (Heinze-Deml & Bouchacourt 2020, "Think before you act"): the seq2seq baseline that
first finds the target, then decodes.

Think, once per episode: the encoder's final state attends over the command (the
attention-weighted command c̄); tanh(W [final; c̄]) attends over the cells, and that
attention's logits are the target-location classifier over the grid cells (it reads c̄ and
every cell's world encoding; additive attention, or scaled dot products with
`think_scorer: dot`); the cells weighted by its softmax are the attention-weighted
world w̄. Act: the baseline's decoder (`seq2seq.Seq2Seq`, unchanged), whose initial state
also reads the thought: (h, c) = tanh(W final + W' [c̄; w̄]). Training adds
`target_loss_weight` x the classifier's cross-entropy against the target's cell to the
baseline's action loss. The paper has no public code; docs/model.md, "AuxLoss", lists
the choices made here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gscan_ros.model.config import AuxLossConfig
from gscan_ros.model.decoder import AdditiveAttention, DecoderState, Seq2SeqBatch
from gscan_ros.model.seq2seq import Seq2Seq


@dataclass
class AuxLossBatch(Seq2SeqBatch):
    """The baseline's batch plus the label of the auxiliary classifier."""

    target_cells: torch.Tensor  # [n] the target object's cell, row * grid_size + column


@dataclass
class Thought:
    """What thinking computes from a batch's encodings, before any action."""

    summary: torch.Tensor  # [n, 2H] the attention-weighted command and world, [c̄; w̄]
    target_logits: torch.Tensor  # [n, cells] the target-location classifier's logits


class DotScorer(nn.Module):
    """Scaled dot-product scores q(query)·k(key)/√hidden, no biases: linear in each key, so
    a cell's score is the sum of what its features contribute (`think_scorer: dot`)."""

    def __init__(self, query: int, key: int, hidden: int):
        super().__init__()
        self.q = nn.Linear(query, hidden, bias=False)
        self.k = nn.Linear(key, hidden, bias=False)
        self.scale = 1.0 / math.sqrt(hidden)

    def scores(self, query, projected_keys):
        """The logit of each key [n, keys]."""
        return torch.bmm(projected_keys, self.q(query)[:, :, None])[..., 0] * self.scale


class AuxLoss(Seq2Seq):
    """`Seq2Seq` with a think step before decoding (module docstring)."""

    kind = "auxloss"

    def __init__(self, cfg: AuxLossConfig, tokens: list[str]):
        super().__init__(cfg, tokens)
        H = cfg.hidden
        self.think_text = AdditiveAttention(H, H, H)  # query: the encoder's final state
        self.think_query = nn.Linear(2 * H, H)  # tanh(W [final; c̄]) asks for the target
        scorer = DotScorer if cfg.think_scorer == "dot" else AdditiveAttention
        self.think_world = scorer(H, self.visual.cfg.feature_dim, H)  # its logits: the classifier
        self.think_to_dec = nn.Linear(2 * H, H, bias=False)  # the thought joins the decoder's initial state

    def think(self, text, final, mask, world) -> Thought:
        """c̄, the target-location logits and w̄ from the encodings (`Seq2Seq.encode`)."""
        command, _ = self.think_text(final, self.think_text.k(text), mask)
        world_keys = self.think_world.k(world)
        query = torch.tanh(self.think_query(torch.cat([final, command], -1)))
        logits = self.think_world.scores(query, world_keys)
        located = torch.bmm(torch.softmax(logits, -1)[:, None], world_keys)[:, 0]
        return Thought(torch.cat([command, located], -1), logits)

    def _think_start(self, commands, first_states) -> tuple[DecoderState, Thought]:
        text, final, mask, world = self.encode(commands, first_states)
        thought = self.think(text, final, mask, world)
        h0 = torch.tanh(self.enc_to_dec(final) + self.think_to_dec(thought.summary))
        return self.decoder_state(text, mask, world, h0), thought

    def _start(self, commands, first_states) -> DecoderState:
        return self._think_start(commands, first_states)[0]

    def _teacher_start(self, batch: AuxLossBatch, rows: list[int]) -> tuple[DecoderState, torch.Tensor]:
        """The decoder state of `rows` and the weighted target-location loss (mean over the rows)."""
        st, thought = self._think_start([batch.commands[i] for i in rows], np.asarray(batch.first_states)[rows])
        cells = batch.target_cells.to(self.device)[rows]
        return st, self.cfg.target_loss_weight * F.cross_entropy(thought.target_logits, cells)

    def make_batch(self, store, ids) -> AuxLossBatch:
        """The baseline's batch and the target cells (`EpisodeStore.target_cells`)."""
        base = super().make_batch(store, ids)
        return AuxLossBatch(base.commands, base.first_states, base.targets,
                            torch.from_numpy(store.target_cells(np.asarray(ids))))
