"""The compositional network of Kuo, Katz & Barbu (2021) as the paper describes it.

References: the paper's §3 and its code, ylkuo/compositional-gscan `model.py` ("CG"; docs/architecture.md,
References).
Every word w of a parse is a module with its own GRU; at time step t, bottom-up,

    att_t^w       = softmax_cells(MLP(h_{t-1}^w, obs_t ⊙ att_t^{c_1}, ..., obs_t ⊙ att_t^{c_n}))
    o_t^w, h_t^w  = GRU^w(Σ_cells obs_t ⊙ att_t^w, h_{t-1}^w)

and the root's output gives the action. `step` is that loop for a whole batch of
different graphs at once; `Rollout` runs it closed loop, one step per world state. The
hyper-parameters are `config.ModelConfig`, obs_t comes from `encoders.VisualEncoder` (which
the baselines share). How the batch is laid out, and the faster equivalents of the plain
computations, live beside this file:

- `modules.py`: the module table (one module per key of the parses: arity, heads, antonyms);
- `layout.py`: graphs as rows of slots grouped by level, parameters gathered per slot (`Bound`);
- `sparse_encoder.py`: the convolutions as one embedding bag over the set input bits;
- `teacher_forcing.py`: every step's loss of a batch of episodes, all maps at once when it can;
- `fast_ops.py`: custom autograd functions (incl. a GRU's recurrence over packed steps), the dropout mask;
- `reference.py`: the same network graph by graph, node by node, the test oracle.

The hidden-state input of an attention is broadcast over the cells and cancels in its
softmax, so it is not computed; with message='attention' only the root's GRU then
matters and only it runs (see `step` and docs/model.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gscan_ros.language.graph import CommandGraph
from gscan_ros.model.config import ModelConfig
from gscan_ros.model.encoders import VisualEncoder
from gscan_ros.model.layout import Bound, Layout, child_maps
from gscan_ros.model.modules import ModuleTable
from gscan_ros.model.sparse_encoder import sparse_states
from gscan_ros.model.teacher_forcing import TeacherBatch, TeacherOutput, all_steps, level_major, stepwise


# ---------------------------------------------------------------------- module bank
def _uniform(shape: Sequence[int], fan_in: int) -> nn.Parameter:
    bound = 1.0 / math.sqrt(fan_in)
    return nn.Parameter(torch.empty(*shape).uniform_(-bound, bound))


def _uniform_rows(shape: Sequence[int], fan_ins: Sequence[int]) -> nn.Parameter:
    """`_uniform` with fan-in `fan_ins[i]` for row i (a module's or unit's own layer). The
    draws run in row order, so rows of one fan-in give `_uniform`'s values bit for bit."""
    weights = torch.empty(*shape)
    for row, fan_in in zip(weights, fan_ins):
        bound = 1.0 / math.sqrt(fan_in)
        row.uniform_(-bound, bound)
    return nn.Parameter(weights)


