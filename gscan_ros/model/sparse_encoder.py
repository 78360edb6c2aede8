"""The visual encoder's convolutions as one embedding bag over the set bits of each state.

The input is one-hot, so each 'same' convolution on the g x g grid is a fixed linear map
from the g*g*C input bits to the g*g*F features: a Toeplitz matrix assembled from the
conv weights once per call, against which a state's features are the sum of the rows of
its ~20 set bits (of 576 on 6x6), about 20x fewer multiply-adds than the dense conv.
`VisualEncoder.dense` (encoders.py) is the plain Conv2d form; the two agree to float
rounding (tests/test_model_reference.py, tests/test_model_fastpaths.py).

On larger grids the Toeplitz matrix grows as cells^2 (50M entries on 12x12), and building
it and its gradient on every training update costs more than the features themselves.
There, training sums rows of the kernel canvas instead: one bag per (state, output cell)
over the canvas rows that link each set bit to that cell, so the weight and its gradient
stay the size of the conv kernels; their weight gradient is a sparse product
(`fast_ops.BagSum`). Closed loop keeps the cached Toeplitz matrix.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gscan_ros.model.fast_ops import BagSum, ReluDrop, RowGather, keep_mask

# Training on grids this wide or wider uses per-cell canvas bags instead of the Toeplitz
# matrix (docs/results.md, "Sparse encoder on 12×12 (split I)": equal at 6x6 with 50 episodes).
PER_CELL_MIN_GRID = 8


class SparseConv:
    """Evaluates a VisualEncoder's conv branches (+ ReLU + dropout) on set-bit bags.

    Holds no parameters (nothing enters the state_dict): the weights are read from the
    `convs` passed to each call.
    """

    def __init__(self, grid_size: int, in_channels: int, feature_dim: int):
        self.grid_size, self.in_channels, self.feature_dim = grid_size, in_channels, feature_dim
        self.cells = grid_size * grid_size
        g = grid_size
        r = torch.arange(g).repeat_interleave(g)  # cell index -> row
        c = torch.arange(g).repeat(g)  # cell index -> col
        # Offset of input cell q relative to output cell p, shifted into [0, 2g-2]: the
        # kernel-canvas position that links them, one per (q, p) pair.
        offset = ((r[:, None] - r[None, :] + g - 1) * (2 * g - 1) + (c[:, None] - c[None, :] + g - 1)).reshape(-1)
        pairs = offset.numel()
        # [(q, p), canvas position] 0/1: the Toeplitz matrix is this times the canvas
        # (`toeplitz`, the plain form that `weight`'s gather is tested against).
        self._placement = torch.sparse_coo_tensor(torch.stack([torch.arange(pairs), offset]), torch.ones(pairs),
                                                  (pairs, (2 * g - 1) ** 2), check_invariants=True).coalesce()
        self._cache_key, self._cache = None, None
        # Input bit (cell q, channel k) -> for every output cell p, its row (offset(q, p), k) in
        # the flattened canvas; the last bit (cells*C) is the bias, row (2g-1)^2*C for every p.
        canvas_rows = offset.view(self.cells, 1, self.cells) * in_channels + torch.arange(in_channels).view(1, -1, 1)
        bias_row = torch.full((1, self.cells), (2 * g - 1) ** 2 * in_channels)
        self._canvas_rows = torch.cat([canvas_rows.reshape(-1, self.cells), bias_row])
        self._gather_plan = RowGather.plan(self._canvas_rows, (2 * g - 1) ** 2 * in_channels + 1)
        self.per_cell = grid_size >= PER_CELL_MIN_GRID

    def _kernel_bank(self, convs: nn.ModuleList) -> torch.Tensor:
        """All branches' weights centred on a (2g-1)^2 canvas: [F, C, 2g-1, 2g-1]."""
        g = self.grid_size
        out = []
        for conv in convs:
            w, half = conv.weight, conv.kernel_size[0] // 2
            if half <= g - 1:
                pad = g - 1 - half
                out.append(F.pad(w, (pad, pad, pad, pad)))
            else:  # offsets beyond the grid never contribute
                cut = half - (g - 1)
                out.append(w[:, :, cut : cut + 2 * g - 1, cut : cut + 2 * g - 1])
        return torch.cat(out, 0)

    def canvas_weight(self, convs: nn.ModuleList, scale: float = 1.0) -> torch.Tensor:
        """[(2g-1)^2*C + 1, F]: the kernel canvas, row (position, channel k), plus the bias
        row; all times `scale`."""
        bank = self._kernel_bank(convs)  # [F, C, 2g-1, 2g-1]
        canvas = bank.permute(2, 3, 1, 0).reshape(-1, bank.shape[0])
        weight = torch.cat([canvas, torch.cat([conv.bias for conv in convs])[None]])
        return weight * scale if scale != 1.0 else weight

    def per_cell_bags(self, bits: torch.Tensor, offsets: torch.Tensor,
                      extra: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Bags of input bits (one per state) -> one bag of canvas rows per (state, output
        cell), state-major; `extra` [n, cells] (optional) is put first in each bag."""
        n, cells, device = offsets.numel(), self.cells, bits.device
        if self._canvas_rows.device != device:
            self._canvas_rows = self._canvas_rows.to(device)
        counts = torch.diff(offsets, append=torch.tensor([bits.numel()], device=device))
        state = torch.repeat_interleave(torch.arange(n, device=device), counts)
        ext = 0 if extra is None else 1
        first = (offsets + ext * torch.arange(n, device=device)) * cells  # bag of (state, cell 0)
        starts = first[:, None] + torch.arange(cells, device=device)[None, :] * (counts + ext)[:, None]
        rows = torch.empty(bits.numel() * cells + ext * n * cells, dtype=torch.long, device=device)
        within = torch.arange(bits.numel(), device=device) - offsets[state] + ext  # place in its bags
        rows[(starts[state] + within[:, None]).view(-1)] = self._canvas_rows[bits].view(-1)
        if extra is not None:
            rows[starts.view(-1)] = extra.reshape(-1)
        return rows, starts.view(-1)

    def _per_cell(self, convs: nn.ModuleList, indices: torch.Tensor, offsets: torch.Tensor,
                  groups: torch.Tensor | None, scale: float) -> torch.Tensor:
        """The pre-activation features [n*cells, F] from canvas bags (see the module docstring)."""
        weight = self.canvas_weight(convs, scale)
        bias_bit, n = self.cells * self.in_channels, offsets.numel()
        if groups is None:
            bits, starts = _with_extra_index(indices, offsets, torch.full((n,), bias_bit, device=indices.device))
            rows, starts = self.per_cell_bags(bits, starts)
            return BagSum.apply(rows, weight, starts)
        (shared, shared_offsets), own, own_offsets = shared_bits(indices, offsets, groups, bias_bit + 1)
        rows, starts = self.per_cell_bags(shared, shared_offsets)
        group_sums = BagSum.apply(rows, weight, starts)  # [groups*cells, F]
        # Each (state, cell) bag: the state's own bits + its group's sum at that cell (rows
        # appended to the weight), or the bias row for a state without a group.
        cells = torch.arange(self.cells, device=indices.device)
        extra = torch.where((groups >= 0)[:, None], weight.shape[0] + groups[:, None] * self.cells + cells,
                            weight.shape[0] - 1)
        rows, starts = self.per_cell_bags(own, own_offsets, extra)
        return BagSum.apply(rows, torch.cat([weight, group_sums]), starts)

    def toeplitz(self, convs: nn.ModuleList, scale: float = 1.0) -> torch.Tensor:
        """[cells*C, cells*F]: row (cell q, channel k) -> contribution to every (cell p, feature o),
        times `scale` (applied to the small kernel bank, not the large matrix)."""
        bank = self._kernel_bank(convs)  # [F, C, 2g-1, 2g-1]
        if scale != 1.0:
            bank = bank * scale
        canvas = bank.permute(2, 3, 1, 0).reshape(-1, bank.shape[1] * bank.shape[0])  # [position, (k, o)]
        if self._placement.device != canvas.device or self._placement.dtype != canvas.dtype:
            self._placement = self._placement.to(device=canvas.device, dtype=canvas.dtype)  # moved on first use
        w = torch.sparse.mm(self._placement, canvas)  # [(q, p), (k, o)]
        return w.view(self.cells, self.cells, self.in_channels, -1).permute(0, 2, 1, 3).reshape(
            self.cells * self.in_channels, -1)

    def weight(self, convs: nn.ModuleList, scale: float = 1.0) -> torch.Tensor:
        """[cells*C + 1, cells*F]: the Toeplitz matrix plus a last row holding the bias of
        every cell, so the bias rides in the embedding bag instead of a full extra pass;
        all times `scale`.

        The plain form is `toeplitz` and the bias row; here both are one gather of
        kernel-canvas rows (`canvas_weight`), each (input bit, output cell) reading the
        row of the offset between them, and the backward is one bag sum (`RowGather`):
        no sparse product, permuted copy or concatenation of the 12 MB matrix."""
        canvas = self.canvas_weight(convs, scale)
        if self._gather_plan[0].device != canvas.device:  # (per_cell_bags may have moved the rows alone)
            self._canvas_rows = self._canvas_rows.to(canvas.device)
            self._gather_plan = tuple(t.to(canvas.device) for t in self._gather_plan)
        return RowGather.apply(canvas, self._canvas_rows, *self._gather_plan).view(self._canvas_rows.shape[0], -1)

    def plain_weight(self, convs: nn.ModuleList, scale: float = 1.0) -> torch.Tensor:
        """`weight` as its definition: the Toeplitz matrix and the bias row, concatenated."""
        bias = torch.cat([conv.bias for conv in convs])
        if scale != 1.0:
            bias = bias * scale
        return torch.cat([self.toeplitz(convs, scale), bias.repeat(self.cells)[None]])

    def _inference_weight(self, convs: nn.ModuleList) -> torch.Tensor:
        """`weight()` cached across no-grad calls (closed loop re-encodes every step)
        until a conv parameter changes (tracked by tensor versions)."""
        key = tuple((p.data_ptr(), p._version) for p in convs.parameters())
        if self._cache_key != key:
            self._cache_key, self._cache = key, self.weight(convs)
        return self._cache

    def __call__(self, convs: nn.ModuleList, indices: torch.Tensor, offsets: torch.Tensor,
                 groups: torch.Tensor | None = None, dropout: float = 0.0) -> torch.Tensor:
        """Set-bit indices of flattened [g, g, C] states (see `sparse_states`) -> ReLU'd,
        dropped-out features [N, cells, F].

        `groups` [N] (optional) names the episode of each state (-1: none). The bits that
        every state of a group has (the objects that stay put, ~3/4 of them) are summed
        once per group, and each state adds only its own changing bits (the agent, a
        pushed object) plus that group sum: about 4x fewer additions in both directions.

        Dropout's 1/(1-p) scale is folded into the weights (ReLU commutes with a positive
        scale) and its mask is applied in the same op as the ReLU (`ReluDrop`): the
        [N, cells, F] features are the largest tensors of a batch and memory-bound.
        """
        n = offsets.numel()
        keep, scale = None, 1.0
        if dropout > 0:
            keep, p = keep_mask(n * self.cells * self.feature_dim, dropout, indices.device)
            scale = 1.0 / (1.0 - p)
        if self.per_cell and torch.is_grad_enabled():
            flat = ReluDrop.apply(self._per_cell(convs, indices, offsets, groups, scale), keep)
            return flat.view(n, self.cells, self.feature_dim)
        if dropout > 0:
            weight = self.weight(convs, scale)
        else:
            weight = self.weight(convs) if torch.is_grad_enabled() else self._inference_weight(convs)
        bias_row = self.cells * self.in_channels
        if groups is None:
            bags, starts = _with_extra_index(indices, offsets, torch.full((n,), bias_row, device=indices.device))
        else:
            shared, own, own_offsets = shared_bits(indices, offsets, groups, bias_row + 1)
            shared_indices, shared_offsets = shared
            group_sums = F.embedding_bag(shared_indices, weight, shared_offsets, mode="sum")
            # A state's bag: its own bits + its group's sum (a row appended to the weight),
            # or the bias row for a state without a group.
            extra = torch.where(groups >= 0, weight.shape[0] + groups, bias_row)
            bags, starts = _with_extra_index(own, own_offsets, extra)
            weight = torch.cat([weight, group_sums])
        flat = F.embedding_bag(bags, weight, starts, mode="sum")
        if not torch.is_grad_enabled():
            flat = flat.relu_() if keep is None else flat.mul_(keep.view_as(flat)).relu_()
        else:  # in place on the bag's output itself: on a view, autograd would copy the gradient
            flat = ReluDrop.apply(flat, keep)
        return flat.view(n, self.cells, self.feature_dim)


def _with_extra_index(indices: torch.Tensor, offsets: torch.Tensor,
                      extra: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bags (indices, offsets) with `extra[i]` put first in bag i."""
    n, device = offsets.numel(), offsets.device
    starts = offsets + torch.arange(n, device=device)
    bags = torch.empty(indices.numel() + n, dtype=torch.long, device=device)
    is_bit = torch.ones(bags.numel(), dtype=torch.bool, device=device)
    is_bit[starts] = False
    bags[is_bit] = indices
    bags[starts] = extra
    return bags, starts


def shared_bits(indices: torch.Tensor, offsets: torch.Tensor, groups: torch.Tensor, width: int):
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
    _, shared = common.nonzero(as_tuple=True)  # bit of each (group, bit) pair, group-major
    shared_offsets = torch.zeros(num_groups, dtype=torch.long, device=device)
    shared_offsets[1:] = common.sum(1).cumsum(0)[:-1]
    return (shared, shared_offsets), own, own_offsets


def sparse_states(states: np.ndarray | torch.Tensor,
                  device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 one-hot states [N, g, g, C] -> (int64 set-bit indices, int64 bag offsets) on `device`."""
    flat = torch.as_tensor(np.asarray(states), device=device).reshape(len(states), -1)
    rows, cols = flat.nonzero(as_tuple=True)
    counts = torch.bincount(rows, minlength=flat.shape[0])
    offsets = torch.zeros(flat.shape[0], dtype=torch.long, device=device)
    offsets[1:] = counts.cumsum(0)[:-1]
    return cols, offsets
