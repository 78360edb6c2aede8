"""The compositional network one graph, one node, one step at a time: the test oracle.

A plain reading of the paper (Kuo et al. 2021, §3) and its code (ylkuo/compositional-gscan `model.py`), with
none of the fast paths:
dense convolution, every node's full attention MLP (the hidden-state term included),
every node's GRU, no batching. It holds no parameters of its own; it reads those of a
`CompositionalNetwork`, so the two share a state_dict and gradients land on the same
tensors. Used only by tests (tests/test_model_reference.py), never for training.

For word w with children c_1..c_n at step t (leaves attend over the raw features):

    att_t^w       = softmax_cells(MLP(h_{t-1}^w, obs_t ⊙ att_t^{c_1}, ..., obs_t ⊙ att_t^{c_n}))
    o_t^w, h_t^w  = GRU^w(Σ_cells obs_t ⊙ att_t^w, h_{t-1}^w)
    logits_t      = W_out^root o_t^root + b_out^root
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from gscan_ros.language.graph import CommandGraph
from gscan_ros.model.compositional import CompositionalNetwork, antonym_overlap, minmax_normalize


@dataclass
class EpisodeTrace:
    """What the network computed over one episode's T+1 steps."""

    logits: torch.Tensor  # [T+1, actions]
    overlap: torch.Tensor  # [T+1] unweighted antonym overlap of each step
    maps: dict[int, torch.Tensor]  # node id -> [T+1, cells], the map the node passes on
    antonym_maps: dict[int, torch.Tensor]  # node id -> [T+1, cells], its antonym head's map (antonym pairs only)


