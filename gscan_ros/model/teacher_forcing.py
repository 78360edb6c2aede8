"""Teacher forcing for the compositional network: a batch of episodes, every step's loss.

With message='attention' and attention_state='broadcast' a module's state cancels in its
own attention's softmax, so the maps are a function of the current world state alone
(docs/model.md). `all_steps` therefore computes every map of every step of every row at
once, a handful of large ops per graph level, and only the root's GRU recurs over time.
Otherwise (a module's state feeds its parent or its own map) `stepwise` runs the batch
step by step through `CompositionalNetwork.step`, as the closed loop does. Both give the
loss, logits and gradients of the plain per-graph network (tests/test_model_reference.py).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from gscan_ros.model.fast_ops import SegmentMatmul, gru_update
from gscan_ros.model.layout import Bound, Layout, child_maps

if TYPE_CHECKING:
    from gscan_ros.model.compositional import CompositionalNetwork, WordModuleBank


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

    def to(self, device: torch.device) -> "TeacherBatch":
        """The batch with its tensors (and its layout's) on `device`; itself when they are there."""
        if self.indices.device == torch.device(device):
            return self
        tensors = ("indices", "offsets", "targets", "rows", "valid", "lengths")
        return dataclasses.replace(self, layout=self.layout.to(device),
                                   **{name: getattr(self, name).to(device) for name in tensors})


@dataclass
class TeacherOutput:
    loss: torch.Tensor
    logits: torch.Tensor  # [steps, actions], packed time-major
    nll: torch.Tensor  # [steps]
    overlap: torch.Tensor  # [steps], unweighted


def all_steps(net: "CompositionalNetwork", batch: TeacherBatch) -> TeacherOutput:
    """Every packed step at once: the features and projections row-major (episodes'
    steps consecutive), a handful of large ops per graph level, then the root GRU
    over time (`_root_gru_logits`) and the loss in time-major order."""
    cfg = net.cfg
    bound = net.bind(batch.layout)
    rm = _RowMajor(batch)
    feats = net.encoder(*rm.bags, groups=rm.groups)  # [N, cells, F], row-major
    proj = _projections(net.bank, bound, feats, rm.sizes)
    rows = rm.rows
    n, cells = feats.shape[0], cfg.cells
    maps_done: list[torch.Tensor] = [feats.new_ones(n, 1, cells)]
    # split, not slices: its backward is one concatenation, not a zero-filled full-size
    # gradient per block.
    proj_blocks = proj.split([hi - lo for lo, hi in bound.spans], 2)
    for blk, p in zip(bound.blocks, proj_blocks):
        maps = net.attend(blk.att_feat_b.index_select(0, rows), blk.score_w.index_select(0, rows),
                          child_maps(maps_done, blk.children.index_select(0, rows)), p)
        passes_minmax = None if blk.passes_minmax is None else blk.passes_minmax.index_select(0, rows)
        maps_done.append(net.passed_maps(maps, passes_minmax))
    maps = torch.cat(maps_done[1:], 1)
    readout = bound.readout
    root = readout.root_slot.index_select(0, rows)[:, None, None]
    x = torch.bmm(maps.gather(1, root.expand(-1, 1, cells)), feats)[:, 0]  # [N, F]
    logits = _root_gru_logits(net.bank, x.index_select(0, rm.to_time_major), batch, readout.root_module)
    if readout.antonym_pairs.shape[1]:
        pairs, pair_mask = readout.antonym_pairs.index_select(0, rows), readout.pair_mask.index_select(0, rows)
        overlap = net.overlap(maps, pairs, pair_mask)
    else:
        overlap = feats.new_zeros(n)
    return net.loss(batch, logits, overlap.index_select(0, rm.to_time_major))


def stepwise(net: "CompositionalNetwork", batch: TeacherBatch) -> TeacherOutput:
    """Step by step through `step` (every slot's GRU runs)."""
    bound = net.bind(batch.layout)
    feats = net.encoder(batch.indices, batch.offsets)
    proj = None
    if net.cfg.uses_attention:
        rm = _RowMajor(batch)
        proj = _projections(net.bank, bound, feats.index_select(0, rm.order), rm.sizes)
        proj = proj.index_select(0, rm.to_time_major).split(batch.active)
    # split (not per-step slicing): its backward is one concatenation, not one
    # full-size zero-filled gradient per step.
    feats = feats.split(batch.active)
    hidden = net.initial_hidden(batch.layout.batch, batch.layout.num_slots)
    logits, overlaps = [], []
    for t, (n, feats_t) in enumerate(zip(batch.active, feats)):
        if n != bound.rows:
            # Nested prefixes: each slice's backward is the size of the previous one.
            bound = bound.prefix(n)
        res = net.step(bound, hidden[:n], feats_t, None if proj is None else proj[t])
        logits.append(res.logits)
        overlaps.append(res.overlap)
        hidden = res.hidden
    return net.loss(batch, torch.cat(logits), torch.cat(overlaps))


def _root_gru_logits(bank: "WordModuleBank", x: torch.Tensor, batch: TeacherBatch,
                     root_module: torch.Tensor) -> torch.Tensor:
    """Action logits [N, actions] of the root's GRU over its inputs x [N, F], packed time-major.

    Layer by layer: the input gates of every step at once (one matmul per root module),
    then the recurrence over time for all rows together, each row with its module's
    recurrent weights gathered once ([B, H, 3H], small). The rows alive at step t are
    a prefix (rows sorted by length), so a step works on prefix slices. (One `aten::gru`
    call per root module with packed sequences was slower in total: docs/results.md.)
    """
    H = bank.cfg.rnn_dim
    step_module = root_module.index_select(0, batch.rows)
    groups = _ModuleGroups(step_module)
    inp = x
    for layer in range(bank.cfg.rnn_layers):
        gx = groups.linear(inp, bank.gru_x[layer], bank.gru_bx[layer])  # [N, 3H]
        wh = bank.gru_h[layer].index_select(0, root_module)  # [B, H, 3H]
        bh = bank.gru_bh[layer].index_select(0, root_module)[:, None]  # [B, 1, 3H]
        h, outs = x.new_zeros(len(root_module), 1, H), []
        for n, gx_t in zip(batch.active, gx.split(batch.active)):
            h = h[:n]
            h = gru_update(gx_t[:, None], torch.baddbmm(bh[:n], h, wh[:n]), h)
            outs.append(h[:, 0])
        inp = torch.cat(outs)
    return groups.linear(inp, bank.out_w, bank.out_b)


def _projections(bank: "WordModuleBank", bound: Bound, feats: torch.Tensor, sizes: list[int]) -> torch.Tensor:
    """[N, cells, J, S, A]: every slot's feature projection at every step, for row-major
    features (row b's steps are `sizes[b]` consecutive entries).

    (feats * map) W == map * (feats W), so the projections do not wait for the children's
    maps. Each row gathers its slots' weights once ([B, F, J*S*A], a few MB); one matmul
    per row then projects all its steps for all its slots, reading the features once.
    """
    units = torch.cat([blk.att_unit for blk in bound.blocks], 1).clamp(min=0)  # [B, J]
    B, J = units.shape
    _, S, Fd, A = bank.att_feat_w.shape
    # index_select: its backward is index_add_, not a serial accumulating index_put
    w = bank.att_feat_w.index_select(0, units.reshape(-1)).view(B, J, S, Fd, A)
    w = w.permute(0, 3, 1, 2, 4).reshape(B, Fd, J * S * A)
    return SegmentMatmul.apply(feats, w, sizes).view(feats.shape[0], feats.shape[1], J, S, A)


class _RowMajor:
    """A time-major TeacherBatch's steps reordered row by row (each row's steps
    consecutive, in time order), as the per-row projection matmuls want them."""

    def __init__(self, batch: TeacherBatch):
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
