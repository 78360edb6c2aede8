"""Batched kernels the compositional network's fast paths share.

Custom autograd functions that save a pass or a copy over what plain torch ops would do,
the dropout keep mask, and torch.nn.GRU's cell on weights gathered per module. Each one
has a test against the plain computation it replaces (tests/test_model_fastpaths.py).
"""
from __future__ import annotations

import itertools

import numpy as np
import torch

_DROP_LEVELS = 1 << 16


def keep_mask(size: int, p: float, device: torch.device | str = "cpu") -> tuple[torch.Tensor, float]:
    """A uint8 keep mask (1 with probability 1-p) of `size` elements on `device` and the
    exact p it drops with (a multiple of 2^-16).

    On the CPU, 16-bit draws are cut from the raw 64-bit words of numpy's PCG64, seeded
    from torch's generator (so `torch.manual_seed` still fixes it), far faster than
    `bernoulli_` on the feature tensors. The bool result is viewed as uint8 at no cost,
    and multiplying by uint8 beat `where` or `masked_fill` with a bool mask (figures:
    docs/results.md "Why these fast paths"). On another device the 16-bit draws come
    from that device's torch generator, so the mask never crosses from the host.
    """
    cut = round(p * _DROP_LEVELS)
    if torch.device(device).type != "cpu":
        draws = torch.randint(0, _DROP_LEVELS, (size,), dtype=torch.int32, device=device)
        return (draws >= cut).view(torch.uint8), cut / _DROP_LEVELS
    rng = np.random.default_rng(int(torch.randint(0, 2**62, (1,))))
    draws = rng.bit_generator.random_raw(-(-size // 4)).view(np.uint16)[:size]
    return torch.from_numpy(draws >= cut).view(torch.uint8), cut / _DROP_LEVELS


class ReluDrop(torch.autograd.Function):
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


class BagSum(torch.autograd.Function):
    """`F.embedding_bag(rows, weight, starts, mode="sum")` whose weight gradient is one
    sparse product: the [weights, bags] incidence of the rows times the bags' gradient.
    torch's own backward (`_embedding_bag_dense_backward`) sorts the rows and adds one
    gradient row per entry, ~2.3x slower on the per-cell bags of a 12x12 update (~330k
    entries of 150 features: docs/results.md, "Sparse encoder on 12×12 (split I)")."""

    @staticmethod
    def forward(ctx, rows: torch.Tensor, weight: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(rows, starts)
        ctx.num_weights = weight.shape[0]
        return torch.nn.functional.embedding_bag(rows, weight, starts, mode="sum")

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        rows, starts = ctx.saved_tensors
        sizes = torch.diff(starts, append=starts.new_tensor([rows.numel()]))
        bags = torch.repeat_interleave(torch.arange(starts.numel(), device=rows.device), sizes)
        incidence = torch.sparse_coo_tensor(torch.stack([rows, bags]), grad.new_ones(rows.numel()),
                                            (ctx.num_weights, starts.numel()), check_invariants=False)
        return None, torch.sparse.mm(incidence, grad.contiguous()), None


class RowGather(torch.autograd.Function):
    """`weight[index]` (index [R, W] of rows of weight [V, F] -> [R, W, F]) for a fixed
    index that is used many times, whose backward sums each weight row's gradient as one
    embedding bag over the index's positions sorted by row (`RowGather.plan`, made once).
    torch's own backward of the gather accumulates row by row in a serial `index_put`."""

    @staticmethod
    def plan(index: torch.Tensor, rows: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(positions of `index` sorted by row, each row's first place in them)."""
        flat = index.reshape(-1)
        order = torch.argsort(flat, stable=True)
        counts = torch.bincount(flat, minlength=rows)
        starts = torch.zeros(rows, dtype=torch.long, device=index.device)
        starts[1:] = counts.cumsum(0)[:-1]
        return order, starts

    @staticmethod
    def forward(ctx, weight: torch.Tensor, index: torch.Tensor, order: torch.Tensor,
                starts: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(order, starts)
        return torch.nn.functional.embedding(index, weight)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        order, starts = ctx.saved_tensors
        flat = grad.contiguous().view(-1, grad.shape[-1])
        return torch.nn.functional.embedding_bag(order, flat, starts, mode="sum"), None, None, None


class ContiguousGrad(torch.autograd.Function):
    """Identity whose backward makes the gradient contiguous before it goes on. Put after
    a gather whose output is then permuted and sliced: `index_select`'s backward
    (`index_add_`) on that strided gradient took ~5.5 ms of an update against ~0.7 ms for a copy plus a
    contiguous `index_add_` (docs/results.md, "Why these fast paths")."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        return grad.contiguous()


class SegmentMatmul(torch.autograd.Function):
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


def gru_cell(x, h, wx, wh, bx, bh) -> torch.Tensor:
    """torch.nn.GRU's cell per group: x [g,w,in], h [g,w,H], wx [g,in,3H], bx [g,1,3H]."""
    return gru_update(torch.baddbmm(bx, x, wx), torch.baddbmm(bh, h, wh), h)


def gru_update(gx: torch.Tensor, gh: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """The new state from input gates gx and recurrent gates gh (r, z, n as in torch.nn.GRU),
    so that callers can compute the gates in whatever batched form suits them."""
    H = h.shape[-1]
    rz = torch.sigmoid(gx[..., : 2 * H] + gh[..., : 2 * H])
    r, z = rz[..., :H], rz[..., H:]
    cand = torch.tanh(gx[..., 2 * H :] + r * gh[..., 2 * H :])
    return cand + z * (h - cand)


class GruRecurrence(torch.autograd.Function):
    """The recurrence of a GRU layer whose input gates are already computed, over packed
    time-major steps, each lane (a row, or a row's slot) with its own recurrent weights.

    gx [N, 3H]: the input gates of every packed step (step t holds the first lanes[t]
    lanes, `lanes` non-increasing); wh [R, H, 3H], bh [R, 1, 3H]: each lane's recurrent
    weights; the state starts at zero. Returns every step's new state [N, H].

    The forward builds no graph: 6 ops a step (baddbmm, add, sigmoid, addcmul, tanh,
    lerp) writing into preallocated buffers whose per-step views come from one `split`
    each. The backward is backpropagation through time written out (one baddbmm and 8
    elementwise ops a step), and the weight gradients are one batched product over all
    steps at the end. Plain autograd over `gru_update` records ~25 nodes a step, and at
    these sizes (H = 20) the time goes into that bookkeeping, not the arithmetic.
    """

    @staticmethod
    def forward(ctx, gx, wh, bh, lanes):
        N, H = gx.shape[0], wh.shape[1]
        gx = gx.view(N, 1, 3 * H)
        gh = gx.new_empty(N, 1, 3 * H)  # recurrent gates h W_h + b_h
        rz = gx.new_empty(N, 1, 2 * H)  # reset and update gates
        cand = gx.new_empty(N, 1, H)
        out = gx.new_empty(N, 1, H)
        steps = zip(lanes, gh.split(lanes), gx[..., : 2 * H].split(lanes), gh[..., : 2 * H].split(lanes),
                    rz.split(lanes), gx[..., 2 * H :].split(lanes), rz[..., :H].split(lanes),
                    gh[..., 2 * H :].split(lanes), cand.split(lanes), rz[..., H:].split(lanes), out.split(lanes))
        h, w, b = gx.new_zeros(lanes[0] if lanes else 0, 1, H), wh, bh
        for n, gh_t, gx_rz, gh_rz, rz_t, gx_n, r_t, gh_n, cand_t, z_t, out_t in steps:
            if n != h.shape[0]:
                h, w, b = h[:n], w[:n], b[:n]
            torch.baddbmm(b, h, w, out=gh_t)
            torch.sigmoid(torch.add(gx_rz, gh_rz), out=rz_t)
            torch.tanh(torch.addcmul(gx_n, r_t, gh_n), out=cand_t)
            h = torch.lerp(cand_t, h, z_t, out=out_t)  # cand + z (h - cand)
        ctx.save_for_backward(wh, out, gh, rz, cand)
        ctx.lanes = lanes
        return out.view(N, H)

    @staticmethod
    def backward(ctx, grad_out):
        wh, out, gh, rz, cand = ctx.saved_tensors
        lanes, H, N = ctx.lanes, wh.shape[1], out.shape[0]
        grad_out = grad_out.contiguous().view(N, 1, H)
        # d(recurrent gates); the input gates' are the same except the candidate's (dgx_n)
        dgh = grad_out.new_empty(N, 1, 3 * H)
        dgx_n = grad_out.new_empty(N, 1, H)
        dsig, dtanh = rz * (1 - rz), 1 - cand * cand
        # The state each step started from, lane-aligned (step t's lanes are a prefix of step t-1's).
        starts = [0, *itertools.accumulate(lanes[:-1])]
        h_prev = torch.cat([out.new_zeros(lanes[0] if lanes else 0, 1, H)]
                           + [out[s : s + n] for s, n in zip(starts, lanes[1:])])
        steps = list(zip(lanes, grad_out.split(lanes), rz[..., :H].split(lanes), rz[..., H:].split(lanes),
                         cand.split(lanes), h_prev.split(lanes), gh[..., 2 * H :].split(lanes), dtanh.split(lanes),
                         dsig.split(lanes), dgh.split(lanes), dgh[..., :H].split(lanes),
                         dgh[..., H : 2 * H].split(lanes), dgh[..., 2 * H :].split(lanes), dgx_n.split(lanes)))
        dh_all, whT = grad_out.new_zeros(lanes[0] if lanes else 0, 1, H), wh.transpose(1, 2)
        prefix = {}
        for n, g_t, r_t, z_t, cand_t, hp_t, ghn_t, dtanh_t, dsig_t, dgh_t, dr_t, dz_t, dghn_t, dn_t in reversed(steps):
            if n not in prefix:
                prefix[n] = dh_all[:n], whT[:n]
            dh, w = prefix[n]
            dh.add_(g_t)
            dcand = torch.addcmul(dh, dh, z_t, value=-1)  # dh (1 - z)
            torch.mul(dh, hp_t - cand_t, out=dz_t)
            torch.mul(dcand, dtanh_t, out=dn_t)  # d(candidate pre-activation) = d(input gate n)
            torch.mul(dn_t, ghn_t, out=dr_t)
            dgh_t[..., : 2 * H].mul_(dsig_t)  # through the sigmoids
            torch.mul(dn_t, r_t, out=dghn_t)
            torch.baddbmm(dh * z_t, dgh_t, w, out=dh)  # dh_{t-1}
        dgx = torch.cat((dgh[..., : 2 * H], dgx_n), 2).view(N, 3 * H)
        lane_of = torch.cat([torch.arange(n, device=out.device) for n in lanes]
                            or [torch.zeros(0, dtype=torch.long, device=out.device)])
        grad_wh = grad_bh = None
        if ctx.needs_input_grad[1]:
            grad_wh = wh.new_zeros(wh.shape).index_add_(0, lane_of, h_prev.transpose(1, 2) * dgh)
        if ctx.needs_input_grad[2]:
            grad_bh = wh.new_zeros(wh.shape[0], 1, 3 * H).index_add_(0, lane_of, dgh)
        return dgx, grad_wh, grad_bh, None