class WordModuleBank(nn.Module):
    """Parameters of every word module, stacked: attention per (module, head) 'unit', GRU and
    output layer per module. Shapes (U units, M modules, S max slots, A att_dim, H rnn_dim):

    att_feat_w [U, S, F, A] / att_feat_b [U, S, A]   weighted features of slot s -> A
    att_state_w [U, L*H, A] / att_state_b [U, A]     previous hidden state (all layers) -> A
    att_out_w [U, S+1, A] / att_out_b [U]            ReLU(concat) -> one logit per cell
    gru_x{l} [M, in_l, 3H], gru_h{l} [M, H, 3H] (+ biases)  gates r, z, n as in torch.nn.GRU
    state_w [M, S*L*H, H] / state_b [M, H]           children's states -> GRU input (pass_state)
    out_w [M, H, n_actions] / out_b [M, n_actions]   action logits (read at the root only)

    A module with fewer slots than S leaves the stacked entries of the slots past its own
    unread (`unused_parameters`); its `att_out_*` and `state_*` are initialised for its own
    slots (`ModelConfig.init_fan_in`).
    """

    def __init__(self, cfg: ModelConfig, table: ModuleTable):
        super().__init__()
        self.cfg = cfg
        M, U = len(table), table.num_units
        S = max((s.slots for s in table.specs), default=1)
        A, H, L, Fd = cfg.att_dim, cfg.rnn_dim, cfg.rnn_layers, cfg.feature_dim
        self.max_slots = S
        self.module_slots = [spec.slots for spec in table.specs]
        self.unit_slots = [spec.slots for spec in table.specs for _ in range(spec.num_heads)]
        own = cfg.init_fan_in == "module"  # else every module as the widest
        if cfg.uses_attention:
            out_fan_ins = [((slots if own else S) + 1) * A for slots in self.unit_slots]
            self.att_feat_w = _uniform((U, S, Fd, A), Fd)
            self.att_feat_b = _uniform((U, S, A), Fd)
            self.att_state_w = _uniform((U, L * H, A), L * H)
            self.att_state_b = _uniform((U, A), L * H)
            self.att_out_w = _uniform_rows((U, S + 1, A), out_fan_ins)
            self.att_out_b = _uniform_rows((U,), out_fan_ins)
        in0 = Fd + (H if cfg.passes_state else 0)  # weighted (or, without attention, summed) features
        self.gru_x = nn.ParameterList(_uniform((M, in0 if layer == 0 else H, 3 * H), H) for layer in range(L))
        self.gru_h = nn.ParameterList(nn.Parameter(_orthogonal_gates(M, H)) for _ in range(L))
        self.gru_bx = nn.ParameterList(_uniform((M, 3 * H), H) for _ in range(L))
        self.gru_bh = nn.ParameterList(_uniform((M, 3 * H), H) for _ in range(L))
        if cfg.passes_state:
            state_fan_ins = [(slots if own else S) * L * H for slots in self.module_slots]
            self.state_w = _uniform_rows((M, S * L * H, H), state_fan_ins)
            self.state_b = _uniform_rows((M, H), state_fan_ins)
        self.out_w = _uniform((M, H, cfg.num_actions), H)
        self.out_b = _uniform((M, cfg.num_actions), H)

    def unused_parameters(self) -> int:
        """Entries stacked for slots past a module's own (zero in a table of one arity):
        `att_feat_*` and `att_out_w` per unit, `state_w` per module. They never reach an
        output nor get a gradient."""
        cfg, S = self.cfg, self.max_slots
        A, H, L, Fd = cfg.att_dim, cfg.rnn_dim, cfg.rnn_layers, cfg.feature_dim
        unused = 0
        if cfg.uses_attention:
            unused += sum(S - slots for slots in self.unit_slots) * (Fd * A + A + A)
        if cfg.passes_state:
            unused += sum(S - slots for slots in self.module_slots) * L * H * H
        return unused


def _orthogonal_gates(modules: int, hidden: int) -> torch.Tensor:
    """Recurrent weights [M, H, 3H], each gate's HxH block orthogonal (CG's GRU init)."""
    w = torch.empty(modules, 3, hidden, hidden)
    for m in range(modules):
        for gate in range(3):
            nn.init.orthogonal_(w[m, gate])
    return w.permute(0, 3, 1, 2).reshape(modules, hidden, 3 * hidden).contiguous()


# ------------------------------------------------------------------------ network
@dataclass
class StepResult:
    logits: torch.Tensor  # [n, num_actions]
    hidden: torch.Tensor  # [n, J, L*H] new hidden states of every slot
    maps: torch.Tensor | None  # [n, J, cells] attention maps (None with message='state')
    overlap: torch.Tensor  # [n] antonym overlap penalty of this step (unweighted)


