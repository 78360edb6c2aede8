"""The attention decoder of the gSCAN baseline (Ruis et al. 2020; LauraRuis/multimodal_seq2seq_gSCAN
"MM", its `BahdanauAttentionDecoderRNN` with conditional attention on), shared by every model
that decodes this way: `seq2seq.Seq2Seq`, `auxloss.AuxLoss` and `lcgn.LCGN`.

An LSTM whose (h, c) start from the model's encodings; each step reads the previous
action's embedding, a Bahdanau context over the command (query h) and one over the cells
(query tanh(W [h; command context])), and the logits come from the embedding, the new
state and both contexts through two bias-free linear maps. Teacher forcing feeds gold
previous actions; closed-loop decoding feeds its own.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gscan_ros.errors import CommandError
from gscan_ros.model.config import SerializableConfig
from gscan_ros.model.teacher_forcing import TeacherOutput


def command_vocabulary() -> list[str]:
    """The 18 gSCAN command tokens ("while spinning" is one token)."""
    from gscan_ros.language.tokens import VOCABULARY

    return sorted(VOCABULARY)


@dataclass
class Seq2SeqBatch:
    """Teacher-forcing inputs of the decoder models: they read the command and the initial state only."""

    commands: list[str]
    first_states: np.ndarray  # uint8 [n, g, g, C]
    targets: torch.Tensor  # [n, T_max] action ids (EOS last), -1 past an episode's end


@dataclass
class DecoderState:
    """What decoding a batch of commands carries from step to step (one row per command)."""

    text_keys: torch.Tensor  # [n, tokens, H] the command attention's keys (and values): k(encoder outputs)
    text_mask: torch.Tensor  # [n, tokens] bool, False on padding tokens
    world_keys: torch.Tensor  # [n, cells, H] the world attention's keys (and values): k(cell features)
    h: torch.Tensor  # [n, H] decoder LSTM state
    c: torch.Tensor  # [n, H] decoder LSTM cell

    def select(self, rows: torch.Tensor) -> "DecoderState":
        return DecoderState(*(getattr(self, f.name).index_select(0, rows) for f in dataclasses.fields(self)))

    def prefix(self, n: int) -> "DecoderState":
        """The first `n` rows (views, no copy)."""
        return DecoderState(*(getattr(self, f.name)[:n] for f in dataclasses.fields(self)))


class AdditiveAttention(nn.Module):
    """Bahdanau attention as MM's `Attention`: v·tanh(q(query) + k(key)), no biases, and the
    retrieved values are the projected keys themselves. The keys do not change while a
    sequence decodes, so `k(keys)` is computed once per sequence (`_start`) and passed in."""

    def __init__(self, query: int, key: int, hidden: int):
        super().__init__()
        self.q = nn.Linear(query, hidden, bias=False)
        self.k = nn.Linear(key, hidden, bias=False)
        self.v = nn.Linear(hidden, 1, bias=False)

    def scores(self, query, projected_keys, mask=None):
        """The logit of each key [n, keys] (-inf where `mask` is False)."""
        score = self.v(torch.tanh(self.q(query)[:, None] + projected_keys))[..., 0]
        return score if mask is None else score.masked_fill(~mask, float("-inf"))

    def forward(self, query, projected_keys, mask=None):
        """The retrieved value [n, hidden] and the attention weights [n, keys]."""
        weights = torch.softmax(self.scores(query, projected_keys, mask), -1)
        return torch.bmm(weights[:, None], projected_keys)[:, 0], weights


class AttentionDecoderModel(nn.Module):
    """What the models with MM's decoder share (the baseline, AuxLoss, LCGN): command tokens,
    teacher forcing, closed-loop decoding and the batch they train on.

    A subclass builds its encoders and the decoder's modules — `action_embed`, `text_att`,
    `world_query`, `world_att`, `decoder` (an LSTMCell), `out` and `drop` (on the previous
    action's embedding) — and implements `_start`: a batch of commands and initial states
    -> the `DecoderState` decoding starts from.
    """

    def __init__(self, cfg: SerializableConfig, tokens: list[str]):
        super().__init__()
        self.cfg, self.tokens = cfg, list(tokens)
        self.index = {t: i + 1 for i, t in enumerate(self.tokens)}  # 0 = padding

    @property
    def sos(self) -> int:
        return self.cfg.num_actions

    @property
    def device(self) -> torch.device:
        return self.out.weight.device

    def token_ids(self, commands: list[str]) -> torch.Tensor:
        """[n, tokens] vocabulary ids of the commands' tokens, 0-padded; CommandError on a token
        the model does not know."""
        from gscan_ros.language.tokens import tokenize

        ids = []
        for c in commands:
            toks = tokenize(c)
            unknown = [t for t in toks if t not in self.index]
            if unknown:
                raise CommandError(f"tokens {unknown} are not in the model's vocabulary")
            ids.append([self.index[t] for t in toks])
        width = max(len(i) for i in ids)
        return torch.tensor([i + [0] * (width - len(i)) for i in ids], device=self.device)

    def _start(self, commands: list[str], first_states: np.ndarray) -> DecoderState:
        """The state decoding `commands` in their initial states `first_states` starts from."""
        raise NotImplementedError

    def decoder_state(self, text, mask, world, h0) -> DecoderState:
        """The state decoding starts from: the attentions' keys and (h, c) = (h0, h0), as MM fills both."""
        return DecoderState(self.text_att.k(text), mask, self.world_att.k(world), h0, h0)

    def _decode(self, st: DecoderState, prev: torch.Tensor) -> torch.Tensor:
        """Action logits of one step after action `prev`; advances `st` in place."""
        emb = self.drop(self.action_embed(prev))
        text_ctx, _ = self.text_att(st.h, st.text_keys, st.text_mask)
        world_ctx, _ = self.world_att(torch.tanh(self.world_query(torch.cat([st.h, text_ctx], -1))), st.world_keys)
        st.h, st.c = self.decoder(torch.cat([emb, text_ctx, world_ctx], -1), (st.h, st.c))
        return self._readout(emb, st.h, text_ctx, world_ctx)

    def _readout(self, emb, h, text_ctx, world_ctx) -> torch.Tensor:
        """MM's output layer: the embedding, the new state and both contexts through two
        bias-free linear maps."""
        return self.out(self.pre_out(torch.cat([emb, h, text_ctx, world_ctx], -1)))

    def make_batch(self, store, ids) -> Seq2SeqBatch:
        """Teacher-forcing inputs from an EpisodeStore: commands, initial states, targets."""
        ids = np.asarray(ids)
        first = store.initial_states(ids)
        targets = [store.actions[store.ep_ptr[i] : store.ep_ptr[i + 1]] for i in ids]
        T = max(len(t) for t in targets)
        tgt = torch.full((len(ids), T), -1, dtype=torch.long)
        for b, t in enumerate(targets):
            tgt[b, : len(t)] = torch.from_numpy(t)
        return Seq2SeqBatch([store.commands[i] for i in ids], first, tgt)

    def forward(self, batch: Seq2SeqBatch) -> TeacherOutput:
        """Teacher forcing: the call DistributedDataParallel wraps."""
        return self.teacher_forcing(batch)

    def teacher_forcing(self, batch: Seq2SeqBatch) -> TeacherOutput:
        """Every step of the batch, gold previous actions fed. The rows are decoded longest
        first, and step t runs only the rows still inside their episode (a prefix), so a
        mixed batch does not decode its short episodes' padding."""
        targets = batch.targets.to(self.device)
        lengths = (targets >= 0).sum(1)
        targets = targets[:, : int(lengths.max())]
        valid = targets >= 0
        order = torch.argsort(lengths, descending=True, stable=True)
        active = torch.bincount(lengths, minlength=targets.shape[1] + 1).flip(0).cumsum(0).flip(0)[1:].tolist()
        st, start_loss = self._teacher_start(batch, order.tolist())
        gold = targets.index_select(0, order)
        prev = torch.full((len(targets),), self.sos, dtype=torch.long, device=self.device)
        logits_sorted = []
        for t, n_t in enumerate(active):  # n_t rows have a step t
            st = st.prefix(n_t)
            out = self._decode(st, prev[:n_t])
            logits_sorted.append(F.pad(out, (0, 0, 0, len(targets) - n_t)))
            prev = gold[:, t].clamp(min=0)
        logits_t = torch.stack(logits_sorted, 1).index_select(0, torch.argsort(order))
        nll = F.cross_entropy(logits_t[valid], targets[valid], reduction="none")
        per_example = nll.new_zeros(len(targets)).index_add(0, valid.nonzero()[:, 0], nll) / valid.sum(1)
        return TeacherOutput(per_example.mean() + start_loss, logits_t[valid], nll, torch.zeros_like(nll))

    def _teacher_start(self, batch: Seq2SeqBatch, rows: list[int]) -> tuple[DecoderState, torch.Tensor | float]:
        """The decoder state of the batch's `rows`, in that order, and the loss of what the
        start predicts besides it: nothing here (AuxLoss: the target's location)."""
        return self._start([batch.commands[i] for i in rows], np.asarray(batch.first_states)[rows]), 0.0

    def rollout(self, graphs) -> "Seq2SeqRollout":
        return Seq2SeqRollout(self, [g.command for g in graphs])


class Seq2SeqRollout:
    """Closed-loop greedy decoding: the first observation is encoded, later ones are
    ignored; each step feeds back the step before's argmax action."""

    def __init__(self, model: AttentionDecoderModel, commands: list[str]):
        self.model, self.commands, self.state = model, commands, None
        self.prev = torch.full((len(commands),), model.sos, dtype=torch.long, device=model.device)
        self.words = [[] for _ in commands]  # no per-word attention maps

    def step(self, observations: np.ndarray):
        if self.state is None:
            self.state = self.model._start(self.commands, observations)
        logits = self.model._decode(self.state, self.prev)
        self.prev = logits.argmax(-1)
        return logits, None

    def keep(self, rows: torch.Tensor) -> None:
        self.commands = [self.commands[i] for i in rows.tolist()]
        self.words = [self.words[i] for i in rows.tolist()]
        rows = rows.to(self.prev.device)
        self.state = self.state.select(rows)
        self.prev = self.prev.index_select(0, rows)
