"""The compositional network of Kuo, Katz & Barbu (2021), batched over heterogeneous parses.

One file, top to bottom: config, module table, visual encoder, word-module bank,
batch layout, and the network. GSCAN_SPEC §8 is the reference; the paper is §3 of
`kuo2021_compositional_gscan.tex`.

How a batch that mixes different parse graphs runs in one pass
---------------------------------------------------------------
Every word module's parameters live in one *bank* (stacked tensors indexed by module /
attention head). A batch of B graphs is laid out as B rows of J *slots*: the nodes of
each graph grouped by level (`CommandGraph.levels()`, leaves first), every level one
block of slots shared by all rows (shorter levels padded). `bind()` gathers, once per
batch, every slot's own parameters from the bank; a time step then evaluates the blocks
in order, each block with a handful of batched tensor ops (`bmm`/`einsum` over the
gathered per-slot weights), whatever modules the slots hold. Padding slots compute
throw-away values that nothing reads.

The visual encoder exploits the one-hot input: a 'same' convolution on a 6x6 grid is a
fixed linear map from the 576 input bits to the 36x150 features, so the convolution is
one `embedding_bag` over the set bits of each state (~20 of 576) against a Toeplitz
matrix assembled from the conv weights once per call. `VisualEncoder.dense` is the plain
`Conv2d` reference path; the two agree to float rounding (tested).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Iterable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gscan_ros.errors import CheckpointError, GraphError, LexiconError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.world.types import GRID_SIZE, NUM_CHANNELS, Action

MESSAGES = ("attention", "state", "attention+state")


# --------------------------------------------------------------------------- config
@dataclass(frozen=True)
class ModelConfig:
    """Hyper-parameters of the compositional network (defaults: CG `config_train.yaml`)."""

    grid_size: int = GRID_SIZE
    """Side of the square grid; the CNN keeps it ('same' padding), 36 cells for gSCAN."""
    in_channels: int = NUM_CHANNELS
    """Channels of the one-hot observation (16 in the released order, GSCAN_SPEC §4)."""
    cnn_kernels: tuple[int, ...] = (1, 5, 7)
    """Kernel sizes of the parallel conv branches (CG: 1, 5 and `cnn_kernel_size` 7)."""
    cnn_channels: int = 50
    """Output channels per conv branch; cell features have len(cnn_kernels) * this."""
    cnn_dropout: float = 0.1
    """Dropout on the concatenated, ReLU'd cell features (training only)."""
    att_dim: int = 10
    """Width each attention input (weighted features per slot, hidden state) is projected to."""
    rnn_layers: int = 2
    """GRU layers per word module; every layer's state feeds the module's attention."""
    rnn_dim: int = 20
    """GRU hidden size per layer (CG main config 20; its no-attention config uses 40)."""
    message: str = "attention"
    """What children pass to parents: 'attention' maps (paper), 'state' (hidden states, no
    attention at all: CG `no_attention`), or 'attention+state' (CG `pass_state`)."""
    antonym_weight: float = 1.0
    """Weight of the antonym overlap loss (CG `compare_weight`); 0 disables the term."""
    num_actions: int = len(Action)
    """Output classes: the six gSCAN actions plus EOS, ids = `Action` values."""

    def __post_init__(self) -> None:
        if self.message not in MESSAGES:
            raise ValueError(f"message must be one of {MESSAGES}, got {self.message!r}")
        object.__setattr__(self, "cnn_kernels", tuple(int(k) for k in self.cnn_kernels))
        if any(k % 2 == 0 for k in self.cnn_kernels):
            raise ValueError(f"cnn_kernels must be odd for 'same' padding, got {self.cnn_kernels}")

    @property
    def feature_dim(self) -> int:
        return self.cnn_channels * len(self.cnn_kernels)

    @property
    def cells(self) -> int:
        return self.grid_size * self.grid_size

    @property
    def uses_attention(self) -> bool:
        return self.message != "state"

    @property
    def passes_state(self) -> bool:
        return self.message != "attention"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cnn_kernels"] = list(self.cnn_kernels)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise CheckpointError(f"unknown model config keys {unknown}")
        return cls(**d)