class CompositionalNetwork(nn.Module):
    """Visual encoder + word-module bank; runs any batch of parse graphs."""

    kind = "compositional"

    def __init__(self, cfg: ModelConfig, table: ModuleTable):
        super().__init__()
        self.cfg, self.table = cfg, table
        self.encoder = VisualEncoder(cfg)
        self.bank = WordModuleBank(cfg, table)

    @property
    def device(self) -> torch.device:
        return self.bank.out_w.device

    def layout(self, graphs: Sequence[CommandGraph]) -> Layout:
        return Layout(graphs, self.table)

    def bind(self, layout: Layout) -> Bound:
        return Bound.gather(layout, self.bank)

    def initial_hidden(self, rows: int, num_slots: int) -> torch.Tensor:
        return self.bank.out_w.new_zeros(rows, num_slots, self.cfg.rnn_layers * self.cfg.rnn_dim)

    def rollout(self, graphs: Sequence[CommandGraph]) -> Rollout:
        return Rollout(self, graphs)

    # -- one time step
    def step(self, bound: Bound, hidden: torch.Tensor, feats: torch.Tensor,
             proj: Sequence[torch.Tensor] | None = None) -> StepResult:
        """Advance every slot one decoding step on cell features obs_t = `feats` [n, cells, F],
        level by level (children before parents).

        `proj`: the slots' feature projections per block ([n, cells, k, S_l, A] each), when
        precomputed (teacher forcing computes them for all steps at once).
        """
        cfg = self.cfg
        n, cells = feats.shape[0], cfg.cells
        L, H = cfg.rnn_layers, cfg.rnn_dim
        maps_done: list[torch.Tensor] = [feats.new_ones(n, 1, cells)]  # pool index 0 = 'no child'
        hid_done: list[torch.Tensor] = [feats.new_zeros(n, 1, L * H)]
        for level, blk in enumerate(bound.blocks):
            k, S = blk.children.shape[1], blk.children.shape[2]
            gru_in = []
            h_prev = None  # h_{t-1}^w; antonym shadows read the state of the word they shadow
            if cfg.runs_every_gru:
                h_prev = hidden.gather(1, blk.state_slot[..., None].expand(-1, -1, L * H))  # [n, k, LH]
            if cfg.uses_attention:
                if proj is None:
                    p = torch.bmm(feats, bound.feat_w(level)).view(n, cells, k, S, -1)
                else:
                    p = proj[level]
                state = None
                if cfg.state_in_attention:
                    state = torch.einsum("nki,nkia->nka", h_prev, blk.att_state_w) + blk.att_state_b
                att = self.attend(blk.att_feat_b, blk.score_w, child_maps(maps_done, blk.children), p, state)
                maps_done.append(self.passed_maps(att, blk.passes_minmax))
                if not cfg.runs_every_gru:
                    continue  # the root's GRU runs after the loop
                gru_in.append(torch.bmm(maps_done[-1], feats))  # Σ_cells obs_t ⊙ att_t^w
            else:  # message='state': no maps, the GRU reads the sum of all cells
                gru_in.append(feats.sum(1, keepdim=True).expand(-1, k, -1))
            if cfg.passes_state:  # + Linear(children's new states): this level's GRUs run now
                hpool = torch.cat(hid_done, 1)
                ch = hpool.gather(1, blk.children.reshape(n, k * S, 1).expand(-1, -1, L * H)).view(n, k, S * L * H)
                gru_in.append(torch.einsum("nki,nkio->nko", ch, blk.child_state_w) + blk.child_state_b)
            hid_done.append(bound.gru[level].run(torch.cat(gru_in, -1), h_prev))
        maps = torch.cat(maps_done[1:], 1) if cfg.uses_attention else None
        readout = bound.readout
        root = readout.root_slot[:, None, None]
        if cfg.runs_every_gru:
            new_hidden = torch.cat(hid_done[1:], 1)
            root_h = new_hidden.gather(1, root.expand(-1, 1, L * H))
        else:
            # With message='attention' a module's state reaches nothing but its own
            # attention, where it cancels (see `attend`): only the root's state, which the
            # action is decoded from, matters. The other slots' GRUs are not run and their
            # states stay zero.
            x = torch.bmm(maps.gather(1, root.expand(-1, 1, cells)), feats)
            root_h = bound.gru_root.run(x, hidden.gather(1, root.expand(-1, 1, L * H)))
            new_hidden = hidden.scatter(1, root.expand(-1, 1, L * H), root_h)
        logits = torch.bmm(root_h[:, :, (L - 1) * H :], readout.out_w)[:, 0] + readout.out_b
        if maps is not None and readout.antonym_pairs.shape[1]:
            overlap = self.overlap(maps, readout.antonym_pairs, readout.pair_mask)
        else:
            overlap = feats.new_zeros(n)
        return StepResult(logits, new_hidden, maps, overlap)

    @staticmethod
    def attend(att_feat_b: torch.Tensor, score_w: torch.Tensor, cmaps: torch.Tensor, proj: torch.Tensor,
               state: torch.Tensor | None = None) -> torch.Tensor:
        """att = softmax_cells(W_out · ReLU([(obs ⊙ att_s) W_s + b_s]_s ++ [h W_h + b_h]) + b) -> [n, k, cells].

        (obs ⊙ map) W == map ⊙ (obs W): `proj` [n, cells, k, S, A] holds every slot's
        feature projection, weighted here by the child's map `cmaps` [n, k, S, cells].
        The hidden-state input (`att_state_*`, its `att_out_w` column and `att_out_b`) is
        broadcast over the cells, so it adds the same constant to every cell's logit and
        cancels in the softmax: it is not computed (CG's `AttentionArgN` maps are exactly
        the same). With attention_state='add', `state` [n, k, A] (h W_h + b_h) is added to
        every argument's projection before the ReLU instead.
        """
        n, k, S, cells = cmaps.shape
        hidden = torch.addcmul(att_feat_b[:, None], proj, cmaps.permute(0, 3, 1, 2)[..., None])
        if state is not None:
            hidden = hidden + state[:, None, :, None, :]
        hidden = hidden.relu_()
        score = (hidden.view(n, cells, k, -1) * score_w[:, None]).sum(-1)  # [n, cells, k]
        return torch.softmax(score, 1).transpose(1, 2)

    @staticmethod
    def passed_maps(maps: torch.Tensor, passes_minmax: torch.Tensor | None) -> torch.Tensor:
        """The maps [n, k, cells] the slots pass on: with size_map='minmax', antonym-pair
        slots pass their min-max normalised map (quirk Q16, docs/model.md); otherwise the softmax maps."""
        if passes_minmax is None:
            return maps
        return torch.where(passes_minmax[..., None], minmax_normalize(maps), maps)

    def overlap(self, maps: torch.Tensor, antonym_pairs: torch.Tensor, pair_mask: torch.Tensor) -> torch.Tensor:
        """Per row, Σ over its antonym pairs of `antonym_overlap` of the two heads' maps (as
        passed on: with size_map='minmax' they arrive normalised, `passed_maps`)."""
        n, P, _ = antonym_pairs.shape
        cells = maps.shape[-1]
        sel = maps.gather(1, antonym_pairs.reshape(n, 2 * P, 1).expand(-1, -1, cells)).view(n, P, 2, cells)
        return (antonym_overlap(sel[:, :, 0], sel[:, :, 1], self.cfg) * pair_mask).sum(-1)

    # -- teacher forcing
    @property
    def active_rows_multiple(self) -> int:
        """What `EpisodeStore.batch` rounds the number of rows alive per step up to: the
        step-by-step path re-slices per-row tensors whenever that number changes (8: few
        changes, few padded steps; docs/results.md "Why these fast paths"); the all-steps
        and level-major paths slice only a few small tensors, so no padding."""
        return 8 if self.cfg.state_in_attention else 1

    def forward(self, batch: TeacherBatch) -> TeacherOutput:
        """Teacher forcing: the call DistributedDataParallel wraps."""
        return self.teacher_forcing(batch)

    def teacher_forcing(self, batch: TeacherBatch) -> TeacherOutput:
        """Loss over a batch whose rows are sorted by length, states packed time-major;
        the batch moves to the network's device first (once per update). All steps at
        once when only the root's GRU matters, level by level when every slot's GRU runs,
        step by step when a module's state moves its map (teacher_forcing.py)."""
        batch = batch.to(self.device)
        if not self.cfg.runs_every_gru:
            return all_steps(self, batch)
        return stepwise(self, batch) if self.cfg.state_in_attention else level_major(self, batch)

    def loss(self, batch: TeacherBatch, logits: torch.Tensor, overlap: torch.Tensor) -> TeacherOutput:
        """Per example (Σ_t NLL + antonym_weight · Σ_t overlap) / (T+1), mean over the batch
        (CG `SentenceNetwork.loss`); padded steps add nothing (quirk Q4, docs/model.md)."""
        valid = batch.valid.float()
        nll = F.cross_entropy(logits, batch.targets.clamp(min=0), reduction="none") * valid
        overlap = overlap * valid
        per_step = nll + self.cfg.antonym_weight * overlap
        per_example = per_step.new_zeros(batch.layout.batch).index_add(0, batch.rows, per_step) / batch.lengths
        return TeacherOutput(per_example.mean(), logits, nll, overlap)


