"""Closed-loop decoding with the compositional network: one batched `step` per world state."""
from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from gscan_ros.language.graph import CommandGraph
from gscan_ros.model.sparse_encoder import sparse_states

if TYPE_CHECKING:
    from gscan_ros.model.compositional import CompositionalNetwork


class Rollout:
    """Closed-loop decoding state of a batch of graphs: feed observations, read action logits.

    The network conditions on world states only, never on its past actions. `keep(rows)`
    drops finished rows so later steps only pay for live episodes.
    """

    def __init__(self, net: "CompositionalNetwork", graphs: Sequence[CommandGraph]):
        layout = net.layout(graphs)
        self.net = net
        self.bound = net.bind(layout)
        self.hidden = net.initial_hidden(layout.batch, layout.num_slots)
        self.words = layout.words  # per row: (slot, word) of the graph's nodes

    def step(self, observations: np.ndarray) -> tuple[torch.Tensor, torch.Tensor | None]:
        """uint8 [n, g, g, C] -> (logits [n, actions], attention maps [n, J, cells] or None)."""
        feats = self.net.encoder(*sparse_states(observations, self.net.device))
        res = self.net.step(self.bound, self.hidden, feats)
        self.hidden = res.hidden
        return res.logits, res.maps

    def word_maps(self, maps: torch.Tensor, row: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Row `row` of `step`'s maps as float32 [g, g] grids: word -> its map, and word -> the
        map of its antonym head run on the same inputs (words of antonym pairs only)."""
        g = self.net.cfg.grid_size
        grids = maps[row].reshape(-1, g, g).cpu().numpy().astype(np.float32)
        word_of = dict(self.words[row])
        readout = self.bound.readout
        pairs, mask = readout.antonym_pairs[row].tolist(), readout.pair_mask[row].tolist()
        return ({word: grids[slot] for slot, word in word_of.items()},
                {word_of[slot]: grids[shadow] for (slot, shadow), m in zip(pairs, mask) if m})

    def keep(self, rows: torch.Tensor) -> None:
        self.words = [self.words[i] for i in rows.tolist()]
        rows = rows.to(self.hidden.device)
        self.bound = self.bound.select(rows)
        self.hidden = self.hidden.index_select(0, rows)
