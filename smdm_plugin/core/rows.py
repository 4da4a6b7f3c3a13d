"""Row operations on ``[rows, ...]`` tensors: gather / scatter of distinct rows and row-wise linear
interpolation, written as native ops (autograd's own nodes: no Python in the backward; the Python
autograd functions they replace cost 25-29 µs more host time per call on the CPU meter; GPU
unmeasured: docs/gpu.md, 0.10.4)."""
from __future__ import annotations

import torch

from . import consts


def arange_rows(n: int, B: int, device: torch.device) -> torch.Tensor:
    """``arange(n * B).view(n, B)`` on ``device``: made once per shape and device (outside tracing),
    a per-call constant (never written to)."""
    return consts.arange(n * B, device).view(n, B)


def lerp_row_pairs(h: torch.Tensor, pairs: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Row ``r`` of the result is ``lerp(h[pairs[r]], h[pairs[R + r]], w[r])`` (``pairs [2R]``:
    the previous rows, then the next ones; ``w [..., 1]`` whose leading dims flatten to the ``R``
    rows, e.g. a transposed ``[N, B, 1]``): one row gather each way."""
    R = pairs.shape[0] // 2
    shape = (2, *w.shape[:-1], -1)                        # w [..., 1] may be a strided view
    prev, nxt = h.index_select(0, pairs).view(shape).unbind(0)
    return torch.lerp(prev, nxt, w).reshape(R, *h.shape[1:])


def lerp_rows(h: torch.Tensor, prev: torch.Tensor, nxt: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Row ``r`` of the result is ``lerp(h[prev[r]], h[nxt[r]], w[r])``; ``w [R, 1]`` (or any
    ``[..., 1]`` whose leading dims flatten to the ``R`` rows, e.g. a transposed ``[N, B, 1]``)."""
    shape = (*w.shape[:-1], -1)
    out = torch.lerp(h.index_select(0, prev).view(shape), h.index_select(0, nxt).view(shape), w)
    return out.reshape(prev.shape[0], *h.shape[1:])


def gather_rows(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows ``idx`` of ``t`` (``t.index_select(0, idx)``)."""
    return t.index_select(0, idx)


def scatter_rows(t: torch.Tensor, idx: torch.Tensor, rows: int) -> torch.Tensor:
    """``[rows, ...]`` zeros with row ``idx[i]`` = ``t[i]`` (``idx`` distinct)."""
    return t.new_zeros(rows, *t.shape[1:]).index_copy(0, idx, t)
