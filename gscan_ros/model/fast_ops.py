"""Batched kernels the compositional network's fast paths share.

Custom autograd functions that save a pass or a copy over what plain torch ops would do,
the dropout keep mask, and torch.nn.GRU's cell on weights gathered per module. Each one
has a test against the plain computation it replaces (tests/test_model_fastpaths.py).
"""
from __future__ import annotations

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

    The forward runs without building a graph (6 ops a step: baddbmm, add, sigmoid,
    addcmul, tanh, lerp) and keeps the gates; the backward is backpropagation through
    time written out (one bmm and ~12 elementwise ops a step), and the weight gradients
    are one batched product over all steps at the end. Plain autograd over `gru_update`
    records ~25 nodes a step, and at these sizes (H = 20) the time goes into that
    bookkeeping, not the arithmetic.
    """

    @staticmethod
    def forward(ctx, gx, wh, bh, lanes):
        H = wh.shape[1]
        out = gx.new_empty(gx.shape[0], H)
        rz_all = gx.new_empty(gx.shape[0], 2 * H)
        cand_all, ghn_all = torch.empty_like(out), torch.empty_like(out)
        h = gx.new_zeros(lanes[0], 1, H) if lanes else gx.new_zeros(0, 1, H)
        start = 0
        for n in lanes:
            stop = start + n
            gx_t, h = gx[start:stop], h[:n]
            gh = torch.baddbmm(bh[:n], h, wh[:n])[:, 0]
            rz = torch.sigmoid(gx_t[:, : 2 * H] + gh[:, : 2 * H], out=rz_all[start:stop])
            ghn = ghn_all[start:stop]
            ghn.copy_(gh[:, 2 * H :])
            cand = torch.tanh(torch.addcmul(gx_t[:, 2 * H :], rz[:, :H], ghn), out=cand_all[start:stop])
            h = torch.lerp(cand, h[:, 0], rz[:, H:], out=out[start:stop])[:, None]
            start = stop
        ctx.save_for_backward(wh, out, rz_all, cand_all, ghn_all)
        ctx.lanes = lanes
        return out

    @staticmethod
    def backward(ctx, grad_out):
        wh, out, rz_all, cand_all, ghn_all = ctx.saved_tensors
        lanes, H = ctx.lanes, wh.shape[1]
        grad_out = grad_out.contiguous()
        d_gates = grad_out.new_empty(out.shape[0], 3 * H)  # d(pre-activations): r, z, candidate
        dgh_n = torch.empty_like(out)  # d(recurrent candidate gate) = d(candidate pre) * r
        whT = wh.transpose(1, 2)
        dh = grad_out.new_zeros(lanes[0] if lanes else 0, H)
        stop = out.shape[0]
        starts = []
        for t in range(len(lanes) - 1, -1, -1):
            n = lanes[t]
            start = stop - n
            starts.append(start)
            h_prev = out[start - lanes[t - 1] : start - lanes[t - 1] + n] if t else None
            dh_t = dh[:n].add_(grad_out[start:stop])
            rz, cand, ghn = rz_all[start:stop], cand_all[start:stop], ghn_all[start:stop]
            r, z = rz[:, :H], rz[:, H:]
            g = d_gates[start:stop]
            # h = cand + z (h_prev - cand)
            dcand = dh_t - dh_t * z
            torch.mul(dh_t, (h_prev if h_prev is not None else 0) - cand, out=g[:, H : 2 * H])  # dz
            torch.mul(dcand, 1 - cand * cand, out=g[:, 2 * H :])  # d(candidate pre-activation)
            torch.mul(g[:, 2 * H :], ghn, out=g[:, :H])  # dr
            g[:, : 2 * H].mul_(rz * (1 - rz))  # through the sigmoids
            torch.mul(g[:, 2 * H :], r, out=dgh_n[start:stop])
            dgh = torch.cat((g[:, : 2 * H], dgh_n[start:stop]), 1)
            dh_t.mul_(z).add_(torch.bmm(dgh[:, None], whT[:n])[:, 0])
            stop = start
        # The state before each step (0 at the first), lane-aligned with the step, and
        # each packed step's lane, for the weight gradients in one go.
        h_prev_all, lane_of = _previous_states(out, lanes)
        dgh_all = torch.cat((d_gates[:, : 2 * H], dgh_n), 1)
        grad_wh = grad_bh = None
        if ctx.needs_input_grad[1]:
            grad_wh = wh.new_zeros(wh.shape).index_add_(0, lane_of, h_prev_all[:, :, None] * dgh_all[:, None, :])
        if ctx.needs_input_grad[2]:
            grad_bh = wh.new_zeros(wh.shape[0], 1, 3 * H).index_add_(0, lane_of, dgh_all[:, None])
        return d_gates, grad_wh, grad_bh, None


def _previous_states(out: torch.Tensor, lanes: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """For packed time-major states `out` [N, H]: the state each step started from (zeros
    at step 0) and each step's lane index."""
    prev = torch.zeros_like(out)
    start, lane_of = 0, []
    for t, n in enumerate(lanes):
        if t:
            prev[start : start + n] = out[start - lanes[t - 1] : start - lanes[t - 1] + n]
        lane_of.append(torch.arange(n, device=out.device))
        start += n
    return prev, torch.cat(lane_of) if lane_of else torch.zeros(0, dtype=torch.long, device=out.device)
