"""Row operations with the backward they need on the CPU: gather / scatter of distinct rows (a row
copy back, not autograd's generic scatter-add) and row-wise linear interpolation (two
``index_add_``, or one for both ends)."""
from __future__ import annotations

import torch

from . import consts


def arange_rows(n: int, B: int, device: torch.device) -> torch.Tensor:
    """``arange(n * B).view(n, B)`` on ``device``: made once per shape and device (outside tracing),
    a per-call constant (never written to)."""
    return consts.arange(n * B, device).view(n, B)


class _RowGather(torch.autograd.Function):
    """``t.index_select(0, idx)`` for *distinct* ``idx``; backward is a row copy (``index_copy``)
    instead of autograd's generic scatter-add, which is slow on CPU."""

    @staticmethod
    def forward(ctx, t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(idx)
        ctx.rows = t.shape[0]
        return t.index_select(0, idx)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        (idx,) = ctx.saved_tensors
        return g.new_zeros(ctx.rows, *g.shape[1:]).index_copy_(0, idx, g), None


def _scatter(t: torch.Tensor, idx: torch.Tensor, rows: int) -> torch.Tensor:
    """The values of :func:`scatter_rows` (no autograd of its own)."""
    return t.new_zeros(rows, *t.shape[1:]).index_copy_(0, idx, t)


class _RowScatter(torch.autograd.Function):
    """``zeros(rows, ...).index_copy_(0, idx, t)`` for distinct ``idx``; backward ``index_select``."""

    @staticmethod
    def forward(ctx, t: torch.Tensor, idx: torch.Tensor, rows: int) -> torch.Tensor:
        ctx.save_for_backward(idx)
        return _scatter(t, idx, rows)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        (idx,) = ctx.saved_tensors
        return g.index_select(0, idx), None, None


def _lerp(h: torch.Tensor, prev: torch.Tensor, nxt: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The values of :func:`lerp_rows` (no autograd of its own)."""
    shape = (*w.shape[:-1], -1)                           # w [..., 1] may be a strided view
    out = torch.lerp(h.index_select(0, prev).view(shape), h.index_select(0, nxt).view(shape), w)
    return out.reshape(prev.shape[0], *h.shape[1:])


def _lerp_pairs(h: torch.Tensor, pairs: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The values of :func:`lerp_row_pairs` (no autograd of its own)."""
    R = pairs.shape[0] // 2
    shape = (*w.shape[:-1], -1)                           # w [..., 1] may be a strided view
    ends = h.index_select(0, pairs)
    return torch.lerp(ends[:R].view(shape), ends[R:].view(shape), w).reshape(R, *h.shape[1:])


class _LerpRows(torch.autograd.Function):
    """``torch.lerp(h[prev], h[next], w)`` row-wise, with a backward made of two ``index_add_``
    (autograd's own ``index_select`` backward is a slow scatter-add on CPU)."""

    @staticmethod
    def forward(ctx, h: torch.Tensor, prev: torch.Tensor, nxt: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(prev, nxt, w)
        ctx.rows = h.shape[0]
        return _lerp(h, prev, nxt, w)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        prev, nxt, w = ctx.saved_tensors
        grad = g.new_zeros(ctx.rows, *g.shape[1:])
        gw = g.view(*w.shape[:-1], -1)
        grad.index_add_(0, prev, (gw * (1 - w)).reshape(g.shape)).index_add_(0, nxt, (gw * w).reshape(g.shape))
        return grad, None, None, None


class _LerpRowPairs(torch.autograd.Function):
    """:class:`_LerpRows` with the rows of both ends in one index ``[2R]`` (``prev`` then ``next``):
    one row gather forward, one ``index_add_`` backward."""

    @staticmethod
    def forward(ctx, h: torch.Tensor, pairs: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(pairs, w)
        ctx.rows = h.shape[0]
        return _lerp_pairs(h, pairs, w)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        pairs, w = ctx.saved_tensors
        gw = g.view(*w.shape[:-1], -1)
        both = g.new_empty(2, *gw.shape)
        torch.mul(gw, 1 - w, out=both[0])
        torch.mul(gw, w, out=both[1])
        grad = g.new_zeros(ctx.rows, *g.shape[1:])
        return grad.index_add_(0, pairs, both.view(-1, *g.shape[1:])), None, None


def _differentiable(*tensors: torch.Tensor) -> bool:
    """Whether a call needs its autograd function (else its forward runs as plain ops: no
    ``Function.apply`` in a sampling call, host time)."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def lerp_row_pairs(h: torch.Tensor, pairs: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Row ``r`` of the result is ``lerp(h[pairs[r]], h[pairs[R + r]], w[r])`` (``pairs [2R]``:
    the previous rows, then the next ones); one gather forward, one ``index_add_`` backward."""
    return _LerpRowPairs.apply(h, pairs, w) if _differentiable(h, w) else _lerp_pairs(h, pairs, w)


def lerp_rows(h: torch.Tensor, prev: torch.Tensor, nxt: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Row ``r`` of the result is ``lerp(h[prev[r]], h[nxt[r]], w[r])``; ``w [R, 1]`` (or any
    ``[..., 1]`` whose leading dims flatten to the ``R`` rows, e.g. a transposed ``[N, B, 1]``)."""
    return _LerpRows.apply(h, prev, nxt, w) if _differentiable(h, w) else _lerp(h, prev, nxt, w)


def gather_rows(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows ``idx`` (distinct) of ``t``; fast backward."""
    return _RowGather.apply(t, idx) if _differentiable(t) else t.index_select(0, idx)


def scatter_rows(t: torch.Tensor, idx: torch.Tensor, rows: int) -> torch.Tensor:
    """``[rows, ...]`` zeros with row ``idx[i]`` = ``t[i]`` (``idx`` distinct); fast backward."""
    return _RowScatter.apply(t, idx, rows) if _differentiable(t) else _scatter(t, idx, rows)