# --------------------------------------------------------------------- module table
@dataclass(frozen=True)
class ModuleSpec:
    """One word module: its key, number of argument slots and attention heads."""

    key: str
    arity: int
    num_heads: int = 1
    antonyms: tuple[tuple[int, int], ...] = ()  # head pairs whose maps should not overlap

    @property
    def slots(self) -> int:
        """Attention inputs: one per child; a leaf attends over the raw features (CG n=0 -> 1)."""
        return max(1, self.arity)

    def antonym_of(self, head: int) -> tuple[int, ...]:
        return tuple(b if a == head else a for a, b in self.antonyms if head in (a, b))


class ModuleTable:
    """The ordered set of word modules a network owns (the model's 'vocabulary')."""

    def __init__(self, specs: Iterable[ModuleSpec]):
        self.specs: tuple[ModuleSpec, ...] = tuple(sorted(specs, key=lambda s: s.key))
        self.index = {s.key: i for i, s in enumerate(self.specs)}
        if len(self.index) != len(self.specs):
            raise ValueError("duplicate module keys")
        bases = np.cumsum([0] + [s.num_heads for s in self.specs])
        self.unit_base = {s.key: int(b) for s, b in zip(self.specs, bases)}
        self.num_units = int(bases[-1])

    def __len__(self) -> int:
        return len(self.specs)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ModuleTable) and self.specs == other.specs

    def spec(self, key: str) -> ModuleSpec:
        return self.specs[self.index[key]]

    @classmethod
    def from_graphs(cls, graphs: Iterable[CommandGraph], lexicon=None) -> "ModuleTable":
        """Collect modules from parses; heads and antonym pairs come from the lexicon if it knows the key."""
        arity: dict[str, int] = {}
        heads: dict[str, int] = {}
        for g in graphs:
            for n in g.nodes:
                if arity.setdefault(n.module, n.arity) != n.arity:
                    raise GraphError(f"module {n.module!r} used with arities {arity[n.module]} and {n.arity}")
                heads[n.module] = max(heads.get(n.module, 1), n.head + 1)
        specs = []
        for key in arity:
            num_heads, pairs = _lexicon_heads(lexicon, key)
            specs.append(ModuleSpec(key, arity[key], max(num_heads, heads[key]), pairs))
        return cls(specs)

    def to_list(self) -> list[dict]:
        return [
            {"key": s.key, "arity": s.arity, "num_heads": s.num_heads, "antonyms": [list(p) for p in s.antonyms]}
            for s in self.specs
        ]

    @classmethod
    def from_list(cls, items: list[dict]) -> "ModuleTable":
        try:
            return cls(
                ModuleSpec(str(d["key"]), int(d["arity"]), int(d["num_heads"]), tuple(tuple(p) for p in d["antonyms"]))
                for d in items
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"malformed module table in checkpoint: {exc}") from None


def _lexicon_heads(lexicon, key: str) -> tuple[int, tuple[tuple[int, int], ...]]:
    """(heads, antonym head pairs) of a concept module; (1, ()) for keys the lexicon does not
    group (structural keys like "NP_2", or no lexicon at all)."""
    if lexicon is None:
        return 1, ()
    try:
        heads = int(lexicon.num_heads(key))
        pairs = {tuple(sorted((int(a), int(b)))) for a, b in lexicon.antonym_heads(key)}
    except (LexiconError, KeyError):
        return 1, ()
    return heads, tuple(sorted(pairs))


