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
batch, every slot's attention parameters from the bank; a time step then evaluates the
blocks in order, each block with a handful of batched tensor ops, whatever modules the
slots hold. GRUs run on slots grouped by module (`SlotGroups`: one `bmm` per gate
matrix with the module's own weight). Padding slots compute throw-away values that
nothing reads.

The hidden-state input of an attention is broadcast over the cells and cancels in its
softmax, so it is not computed; with message='attention' only the root's GRU then
matters and only it runs (see `CompositionalNetwork.step` and docs/model.md).

The visual encoder exploits the one-hot input: a 'same' convolution on a 6x6 grid is a
fixed linear map from the 576 input bits to the 36x150 features, so the convolution is
one `embedding_bag` over the set bits of each state (~20 of 576) against a Toeplitz
matrix assembled from the conv weights once per call. `VisualEncoder.dense` is the plain
`Conv2d` reference path; the two agree to float rounding (tested).
"""
from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import asdict, dataclass, fields
from typing import Iterable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gscan_ros.errors import CheckpointError, GraphError, LexiconError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.world.types import GRID_SIZE, NUM_CHANNELS, SUPPORTED_GRID_SIZES, Action

MESSAGES = ("attention", "state", "attention+state")
ATTENTION_STATES = ("broadcast", "add")
SIZE_MAPS = ("softmax", "minmax")


# --------------------------------------------------------------------------- config
class DictConfig:
    """to_dict/from_dict of the frozen config dataclasses that checkpoints store (tuples
    as lists; unknown keys are a CheckpointError)."""

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict):
        unknown = sorted(set(d) - {f.name for f in fields(cls)})
        if unknown:
            raise CheckpointError(f"unknown {cls.__name__} keys {unknown}")
        return cls(**d)


@dataclass(frozen=True)
class ModelConfig(DictConfig):
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
    attention_state: str = "broadcast"
    """How a module's previous state enters its attention MLP. 'broadcast' (GSCAN_SPEC
    §8.4): projected, concatenated after the arguments' projections and broadcast over the
    cells, where it cancels in the softmax. 'add': added to every argument's projection
    before the ReLU, so the module's own state shapes its map (one reading of the paper's
    "mapped to the same dimension before being combined"). Same parameters either way;
    'add' runs every module's GRU and trains step by step."""
    size_map: str = "softmax"
    """The map an antonym-pair module (big|small) passes to its parent: its 'softmax'
    attention (this project's default), or 'minmax': the min-max normalised map of the
    overlap loss, as the original code passes it (GSCAN_SPEC §8.6, quirk Q16) and as the
    published numbers were produced."""
    num_actions: int = len(Action)
    """Output classes: the six gSCAN actions plus EOS, ids = `Action` values."""

    def __post_init__(self) -> None:
        if self.message not in MESSAGES:
            raise ValueError(f"message must be one of {MESSAGES}, got {self.message!r}")
        if self.attention_state not in ATTENTION_STATES:
            raise ValueError(f"attention_state must be one of {ATTENTION_STATES}, got {self.attention_state!r}")
        if self.size_map not in SIZE_MAPS:
            raise ValueError(f"size_map must be one of {SIZE_MAPS}, got {self.size_map!r}")
        if self.attention_state == "add" and not self.uses_attention:
            raise ValueError("attention_state='add' needs attention maps; message='state' has none")
        # Sizes come from YAML and checkpoints: a list, a float or a negative fails here, not in torch.
        for name in ("grid_size", "in_channels", "cnn_channels", "att_dim", "rnn_layers", "rnn_dim", "num_actions"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if self.grid_size not in SUPPORTED_GRID_SIZES:
            raise ValueError(f"grid_size {self.grid_size} is not supported "
                             f"({SUPPORTED_GRID_SIZES[0]} to {SUPPORTED_GRID_SIZES[-1]})")
        kernels = self.cnn_kernels
        if not (isinstance(kernels, (list, tuple)) and kernels
                and all(isinstance(k, int) and not isinstance(k, bool) and k > 0 for k in kernels)):
            raise ValueError(f"cnn_kernels must be a non-empty list of positive integers, got {kernels!r}")
        object.__setattr__(self, "cnn_kernels", tuple(kernels))
        if any(k % 2 == 0 for k in self.cnn_kernels):
            raise ValueError(f"cnn_kernels must be odd for 'same' padding, got {self.cnn_kernels}")
        if not (isinstance(self.cnn_dropout, (int, float)) and 0 <= self.cnn_dropout < 1):
            raise ValueError(f"cnn_dropout must be a number in [0, 1), got {self.cnn_dropout!r}")
        if not (isinstance(self.antonym_weight, (int, float)) and 0 <= self.antonym_weight < math.inf):
            raise ValueError(f"antonym_weight must be a finite number >= 0, got {self.antonym_weight!r}")

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

    @property
    def state_in_attention(self) -> bool:
        """A module's state changes its map (so every module's GRU matters)."""
        return self.attention_state == "add"

    @property
    def runs_every_gru(self) -> bool:
        """Every slot's GRU runs, block by block; otherwise only the root's (see `step`)."""
        return self.passes_state or self.state_in_attention


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
        self.level_cache: dict[str, list] = {}  # graph JSON -> _graph_levels(graph, self)
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
        # Offset of input cell q relative to output cell p, shifted into [0, 2g-2]: the
        # kernel-canvas position that links them, one per (q, p) pair.
        offset = ((r[:, None] - r[None, :] + g - 1) * (2 * g - 1) + (c[:, None] - c[None, :] + g - 1)).reshape(-1)
        pairs = offset.numel()
        # [(q, p), canvas position] 0/1: the Toeplitz matrix is this times the canvas, a
        # sparse matmul in both directions (an indexing gather would backprop through a
        # serial accumulating index_put, ~5x slower).
        self._placement = torch.sparse_coo_tensor(
            torch.stack([torch.arange(pairs), offset]), torch.ones(pairs), (pairs, (2 * g - 1) ** 2), check_invariants=True
        ).coalesce()

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

    def toeplitz(self, scale: float = 1.0) -> torch.Tensor:
        """[cells*C, cells*F]: row (cell q, channel k) -> contribution to every (cell p, feature o),
        times `scale` (applied to the small kernel bank, not the large matrix)."""
        bank = self._kernel_bank()  # [F, C, 2g-1, 2g-1]
        if scale != 1.0:
            bank = bank * scale
        canvas = bank.permute(2, 3, 1, 0).reshape(-1, bank.shape[1] * bank.shape[0])  # [position, (k, o)]
        if self._placement.device != canvas.device:  # not a buffer (no state_dict entry): moved on first use
            self._placement = self._placement.to(canvas.device)
        w = torch.sparse.mm(self._placement, canvas)  # [(q, p), (k, o)]
        cells, C = self.cfg.cells, self.cfg.in_channels
        return w.view(cells, cells, C, -1).permute(0, 2, 1, 3).reshape(cells * C, -1)

    @property
    def bias(self) -> torch.Tensor:
        return torch.cat([conv.bias for conv in self.convs])

    def _weight(self, scale: float = 1.0) -> torch.Tensor:
        """[cells*C + 1, cells*F]: the Toeplitz matrix plus a last row holding the bias of
        every cell, so the bias rides in the embedding bag instead of a full extra pass;
        all times `scale`."""
        bias = self.bias if scale == 1.0 else self.bias * scale
        return torch.cat([self.toeplitz(scale), bias.repeat(self.cfg.cells)[None]])

    def _inference_weight(self) -> torch.Tensor:
        """`_weight()` cached across no-grad calls (closed loop re-encodes every step)
        until a conv parameter changes (tracked by tensor versions)."""
        key = tuple((p.data_ptr(), p._version) for p in self.parameters())
        if getattr(self, "_cache_key", None) != key:
            self._cache_key, self._cache = key, self._weight()
        return self._cache

    def forward(self, indices: torch.Tensor, offsets: torch.Tensor, groups: torch.Tensor | None = None) -> torch.Tensor:
        """Sparse path: set-bit indices of flattened [g, g, C] states (see `sparse_states`) -> [N, cells, F].

        `groups` [N] (optional) names the episode of each state (-1: none). The bits that
        every state of a group has (the objects that stay put, ~3/4 of them) are summed
        once per group, and each state adds only its own changing bits (the agent, a
        pushed object) plus that group sum: about 4x fewer additions in both directions.

        Dropout's 1/(1-p) scale is folded into the weights (ReLU commutes with a positive
        scale) and its mask is applied in the same op as the ReLU (`_ReluDrop`): the
        [N, cells, F] features are the largest tensors of a batch and memory-bound.
        """
        n = offsets.numel()
        keep = None
        if self.training and self.cfg.cnn_dropout > 0:
            keep, p = _keep_mask(n * self.cfg.cells * self.cfg.feature_dim, self.cfg.cnn_dropout, indices.device)
            weight = self._weight(1.0 / (1.0 - p))
        else:
            weight = self._weight() if torch.is_grad_enabled() else self._inference_weight()
        bias_row = self.cfg.cells * self.cfg.in_channels
        if groups is None:
            bags, starts = _with_extra_index(indices, offsets, torch.full((n,), bias_row, device=indices.device))
        else:
            shared, own, own_offsets = _shared_bits(indices, offsets, groups, bias_row + 1)
            shared_bits, shared_offsets = shared
            group_sums = F.embedding_bag(shared_bits, weight, shared_offsets, mode="sum")
            # A state's bag: its own bits + its group's sum (a row appended to the weight),
            # or the bias row for a state without a group.
            extra = torch.where(groups >= 0, weight.shape[0] + groups, bias_row)
            bags, starts = _with_extra_index(own, own_offsets, extra)
            weight = torch.cat([weight, group_sums])
        flat = F.embedding_bag(bags, weight, starts, mode="sum")
        if not torch.is_grad_enabled():
            flat = flat.relu_() if keep is None else flat.mul_(keep.view_as(flat)).relu_()
        else:  # in place on the bag's output itself: on a view, autograd would copy the gradient
            flat = _ReluDrop.apply(flat, keep)
        return flat.view(n, self.cfg.cells, self.cfg.feature_dim)

    def dense(self, states: torch.Tensor) -> torch.Tensor:
        """Reference path on float/uint8 [N, g, g, C] states -> [N, cells, F]."""
        x = states.float().permute(0, 3, 1, 2)
        feats = torch.cat([conv(x) for conv in self.convs], 1)
        return self.dropout(F.relu(feats)).flatten(2).transpose(1, 2)


def _with_extra_index(indices: torch.Tensor, offsets: torch.Tensor, extra: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bags (indices, offsets) with `extra[i]` put first in bag i."""
    n, device = offsets.numel(), offsets.device
    starts = offsets + torch.arange(n, device=device)
    bags = torch.empty(indices.numel() + n, dtype=torch.long, device=device)
    is_bit = torch.ones(bags.numel(), dtype=torch.bool, device=device)
    is_bit[starts] = False
    bags[is_bit] = indices
    bags[starts] = extra
    return bags, starts


def _shared_bits(indices: torch.Tensor, offsets: torch.Tensor, groups: torch.Tensor, width: int):
    """Split bags into the bits common to every bag of their group and the rest.

    Returns ((shared bits, shared offsets) per group 0..G-1, plus the bias row `width-1`
    in each), and the bags' remaining (indices, offsets). Bags of group -1 keep all bits.
    """
    n, device = offsets.numel(), offsets.device
    counts = torch.diff(offsets, append=torch.tensor([indices.numel()], device=device))
    bag_group = torch.repeat_interleave(groups, counts)
    num_groups = int(groups.max()) + 1 if n else 0
    in_group = bag_group >= 0
    key = bag_group.clamp(min=0) * width + indices
    seen = torch.bincount(key[in_group], minlength=num_groups * width)
    members = torch.bincount(groups[groups >= 0], minlength=num_groups)
    common = (seen.view(num_groups, width) == members[:, None]) & (members[:, None] > 0)
    common[:, width - 1] = True  # the bias row: once per group
    is_shared = in_group & common.view(-1)[key]
    own = indices[~is_shared]
    row_of_bit = torch.repeat_interleave(torch.arange(n, device=device), counts)
    own_counts = counts - torch.zeros(n, dtype=torch.long, device=device).index_add_(0, row_of_bit, is_shared.long())
    own_offsets = torch.zeros(n, dtype=torch.long, device=device)
    own_offsets[1:] = own_counts.cumsum(0)[:-1]
    group_ids, shared = common.nonzero(as_tuple=True)
    shared_offsets = torch.zeros(num_groups, dtype=torch.long, device=device)
    shared_offsets[1:] = common.sum(1).cumsum(0)[:-1]
    return (shared, shared_offsets), own, own_offsets


_DROP_LEVELS = 1 << 16


def _keep_mask(size: int, p: float, device: torch.device | str = "cpu") -> tuple[torch.Tensor, float]:
    """A uint8 keep mask (1 with probability 1-p) of `size` elements on `device` and the
    exact p it drops with (a multiple of 2^-16).

    On the CPU, 16-bit draws are cut from the raw 64-bit words of numpy's PCG64, seeded
    from torch's generator (so `torch.manual_seed` still fixes it): ~15x faster than
    `bernoulli_` on the 20M-element feature tensors. The bool result is viewed as uint8 at
    no cost, and multiplying by uint8 is faster than `where` or `masked_fill` with a bool
    mask. On another device the 16-bit draws come from that device's torch generator, so
    the mask never crosses from the host.
    """
    cut = round(p * _DROP_LEVELS)
    if torch.device(device).type != "cpu":
        draws = torch.randint(0, _DROP_LEVELS, (size,), dtype=torch.int32, device=device)
        return (draws >= cut).view(torch.uint8), cut / _DROP_LEVELS
    rng = np.random.default_rng(int(torch.randint(0, 2**62, (1,))))
    draws = rng.bit_generator.random_raw(-(-size // 4)).view(np.uint16)[:size]
    return torch.from_numpy(draws >= cut).view(torch.uint8), cut / _DROP_LEVELS


class _ReluDrop(torch.autograd.Function):
    """Zero the dropped elements and ReLU, in place on the (otherwise unused) encoder
    output. The backward needs only the output (an element passes gradient iff it is
    > 0) and runs as one fused `threshold_backward`."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, keep: torch.Tensor | None) -> torch.Tensor:
        if keep is not None:
            x.mul_(keep.view_as(x))
        y = x.relu_()
        ctx.mark_dirty(x)
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (y,) = ctx.saved_tensors
        return torch.ops.aten.threshold_backward(grad, y, 0), None


def sparse_states(states: np.ndarray | torch.Tensor, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 one-hot states [N, g, g, C] -> (int64 set-bit indices, int64 bag offsets) on `device`."""
    flat = torch.as_tensor(np.asarray(states), device=device).reshape(len(states), -1)
    rows, cols = flat.nonzero(as_tuple=True)
    counts = torch.bincount(rows, minlength=flat.shape[0])
    offsets = torch.zeros(flat.shape[0], dtype=torch.long, device=device)
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
        # Filled in numpy (element writes to torch tensors cost ~50x more), converted once.
        unit = np.zeros((B, J), dtype=np.int64)
        module = np.zeros((B, J), dtype=np.int64)
        child = np.zeros((B, J, S), dtype=np.int64)
        slot_mask = np.zeros((B, J, S), dtype=np.float32)
        src = np.tile(np.arange(J), (B, 1))
        root = np.zeros(B, dtype=np.int64)
        occupied = np.zeros((B, J), dtype=bool)
        has_antonyms = np.zeros((B, J), dtype=bool)
        pairs: list[list[tuple[int, int]]] = []
        self.words: list[list[tuple[int, str]]] = []
        slots_of = [s.slots for s in table.specs]
        for b, (g, levels) in enumerate(zip(graphs, per_graph)):
            slot_of: dict[int, int] = {}
            shadows: list[tuple[int, _Entry]] = []
            for (lo, _), level in zip(self.blocks, levels):
                for j, e in enumerate(level, lo):
                    unit[b, j], module[b, j] = e.unit, e.module
                    occupied[b, j] = True
                    has_antonyms[b, j] = bool(table.specs[e.module].antonyms)
                    if e.shadow_of is None:
                        slot_of[e.node] = j
                    else:
                        shadows.append((j, e))
            for (lo, _), level in zip(self.blocks, levels):
                for j, e in enumerate(level, lo):
                    owner = e.node if e.shadow_of is None else e.shadow_of
                    slot_mask[b, j, : slots_of[e.module]] = 1.0
                    for s, c in enumerate(e.children):
                        child[b, j, s] = slot_of[c] + 1
                    src[b, j] = slot_of[owner]
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
        self.unit, self.module, self.child, self.slot_mask = t(unit), t(module), t(child), t(slot_mask)
        self.src, self.root, self.pairs, self.pair_mask = t(src), t(root), t(pair_t), t(pair_mask)
        self.occupied, self.has_antonyms = t(occupied), t(has_antonyms)

    def to(self, device: torch.device) -> "Layout":
        """This layout with its slot tensors on `device` (itself when they are there)."""
        if self.unit.device == torch.device(device):
            return self
        moved = copy.copy(self)
        for name in _LAYOUT_TENSORS:
            setattr(moved, name, getattr(self, name).to(device))
        return moved


_LAYOUT_TENSORS = ("unit", "module", "child", "slot_mask", "src", "root", "pairs", "pair_mask", "occupied",
                   "has_antonyms")


def _graph_levels(graph: CommandGraph, table: ModuleTable) -> list[list[_Entry]]:
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
            real.append(_Entry(nid, n.word, m, base + n.head, children))
            for other in spec.antonym_of(n.head):
                shadows.append(_Entry(nid, n.word, m, base + other, children, shadow_of=nid))
        levels.append(real + shadows)
    if len(cache) > 4096:
        cache.clear()
    cache[key] = levels
    return levels


# -------------------------------------------------------------------- bound params
class Bound:
    """A layout with every slot's parameters gathered from the bank (one gather per batch).

    Per block: a dict of tensors with leading dims [B, k] (k = block width); plus the
    root's output layer and the antonym pairs. `select(rows)` keeps a subset of rows
    (closed-loop evaluation drops finished episodes); `prefix(n)` is the cheap variant
    for teacher forcing, where rows are sorted by length.

    The GRUs do not use per-slot gathered weights: the slots that run one (the root with
    message='attention', every real slot block by block with pass_state) are grouped by
    module (`SlotGroups`), so a layer is one `bmm` per gate matrix with one weight per
    module present, and its weight gradient is a dense reduction over the group's rows.
    """

    def __init__(self, blocks: list[dict[str, torch.Tensor]], top: dict[str, torch.Tensor], num_slots: int,
                 spans: list[tuple[int, int]], bank: "WordModuleBank"):
        self.blocks, self.top, self.num_slots, self.spans, self.bank = blocks, top, num_slots, spans, bank
        if bank.cfg.runs_every_gru:  # GRUs run block by block (see CompositionalNetwork.step)
            self.gru = [_GruGroups(blk["gru_module"], bank) for blk in blocks]
        else:  # only the root's GRU matters (see CompositionalNetwork.step)
            self.gru_root = _GruGroups(top["root_module"][:, None], bank)
        self._feat_w: list[torch.Tensor | None] = [None] * len(blocks)

    @property
    def rows(self) -> int:
        return self.top["root"].shape[0]

    def feat_w(self, block: int) -> torch.Tensor:
        """[n, F, k*S*A]: every slot's feature projection weights, so that one `bmm` projects
        a step's features for the whole block. Built on first use: only closed-loop
        decoding needs it (teacher forcing precomputes the projections for all steps)."""
        if self._feat_w[block] is None:
            units = self.blocks[block]["att_unit"].clamp(min=0)
            n, k = units.shape
            w = self.bank.att_feat_w[units]  # [n, k, S, F, A]
            self._feat_w[block] = w.permute(0, 3, 1, 2, 4).reshape(n, w.shape[3], -1)
        return self._feat_w[block]

    def _map(self, fn) -> "Bound":
        return Bound([{k: fn(v) for k, v in blk.items()} for blk in self.blocks],
                     {k: fn(v) for k, v in self.top.items()}, self.num_slots, self.spans, self.bank)

    def select(self, rows: torch.Tensor) -> "Bound":
        return self._map(lambda t: t.index_select(0, rows))

    def prefix(self, n: int) -> "Bound":
        return self if n == self.rows else self._map(lambda t: t[:n])


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


class _GruGroups(SlotGroups):
    """Real slots by module, with the modules' GRU weights gathered once per grouping."""

    def __init__(self, gru_module: torch.Tensor, bank: "WordModuleBank"):
        super().__init__(gru_module)
        self.w = {}
        for layer in range(bank.cfg.rnn_layers):
            self.w[f"x{layer}"] = bank.gru_x[layer].index_select(0, self.keys)
            self.w[f"h{layer}"] = bank.gru_h[layer].index_select(0, self.keys)
            self.w[f"bx{layer}"] = bank.gru_bx[layer].index_select(0, self.keys)[:, None]
            self.w[f"bh{layer}"] = bank.gru_bh[layer].index_select(0, self.keys)[:, None]

    def run(self, x: torch.Tensor, h_prev: torch.Tensor, layers: int, hidden: int) -> torch.Tensor:
        """All layers of every real slot: x [n, k, in], h_prev [n, k, L*H] -> [n, k, L*H]."""
        n, k = x.shape[:2]
        shape = (self.groups, self.width)
        xg = x.reshape(n * k, -1).index_select(0, self.idx).view(*shape, -1)
        hg = h_prev.reshape(n * k, -1).index_select(0, self.idx).view(*shape, -1)
        w, out = self.w, []
        for layer in range(layers):
            h = hg[..., layer * hidden : (layer + 1) * hidden]
            xg = _gru_cell(xg, h, w[f"x{layer}"], w[f"h{layer}"], w[f"bx{layer}"], w[f"bh{layer}"])
            out.append(xg)
        h_new = torch.cat(out, -1) if layers > 1 else out[0]
        return h_new.view(self.groups * self.width, -1).index_select(0, self.inv).view(n, k, -1)


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

    @property
    def device(self) -> torch.device:
        return self.bank.out_w.device

    def bind(self, layout: Layout) -> Bound:
        bank, cfg = self.bank, self.cfg
        A = cfg.att_dim
        layout = layout.to(self.device)
        blocks = []
        for lo, hi in layout.blocks:
            u, m = layout.unit[:, lo:hi], layout.module[:, lo:hi]
            B, k = u.shape
            blk = {"child": layout.child[:, lo:hi], "src": layout.src[:, lo:hi]}
            if cfg.uses_attention:
                blk["att_unit"] = torch.where(layout.occupied[:, lo:hi], u, -1)
                blk["feat_b"] = bank.att_feat_b[u]
                # Output weights of the feature inputs; slots past a module's arity weigh 0.
                S = bank.max_slots
                score_w = bank.att_out_w[u][:, :, :S] * layout.slot_mask[:, lo:hi, :, None]
                blk["score_w"] = score_w.reshape(B, k, S * A)
            if cfg.uses_attention and cfg.size_map == "minmax":
                blk["minmax"] = layout.has_antonyms[:, lo:hi]
            if cfg.state_in_attention:
                blk["att_state_w"], blk["att_state_b"] = bank.att_state_w[u], bank.att_state_b[u]
            if cfg.passes_state:
                blk["pass_w"], blk["pass_b"] = bank.state_w[m], bank.state_b[m]
            if cfg.runs_every_gru:
                # Real slots run their module's GRU; padding and antonym shadows (src != own slot) none.
                real = layout.occupied[:, lo:hi] & (layout.src[:, lo:hi] == torch.arange(lo, hi, device=self.device))
                blk["gru_module"] = torch.where(real, m, -1)
            blocks.append(blk)
        root_module = layout.module.gather(1, layout.root[:, None])[:, 0]
        top = {
            "root": layout.root,
            "root_module": root_module,
            "out_w": bank.out_w[root_module],
            "out_b": bank.out_b[root_module],
            "pairs": layout.pairs,
            "pair_mask": layout.pair_mask,
        }
        return Bound(blocks, top, layout.num_slots, list(layout.blocks), bank)

    def initial_hidden(self, rows: int, num_slots: int) -> torch.Tensor:
        return torch.zeros(rows, num_slots, self.cfg.rnn_layers * self.cfg.rnn_dim, device=self.device)

    def rollout(self, graphs: Sequence[CommandGraph]) -> "Rollout":
        return Rollout(self, graphs)

    # -- one time step
    def step(self, bound: Bound, hidden: torch.Tensor, feats: torch.Tensor,
             proj: torch.Tensor | None = None) -> StepResult:
        """Advance every slot one decoding step on cell features `feats` [n, cells, F].

        `proj` [n, cells, J, S, A]: the slots' feature projections, when precomputed
        (teacher forcing computes them for all steps at once, see `_projections`).
        """
        cfg = self.cfg
        n, cells = feats.shape[0], cfg.cells
        L, H = cfg.rnn_layers, cfg.rnn_dim
        maps_done: list[torch.Tensor] = [feats.new_ones(n, 1, cells)]  # pool index 0 = 'no child'
        hid_done: list[torch.Tensor] = [feats.new_zeros(n, 1, L * H)]
        for b_i, ((lo, hi), blk) in enumerate(zip(bound.spans, bound.blocks)):
            child = blk["child"]
            k, S = child.shape[1], child.shape[2]
            parts = []
            h_prev = None
            if cfg.runs_every_gru:  # antonym shadows read their owner's state (src)
                h_prev = hidden.gather(1, blk["src"][..., None].expand(-1, -1, L * H))  # [n, k, LH]
            if cfg.uses_attention:
                if proj is None:
                    p = torch.bmm(feats, bound.feat_w(b_i)).view(n, cells, k, S, -1)
                else:
                    p = proj[:, :, lo:hi]
                state = None
                if cfg.state_in_attention:
                    state = torch.einsum("nki,nkia->nka", h_prev, blk["att_state_w"]) + blk["att_state_b"]
                maps_done.append(_size_maps(blk, self._attend(blk, _child_maps(maps_done, child), p, state)))
                if not cfg.runs_every_gru:
                    continue  # the root's GRU runs after the loop
                parts.append(torch.bmm(maps_done[-1], feats))  # attention-weighted feature sum
            else:
                parts.append(feats.sum(1, keepdim=True).expand(-1, k, -1))
            if cfg.passes_state:
                # Parents read their children's new states: this block's GRUs run now.
                hpool = torch.cat(hid_done, 1)
                ch = hpool.gather(1, child.reshape(n, k * S, 1).expand(-1, -1, L * H)).view(n, k, S * L * H)
                parts.append(torch.einsum("nki,nkio->nko", ch, blk["pass_w"]) + blk["pass_b"])
            hid_done.append(bound.gru[b_i].run(torch.cat(parts, -1), h_prev, L, H))
        maps = torch.cat(maps_done[1:], 1) if cfg.uses_attention else None
        top = bound.top
        root = top["root"][:, None, None]
        if cfg.runs_every_gru:
            new_hidden = torch.cat(hid_done[1:], 1)
            root_h = new_hidden.gather(1, root.expand(-1, 1, L * H))
        else:
            # With message='attention' a module's state reaches nothing but its own
            # attention, where it cancels (see `_attend`): only the root's state, which
            # the action is decoded from, matters. The other slots' GRUs are not run and
            # their states stay zero.
            x = torch.bmm(maps.gather(1, root.expand(-1, 1, cells)), feats)
            root_h = bound.gru_root.run(x, hidden.gather(1, root.expand(-1, 1, L * H)), L, H)
            new_hidden = hidden.scatter(1, root.expand(-1, 1, L * H), root_h)
        logits = torch.bmm(root_h[:, :, (L - 1) * H :], top["out_w"])[:, 0] + top["out_b"]
        overlap = self._overlap(maps, top) if maps is not None and top["pairs"].shape[1] else feats.new_zeros(n)
        return StepResult(logits, new_hidden, maps, overlap)

    @staticmethod
    def _attend(blk, cmaps, proj, state: torch.Tensor | None = None) -> torch.Tensor:
        """softmax_cells( W_out . ReLU([ (feats*map_s) W_s + b_s ]_s ++ [h W_h + b_h]) + b ) -> [n, k, cells].

        (feats * map) W == map * (feats W): `proj` [n, cells, k, S, A] holds every slot's
        feature projection, weighted here by the child's map `cmaps` [n, k, S, cells].
        The hidden-state input (`att_state_*`, its `att_out_w` column and `att_out_b`) is
        broadcast over the cells, so it adds the same constant to every cell's logit and
        cancels in the softmax: it is not computed (GSCAN_SPEC §8.4's maps are exactly
        the same). With attention_state='add', `state` [n, k, A] (h W_h + b_h) is added to
        every argument's projection before the ReLU instead.
        """
        n, k, S, cells = cmaps.shape
        hidden = torch.addcmul(blk["feat_b"][:, None], proj, cmaps.permute(0, 3, 1, 2)[..., None])
        if state is not None:
            hidden = hidden + state[:, None, :, None, :]
        hidden = hidden.relu_()
        score = (hidden.view(n, cells, k, -1) * blk["score_w"][:, None]).sum(-1)  # [n, cells, k]
        return torch.softmax(score, 1).transpose(1, 2)

    @staticmethod
    def _overlap(maps: torch.Tensor, top: dict) -> torch.Tensor:
        """Σ_cells(minmax(map_word) * minmax(map_antonym)) / cells per row (GSCAN_SPEC §8.6)."""
        pairs = top["pairs"]
        n, P, _ = pairs.shape
        cells = maps.shape[-1]
        sel = maps.gather(1, pairs.reshape(n, 2 * P, 1).expand(-1, -1, cells)).view(n, P, 2, cells)
        norm = minmax_normalize(sel)
        prod = (norm[:, :, 0] * norm[:, :, 1]).sum(-1) / cells
        return (prod * top["pair_mask"]).sum(-1)

    # -- teacher forcing
    @property
    def teacher_quantum(self) -> int:
        """The `quantum` for `EpisodeStore.batch`: the step-by-step path re-slices per-row
        tensors whenever the number of live rows changes (8: few changes, ~10% padded
        steps); the all-steps-at-once path has no such cost, so no padding."""
        return 8 if self.cfg.runs_every_gru else 1

    def forward(self, batch: "TeacherBatch") -> "TeacherOutput":
        """Teacher forcing: the call DistributedDataParallel wraps."""
        return self.teacher_forcing(batch)

    def teacher_forcing(self, batch: "TeacherBatch") -> "TeacherOutput":
        """Loss over a batch whose rows are sorted by length, states packed time-major;
        the batch moves to the network's device first (once per update).

        With message='attention' the maps depend on the world state only (see `step`), so
        every step of every row is computed at once and only the root's GRU recurs
        (`_teacher_forcing_parallel`); with pass_state (the slots' states feed their
        parents) or attention_state='add' (a slot's state shapes its own map) the batch
        runs step by step (`_teacher_forcing_stepwise`).
        """
        batch = batch.to(self.device)
        if self.cfg.runs_every_gru:
            return self._teacher_forcing_stepwise(batch)
        return self._teacher_forcing_parallel(batch)

    def _loss(self, batch: "TeacherBatch", logits: torch.Tensor, overlap: torch.Tensor) -> "TeacherOutput":
        valid = batch.valid.float()
        nll = F.cross_entropy(logits, batch.targets.clamp(min=0), reduction="none") * valid
        overlap = overlap * valid  # quirk Q4: padded steps add nothing
        per_step = nll + self.cfg.antonym_weight * overlap
        per_example = per_step.new_zeros(batch.layout.batch).index_add(0, batch.rows, per_step) / batch.lengths
        return TeacherOutput(per_example.mean(), logits, nll, overlap)

    def _teacher_forcing_parallel(self, batch: "TeacherBatch") -> "TeacherOutput":
        """Every packed step at once: the features and projections row-major (episodes'
        steps consecutive), a handful of large ops per graph level, then the root GRU
        over time (`_root_gru_logits`) and the loss in time-major order."""
        cfg = self.cfg
        bound = self.bind(batch.layout)
        rm = _RowMajor(batch)
        feats = self.encoder(*rm.bags, groups=rm.groups)  # [N, cells, F], row-major
        proj = self._projections(bound, feats, rm.sizes)
        rows = rm.rows
        n, cells = feats.shape[0], cfg.cells
        maps_done: list[torch.Tensor] = [feats.new_ones(n, 1, cells)]
        # split, not slices: its backward is one concatenation, not a zero-filled full-size
        # gradient per block.
        proj_blocks = proj.split([hi - lo for lo, hi in bound.spans], 2)
        for blk, p in zip(bound.blocks, proj_blocks):
            step_blk = {key: blk[key].index_select(0, rows) for key in ("feat_b", "score_w", "minmax") if key in blk}
            cmaps = _child_maps(maps_done, blk["child"].index_select(0, rows))
            maps_done.append(_size_maps(step_blk, self._attend(step_blk, cmaps, p)))
        maps = torch.cat(maps_done[1:], 1)
        top = bound.top
        root = top["root"].index_select(0, rows)[:, None, None]
        x = torch.bmm(maps.gather(1, root.expand(-1, 1, cells)), feats)[:, 0]  # [N, F]
        logits = self._root_gru_logits(x.index_select(0, rm.to_time_major), batch, top["root_module"])
        pairs = {"pairs": top["pairs"].index_select(0, rows), "pair_mask": top["pair_mask"].index_select(0, rows)}
        overlap = self._overlap(maps, pairs) if pairs["pairs"].shape[1] else feats.new_zeros(n)
        return self._loss(batch, logits, overlap.index_select(0, rm.to_time_major))

    def _root_gru_logits(self, x: torch.Tensor, batch: "TeacherBatch", root_module: torch.Tensor) -> torch.Tensor:
        """Action logits [N, actions] of the root's GRU over its inputs x [N, F], packed time-major.

        Layer by layer: the input gates of every step at once (one matmul per root module),
        then the recurrence over time for all rows together, each row with its module's
        recurrent weights gathered once ([B, H, 3H], small). The rows alive at step t are
        a prefix (rows sorted by length), so a step works on prefix slices.
        """
        bank, H = self.bank, self.cfg.rnn_dim
        step_module = root_module.index_select(0, batch.rows)
        groups = _ModuleGroups(step_module)
        inp = x
        for layer in range(self.cfg.rnn_layers):
            gx = groups.linear(inp, bank.gru_x[layer], bank.gru_bx[layer])  # [N, 3H]
            wh = bank.gru_h[layer].index_select(0, root_module)  # [B, H, 3H]
            bh = bank.gru_bh[layer].index_select(0, root_module)[:, None]  # [B, 1, 3H]
            h, outs = x.new_zeros(len(root_module), 1, H), []
            for n, gx_t in zip(batch.active, gx.split(batch.active)):
                h = h[:n]
                h = _gru_update(gx_t[:, None], torch.baddbmm(bh[:n], h, wh[:n]), h)
                outs.append(h[:, 0])
            inp = torch.cat(outs)
        return groups.linear(inp, bank.out_w, bank.out_b)

    def _teacher_forcing_stepwise(self, batch: "TeacherBatch") -> "TeacherOutput":
        """Step by step through `step` (every slot's GRU runs)."""
        bound = self.bind(batch.layout)
        feats = self.encoder(batch.indices, batch.offsets)
        proj = None
        if self.cfg.uses_attention:
            rm = _RowMajor(batch)
            proj = self._projections(bound, feats.index_select(0, rm.order), rm.sizes)
            proj = proj.index_select(0, rm.to_time_major).split(batch.active)
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
        return self._loss(batch, torch.cat(logits), torch.cat(overlaps))

    def _projections(self, bound: Bound, feats: torch.Tensor, sizes: list[int]) -> torch.Tensor:
        """[N, cells, J, S, A]: every slot's feature projection at every step, for row-major
        features (row b's steps are `sizes[b]` consecutive entries).

        Each row gathers its slots' weights once ([B, F, J*S*A], a few MB); one matmul
        per row then projects all its steps for all its slots, reading the features once.
        """
        units = torch.cat([blk["att_unit"] for blk in bound.blocks], 1).clamp(min=0)  # [B, J]
        B, J = units.shape
        _, S, Fd, A = self.bank.att_feat_w.shape
        # index_select: its backward is index_add_, not a serial accumulating index_put
        w = self.bank.att_feat_w.index_select(0, units.reshape(-1)).view(B, J, S, Fd, A)
        w = w.permute(0, 3, 1, 2, 4).reshape(B, Fd, J * S * A)
        return _SegmentMatmul.apply(feats, w, sizes).view(feats.shape[0], feats.shape[1], J, S, A)


def minmax_normalize(maps: torch.Tensor) -> torch.Tensor:
    """Each map (last dim = cells) scaled to [0, 1] (a flat map divides by 1), + 1e-5,
    clipped to [0, 1]: the original's normalisation of size-word maps (GSCAN_SPEC §8.6)."""
    lo, hi = maps.amin(-1, keepdim=True), maps.amax(-1, keepdim=True)
    rng = hi - lo
    return ((maps - lo) / torch.where(rng > 0, rng, torch.ones_like(rng)) + 1e-5).clamp(0.0, 1.0)


def _size_maps(blk: dict, maps: torch.Tensor) -> torch.Tensor:
    """With size_map='minmax', antonym-pair slots pass their min-max normalised map on
    (maps [n, k, cells]); otherwise the softmax maps unchanged."""
    if "minmax" not in blk:
        return maps
    return torch.where(blk["minmax"][..., None], minmax_normalize(maps), maps)


def _child_maps(maps_done: list[torch.Tensor], child: torch.Tensor) -> torch.Tensor:
    """[n, k, S, cells]: the maps feeding each slot's arguments. `maps_done` holds the
    all-ones 'no child' map then every finished block's maps; `child` [n, k, S] indexes
    that pool (0 = no child, j+1 = slot j)."""
    pool = torch.cat(maps_done, 1)
    n, k, S = child.shape
    cells = pool.shape[-1]
    return pool.gather(1, child.reshape(n, k * S, 1).expand(-1, -1, cells)).view(n, k, S, cells)


class _RowMajor:
    """A time-major TeacherBatch's steps reordered row by row (each row's steps
    consecutive, in time order), as the per-row projection matmuls want them."""

    def __init__(self, batch: "TeacherBatch"):
        self.order = torch.argsort(batch.rows, stable=True)  # row-major position -> time-major step
        self.to_time_major = torch.empty_like(self.order)
        self.to_time_major[self.order] = torch.arange(self.order.numel(), device=self.order.device)
        self.rows = batch.rows.index_select(0, self.order)
        self.groups = torch.where(batch.valid.index_select(0, self.order), self.rows, -1)  # episode of each real step
        self.sizes = torch.bincount(batch.rows, minlength=batch.layout.batch).tolist()
        self._batch = batch

    @property
    def bags(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(indices, offsets) of the encoder's bags in row-major order."""
        offsets, indices = self._batch.offsets, self._batch.indices
        counts = torch.diff(offsets, append=torch.tensor([indices.numel()], device=offsets.device))
        counts, starts = counts[self.order], offsets[self.order]
        new_offsets = torch.zeros_like(offsets)
        new_offsets[1:] = counts.cumsum(0)[:-1]
        gather = torch.repeat_interleave(starts - new_offsets, counts) + torch.arange(indices.numel(),
                                                                                      device=offsets.device)
        return indices[gather], new_offsets


class _SegmentMatmul(torch.autograd.Function):
    """out[seg b] = x[seg b] @ w[b]: x [N, R, K] cut along N into consecutive segments of
    `sizes`, w [B, K, W] one matrix per segment -> [N, R, W]. Both directions are one
    matmul per segment writing straight into its slice of the result."""

    @staticmethod
    def forward(ctx, x, w, sizes):
        ctx.save_for_backward(x, w)
        ctx.sizes = sizes
        out = x.new_empty(x.shape[0], x.shape[1], w.shape[2])
        k = x.shape[-1]
        for b, (xs, os) in enumerate(zip(x.split(sizes), out.split(sizes))):
            torch.mm(xs.view(-1, k), w[b], out=os.view(-1, w.shape[2]))
        return out

    @staticmethod
    def backward(ctx, grad):
        x, w = ctx.saved_tensors
        grad = grad.contiguous()
        k, width = x.shape[-1], w.shape[2]
        grad_x = torch.empty_like(x) if ctx.needs_input_grad[0] else None
        grad_w = torch.empty_like(w) if ctx.needs_input_grad[1] else None
        gx_parts = grad_x.split(ctx.sizes) if grad_x is not None else [None] * len(ctx.sizes)
        for b, (xs, gs, gx) in enumerate(zip(x.split(ctx.sizes), grad.split(ctx.sizes), gx_parts)):
            g = gs.view(-1, width)
            if gx is not None:
                torch.mm(g, w[b].T, out=gx.view(-1, k))
            if grad_w is not None:
                torch.mm(xs.reshape(-1, k).T, g, out=grad_w[b])
        return grad_x, grad_w, None


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

    def to(self, device: torch.device) -> "TeacherBatch":
        """The batch with its tensors (and its layout's) on `device`; itself when they are there."""
        if self.indices.device == torch.device(device):
            return self
        return dataclasses.replace(
            self, layout=self.layout.to(device),
            **{name: getattr(self, name).to(device) for name in ("indices", "offsets", "targets", "rows", "valid", "lengths")})


@dataclass
class TeacherOutput:
    loss: torch.Tensor
    logits: torch.Tensor  # [steps, actions], packed time-major
    nll: torch.Tensor  # [steps]
    overlap: torch.Tensor  # [steps], unweighted


class _ModuleGroups:
    """Packed steps grouped by the module whose weights apply to them."""

    def __init__(self, step_module: torch.Tensor):
        order = torch.argsort(step_module, stable=True)
        self.modules, counts = torch.unique_consecutive(step_module.index_select(0, order), return_counts=True)
        self.members = order.split(counts.tolist())
        self.inverse = torch.empty_like(order)
        self.inverse[order] = torch.arange(order.numel(), device=order.device)

    def linear(self, x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """x [N, in] -> [N, out], each step through its module's w [M, in, out] + b [M, out]."""
        parts = [torch.addmm(b[m], x.index_select(0, idx), w[m]) for m, idx in zip(self.modules.tolist(), self.members)]
        return torch.cat(parts).index_select(0, self.inverse)


def _gru_cell(x, h, wx, wh, bx, bh) -> torch.Tensor:
    """torch.nn.GRU's cell per group: x [g,w,in], h [g,w,H], wx [g,in,3H], bx [g,1,3H]."""
    return _gru_update(torch.baddbmm(bx, x, wx), torch.baddbmm(bh, h, wh), h)


def _gru_update(gx: torch.Tensor, gh: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """The new state from input gates gx and recurrent gates gh (r, z, n as in torch.nn.GRU)."""
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
        pairs, mask = self.bound.top["pairs"][row].tolist(), self.bound.top["pair_mask"][row].tolist()
        return ({word: grids[slot] for slot, word in word_of.items()},
                {word_of[slot]: grids[shadow] for (slot, shadow), m in zip(pairs, mask) if m})

    def advance(self, actions: torch.Tensor) -> None:
        """The network conditions on world states only, not on its past actions."""

    def keep(self, rows: torch.Tensor) -> None:
        self.words = [self.words[i] for i in rows.tolist()]
        rows = rows.to(self.hidden.device)
        self.bound = self.bound.select(rows)
        self.hidden = self.hidden.index_select(0, rows)
