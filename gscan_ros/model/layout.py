"""How a batch of different parse graphs runs as one: slots, levels and gathered parameters.

A batch of B graphs is laid out as B rows of J *slots*: the nodes of each graph grouped
by level (`CommandGraph.levels()`, leaves first), every level one span of slots shared by
all rows (shorter levels padded with inert slots). `Bound.gather` collects every slot's
attention parameters from the bank once per batch; a time step then evaluates the levels
in order, each with a handful of batched tensor ops, whichever modules the slots hold.
GRUs run on slots grouped by module (`GruGroups`: one `bmm` per gate matrix with the
module's own weight). Padding slots compute throw-away values that nothing reads.

A word of an antonym pair (big|small) also gets a *shadow* slot in its level: the
antonym's attention head run on the word's inputs and state, for the overlap loss.

A `bank` here is the network's `WordModuleBank` (compositional.py, which uses this module;
typed as a plain nn.Module so that this module does not import the network back).
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence

import numpy as np
import torch
from torch import nn

from gscan_ros.errors import GraphError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.model.fast_ops import gru_cell

if TYPE_CHECKING:
    from gscan_ros.model.modules import ModuleTable


@dataclass
class _Entry:
    node: int  # graph node id
    module: int
    unit: int
    children: tuple[int, ...]  # node ids in slot order
    shadow_of: int | None = None  # for antonym shadows: the node whose inputs they share


class Layout:
    """B graphs as B rows of J slots grouped by level (see the module docstring).

    Slot tensors (CPU, long unless noted): unit/module/state_slot [B, J], children [B, J, S]
    (0 = 'no child' -> all-ones map, j+1 = slot j), slot_mask [B, J, S] float,
    occupied [B, J] bool (False for padding slots), has_antonyms [B, J] bool,
    root_slot [B], antonym_pairs [B, P, 2] (word slot, antonym-shadow slot) with pair_mask [B, P].
    `level_spans` holds each level's slots [lo, hi); `words[b]` lists (slot, word) of the
    real nodes of row b.
    """

    def __init__(self, graphs: Sequence[CommandGraph], table: "ModuleTable"):
        S = max((s.slots for s in table.specs), default=1)
        per_graph = [_graph_levels(g, table) for g in graphs]
        depth = max(len(levels) for levels in per_graph)
        widths = [max((len(lv[i]) if i < len(lv) else 0) for lv in per_graph) for i in range(depth)]
        self.level_spans: list[tuple[int, int]] = []
        lo = 0
        for w in widths:
            self.level_spans.append((lo, lo + w))
            lo += w
        B, J = len(graphs), lo
        self.batch, self.num_slots = B, J
        # Filled in numpy (element writes to torch tensors are far slower: docs/results.md), converted once.
        unit = np.zeros((B, J), dtype=np.int64)
        module = np.zeros((B, J), dtype=np.int64)
        children = np.zeros((B, J, S), dtype=np.int64)
        slot_mask = np.zeros((B, J, S), dtype=np.float32)
        state_slot = np.tile(np.arange(J), (B, 1))
        root = np.zeros(B, dtype=np.int64)
        occupied = np.zeros((B, J), dtype=bool)
        has_antonyms = np.zeros((B, J), dtype=bool)
        pairs: list[list[tuple[int, int]]] = []
        self.words: list[list[tuple[int, str]]] = []
        slots_of = [s.slots for s in table.specs]
        for b, (g, levels) in enumerate(zip(graphs, per_graph)):
            slot_of: dict[int, int] = {}
            shadows: list[tuple[int, _Entry]] = []
            for (lo, _), level in zip(self.level_spans, levels):
                for j, e in enumerate(level, lo):
                    unit[b, j], module[b, j] = e.unit, e.module
                    occupied[b, j] = True
                    has_antonyms[b, j] = bool(table.specs[e.module].antonyms)
                    if e.shadow_of is None:
                        slot_of[e.node] = j
                    else:
                        shadows.append((j, e))
            for (lo, _), level in zip(self.level_spans, levels):
                for j, e in enumerate(level, lo):
                    owner = e.node if e.shadow_of is None else e.shadow_of
                    slot_mask[b, j, : slots_of[e.module]] = 1.0
                    for s, c in enumerate(e.children):
                        children[b, j, s] = slot_of[c] + 1
                    state_slot[b, j] = slot_of[owner]
            pairs.append([(slot_of[e.shadow_of], j) for j, e in shadows])
            root[b] = slot_of[g.root]
            self.words.append([(slot_of[n.id], n.word) for n in g.nodes])
        P = max((len(p) for p in pairs), default=0)
        pair_t = np.zeros((B, P, 2), dtype=np.int64)
        pair_mask = np.zeros((B, P), dtype=np.float32)
        for b, ps in enumerate(pairs):
            if ps:
                pair_t[b, : len(ps)] = ps
                pair_mask[b, : len(ps)] = 1.0
        t = torch.from_numpy
        self.unit, self.module, self.children, self.slot_mask = t(unit), t(module), t(children), t(slot_mask)
        self.state_slot, self.root_slot = t(state_slot), t(root)
        self.antonym_pairs, self.pair_mask = t(pair_t), t(pair_mask)
        self.occupied, self.has_antonyms = t(occupied), t(has_antonyms)

    def to(self, device: torch.device) -> "Layout":
        """This layout with its slot tensors on `device` (itself when they are there)."""
        if self.unit.device == torch.device(device):
            return self
        moved = copy.copy(self)
        for name in _LAYOUT_TENSORS:
            setattr(moved, name, getattr(self, name).to(device))
        return moved


_LAYOUT_TENSORS = ("unit", "module", "children", "slot_mask", "state_slot", "root_slot", "antonym_pairs",
                   "pair_mask", "occupied", "has_antonyms")


def _graph_levels(graph: CommandGraph, table: "ModuleTable") -> list[list[_Entry]]:
    """Per level the graph's nodes (+ antonym shadows after them), checked against the table."""
    cache = table.level_cache  # lives and dies with the table (an id() key could be reused)
    key = graph.to_json()
    if key in cache:
        return cache[key]
    levels = []
    for level in graph.levels():
        real, shadows = [], []
        for nid in level:
            n = graph.node(nid)
            if n.module not in table.index:
                raise GraphError(f"word {n.word!r} needs module {n.module!r}, which this model does not have")
            spec = table.spec(n.module)
            if n.arity != spec.arity or n.head >= spec.num_heads:
                raise GraphError(
                    f"node {n.word!r} uses module {n.module!r} with arity {n.arity} head {n.head}; "
                    f"the model's module has arity {spec.arity} and {spec.num_heads} heads"
                )
            m, base = table.index[n.module], table.unit_base[n.module]
            children = graph.children(nid)
            real.append(_Entry(nid, m, base + n.head, children))
            for other in spec.antonym_of(n.head):
                shadows.append(_Entry(nid, m, base + other, children, shadow_of=nid))
        levels.append(real + shadows)
    if len(cache) > 4096:
        cache.clear()
    cache[key] = levels
    return levels


