"""The Triton kernels of ``smdm::fsq_code`` and its backward (the ``cuda`` kernels; see
:mod:`.fsq_code`). Elementwise over ``z``'s rows of ``C`` channels (rows may be strided: the key
pre-codes are a column block of the in-projection's output); float32 maths, tanh from ``exp`` and
round half to even: the composite's values, but for a pre-code within the last bits of tanh of a
level boundary. The kernels use only core ``tl`` ops, so Triton's interpreter runs them on the CPU
(the tests). Importing this module needs ``triton``."""
from __future__ import annotations

from typing import Tuple

import torch
import triton
import triton.language as tl

BLOCK = 1024


@triton.jit
def _tanh(z):
    """``tanh(z)`` from ``exp(-2|z|)`` (stable; the composite's ``torch.tanh`` to the last bits)."""
    e = tl.exp(-2.0 * tl.abs(z))
    t = (1.0 - e) / (1.0 + e)
    return tl.where(z < 0, -t, t)


@triton.jit
def _round_half_even(x):
    """``torch.round``: to the nearest integer, ties to even."""
    r = tl.floor(x + 0.5)
    return tl.where((r - x == 0.5) & (r - 2.0 * tl.floor(r * 0.5) != 0.0), r - 1.0, r)


@triton.jit
def _code_kernel(Z, NEG, HALF, OUT, n, C, zs, BLOCK: tl.constexpr):
    offs = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    m = offs < n
    row, col = offs // C, offs % C
    z = tl.load(Z + row * zs + col, mask=m, other=0.0).to(tl.float32)
    neg = tl.load(NEG + col, mask=m, other=0.0)
    half = tl.load(HALF + col, mask=m, other=0.0)
    r = _round_half_even(_tanh(z) * half + neg)
    tl.store(OUT + offs, r.to(OUT.dtype.element_ty), mask=m)


@triton.jit
def _grad_kernel(G, Z, HALF, OUT, n, C, gs, zs, BLOCK: tl.constexpr):
    offs = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    m = offs < n
    row, col = offs // C, offs % C
    g = tl.load(G + row * gs + col, mask=m, other=0.0).to(tl.float32)
    z = tl.load(Z + row * zs + col, mask=m, other=0.0).to(tl.float32)
    half = tl.load(HALF + col, mask=m, other=0.0)
    t = _tanh(z)
    tl.store(OUT + offs, (g * half * (1.0 - t * t)).to(OUT.dtype.element_ty), mask=m)


def _rows(t: torch.Tensor) -> Tuple[torch.Tensor, int]:
    """``t [..., C]`` as rows of ``C`` unit-stride channels with one row stride (a copy if it cannot be)."""
    C = t.shape[-1]
    if t.stride(-1) != 1:
        t = t.contiguous()
    try:
        r = t.view(-1, C) if t.dim() != 2 else t
    except RuntimeError:
        t = t.contiguous()
        r = t.view(-1, C)
    if r.shape[0] > 1 and r.stride(0) < C:
        r = r.contiguous()
    return r, (r.stride(0) if r.shape[0] > 1 else C)


def fsq_code_triton(z: torch.Tensor, neg_offset: torch.Tensor, half_l: torch.Tensor) -> torch.Tensor:
    zr, zs = _rows(z)
    out = torch.empty(z.shape, dtype=z.dtype, device=z.device)
    n = out.numel()
    if n:
        _code_kernel[(triton.cdiv(n, BLOCK),)](zr, neg_offset.contiguous(), half_l.contiguous(), out, n,
                                               z.shape[-1], zs, BLOCK=BLOCK)
    return out


def fsq_code_backward_triton(grad: torch.Tensor, z: torch.Tensor, half_l: torch.Tensor) -> torch.Tensor:
    gr, gs = _rows(grad)
    zr, zs = _rows(z)
    out = torch.empty(z.shape, dtype=grad.dtype, device=z.device)
    n = out.numel()
    if n:
        _grad_kernel[(triton.cdiv(n, BLOCK),)](gr, zr, half_l.contiguous(), out, n, z.shape[-1], gs, zs,
                                               BLOCK=BLOCK)
    return out