class ReferenceNetwork:
    """`CompositionalNetwork`'s function, computed per graph and per node (see the module docstring)."""

    def __init__(self, net: CompositionalNetwork):
        self.net, self.cfg, self.bank, self.table = net, net.cfg, net.bank, net.table

    def loss(self, graphs: list[CommandGraph], states: list[np.ndarray], targets: list[np.ndarray]
             ) -> tuple[torch.Tensor, list[EpisodeTrace]]:
        """Mean over episodes of (Σ_t NLL(target_t) + antonym_weight · Σ_t overlap_t) / (T+1).

        states[i]: uint8 [T+1, g, g, C] (the state before each gold action and the last);
        targets[i]: [T+1] action ids ending with EOS.
        """
        traces = [self.episode(g, s) for g, s in zip(graphs, states)]
        per_episode = []
        for trace, target in zip(traces, targets):
            nll = F.cross_entropy(trace.logits, torch.as_tensor(target, dtype=torch.long), reduction="sum")
            per_episode.append((nll + self.cfg.antonym_weight * trace.overlap.sum()) / len(target))
        return torch.stack(per_episode).mean(), traces

    def episode(self, graph: CommandGraph, states: np.ndarray) -> EpisodeTrace:
        """Run `graph` over the world states [T+1, g, g, C], every node bottom-up at every step."""
        cfg, bank, table = self.cfg, self.bank, self.table
        weights = bank.out_w
        order = [nid for level in graph.levels() for nid in level]  # children before parents
        h = {nid: weights.new_zeros(cfg.rnn_layers * cfg.rnn_dim) for nid in order}
        obs_seq = self.net.encoder.dense(torch.as_tensor(np.asarray(states)))  # [T+1, cells, F]
        logits, overlaps = [], []
        maps: dict[int, list[torch.Tensor]] = {nid: [] for nid in order}
        antonym_maps: dict[int, list[torch.Tensor]] = {}
        for obs in obs_seq:
            att: dict[int, torch.Tensor] = {}
            new_h: dict[int, torch.Tensor] = {}
            overlap = weights.new_zeros(())
            for nid in order:
                node = graph.node(nid)
                spec, module = table.spec(node.module), table.index[node.module]
                children = graph.children(nid)
                if cfg.uses_attention:
                    args = [att[c] for c in children] or [obs.new_ones(cfg.cells)]  # a leaf attends over obs
                    att[nid] = self.passed(node.module, self.attention(node.module, node.head, obs, args, h[nid]))
                    maps[nid].append(att[nid])
                    for other in spec.antonym_of(node.head):  # the antonym's head on the same inputs
                        shadow = self.passed(node.module, self.attention(node.module, other, obs, args, h[nid]))
                        antonym_maps.setdefault(nid, []).append(shadow)
                        overlap = overlap + antonym_overlap(att[nid], shadow, cfg)
                    x = (obs * att[nid][:, None]).sum(0)  # Σ_cells obs ⊙ att^w
                else:  # message='state': no maps
                    x = obs.sum(0)
                if cfg.passes_state:  # + Linear(children's new states, in slot order, zeros past the arity)
                    states_in = [new_h[c] for c in children]
                    states_in += [torch.zeros_like(h[nid])] * (bank.max_slots - len(children))
                    x = torch.cat([x, torch.cat(states_in) @ bank.state_w[module] + bank.state_b[module]])
                new_h[nid] = self.gru(module, x, h[nid])
            h = new_h
            root = table.index[graph.node(graph.root).module]
            top = h[graph.root][(cfg.rnn_layers - 1) * cfg.rnn_dim :]
            logits.append(top @ bank.out_w[root] + bank.out_b[root])
            overlaps.append(overlap)
        return EpisodeTrace(torch.stack(logits), torch.stack(overlaps),
                            {nid: torch.stack(m) for nid, m in maps.items() if m},
                            {nid: torch.stack(m) for nid, m in antonym_maps.items()})

    def attention(self, module: str, head: int, obs: torch.Tensor, args: list[torch.Tensor],
                  h_prev: torch.Tensor) -> torch.Tensor:
        """softmax over cells of Linear(ReLU([obs ⊙ att_s) W_s + b_s]_s ++ [h W_h + b_h]))
        (`AttentionArgN` in CG's `model.py`); with attention_state='add' the state's
        projection is also added to each argument's."""
        bank = self.bank
        unit = self.table.unit_base[module] + head
        state = h_prev @ bank.att_state_w[unit] + bank.att_state_b[unit]  # [A]
        # The state's own column, broadcast over the cells: the same constant in every cell's score.
        score = F.relu(state) @ bank.att_out_w[unit, bank.max_slots] + bank.att_out_b[unit]
        for s, arg in enumerate(args):
            x = (obs * arg[:, None]) @ bank.att_feat_w[unit, s] + bank.att_feat_b[unit, s]  # [cells, A]
            if self.cfg.state_in_attention:
                x = x + state
            score = score + F.relu(x) @ bank.att_out_w[unit, s]
        return torch.softmax(score, 0)

    def passed(self, module: str, att: torch.Tensor) -> torch.Tensor:
        """The map a node passes on: min-max normalised for an antonym-pair module with
        size_map='minmax' (quirk Q16, docs/model.md), else the softmax map itself."""
        if self.cfg.uses_attention and self.cfg.size_map == "minmax" and self.table.spec(module).antonyms:
            return minmax_normalize(att)
        return att

    def gru(self, module: int, x: torch.Tensor, h_prev: torch.Tensor) -> torch.Tensor:
        """The module's stacked GRU (torch.nn.GRU's equations) one step: x [in], h_prev [L*H] -> [L*H]."""
        bank, H = self.bank, self.cfg.rnn_dim
        out = []
        for layer in range(self.cfg.rnn_layers):
            h = h_prev[layer * H : (layer + 1) * H]
            gx = x @ bank.gru_x[layer][module] + bank.gru_bx[layer][module]
            gh = h @ bank.gru_h[layer][module] + bank.gru_bh[layer][module]
            r = torch.sigmoid(gx[:H] + gh[:H])
            z = torch.sigmoid(gx[H : 2 * H] + gh[H : 2 * H])
            n = torch.tanh(gx[2 * H :] + r * gh[2 * H :])
            x = (1 - z) * n + z * h
            out.append(x)
        return torch.cat(out)
