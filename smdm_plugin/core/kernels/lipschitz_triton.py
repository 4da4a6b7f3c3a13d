"""The Triton kernels of ``smdm::lipschitz_weight`` and its backward (the ``cuda`` kernels; see
:mod:`.lipschitz_op`): one program per output row, which reads its row in blocks (any width), float32
maths. Values: the composite's up to the order of the row sums. The kernels use only core ``tl`` ops,
so Triton's interpreter runs them on the CPU (the tests). Importing this module needs ``triton``."""
from __future__ import annotations

from typing import Tuple

import torch
import triton
import triton.language as tl


@triton.jit
def _softplus(c):
    """``F.softplus(c)`` (threshold 20): ``max(c, 0) + log1p(exp(-|c|))``, log1p as ``log(u)·x/(u-1)``."""
    x = tl.exp(-tl.abs(c))
    u = 1.0 + x
    lp = tl.where(u == 1.0, x, tl.log(u) * x / (u - 1.0))
    return tl.where(c > 20.0, c, tl.maximum(c, 0.0) + lp)


@triton.jit
def _weight_kernel(W, C, OUT, ncols, ws, BLOCK: tl.constexpr):
    row = tl.program_id(0).to(tl.int64)
    acc = tl.zeros([BLOCK], dtype=tl.float32)
    for start in range(0, ncols, BLOCK):
        cols = start + tl.arange(0, BLOCK)
        acc += tl.abs(tl.load(W + row * ws + cols, mask=cols < ncols, other=0.0).to(tl.float32))
    rowsum = tl.sum(acc, axis=0)
    scale = tl.minimum(_softplus(tl.load(C).to(tl.float32)) / rowsum, 1.0)
    for start in range(0, ncols, BLOCK):
        cols = start + tl.arange(0, BLOCK)
        m = cols < ncols
        w = tl.load(W + row * ws + cols, mask=m, other=0.0).to(tl.float32)
        tl.store(OUT + row * ncols + cols, (w * scale).to(OUT.dtype.element_ty), mask=m)


@triton.jit
def _grad_kernel(G, W, C, DW, ROWS, ncols, gs, ws, eps, BLOCK: tl.constexpr):
    row = tl.program_id(0).to(tl.int64)
    acc = tl.zeros([BLOCK], dtype=tl.float32)
    dot = tl.zeros([BLOCK], dtype=tl.float32)
    for start in range(0, ncols, BLOCK):
        cols = start + tl.arange(0, BLOCK)
        m = cols < ncols
        w = tl.load(W + row * ws + cols, mask=m, other=0.0).to(tl.float32)
        g = tl.load(G + row * gs + cols, mask=m, other=0.0).to(tl.float32)
        acc += tl.abs(w)
        dot += g * w
    rowsum = tl.sum(acc, axis=0)
    gw = tl.sum(dot, axis=0)
    c = tl.load(C).to(tl.float32)
    ratio = _softplus(c) / rowsum
    scale = tl.minimum(ratio, 1.0)
    g_bound = tl.where(ratio <= 1.0, gw / rowsum, 0.0)
    r = tl.where(rowsum >= eps, g_bound * ratio, 0.0)
    for start in range(0, ncols, BLOCK):
        cols = start + tl.arange(0, BLOCK)
        m = cols < ncols
        w = tl.load(W + row * ws + cols, mask=m, other=0.0).to(tl.float32)
        g = tl.load(G + row * gs + cols, mask=m, other=0.0).to(tl.float32)
        sign = tl.where(w > 0.0, 1.0, tl.where(w < 0.0, -1.0, 0.0))
        tl.store(DW + row * ncols + cols, (g * scale - sign * r).to(DW.dtype.element_ty), mask=m)
    dsoft = tl.where(c > 20.0, 1.0, 1.0 / (1.0 + tl.exp(-c)))                # softplus'(c)
    tl.store(ROWS + row, (g_bound * dsoft).to(ROWS.dtype.element_ty))


def _block(ncols: int) -> int:
    return min(1024, triton.next_power_of_2(max(ncols, 16)))


def _rows(t: torch.Tensor) -> torch.Tensor:
    """``t [out, in]`` with unit column stride (a copy if not)."""
    return t if t.stride(1) == 1 else t.contiguous()


def lipschitz_weight_triton(weight: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    w = _rows(weight)
    R, ncols = w.shape
    out = torch.empty((R, ncols), dtype=weight.dtype, device=weight.device)
    if out.numel():
        _weight_kernel[(R,)](w, c, out, ncols, w.stride(0), BLOCK=_block(ncols))
    return out


def lipschitz_weight_backward_triton(grad: torch.Tensor, weight: torch.Tensor, c: torch.Tensor
                                     ) -> Tuple[torch.Tensor, torch.Tensor]:
    w, g = _rows(weight), _rows(grad)
    R, ncols = w.shape
    dw = torch.empty((R, ncols), dtype=weight.dtype, device=weight.device)
    rows = torch.empty(R, dtype=c.dtype, device=weight.device)
    if dw.numel():
        _grad_kernel[(R,)](g, w, c, dw, rows, ncols, g.stride(0), w.stride(0), torch.finfo(weight.dtype).eps,
                           BLOCK=_block(ncols))
    return dw, rows
