"""Teacher forcing for the compositional network: a batch of episodes, every step's loss.

With attention_state='broadcast' a module's state cancels in its own attention's
softmax, so the maps are a function of the current world state alone (docs/model.md),
and every map of every step of every row can be computed at once, a handful of large ops
per graph level. What recurs over time is then only the GRUs:
- `all_steps` (message='attention'): only the root's GRU matters, run over time once;
- `level_major` (message='state' or 'attention+state'): children's states feed their
  parents at the same step, so the levels run in order, leaves first; per level the GRU
  input gates of every step are one batch of matmuls and only the recurrent product
  runs step by step.
With attention_state='add' a module's state moves its own map, so `stepwise` runs the
batch step by step through `CompositionalNetwork.step`, as the closed loop does. All
give the loss, logits and gradients of the plain per-graph network
(tests/test_model_reference.py).

`net` is the `CompositionalNetwork` and `bank` its `WordModuleBank` (compositional.py, which
calls these functions; typed as plain nn.Modules so that this module does not import the
network back).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import nn

from gscan_ros.model.fast_ops import ContiguousGrad, GruRecurrence, SegmentMatmul
from gscan_ros.model.layout import Bound, Layout, child_maps


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
    """A teacher-forcing pass of any model kind (the attention decoder's overlap is zero)."""

    loss: torch.Tensor
    logits: torch.Tensor  # [steps, actions], packed time-major
    nll: torch.Tensor  # [steps]
    overlap: torch.Tensor  # [steps], unweighted


def all_steps(net: nn.Module, batch: TeacherBatch) -> TeacherOutput:
    """Every packed step at once: the features and maps row-major (episodes' steps
    consecutive), then the root GRU over time (`_root_gru_logits`) and the loss in
    time-major order."""
    cfg = net.cfg
    bound = net.bind(batch.layout)
    rm = _RowMajor(batch)
    feats = net.encoder(*rm.bags, groups=rm.groups)  # [N, cells, F], row-major
    maps = _all_maps(net, bound, feats, rm)
    readout = bound.readout
    root = readout.root_slot.index_select(0, rm.rows)[:, None, None]
    x = torch.bmm(maps.gather(1, root.expand(-1, 1, cfg.cells)), feats)[:, 0]  # [N, F]
    logits = _root_gru_logits(net.bank, x.index_select(0, rm.to_time_major), batch, readout.root_module)
    return net.loss(batch, logits, _overlap(net, bound, maps, rm))


def level_major(net: nn.Module, batch: TeacherBatch) -> TeacherOutput:
    """Every slot's GRU, level by level (children's new states feed their parents at the
    same step), each level's input gates for all steps at once (`_level_grus`). The
    GRU's own input is the map-weighted features (all maps computed at once, as in
    `all_steps`) or, with message='state', the sum over cells."""
    cfg = net.cfg
    bound = net.bind(batch.layout)
    rm = _RowMajor(batch)
    feats = net.encoder(*rm.bags, groups=rm.groups)  # [N, cells, F], row-major
    if cfg.uses_attention:
        maps = _all_maps(net, bound, feats, rm)
        x = torch.bmm(maps, feats).index_select(0, rm.to_time_major)  # [N, J, F]
        overlap = _overlap(net, bound, maps, rm)
    else:
        x = feats.sum(1, keepdim=True).index_select(0, rm.to_time_major)  # [N, 1, F], every slot reads it
        overlap = feats.new_zeros(batch.rows.numel())
    hidden = _level_grus(net.bank, bound, batch, x)  # [N, J, L*H] time-major
    readout = bound.readout
    H = cfg.rnn_dim
    root = readout.root_slot.index_select(0, batch.rows)[:, None, None].expand(-1, 1, H)
    root_h = hidden[..., -H:].gather(1, root)[:, 0]  # the root's last layer [N, H]
    groups = _ModuleGroups(readout.root_module.index_select(0, batch.rows))
    return net.loss(batch, groups.linear(root_h, net.bank.out_w, net.bank.out_b), overlap)


def stepwise(net: nn.Module, batch: TeacherBatch) -> TeacherOutput:
    """Step by step through `step` (every slot's GRU runs; any configuration)."""
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
        res = net.step(bound, hidden[:n], feats_t, None if proj is None else _block_projections(bound, proj[t]))
        logits.append(res.logits)
        overlaps.append(res.overlap)
        hidden = res.hidden
    return net.loss(batch, torch.cat(logits), torch.cat(overlaps))


def _all_maps(net: nn.Module, bound: Bound, feats: torch.Tensor, rm: "_RowMajor") -> torch.Tensor:
    """[N, J, cells]: the map every slot passes on at every step, row-major, level by
    level from the projections of all steps (`_projections`)."""
    rows, n, cells = rm.rows, feats.shape[0], net.cfg.cells
    proj = _block_projections(bound, _projections(net.bank, bound, feats, rm.sizes))
    maps_done: list[torch.Tensor] = [feats.new_ones(n, 1, cells)]
    for blk, p in zip(bound.blocks, proj):
        maps = net.attend(blk.att_feat_b.index_select(0, rows), blk.score_w.index_select(0, rows),
                          child_maps(maps_done, blk.children.index_select(0, rows)), p)
        passes_minmax = None if blk.passes_minmax is None else blk.passes_minmax.index_select(0, rows)
        maps_done.append(net.passed_maps(maps, passes_minmax))
    return torch.cat(maps_done[1:], 1)


def _overlap(net: nn.Module, bound: Bound, maps: torch.Tensor, rm: "_RowMajor") -> torch.Tensor:
    """[N] antonym overlap of every step, time-major, from row-major maps."""
    readout = bound.readout
    if not readout.antonym_pairs.shape[1]:
        return maps.new_zeros(maps.shape[0])
    pairs = readout.antonym_pairs.index_select(0, rm.rows)
    overlap = net.overlap(maps, pairs, readout.pair_mask.index_select(0, rm.rows))
    return overlap.index_select(0, rm.to_time_major)


def _level_grus(bank: nn.Module, bound: Bound, batch: TeacherBatch, x: torch.Tensor) -> torch.Tensor:
    """[N, J, L*H]: every slot's new state (all layers) at every packed step (time-major),
    from the GRUs' own inputs x [N, J or 1, F].

    Per level, per layer: the input gates of every (step, slot) at once, grouped by module
    (layer 0 reads x and a Linear of the children's new states, which the levels below
    have finished), then the recurrence over time, each slot with its module's recurrent
    weights gathered once ([B, k, H, 3H]). Padding slots and antonym shadows run no GRU
    of their own (-1 in `gru_module`): their states stay zero, and nothing reads them.
    """
    cfg = bank.cfg
    L, H = cfg.rnn_layers, cfg.rnn_dim
    rows, n_steps = batch.rows, batch.rows.numel()
    levels: list[torch.Tensor] = [x.new_zeros(n_steps, 1, L * H)]  # pool index 0 = 'no child'
    for (lo, hi), blk in zip(bound.spans, bound.blocks):
        k, S = blk.children.shape[1], blk.children.shape[2]
        module = blk.gru_module  # [B, k]
        groups = _ModuleGroups(module.index_select(0, rows).reshape(-1))
        inp = [x[:, lo:hi] if x.shape[1] > 1 else x.expand(-1, k, -1)]
        if cfg.passes_state:
            pool = torch.cat(levels, 1)
            children = blk.children.index_select(0, rows).reshape(n_steps, k * S, 1).expand(-1, -1, L * H)
            ch = pool.gather(1, children).reshape(n_steps * k, S * L * H)
            inp.append(groups.linear(ch, bank.state_w[:, : S * L * H], bank.state_b).view(n_steps, k, H))
        inp = torch.cat(inp, -1).reshape(n_steps * k, -1)
        lane_module = module.clamp(min=0).reshape(-1)  # lanes = (row, slot), row-major: a step's lanes are a prefix
        lanes = [n * k for n in batch.active]
        outs = []
        for layer in range(L):
            gx = groups.linear(inp, bank.gru_x[layer], bank.gru_bx[layer])  # [N*k, 3H]
            wh = bank.gru_h[layer].index_select(0, lane_module)
            bh = bank.gru_bh[layer].index_select(0, lane_module)[:, None]
            inp = GruRecurrence.apply(gx, wh, bh, lanes)  # [N*k, H]
            outs.append(inp.view(n_steps, k, H))
        levels.append(torch.cat(outs, -1) * (module >= 0).index_select(0, rows)[..., None])
    return torch.cat(levels[1:], 1)


def _root_gru_logits(bank: nn.Module, x: torch.Tensor, batch: TeacherBatch,
                     root_module: torch.Tensor) -> torch.Tensor:
    """Action logits [N, actions] of the root's GRU over its inputs x [N, F], packed time-major.

    Layer by layer: the input gates of every step at once (one matmul per root module),
    then the recurrence over time for all rows together, each row with its module's
    recurrent weights gathered once ([B, H, 3H], small; `GruRecurrence`). The rows alive
    at step t are a prefix (rows sorted by length). (One `aten::gru` call per root module
    with packed sequences was slower in total: docs/results.md.)
    """
    step_module = root_module.index_select(0, batch.rows)
    groups = _ModuleGroups(step_module)
    inp = x
    for layer in range(bank.cfg.rnn_layers):
        gx = groups.linear(inp, bank.gru_x[layer], bank.gru_bx[layer])  # [N, 3H]
        wh = bank.gru_h[layer].index_select(0, root_module)  # [B, H, 3H]
        bh = bank.gru_bh[layer].index_select(0, root_module)[:, None]  # [B, 1, 3H]
        inp = GruRecurrence.apply(gx, wh, bh, batch.active)
    return groups.linear(inp, bank.out_w, bank.out_b)


def _projections(bank: nn.Module, bound: Bound, feats: torch.Tensor, sizes: list[int]) -> torch.Tensor:
    """[N, cells, P]: every slot's feature projection at every step, for row-major
    features (row b's steps are `sizes[b]` consecutive entries); block l holds its
    share k*S_l*A of P (`Bound.proj_widths`, `_block_projections`).

    (feats * map) W == map * (feats W), so the projections do not wait for the children's
    maps. Each row gathers its slots' weights once ([B, F, P], a few MB); one matmul
    per row then projects all its steps for all its slots, reading the features once.
    """
    _, _, Fd, A = bank.att_feat_w.shape
    weights = []
    for blk in bound.blocks:
        units = blk.att_unit.clamp(min=0)
        (B, k), S = units.shape, blk.children.shape[2]
        # index_select: its backward is index_add_, not a serial accumulating index_put
        w = ContiguousGrad.apply(bank.att_feat_w[:, :S].index_select(0, units.reshape(-1))).view(B, k, S, Fd, A)
        weights.append(w.permute(0, 3, 1, 2, 4).reshape(B, Fd, k * S * A))
    return SegmentMatmul.apply(feats, torch.cat(weights, 2), sizes)


def _block_projections(bound: Bound, proj: torch.Tensor) -> list[torch.Tensor]:
    """Flat projections [n, cells, P] as one [n, cells, k, S_l, A] view per block.
    (split, not slices: its backward is one concatenation, not a zero-filled full-size
    gradient per block.)"""
    return [p.unflatten(2, (blk.children.shape[1], blk.children.shape[2], -1))
            for blk, p in zip(bound.blocks, proj.split(bound.proj_widths(), 2))]


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
    """Packed items grouped by the module whose weights apply to them (-1: none)."""

    def __init__(self, item_module: torch.Tensor):
        self.size = item_module.numel()
        order = torch.argsort(item_module, stable=True)
        modules, counts = torch.unique_consecutive(item_module.index_select(0, order), return_counts=True)
        members = order.split(counts.tolist())
        if modules.numel() and modules[0] < 0:  # items of no module come first: skip them
            modules, members = modules[1:], members[1:]
        self.modules, self.members = modules.tolist(), members
        self.order = torch.cat(members) if members else order[:0]
        self.inverse = None
        if self.order.numel() == self.size:  # every item has a module: results are a permutation away
            self.inverse = torch.empty_like(order)
            self.inverse[self.order] = torch.arange(self.size, device=order.device)

    def linear(self, x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """x [N, in] -> [N, out], each item through its module's w [M, in, out] + b [M, out]
        (0 for items of no module)."""
        parts = [torch.addmm(b[m], x.index_select(0, idx), w[m]) for m, idx in zip(self.modules, self.members)]
        out = torch.cat(parts) if parts else x.new_zeros(0, w.shape[-1])
        if self.inverse is not None:
            return out.index_select(0, self.inverse)
        return x.new_zeros(self.size, w.shape[-1]).index_copy(0, self.order, out)