# ------------------------------------------------------------------ bound parameters
# Closed-loop projection weights this wide or narrower are kept column-major (`Bound.feat_w`).
COLUMN_MAJOR_MAX_WIDTH = 16


@dataclass
class SlotBlock:
    """One level's slots [n, k] (n rows, k slots) with their parameters gathered from the
    bank. Fields a configuration does not use are None."""

    children: torch.Tensor  # [n, k, S_l] source of each argument's map: 0 = none (all-ones map), j+1 = slot j
    state_slot: torch.Tensor  # [n, k] slot whose state this slot reads: itself, or for an antonym shadow its word's
    att_unit: torch.Tensor | None = None  # [n, k] attention unit (module head); -1 on padding slots
    att_feat_b: torch.Tensor | None = None  # [n, k, S_l, A] bias of each argument's feature projection
    score_w: torch.Tensor | None = None  # [n, k, S_l*A] att_out_w's argument columns, 0 past the module's arity
    passes_minmax: torch.Tensor | None = None  # [n, k] bool: size_map='minmax' and an antonym-pair module
    att_state_w: torch.Tensor | None = None  # [n, k, L*H, A] (attention_state='add')
    att_state_b: torch.Tensor | None = None  # [n, k, A]
    child_state_w: torch.Tensor | None = None  # [n, k, S_l*L*H, H] children's states -> GRU input (pass_state)
    child_state_b: torch.Tensor | None = None  # [n, k, H]
    gru_module: torch.Tensor | None = None  # [n, k] module whose GRU the slot runs; -1: none (padding, shadows)


