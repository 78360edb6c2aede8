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
