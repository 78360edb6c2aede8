"""The gSCAN seq2seq baseline (Ruis et al. 2020; LauraRuis/multimodal_seq2seq_gSCAN "MM"), in the same framework.

Command: embedding -> 1-layer BiLSTM on packed sequences (directions summed). World: the
same 3-branch CNN, on the *initial* state only (the baseline never sees later states).
Decoder (MM's `BahdanauAttentionDecoderRNN`, conditional attention on): an LSTM whose
(h, c) start as tanh(W · the encoder's final state); each step reads the previous
action's embedding, a Bahdanau context over the command (query h) and one over the cells
(query tanh(W [h; command context])), and the logits come from the embedding, the new
state and both contexts through two bias-free linear maps. Teacher forcing feeds gold
previous actions; closed-loop decoding feeds its own.

`AttentionDecoderModel` is this decoder with teacher forcing and closed-loop decoding, for
every model that decodes this way (`auxloss.AuxLoss`, `lcgn.LCGN`); `Seq2Seq` adds the
baseline's encoders.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gscan_ros.errors import CommandError, quoted
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
    """Command-token embedding width (the previous action's embedding is `hidden` wide, as MM's)."""
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
        check_settings(self, ("embedding_dim", "hidden", "cnn_channels", "num_actions", "grid_size"),
                       ("dropout", "cnn_dropout"))


def check_settings(cfg, sizes: tuple[str, ...], rates: tuple[str, ...]) -> None:
    """ValueError unless the settings `sizes` of `cfg` are positive integers, its `rates` numbers
    in [0, 1) and its `cnn_kernels` odd positive integers (stored as a tuple). Settings come
    from YAML and checkpoints: a list, a float or a negative fails here, not in torch."""
    for name in sizes:
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {quoted(value)}")
    kernels = cfg.cnn_kernels
    if not (isinstance(kernels, (list, tuple)) and kernels
            and all(isinstance(k, int) and not isinstance(k, bool) and k > 0 and k % 2 for k in kernels)):
        raise ValueError(f"cnn_kernels must be a non-empty list of odd positive integers, got {quoted(kernels)}")
    object.__setattr__(cfg, "cnn_kernels", tuple(kernels))
    for name in rates:
        value = getattr(cfg, name)
        if not (isinstance(value, (int, float)) and 0 <= value < 1):
            raise ValueError(f"{name} must be a number in [0, 1), got {quoted(value)}")


@dataclass
class Seq2SeqBatch:
    """Teacher-forcing inputs of the baseline: it reads the command and the initial state only."""

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


def packed_lstm(lstm: nn.LSTM, embedded: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A bidirectional `lstm` over padded token embeddings [n, tokens, E] on packed sequences, so
    padding never enters it: outputs [n, tokens, 2H] (zero on padding) and final states [2, n, H]."""
    packed = nn.utils.rnn.pack_padded_sequence(embedded, mask.sum(1).cpu(), batch_first=True, enforce_sorted=False)
    out, (h_n, _) = lstm(packed)
    out, _ = nn.utils.rnn.pad_packed_sequence(out, batch_first=True, total_length=mask.shape[1])
    return out, h_n


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


class Seq2Seq(AttentionDecoderModel):
    """MM's `Model` with its `BahdanauAttentionDecoderRNN` (conditional attention on)."""

    kind = "seq2seq"

    def __init__(self, cfg: Seq2SeqConfig, tokens: list[str]):
        super().__init__(cfg, tokens)
        E, H = cfg.embedding_dim, cfg.hidden
        self.embed = nn.Embedding(len(self.tokens) + 1, E, padding_idx=0)
        self.encoder = nn.LSTM(E, H, batch_first=True, bidirectional=True)
        self.enc_to_dec = nn.Linear(H, H)  # the encoder's final state -> the decoder's initial (h, c)
        self.visual = VisualEncoder(ModelConfig(cnn_kernels=cfg.cnn_kernels, cnn_channels=cfg.cnn_channels,
                                                cnn_dropout=cfg.cnn_dropout, grid_size=cfg.grid_size))
        self.action_embed = nn.Embedding(cfg.num_actions + 1, H)  # last id = start of sequence
        self.text_att = AdditiveAttention(H, H, H)
        self.world_query = nn.Linear(2 * H, H)  # conditional attention: tanh(W [h; command context])
        self.world_att = AdditiveAttention(H, self.visual.cfg.feature_dim, H)
        self.decoder = nn.LSTMCell(3 * H, H)
        self.pre_out = nn.Linear(4 * H, H, bias=False)
        self.out = nn.Linear(H, cfg.num_actions, bias=False)
        self.drop = nn.Dropout(cfg.dropout)

    def encode_commands(self, commands: list[str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Encoder outputs [n, tokens, H] and final state [n, H] (both directions summed), and
        the token mask."""
        padded = self.token_ids(commands)
        mask = padded > 0
        out, h_n = packed_lstm(self.encoder, self.drop(self.embed(padded)), mask)
        H = self.cfg.hidden
        return out[..., :H] + out[..., H:], h_n[0] + h_n[1], mask

    def encode(self, commands: list[str], first_states: np.ndarray):
        """`encode_commands` and the cell features [n, cells, F] of the initial states."""
        text, final, mask = self.encode_commands(commands)
        return text, final, mask, self.visual(*sparse_states(first_states, self.device))

    def _start(self, commands, first_states) -> DecoderState:
        text, final, mask, world = self.encode(commands, first_states)
        return self.decoder_state(text, mask, world, torch.tanh(self.enc_to_dec(final)))


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
