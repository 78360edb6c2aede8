"""LCGN for gSCAN (Gao, Huang & Mooney 2020; HQ01/gSCAN_with_language_conditioned_embedding), in
the same framework: the initial state's occupied cells are the nodes of a fully connected
graph whose features T rounds of language-conditioned message passing (Hu et al. 2019)
contextualise, and the baseline's decoder reads them.

Command: embedding -> BiLSTM on packed sequences, the two directions concatenated.
Nodes: every occupied cell (an object, the agent, or both), embedded per attribute — size,
shape, colour and agent+heading, each a bias-free linear map of its one-hot channels,
concatenated. Round t: a textual command c_t = attention over the command's words with a
query of the round's own (W2_t relu(W3 final)); each node i receives the message
Σ_j softmax_j(dst_i · src_j) val_j from every other node j, with src and val gated by c_t,
and updates its context x_ctx. The nodes' outputs W [x_loc; x_ctx] go back to their cells
(empty cells are zero), the 3-branch CNN encodes that grid, and MM's decoder (`decoder.py`)
attends over its cells and the command; its logits read the LSTM state alone. The graph
is batched dense over all cells, with masks for empty cells and self-edges.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from gscan_ros.model.config import LCGNConfig, ModelConfig
from gscan_ros.model.decoder import AdditiveAttention, AttentionDecoderModel, DecoderState
from gscan_ros.model.encoders import VisualEncoder, packed_lstm
from gscan_ros.world.types import COLORS, NUM_CHANNELS, SHAPES, SIZES

# The 16 observation channels in attribute groups (the released order): sizes, shapes, colours,
# agent + its four headings.
ATTRIBUTE_CHANNELS = (len(SIZES), len(SHAPES), len(COLORS), NUM_CHANNELS - len(SIZES) - len(SHAPES) - len(COLORS))


class LanguageConditionedGraph(nn.Module):
    """The message passing of LCGN (Hu et al. 2019, as gSCAN's LCGN runs it: `model/gnn.py`).

    All linear maps are bias-free except the textual command's W3. Per round t, with
    cat = [x_loc; x_ctx; W4 drop(x_loc) ⊙ W5 drop(x_ctx)]:
        src = W7 cat ⊙ W8 c_t,  dst = W6 cat,  val = W9 cat ⊙ W10 c_t
        x_ctx <- W11 x_ctx + W11b Σ_{j≠i} softmax_j(dst_i · src_j) val_j
    """

    def __init__(self, cfg: LCGNConfig):
        super().__init__()
        C, N = cfg.command_dim, cfg.node_dim
        self.attributes = nn.ModuleList(nn.Linear(n, cfg.attribute_dim, bias=False) for n in ATTRIBUTE_CHANNELS)
        self.node_in = nn.Linear(len(ATTRIBUTE_CHANNELS) * cfg.attribute_dim, N, bias=False)
        self.initial_context = nn.Parameter(torch.randn(N))
        self.command_query = nn.Linear(C, C)  # W3
        self.round_query = nn.ModuleList(nn.Linear(C, C, bias=False) for _ in range(cfg.rounds))  # W2_t
        self.word_score = nn.Linear(C, 1, bias=False)  # W1
        self.fuse_loc, self.fuse_ctx = nn.Linear(N, N, bias=False), nn.Linear(N, N, bias=False)
        self.receiver = nn.Linear(3 * N, N, bias=False)  # W6
        self.sender, self.sender_gate = nn.Linear(3 * N, N, bias=False), nn.Linear(C, N, bias=False)  # W7, W8
        self.value, self.value_gate = nn.Linear(3 * N, N, bias=False), nn.Linear(C, N, bias=False)  # W9, W10
        self.keep_context, self.add_message = nn.Linear(N, N, bias=False), nn.Linear(N, N, bias=False)  # W11, W11b
        self.node_out = nn.Linear(2 * N, N, bias=False)  # W12
        self.read_drop = nn.Dropout(cfg.read_dropout)

    def textual_command(self, text, text_mask, final, t: int) -> torch.Tensor:
        """Round t's command vector [n, C]: the words weighted by softmax(W1 (e_i ⊙ W2_t relu(W3 final)))."""
        query = self.round_query[t](torch.relu(self.command_query(final)))
        score = self.word_score(text * query[:, None])[..., 0].masked_fill(~text_mask, float("-inf"))
        return torch.bmm(torch.softmax(score, -1)[:, None], text)[:, 0]

    def forward(self, states: torch.Tensor, text, text_mask, final) -> torch.Tensor:
        """One-hot states [n, cells, 16] -> node outputs [n, cells, N], zero on empty cells."""
        present = states.sum(-1) > 0  # [n, cells]
        edges = present[:, :, None] & present[:, None, :] & ~torch.eye(states.shape[1], dtype=torch.bool,
                                                                       device=states.device)
        groups = states.split(ATTRIBUTE_CHANNELS, -1)
        x_loc = self.node_in(torch.cat([embed(g) for embed, g in zip(self.attributes, groups)], -1))
        x_ctx = self.initial_context.expand_as(x_loc)
        for t in range(len(self.round_query)):
            command = self.textual_command(text, text_mask, final, t)
            fused = self.fuse_loc(self.read_drop(x_loc)) * self.fuse_ctx(self.read_drop(x_ctx))
            joint = torch.cat([x_loc, x_ctx, fused], -1)
            src = self.sender(joint) * self.sender_gate(command)[:, None]
            dst = self.receiver(joint)
            score = torch.bmm(dst, src.transpose(1, 2))  # [n, receiver i, sender j]
            # A node without senders gets no message (the original's DGL graph: an empty sum).
            weights = torch.softmax(score.masked_fill(~edges, torch.finfo(score.dtype).min), -1) * edges
            message = torch.bmm(weights, self.value(joint) * self.value_gate(command)[:, None])
            x_ctx = self.keep_context(x_ctx) + self.add_message(message)
        return self.node_out(torch.cat([x_loc, x_ctx], -1)) * present[..., None]


class LCGN(AttentionDecoderModel):
    """LCGN's `GSCAN_model` (module docstring)."""

    kind = "lcgn"

    def __init__(self, cfg: LCGNConfig, tokens: list[str]):
        super().__init__(cfg, tokens)
        E, C, H = cfg.embedding_dim, cfg.command_dim, cfg.hidden
        self.embed = nn.Embedding(len(self.tokens) + 1, E, padding_idx=0)
        self.encoder = nn.LSTM(E, C // 2, batch_first=True, bidirectional=True)
        self.embed_drop, self.command_drop = nn.Dropout(cfg.embedding_dropout), nn.Dropout(cfg.command_dropout)
        self.graph = LanguageConditionedGraph(cfg)
        self.visual = VisualEncoder(ModelConfig(in_channels=cfg.node_dim, cnn_kernels=cfg.cnn_kernels,
                                                cnn_channels=cfg.cnn_channels, cnn_dropout=cfg.cnn_dropout,
                                                grid_size=cfg.grid_size))
        self.enc_to_dec = nn.Linear(C, H)  # the encoder's final state -> the decoder's initial (h, c)
        self.action_embed = nn.Embedding(cfg.num_actions + 1, H)  # last id = start of sequence
        self.text_att = AdditiveAttention(H, C, H)
        self.world_query = nn.Linear(2 * H, H)  # conditional attention: tanh(W [h; command context])
        self.world_att = AdditiveAttention(H, self.visual.cfg.feature_dim, H)
        self.decoder = nn.LSTMCell(3 * H, H)
        self.out = nn.Linear(H, cfg.num_actions, bias=False)
        self.drop = nn.Dropout(cfg.dropout)

    def encode_commands(self, commands: list[str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Encoder outputs [n, tokens, C] and final state [n, C] (both directions concatenated),
        and the token mask."""
        padded = self.token_ids(commands)
        mask = padded > 0
        out, h_n = packed_lstm(self.encoder, self.embed_drop(self.embed(padded)), mask)
        return out, self.command_drop(torch.cat([h_n[0], h_n[1]], -1)), mask

    def encode(self, commands: list[str], first_states: np.ndarray):
        """`encode_commands` and the cell features [n, cells, F]: the CNN over the node outputs."""
        text, final, mask = self.encode_commands(commands)
        states = torch.as_tensor(np.asarray(first_states), device=self.device)
        n, g = states.shape[:2]
        nodes = self.graph(states.flatten(1, 2).to(self.out.weight.dtype), text, mask, final)
        return text, final, mask, self.visual.dense(nodes.view(n, g, g, -1))

    def _start(self, commands, first_states) -> DecoderState:
        text, final, mask, world = self.encode(commands, first_states)
        return self.decoder_state(text, mask, world, torch.tanh(self.enc_to_dec(final)))

    def _readout(self, emb, h, text_ctx, world_ctx) -> torch.Tensor:
        """The original's LCGN decoder: the logits read the LSTM state alone."""
        return self.out(h)