@dataclass
class Readout:
    """Per row: the root slot and its output layer, and the antonym pairs of the overlap loss."""

    root_slot: torch.Tensor  # [n]
    root_module: torch.Tensor  # [n]
    out_w: torch.Tensor  # [n, H, actions]
    out_b: torch.Tensor  # [n, actions]
    antonym_pairs: torch.Tensor  # [n, P, 2] (word slot, antonym-shadow slot)
    pair_mask: torch.Tensor  # [n, P] float, 0 on padding pairs


def _map_tensors(obj, fn: Callable[[torch.Tensor], torch.Tensor]):
    """The dataclass `obj` with `fn` applied to each of its tensors (None fields stay None)."""
    return dataclasses.replace(obj, **{f.name: fn(v) for f in dataclasses.fields(obj)
                                       if (v := getattr(obj, f.name)) is not None})


class Bound:
    """A layout with every slot's parameters gathered from the bank (one gather per batch).

    `blocks` holds one `SlotBlock` per level, `readout` the root's output layer and the
    antonym pairs. `select(rows)` keeps a subset of rows (closed-loop evaluation drops
    finished episodes); `prefix(n)` is the cheap variant for teacher forcing, where rows
    are sorted by length.

    The GRUs do not use per-slot gathered weights: the slots that run one (the root with
    message='attention', every real slot level by level otherwise) are grouped by module
    (`GruGroups`), so a layer is one `bmm` per gate matrix with one weight per module
    present, and its weight gradient is a dense reduction over the group's rows.
    """

    def __init__(self, blocks: list[SlotBlock], readout: Readout, num_slots: int,
                 spans: list[tuple[int, int]], bank: nn.Module):
        self.blocks, self.readout, self.num_slots, self.spans, self.bank = blocks, readout, num_slots, spans, bank
        if bank.cfg.runs_every_gru:  # GRUs run level by level (see CompositionalNetwork.step)
            self.gru = [GruGroups(blk.gru_module, bank) for blk in blocks]
        else:  # only the root's GRU matters (see CompositionalNetwork.step)
            self.gru_root = GruGroups(readout.root_module[:, None], bank)
        self._feat_w: list[torch.Tensor | None] = [None] * len(blocks)

    @classmethod
    def gather(cls, layout: Layout, bank: nn.Module) -> "Bound":
        """Every slot's parameters of `layout` gathered from `bank` (on the bank's device)."""
        cfg, device = bank.cfg, bank.out_w.device
        A, L, H = cfg.att_dim, cfg.rnn_layers, cfg.rnn_dim
        layout = layout.to(device)
        blocks = []
        for lo, hi in layout.level_spans:
            u, m = layout.unit[:, lo:hi], layout.module[:, lo:hi]
            B, k = u.shape
            # The level's argument slots: as many as its widest module has (a level of
            # leaves needs 1 of the table's S), so no work goes into arguments that weigh 0.
            S = max(int((layout.slot_mask[:, lo:hi].sum((0, 1)) > 0).sum()), 1)
            blk = SlotBlock(children=layout.children[:, lo:hi, :S], state_slot=layout.state_slot[:, lo:hi])
            if cfg.uses_attention:
                blk.att_unit = torch.where(layout.occupied[:, lo:hi], u, -1)
                blk.att_feat_b = bank.att_feat_b[u][:, :, :S]
                # Output weights of the feature inputs; slots past a module's arity weigh 0.
                score_w = bank.att_out_w[u][:, :, :S] * layout.slot_mask[:, lo:hi, :S, None]
                blk.score_w = score_w.reshape(B, k, S * A)
                if cfg.size_map == "minmax":
                    blk.passes_minmax = layout.has_antonyms[:, lo:hi]
            if cfg.state_in_attention:
                blk.att_state_w, blk.att_state_b = bank.att_state_w[u], bank.att_state_b[u]
            if cfg.passes_state:
                blk.child_state_w, blk.child_state_b = bank.state_w[m][:, :, : S * L * H], bank.state_b[m]
            if cfg.runs_every_gru:
                # Real slots run their module's GRU; padding and antonym shadows (which read another slot's state) none.
                own_state = layout.state_slot[:, lo:hi] == torch.arange(lo, hi, device=device)
                real = layout.occupied[:, lo:hi] & own_state
                blk.gru_module = torch.where(real, m, -1)
            blocks.append(blk)
        root_module = layout.module.gather(1, layout.root_slot[:, None])[:, 0]
        readout = Readout(root_slot=layout.root_slot, root_module=root_module, out_w=bank.out_w[root_module],
                          out_b=bank.out_b[root_module], antonym_pairs=layout.antonym_pairs, pair_mask=layout.pair_mask)
        return cls(blocks, readout, layout.num_slots, list(layout.level_spans), bank)

    @property
    def rows(self) -> int:
        return self.readout.root_slot.shape[0]

    def feat_w(self, block: int) -> torch.Tensor:
        """[n, F, k*S_l*A]: every slot's feature projection weights, so that one `bmm` projects
        a step's features for the whole block. Built on first use: only closed-loop
        decoding needs it (teacher forcing precomputes the projections for all steps).

        A block only `COLUMN_MAJOR_MAX_WIDTH` wide (one single-argument slot: a level of
        leaves) is stored as [n, k*S_l*A, F] and returned as its transposed view: torch's
        CPU `bmm` of [36, 150] by a row-major [150, 10] is ~1.7x slower than by a
        column-major one, while from 20 columns on row-major is as fast or faster
        (docs/results.md, "Closed-loop evaluation throughput")."""
        if self._feat_w[block] is None:
            blk = self.blocks[block]
            units = blk.att_unit.clamp(min=0)
            n, k = units.shape
            w = self.bank.att_feat_w[units][:, :, : blk.children.shape[2]]  # [n, k, S_l, F, A]
            if k * w.shape[2] * w.shape[4] <= COLUMN_MAJOR_MAX_WIDTH:
                self._feat_w[block] = w.transpose(3, 4).reshape(n, -1, w.shape[3]).contiguous().transpose(1, 2)
            else:
                self._feat_w[block] = w.permute(0, 3, 1, 2, 4).reshape(n, w.shape[3], -1)
        return self._feat_w[block]

    def proj_widths(self) -> list[int]:
        """Each block's share k*S_l*A of the flat feature projections (`teacher_forcing._projections`)."""
        return [blk.children.shape[1] * blk.children.shape[2] * self.bank.cfg.att_dim for blk in self.blocks]

    def _map(self, fn) -> "Bound":
        return Bound([_map_tensors(blk, fn) for blk in self.blocks], _map_tensors(self.readout, fn),
                     self.num_slots, self.spans, self.bank)

    def select(self, rows: torch.Tensor) -> "Bound":
        """These rows only; feature projection weights already built are carried over, so
        closed-loop decoding, which drops finished rows nearly every step, builds them once."""
        kept = self._map(lambda t: t.index_select(0, rows))
        kept._feat_w = [None if w is None else _select_rows_keeping_layout(w, rows) for w in self._feat_w]
        return kept

    def prefix(self, n: int) -> "Bound":
        return self if n == self.rows else self._map(lambda t: t[:n])


