"""The gSCAN seq2seq baseline (Ruis et al. 2020; LauraRuis/multimodal_seq2seq_gSCAN "MM"), in the same framework.

Command: embedding -> 1-layer BiLSTM on packed sequences (directions summed). World: the
same 3-branch CNN, on the *initial* state only (the baseline never sees later states).
Decoder: MM's `BahdanauAttentionDecoderRNN` (`decoder.AttentionDecoderModel`, which AuxLoss
and LCGN share), its (h, c) starting as tanh(W · the encoder's final state).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from gscan_ros.model.config import ModelConfig, Seq2SeqConfig
from gscan_ros.model.decoder import AdditiveAttention, AttentionDecoderModel, DecoderState
from gscan_ros.model.encoders import VisualEncoder, packed_lstm
from gscan_ros.model.sparse_encoder import sparse_states


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