# ------------------------------------------------------------------- visual encoder
class VisualEncoder(nn.Module):
    """Three parallel 'same' conv branches -> concat -> ReLU -> dropout, one vector per cell."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.convs = nn.ModuleList(
            nn.Conv2d(cfg.in_channels, cfg.cnn_channels, k, padding=k // 2) for k in cfg.cnn_kernels
        )
        self.dropout = nn.Dropout(cfg.cnn_dropout)
        g = cfg.grid_size
        r = torch.arange(g).repeat_interleave(g)  # cell index -> row
        c = torch.arange(g).repeat(g)  # cell index -> col
        # Offset of input cell q relative to output cell p, shifted into [0, 2g-2].
        self.register_buffer("_dr", (r[:, None] - r[None, :] + g - 1), persistent=False)
        self.register_buffer("_dc", (c[:, None] - c[None, :] + g - 1), persistent=False)

    def _kernel_bank(self) -> torch.Tensor:
        """All branches' weights centred on a (2g-1)^2 canvas: [F, C, 2g-1, 2g-1]."""
        g = self.cfg.grid_size
        out = []
        for conv in self.convs:
            w, half = conv.weight, conv.kernel_size[0] // 2
            if half <= g - 1:
                pad = g - 1 - half
                out.append(F.pad(w, (pad, pad, pad, pad)))
            else:  # offsets beyond the grid never contribute
                cut = half - (g - 1)
                out.append(w[:, :, cut : cut + 2 * g - 1, cut : cut + 2 * g - 1])
        return torch.cat(out, 0)

    def toeplitz(self) -> torch.Tensor:
        """[cells*C, cells*F]: row (cell q, channel k) -> contribution to every (cell p, feature o)."""
        w = self._kernel_bank()[:, :, self._dr, self._dc]  # [F, C, q, p]
        n_in = self.cfg.cells * self.cfg.in_channels
        return w.permute(2, 1, 3, 0).reshape(n_in, -1)

    @property
    def bias(self) -> torch.Tensor:
        return torch.cat([conv.bias for conv in self.convs])

    def _inference_toeplitz(self) -> torch.Tensor:
        """Toeplitz matrix cached across no-grad calls (closed loop re-encodes every step)
        until a conv parameter changes (tracked by tensor versions)."""
        key = tuple((p.data_ptr(), p._version) for p in self.parameters())
        if getattr(self, "_cache_key", None) != key:
            self._cache_key, self._cache = key, self.toeplitz()
        return self._cache

    def forward(self, indices: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        """Sparse path: set-bit indices of flattened [g, g, C] states (see `sparse_states`) -> [N, cells, F]."""
        weight = self.toeplitz() if torch.is_grad_enabled() else self._inference_toeplitz()
        flat = F.embedding_bag(indices, weight, offsets, mode="sum")
        feats = flat.view(-1, self.cfg.cells, self.cfg.feature_dim) + self.bias
        return self.dropout(F.relu(feats))

    def dense(self, states: torch.Tensor) -> torch.Tensor:
        """Reference path on float/uint8 [N, g, g, C] states -> [N, cells, F]."""
        x = states.float().permute(0, 3, 1, 2)
        feats = torch.cat([conv(x) for conv in self.convs], 1)
        return self.dropout(F.relu(feats)).flatten(2).transpose(1, 2)


def sparse_states(states: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 one-hot states [N, g, g, C] -> (int64 set-bit indices, int64 bag offsets)."""
    flat = torch.as_tensor(np.asarray(states)).reshape(len(states), -1)
    rows, cols = flat.nonzero(as_tuple=True)
    counts = torch.bincount(rows, minlength=flat.shape[0])
    offsets = torch.zeros(flat.shape[0], dtype=torch.long)
    offsets[1:] = counts.cumsum(0)[:-1]
    return cols, offsets


# ---------------------------------------------------------------------- module bank
def _uniform(shape: Sequence[int], fan_in: int) -> nn.Parameter:
    bound = 1.0 / math.sqrt(fan_in)
    return nn.Parameter(torch.empty(*shape).uniform_(-bound, bound))


class WordModuleBank(nn.Module):
    """Parameters of every word module, stacked: attention per (module, head) 'unit', GRU and
    output layer per module. Shapes (U units, M modules, S max slots, A att_dim, H rnn_dim):

    att_feat_w [U, S, F, A] / att_feat_b [U, S, A]   weighted features of slot s -> A
    att_state_w [U, L*H, A] / att_state_b [U, A]     previous hidden state (all layers) -> A
    att_out_w [U, S+1, A] / att_out_b [U]            ReLU(concat) -> one logit per cell
    gru_x{l} [M, in_l, 3H], gru_h{l} [M, H, 3H] (+ biases)  gates r, z, n as in torch.nn.GRU
    state_w [M, S*L*H, H] / state_b [M, H]           children's states -> GRU input (pass_state)
    out_w [M, H, n_actions] / out_b [M, n_actions]   action logits (read at the root only)
    """

    def __init__(self, cfg: ModelConfig, table: ModuleTable):
        super().__init__()
        self.cfg = cfg
        M, U = len(table), table.num_units
        S = max((s.slots for s in table.specs), default=1)
        A, H, L, Fd = cfg.att_dim, cfg.rnn_dim, cfg.rnn_layers, cfg.feature_dim
        self.max_slots = S
        if cfg.uses_attention:
            self.att_feat_w = _uniform((U, S, Fd, A), Fd)
            self.att_feat_b = _uniform((U, S, A), Fd)
            self.att_state_w = _uniform((U, L * H, A), L * H)
            self.att_state_b = _uniform((U, A), L * H)
            self.att_out_w = _uniform((U, S + 1, A), (S + 1) * A)
            self.att_out_b = _uniform((U,), (S + 1) * A)
        in0 = Fd + (H if cfg.passes_state else 0)  # weighted (or, without attention, summed) features
        self.gru_x = nn.ParameterList(_uniform((M, in0 if l == 0 else H, 3 * H), H) for l in range(L))
        self.gru_h = nn.ParameterList(nn.Parameter(_orthogonal_gates(M, H)) for _ in range(L))
        self.gru_bx = nn.ParameterList(_uniform((M, 3 * H), H) for _ in range(L))
        self.gru_bh = nn.ParameterList(_uniform((M, 3 * H), H) for _ in range(L))
        if cfg.passes_state:
            self.state_w = _uniform((M, S * L * H, H), S * L * H)
            self.state_b = _uniform((M, H), S * L * H)
        self.out_w = _uniform((M, H, cfg.num_actions), H)
        self.out_b = _uniform((M, cfg.num_actions), H)


def _orthogonal_gates(modules: int, hidden: int) -> torch.Tensor:
    """Recurrent weights [M, H, 3H], each gate's HxH block orthogonal (CG's GRU init)."""
    w = torch.empty(modules, 3, hidden, hidden)
    for m in range(modules):
        for gate in range(3):
            nn.init.orthogonal_(w[m, gate])
    return w.permute(0, 3, 1, 2).reshape(modules, hidden, 3 * hidden).contiguous()


# ------------------------------------------------------------------------ layout
@dataclass
class _Entry:
    node: int  # graph node id
    word: str
    module: int
    unit: int
    children: tuple[int, ...]  # node ids in slot order
    shadow_of: int | None = None  # for antonym shadows: the node whose inputs they share


class Layout:
    """B graphs as B rows of J slots grouped by level (see the module docstring).

    Slot tensors (CPU, long unless noted): unit/module/src [B, J], child [B, J, S]
    (0 = 'no child' -> all-ones map, j+1 = slot j), slot_mask [B, J, S] float,
    occupied [B, J] bool (False for padding slots),
    root [B], pairs [B, P, 2] (word slot, antonym-shadow slot) with pair_mask [B, P].
    `words[b]` lists (slot, word) of the real nodes of row b.
    """

    def __init__(self, graphs: Sequence[CommandGraph], table: ModuleTable):
        S = max((s.slots for s in table.specs), default=1)
        per_graph = [_graph_levels(g, table) for g in graphs]
        depth = max(len(levels) for levels in per_graph)
        widths = [max((len(lv[i]) if i < len(lv) else 0) for lv in per_graph) for i in range(depth)]
        self.blocks = []
        lo = 0
        for w in widths:
            self.blocks.append((lo, lo + w))
            lo += w
        B, J = len(graphs), lo
        self.batch, self.num_slots = B, J
        unit = torch.zeros(B, J, dtype=torch.long)
        module = torch.zeros(B, J, dtype=torch.long)
        child = torch.zeros(B, J, S, dtype=torch.long)
        slot_mask = torch.zeros(B, J, S)
        src = torch.arange(J).repeat(B, 1)
        root = torch.zeros(B, dtype=torch.long)
        occupied = torch.zeros(B, J, dtype=torch.bool)
        pairs: list[list[tuple[int, int]]] = []
        self.words: list[list[tuple[int, str]]] = []
        for b, (g, levels) in enumerate(zip(graphs, per_graph)):
            slot_of: dict[int, int] = {}
            shadows: list[tuple[int, _Entry]] = []
            for li, level in enumerate(levels):
                for pos, e in enumerate(level):
                    j = self.blocks[li][0] + pos
                    unit[b, j], module[b, j] = e.unit, e.module
                    occupied[b, j] = True
                    if e.shadow_of is None:
                        slot_of[e.node] = j
                    else:
                        shadows.append((j, e))
            for li, level in enumerate(levels):
                for pos, e in enumerate(level):
                    j = self.blocks[li][0] + pos
                    owner = e.node if e.shadow_of is None else e.shadow_of
                    slots = table.specs[e.module].slots
                    slot_mask[b, j, :slots] = 1.0
                    for s, c in enumerate(e.children):
                        child[b, j, s] = slot_of[c] + 1
                    src[b, j] = slot_of[owner]
            pairs.append([(slot_of[e.shadow_of], j) for j, e in shadows])
            root[b] = slot_of[g.root]
            self.words.append([(slot_of[n.id], n.word) for n in g.nodes])
        P = max((len(p) for p in pairs), default=0)
        pair_t = torch.zeros(B, P, 2, dtype=torch.long)
        pair_mask = torch.zeros(B, P)
        for b, ps in enumerate(pairs):
            for i, p in enumerate(ps):
                pair_t[b, i] = torch.tensor(p)
                pair_mask[b, i] = 1.0
        self.unit, self.module, self.child, self.slot_mask = unit, module, child, slot_mask
        self.src, self.root, self.pairs, self.pair_mask = src, root, pair_t, pair_mask
        self.occupied = occupied


_LEVEL_CACHE: dict[tuple[int, str], list[list[_Entry]]] = {}


def _graph_levels(graph: CommandGraph, table: ModuleTable) -> list[list[_Entry]]:
    """Per level the graph's nodes (+ antonym shadows after them), checked against the table."""
    key = (id(table), graph.to_json())
    if key in _LEVEL_CACHE:
        return _LEVEL_CACHE[key]
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
            real.append(_Entry(nid, n.word, m, base + n.head, children))
            for other in spec.antonym_of(n.head):
                shadows.append(_Entry(nid, n.word, m, base + other, children, shadow_of=nid))
        levels.append(real + shadows)
    if len(_LEVEL_CACHE) > 4096:
        _LEVEL_CACHE.clear()
    _LEVEL_CACHE[key] = levels
    return levels


# -------------------------------------------------------------------- bound params
class Bound:
    """A layout with every slot's parameters gathered from the bank (one gather per batch).

    Per block: a dict of tensors with leading dims [B, k] (k = block width); plus the
    root's output layer and the antonym pairs. `select(rows)` keeps a subset of rows
    (closed-loop evaluation drops finished episodes); `prefix(n)` is the cheap variant
    for teacher forcing, where rows are sorted by length.
    """

    def __init__(self, blocks: list[dict[str, torch.Tensor]], top: dict[str, torch.Tensor], num_slots: int,
                 spans: list[tuple[int, int]]):
        self.blocks, self.top, self.num_slots, self.spans = blocks, top, num_slots, spans

    @property
    def rows(self) -> int:
        return self.top["root"].shape[0]

    def _map(self, fn) -> "Bound":
        return Bound([{k: fn(v) for k, v in blk.items()} for blk in self.blocks],
                     {k: fn(v) for k, v in self.top.items()}, self.num_slots, self.spans)

    def select(self, rows: torch.Tensor) -> "Bound":
        return self._map(lambda t: t.index_select(0, rows))

    def prefix(self, n: int) -> "Bound":
        return self if n == self.rows else self._map(lambda t: t[:n])


# ------------------------------------------------------------------------ network
@dataclass
class StepResult:
    logits: torch.Tensor  # [n, num_actions]
    hidden: torch.Tensor  # [n, J, L*H] new hidden states of every slot
    maps: torch.Tensor | None  # [n, J, cells] attention maps (None with message='state')
    overlap: torch.Tensor  # [n] antonym overlap penalty of this step (unweighted)


class CompositionalNetwork(nn.Module):
    """Visual encoder + word-module bank; runs any batch of parse graphs."""

    def __init__(self, cfg: ModelConfig, table: ModuleTable):
        super().__init__()
        self.cfg, self.table = cfg, table
        self.encoder = VisualEncoder(cfg)
        self.bank = WordModuleBank(cfg, table)

    # -- layout / binding
    def layout(self, graphs: Sequence[CommandGraph]) -> Layout:
        return Layout(graphs, self.table)

    def bind(self, layout: Layout) -> Bound:
        bank, cfg = self.bank, self.cfg
        L, H, A = cfg.rnn_layers, cfg.rnn_dim, cfg.att_dim
        blocks = []
        for lo, hi in layout.blocks:
            u, m = layout.unit[:, lo:hi], layout.module[:, lo:hi]
            B, k = u.shape
            blk = {"child": layout.child[:, lo:hi], "src": layout.src[:, lo:hi]}
            if cfg.uses_attention:
                S = bank.max_slots
                # [B, k, S, F, A] -> [B, F, k*S*A]: one bmm projects every slot of the block.
                blk["feat_w"] = bank.att_feat_w[u].permute(0, 3, 1, 2, 4).reshape(B, cfg.feature_dim, k * S * A)
                blk["feat_b"] = bank.att_feat_b[u]
                blk["state_w"], blk["state_b"] = bank.att_state_w[u], bank.att_state_b[u]
                blk["out_w"], blk["out_b"] = bank.att_out_w[u], bank.att_out_b[u]
                blk["slot_mask"] = layout.slot_mask[:, lo:hi]
            if cfg.passes_state:
                blk["pass_w"], blk["pass_b"] = bank.state_w[m], bank.state_b[m]
            for layer in range(L):
                blk[f"gx{layer}"], blk[f"gh{layer}"] = bank.gru_x[layer][m], bank.gru_h[layer][m]
                blk[f"bx{layer}"], blk[f"bh{layer}"] = bank.gru_bx[layer][m], bank.gru_bh[layer][m]
            blocks.append(blk)
        root_module = layout.module.gather(1, layout.root[:, None])[:, 0]
        top = {
            "root": layout.root,
            "out_w": bank.out_w[root_module],
            "out_b": bank.out_b[root_module],
            "pairs": layout.pairs,
            "pair_mask": layout.pair_mask,
        }
        return Bound(blocks, top, layout.num_slots, list(layout.blocks))

    def initial_hidden(self, rows: int, num_slots: int) -> torch.Tensor:
        return torch.zeros(rows, num_slots, self.cfg.rnn_layers * self.cfg.rnn_dim)

    def rollout(self, graphs: Sequence[CommandGraph]) -> "Rollout":
        return Rollout(self, graphs)

    # -- one time step
    def step(self, bound: Bound, hidden: torch.Tensor, feats: torch.Tensor,
             proj: torch.Tensor | None = None) -> StepResult:
        """Advance every slot one decoding step on cell features `feats` [n, cells, F].

        `proj` [n, J, cells, S*A]: the slots' feature projections, when precomputed
        (teacher forcing computes them for all steps at once, see `_projections`).
        """
        cfg = self.cfg
        n, cells = feats.shape[0], cfg.cells
        L, H = cfg.rnn_layers, cfg.rnn_dim
        maps_done: list[torch.Tensor] = [feats.new_ones(n, 1, cells)]  # pool index 0 = 'no child'
        hid_done: list[torch.Tensor] = [feats.new_zeros(n, 1, L * H)]
        for (lo, hi), blk in zip(bound.spans, bound.blocks):
            child, src = blk["child"], blk["src"]
            k, S = child.shape[1], child.shape[2]
            h_prev = hidden.gather(1, src[..., None].expand(-1, -1, L * H))  # [n, k, LH]
            parts = []
            if cfg.uses_attention:
                pool = torch.cat(maps_done, 1)
                cmaps = pool.gather(1, child.reshape(n, k * S, 1).expand(-1, -1, cells)).view(n, k, S, cells)
                att = self._attend(blk, feats, cmaps, h_prev, None if proj is None else proj[:, lo:hi])
                maps_done.append(att)
                parts.append(torch.bmm(att, feats))  # attention-weighted feature sum
            else:
                parts.append(feats.sum(1, keepdim=True).expand(-1, k, -1))
            if cfg.passes_state:
                hpool = torch.cat(hid_done, 1)
                ch = hpool.gather(1, child.reshape(n, k * S, 1).expand(-1, -1, L * H)).view(n, k, S * L * H)
                parts.append(torch.einsum("nki,nkio->nko", ch, blk["pass_w"]) + blk["pass_b"])
            x = torch.cat(parts, -1) if len(parts) > 1 else parts[0]
            h_new = []
            for layer in range(L):
                h = h_prev[..., layer * H : (layer + 1) * H]
                x = _gru_cell(x, h, blk[f"gx{layer}"], blk[f"gh{layer}"], blk[f"bx{layer}"], blk[f"bh{layer}"])
                h_new.append(x)
            hid_done.append(torch.cat(h_new, -1))
        new_hidden = torch.cat(hid_done[1:], 1)
        top = bound.top
        root_h = new_hidden.gather(1, top["root"][:, None, None].expand(-1, 1, L * H))[:, 0, (L - 1) * H :]
        logits = torch.bmm(root_h[:, None], top["out_w"])[:, 0] + top["out_b"]
        maps = torch.cat(maps_done[1:], 1) if cfg.uses_attention else None
        overlap = self._overlap(maps, top) if maps is not None and top["pairs"].shape[1] else feats.new_zeros(n)
        return StepResult(logits, new_hidden, maps, overlap)

    def _attend(self, blk, feats, cmaps, h_prev, proj) -> torch.Tensor:
        """softmax_cells( W_out . ReLU([ (feats*map_s) W_s + b_s ]_s ++ [h W_h + b_h]) + b ) -> [n, k, cells]."""
        n, k, S, cells = cmaps.shape
        A = self.cfg.att_dim
        # (feats * map) W == map * (feats W): project once per slot, then weight by the child's map.
        if proj is None:
            proj = torch.bmm(feats, blk["feat_w"]).view(n, cells, k, S, A)
        else:
            proj = proj.transpose(1, 2).reshape(n, cells, k, S, A)
        proj = proj * cmaps.permute(0, 3, 1, 2)[..., None] + blk["feat_b"][:, None]
        out_w = blk["out_w"]
        score = (F.relu(proj) * out_w[:, None, :, :S]).sum(-1)  # [n, cells, k, S]
        score = (score * blk["slot_mask"][:, None]).sum(-1)  # [n, cells, k]
        state = F.relu(torch.einsum("nkh,nkha->nka", h_prev, blk["state_w"]) + blk["state_b"])
        score = score + ((state * out_w[:, :, S]).sum(-1) + blk["out_b"])[:, None]
        return torch.softmax(score, 1).transpose(1, 2)

    @staticmethod
    def _overlap(maps: torch.Tensor, top: dict) -> torch.Tensor:
        """Σ_cells(minmax(map_word) * minmax(map_antonym)) / cells per row (GSCAN_SPEC §8.6)."""
        pairs = top["pairs"]
        n, P, _ = pairs.shape
        cells = maps.shape[-1]
        sel = maps.gather(1, pairs.reshape(n, 2 * P, 1).expand(-1, -1, cells)).view(n, P, 2, cells)
        lo, hi = sel.amin(-1, keepdim=True), sel.amax(-1, keepdim=True)
        rng = hi - lo
        norm = ((sel - lo) / torch.where(rng > 0, rng, torch.ones_like(rng)) + 1e-5).clamp(0.0, 1.0)
        prod = (norm[:, :, 0] * norm[:, :, 1]).sum(-1) / cells
        return (prod * top["pair_mask"]).sum(-1)

    # -- teacher forcing
    def teacher_forcing(self, batch: "TeacherBatch") -> "TeacherOutput":
        """Loss over a batch whose rows are sorted by length, states packed time-major."""
        bound = self.bind(batch.layout)
        feats = self.encoder(batch.indices, batch.offsets)
        proj = self._projections(batch, feats).split(batch.active) if self.cfg.uses_attention else None
        # split (not per-step slicing): its backward is one concatenation, not one
        # full-size zero-filled gradient per step.
        feats = feats.split(batch.active)
        hidden = self.initial_hidden(batch.layout.batch, batch.layout.num_slots)
        logits, overlaps = [], []
        for t, (n, feats_t) in enumerate(zip(batch.active, feats)):
            if n != bound.rows:
                # Nested prefixes: each slice's backward is the size of the previous one.
                bound = bound.prefix(n)
            res = self.step(bound, hidden[:n], feats_t, None if proj is None else proj[t])
            logits.append(res.logits)
            overlaps.append(res.overlap)
            hidden = res.hidden
        logits_t = torch.cat(logits)
        valid = batch.valid.float()
        nll = F.cross_entropy(logits_t, batch.targets.clamp(min=0), reduction="none") * valid
        overlap = torch.cat(overlaps) * valid  # quirk Q4: padded steps add nothing
        per_step = nll + self.cfg.antonym_weight * overlap
        per_example = torch.zeros(batch.layout.batch).index_add(0, batch.rows, per_step) / batch.lengths
        return TeacherOutput(per_example.mean(), logits_t, nll, overlap)

    def _projections(self, batch: "TeacherBatch", feats: torch.Tensor) -> torch.Tensor:
        """[steps, J, cells, S*A]: every occupied slot's feature projection at every real step.

        Grouped by attention unit, each group is one large matmul over all its steps
        (instead of a small per-slot bmm inside the time loop); unoccupied slots and
        padded steps stay zero.
        """
        layout, bank = batch.layout, self.bank
        steps = batch.rows.shape[0]
        J, S, A, cells = layout.num_slots, bank.max_slots, self.cfg.att_dim, self.cfg.cells
        use = layout.occupied[batch.rows] & batch.valid[:, None]  # [steps, J]
        step_idx, slot_idx = use.nonzero(as_tuple=True)
        units = layout.unit[batch.rows[step_idx], slot_idx]
        order = torch.argsort(units, stable=True)
        step_idx, slot_idx, units = step_idx[order], slot_idx[order], units[order]
        present, counts = torch.unique_consecutive(units, return_counts=True)
        gathered = feats.index_select(0, step_idx)  # one gather: its backward is one index_add
        parts = []
        for u, rows in zip(present.tolist(), gathered.split(counts.tolist())):
            w = bank.att_feat_w[u].permute(1, 0, 2).reshape(-1, S * A)  # [F, S*A]
            parts.append(rows @ w)
        out = feats.new_zeros(steps, J, cells, S * A)
        return out.index_put((step_idx, slot_idx), torch.cat(parts))


@dataclass
class TeacherBatch:
    """A teacher-forcing batch. Row b has lengths[b] = T_b + 1 steps (T gold actions + EOS);
    rows are sorted by length (descending), so the rows alive at step t are a prefix of
    size active[t]. States, targets and rows are packed time-major (step 0 of every row,
    then step 1 ...). `active` may be rounded up (finished rows riding along on empty
    grids, `valid` False) so that it changes value only a few times per batch: each
    change costs one re-slice of every per-row parameter tensor."""

    layout: Layout
    indices: torch.Tensor  # set bits of all packed states (see sparse_states)
    offsets: torch.Tensor
    targets: torch.Tensor  # [steps] action id / Action.EOS; -1 on padded steps
    rows: torch.Tensor  # [steps] batch row of each packed step
    valid: torch.Tensor  # [steps] bool: a real step (rows past their length ride along padded)
    lengths: torch.Tensor  # [B] float
    active: list[int]  # rows alive per step
    episode_ids: np.ndarray | None = None  # dataset index of each row (bookkeeping only)


@dataclass
class TeacherOutput:
    loss: torch.Tensor
    logits: torch.Tensor  # [steps, actions], packed time-major
    nll: torch.Tensor  # [steps]
    overlap: torch.Tensor  # [steps], unweighted


def _gru_cell(x, h, wx, wh, bx, bh) -> torch.Tensor:
    """torch.nn.GRU's cell with per-slot weights: x [n,k,in], h [n,k,H], wx [n,k,in,3H]."""
    gx = torch.einsum("nki,nkio->nko", x, wx) + bx
    gh = torch.einsum("nki,nkio->nko", h, wh) + bh
    H = h.shape[-1]
    rz = torch.sigmoid(gx[..., : 2 * H] + gh[..., : 2 * H])
    r, z = rz[..., :H], rz[..., H:]
    cand = torch.tanh(gx[..., 2 * H :] + r * gh[..., 2 * H :])
    return cand + z * (h - cand)


class Rollout:
    """Closed-loop decoding state of a batch of graphs: feed observations, read action logits.

    `keep(rows)` drops finished rows so later steps only pay for live episodes.
    """

    def __init__(self, net: CompositionalNetwork, graphs: Sequence[CommandGraph]):
        layout = net.layout(graphs)
        self.net = net
        self.bound = net.bind(layout)
        self.hidden = net.initial_hidden(layout.batch, layout.num_slots)
        self.words = layout.words  # per row: (slot, word) of the graph's nodes

    def step(self, observations: np.ndarray) -> tuple[torch.Tensor, torch.Tensor | None]:
        """uint8 [n, g, g, C] -> (logits [n, actions], attention maps [n, J, cells] or None)."""
        feats = self.net.encoder(*sparse_states(observations))
        res = self.net.step(self.bound, self.hidden, feats)
        self.hidden = res.hidden
        return res.logits, res.maps

    def advance(self, actions: torch.Tensor) -> None:
        """The network conditions on world states only, not on its past actions."""

    def keep(self, rows: torch.Tensor) -> None:
        self.bound = self.bound.select(rows)
        self.hidden = self.hidden.index_select(0, rows)
        self.words = [self.words[i] for i in rows.tolist()]