def antonym_overlap(a: torch.Tensor, b: torch.Tensor, cfg: ModelConfig) -> torch.Tensor:
    """The overlap of maps `a` and `b` (last dim = cells) as `cfg.overlap` defines it; the
    one implementation the fast paths and the reference share."""
    if cfg.overlap == "cosine":
        return (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(1e-12)
    if cfg.size_map != "minmax":  # with size_map='minmax' the maps passed on are normalised already
        a, b = minmax_normalize(a), minmax_normalize(b)
    return (a * b).sum(-1) / a.shape[-1]


def minmax_normalize(maps: torch.Tensor) -> torch.Tensor:
    """Each map (last dim = cells) scaled to [0, 1] (a flat map divides by 1), + 1e-5,
    clipped to [0, 1]: the original's normalisation of size-word maps (CG `SentenceNetwork.loss`)."""
    lo, hi = maps.amin(-1, keepdim=True), maps.amax(-1, keepdim=True)
    rng = hi - lo
    return ((maps - lo) / torch.where(rng > 0, rng, torch.ones_like(rng)) + 1e-5).clamp(0.0, 1.0)


# -------------------------------------------------------------------- closed loop
class Rollout:
    """Closed-loop decoding state of a batch of graphs: feed observations, read action logits.

    The network conditions on world states only, never on its past actions. `keep(rows)`
    drops finished rows so later steps only pay for live episodes.
    """

    def __init__(self, net: CompositionalNetwork, graphs: Sequence[CommandGraph]):
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
