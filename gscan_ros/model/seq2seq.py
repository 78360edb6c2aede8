"""The gSCAN seq2seq baseline (Ruis et al. 2020; LauraRuis/multimodal_seq2seq_gSCAN), in the same framework.

Command: embedding -> 1-layer BiLSTM (directions summed). World: the same 3-branch CNN,
on the *initial* state only (the baseline never sees later states). Decoder: an LSTM
fed the previous action, with additive (Bahdanau) attention over the command and
attention over the 36 cells conditioned on the command context. Teacher forcing feeds
gold previous actions; closed-loop decoding feeds its own.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gscan_ros.errors import CommandError
from gscan_ros.model.checkpoint import SerializableConfig
from gscan_ros.model.compositional import ModelConfig, VisualEncoder
from gscan_ros.model.sparse_encoder import sparse_states
from gscan_ros.model.teacher_forcing import TeacherOutput
from gscan_ros.world.types import GRID_SIZE, Action


def command_vocabulary() -> list[str]:
    """The 18 gSCAN command tokens ("while spinning" is one token)."""
    from gscan_ros.language.tokens import VOCABULARY

    return sorted(VOCABULARY)


@dataclass(frozen=True)
class Seq2SeqConfig(SerializableConfig):
    """Hyper-parameters of the baseline (defaults: MM `all_experiments.sh`)."""

    embedding_dim: int = 25
    """Command-token and previous-action embedding width."""
    hidden: int = 100
    """Encoder (per direction, summed) and decoder LSTM width."""
    dropout: float = 0.3
    """Dropout on embeddings and decoder outputs."""
    cnn_kernels: tuple[int, ...] = (1, 5, 7)
    """Kernel sizes of the shared-design visual encoder."""
    cnn_channels: int = 50
    """Channels per conv branch."""
    cnn_dropout: float = 0.1
    """Dropout on the cell features."""
    num_actions: int = len(Action)
    """Output classes: six actions + EOS (`Action` values)."""
    grid_size: int = GRID_SIZE
    """Side of the square grid the observations have (6 compositional, 12 for split I)."""

    def __post_init__(self) -> None:
        # Sizes come from YAML and checkpoints: a list, a float or a negative fails here, not in torch.
        for name in ("embedding_dim", "hidden", "cnn_channels", "num_actions", "grid_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        kernels = self.cnn_kernels
        if not (isinstance(kernels, (list, tuple)) and kernels
                and all(isinstance(k, int) and not isinstance(k, bool) and k > 0 and k % 2 for k in kernels)):
            raise ValueError(f"cnn_kernels must be a non-empty list of odd positive integers, got {kernels!r}")
        object.__setattr__(self, "cnn_kernels", tuple(kernels))
        for name in ("dropout", "cnn_dropout"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 <= value < 1):
                raise ValueError(f"{name} must be a number in [0, 1), got {value!r}")


@dataclass
class Seq2SeqBatch:
    """Teacher-forcing inputs of the baseline: it reads the command and the initial state only."""

    commands: list[str]
    first_states: np.ndarray  # uint8 [n, g, g, C]
    targets: torch.Tensor  # [n, T_max] action ids (EOS last), -1 past an episode's end


@dataclass
class DecoderState:
    """What decoding a batch of commands carries from step to step (one row per command)."""

    text: torch.Tensor  # [n, tokens, H] encoded command
    text_keys: torch.Tensor  # [n, tokens, H] the command attention's key projection of `text`
    text_mask: torch.Tensor  # [n, tokens] bool, False on padding tokens
    world: torch.Tensor  # [n, cells, H] projected features of the initial state
    world_keys: torch.Tensor  # [n, cells, H] the world attention's key projection of `world`
    h: torch.Tensor  # [n, H] decoder LSTM state
    c: torch.Tensor  # [n, H] decoder LSTM cell

    def select(self, rows: torch.Tensor) -> "DecoderState":
        return DecoderState(*(getattr(self, f.name).index_select(0, rows) for f in dataclasses.fields(self)))

    def prefix(self, n: int) -> "DecoderState":
        """The first `n` rows (views, no copy)."""
        return DecoderState(*(getattr(self, f.name)[:n] for f in dataclasses.fields(self)))


class _Additive(nn.Module):
    """Bahdanau attention. The keys do not change while a sequence decodes, so their
    projection `k(keys)` is computed once per sequence (`_start`) and passed in."""

    def __init__(self, query: int, key: int, hidden: int):
        super().__init__()
        self.q, self.k, self.v = nn.Linear(query, hidden), nn.Linear(key, hidden, bias=False), nn.Linear(hidden, 1)

    def forward(self, query, keys, projected_keys, mask=None):
        score = self.v(torch.tanh(self.q(query)[:, None] + projected_keys))[..., 0]
        if mask is not None:
            score = score.masked_fill(~mask, float("-inf"))
        weights = torch.softmax(score, -1)
        return torch.bmm(weights[:, None], keys)[:, 0], weights


class Seq2Seq(nn.Module):
    def __init__(self, cfg: Seq2SeqConfig, tokens: list[str]):
        super().__init__()
        self.cfg, self.tokens = cfg, list(tokens)
        self.index = {t: i + 1 for i, t in enumerate(self.tokens)}  # 0 = padding
        E, H = cfg.embedding_dim, cfg.hidden
        self.embed = nn.Embedding(len(self.tokens) + 1, E, padding_idx=0)
        self.encoder = nn.LSTM(E, H, batch_first=True, bidirectional=True)
        self.visual = VisualEncoder(ModelConfig(cnn_kernels=cfg.cnn_kernels, cnn_channels=cfg.cnn_channels,
                                                cnn_dropout=cfg.cnn_dropout, grid_size=cfg.grid_size))
        self.visual_proj = nn.Linear(self.visual.cfg.feature_dim, H)
        self.action_embed = nn.Embedding(cfg.num_actions + 1, E)  # last id = start of sequence
        self.decoder = nn.LSTMCell(E + 2 * H, H)
        self.text_att = _Additive(H, H, H)
        self.world_att = _Additive(2 * H, H, H)
        self.out = nn.Linear(3 * H, cfg.num_actions)
        self.drop = nn.Dropout(cfg.dropout)

    @property
    def sos(self) -> int:
        return self.cfg.num_actions

    @property
    def device(self) -> torch.device:
        return self.out.weight.device

    def encode_commands(self, commands: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        from gscan_ros.language.tokens import tokenize

        ids = []
        for c in commands:
            toks = tokenize(c)
            unknown = [t for t in toks if t not in self.index]
            if unknown:
                raise CommandError(f"tokens {unknown} are not in the model's vocabulary")
            ids.append([self.index[t] for t in toks])
        width = max(len(i) for i in ids)
        padded = torch.tensor([i + [0] * (width - len(i)) for i in ids], device=self.device)
        mask = padded > 0
        out, _ = self.encoder(self.drop(self.embed(padded)))
        H = self.cfg.hidden
        return out[..., :H] + out[..., H:], mask

    def _start(self, commands, first_states) -> DecoderState:
        text, mask = self.encode_commands(commands)
        world = self.visual_proj(self.visual(*sparse_states(first_states, self.device)))
        n, H = len(commands), self.cfg.hidden
        return DecoderState(text, self.text_att.k(text), mask, world, self.world_att.k(world),
                            text.new_zeros(n, H), text.new_zeros(n, H))

    def _decode(self, st: DecoderState, prev: torch.Tensor) -> torch.Tensor:
        """Action logits of one step after action `prev`; advances `st` in place."""
        text_ctx, _ = self.text_att(st.h, st.text, st.text_keys, st.text_mask)
        world_ctx, _ = self.world_att(torch.cat([st.h, text_ctx], -1), st.world, st.world_keys)
        x = torch.cat([self.drop(self.action_embed(prev)), text_ctx, world_ctx], -1)
        st.h, st.c = self.decoder(x, (st.h, st.c))
        return self.out(self.drop(torch.cat([st.h, text_ctx, world_ctx], -1)))

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
        rows = order.tolist()
        st = self._start([batch.commands[i] for i in rows], np.asarray(batch.first_states)[rows])
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
        return TeacherOutput(per_example.mean(), logits_t[valid], nll, torch.zeros_like(nll))

    def rollout(self, graphs) -> "Seq2SeqRollout":
        return Seq2SeqRollout(self, [g.command for g in graphs])


class Seq2SeqRollout:
    """Closed-loop greedy decoding: the first observation is encoded, later ones are
    ignored; each step feeds back the step before's argmax action."""

    def __init__(self, model: Seq2Seq, commands: list[str]):
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
