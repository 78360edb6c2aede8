"""The encoders every model kind builds on: the grid's (the 3-branch CNN of Kuo et al. 2021,
which the gSCAN baseline shares) and the command's (a BiLSTM on packed sequences)."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gscan_ros.model.config import ModelConfig
from gscan_ros.model.sparse_encoder import SparseConv


class VisualEncoder(nn.Module):
    """obs_t: three parallel 'same' conv branches -> concat -> ReLU -> dropout, one vector per cell."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.convs = nn.ModuleList(
            nn.Conv2d(cfg.in_channels, cfg.cnn_channels, k, padding=k // 2) for k in cfg.cnn_kernels
        )
        self.dropout = nn.Dropout(cfg.cnn_dropout)
        self.sparse = SparseConv(cfg.grid_size, cfg.in_channels, cfg.feature_dim)  # no parameters of its own

    def dense(self, states: torch.Tensor) -> torch.Tensor:
        """The definition, on float/uint8 [N, g, g, C] states -> [N, cells, F]."""
        x = states.to(self.convs[0].weight.dtype).permute(0, 3, 1, 2)
        feats = torch.cat([conv(x) for conv in self.convs], 1)
        return self.dropout(F.relu(feats)).flatten(2).transpose(1, 2)

    def forward(self, indices: torch.Tensor, offsets: torch.Tensor, groups: torch.Tensor | None = None) -> torch.Tensor:
        """`dense` on set-bit bags of the states (see `sparse_states` and `SparseConv`), ~20x
        fewer multiply-adds; `groups` [N] names each state's episode (-1: none)."""
        dropout = self.cfg.cnn_dropout if self.training else 0.0
        return self.sparse(self.convs, indices, offsets, groups, dropout)


def packed_lstm(lstm: nn.LSTM, embedded: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A bidirectional `lstm` over padded token embeddings [n, tokens, E] on packed sequences, so
    padding never enters it: outputs [n, tokens, 2H] (zero on padding) and final states [2, n, H]."""
    packed = nn.utils.rnn.pack_padded_sequence(embedded, mask.sum(1).cpu(), batch_first=True, enforce_sorted=False)
    out, (h_n, _) = lstm(packed)
    out, _ = nn.utils.rnn.pad_packed_sequence(out, batch_first=True, total_length=mask.shape[1])
    return out, h_n