def _select_rows_keeping_layout(w: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """`w.index_select(0, rows)` of a [n, F, W] tensor, column-major again if `w` is."""
    if w.shape[2] > 1 and w.stride(2) != 1:
        return w.transpose(1, 2).index_select(0, rows).transpose(1, 2)
    return w.index_select(0, rows)


def child_maps(maps_done: list[torch.Tensor], children: torch.Tensor) -> torch.Tensor:
    """[n, k, S, cells]: the maps feeding each slot's arguments. `maps_done` holds the
    all-ones 'no child' map then every finished block's maps; `children` [n, k, S] indexes
    that pool (0 = no child, j+1 = slot j)."""
    pool = torch.cat(maps_done, 1)
    n, k, S = children.shape
    cells = pool.shape[-1]
    return pool.gather(1, children.reshape(n, k * S, 1).expand(-1, -1, cells)).view(n, k, S, cells)


class SlotGroups:
    """A block's slots [n, k] grouped by a key (module or attention unit; -1 = skip the
    slot), padded to [groups, width] so that one `bmm` applies each group's own weight.

    `keys` [groups] are the distinct keys; `idx` [groups*width] the flattened n*k slot of
    each member (padding members repeat a real one; their results are never read); `inv`
    [n*k] where each slot's result lands (skipped slots point at an arbitrary result).
    """

    def __init__(self, slot_keys: torch.Tensor):
        flat, device = slot_keys.reshape(-1), slot_keys.device
        members = (flat >= 0).nonzero().squeeze(1)
        if members.numel() == 0:  # e.g. a level that no row of this prefix has
            members = torch.zeros(1, dtype=torch.long, device=device)
            keys_of = torch.zeros(1, dtype=torch.long, device=device)
        else:
            keys_of = flat[members]
            order = torch.argsort(keys_of, stable=True)
            members, keys_of = members[order], keys_of[order]
        self.keys, counts = torch.unique_consecutive(keys_of, return_counts=True)
        self.groups, self.width = self.keys.numel(), int(counts.max())
        group = torch.repeat_interleave(torch.arange(self.groups, device=device), counts)
        target = (group * self.width + torch.arange(members.numel(), device=device)
                  - torch.repeat_interleave(counts.cumsum(0) - counts, counts))
        self.idx = members[0].repeat(self.groups * self.width)
        self.idx[target] = members
        self.inv = torch.full((flat.numel(),), int(target[0]), dtype=torch.long, device=device)
        self.inv[members] = target


class GruLayerWeights(NamedTuple):
    """One GRU layer's weights for each group's module: x [g, in, 3H], h [g, H, 3H], bx/bh [g, 1, 3H]."""

    x: torch.Tensor
    h: torch.Tensor
    bx: torch.Tensor
    bh: torch.Tensor


class GruGroups(SlotGroups):
    """Real slots by module, with the modules' GRU weights gathered once per grouping."""

    def __init__(self, gru_module: torch.Tensor, bank: nn.Module):
        super().__init__(gru_module)
        self.layers = [GruLayerWeights(bank.gru_x[layer].index_select(0, self.keys),
                                       bank.gru_h[layer].index_select(0, self.keys),
                                       bank.gru_bx[layer].index_select(0, self.keys)[:, None],
                                       bank.gru_bh[layer].index_select(0, self.keys)[:, None])
                       for layer in range(bank.cfg.rnn_layers)]

    def run(self, x: torch.Tensor, h_prev: torch.Tensor) -> torch.Tensor:
        """All layers of every real slot: x [n, k, in], h_prev [n, k, L*H] -> [n, k, L*H]."""
        n, k = x.shape[:2]
        shape = (self.groups, self.width)
        hidden = h_prev.shape[-1] // len(self.layers)
        xg = x.reshape(n * k, -1).index_select(0, self.idx).view(*shape, -1)
        hg = h_prev.reshape(n * k, -1).index_select(0, self.idx).view(*shape, -1)
        out = []
        for layer, w in enumerate(self.layers):
            h = hg[..., layer * hidden : (layer + 1) * hidden]
            xg = gru_cell(xg, h, w.x, w.h, w.bx, w.bh)
            out.append(xg)
        h_new = torch.cat(out, -1) if len(out) > 1 else out[0]
        return h_new.view(self.groups * self.width, -1).index_select(0, self.inv).view(n, k, -1)
