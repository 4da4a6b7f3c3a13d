"""Visvalingam–Whyatt as one Triton kernel (the ``cuda`` kernel of ``smdm::vw_keyframes``).

One program per motion. Keys (float64) and the prev/next links of the live points stay in
registers as ``[BLOCK_N]`` vectors; each removal is an ``argmin`` (ties: lowest frame), a few masked
reductions to read the neighbours, and two new keys from four feature rows loaded from global
memory (L1/L2-resident: one motion's features are ~50 KB). The initial keys are computed ``ROWS``
frames at a time through a small float64 scratch row. No host synchronisation; inactive samples
(``active[b] == 0``) leave the loop at once with an all-False row. FP contraction is off, so every
key is the plain float64 ``|a|²|b|² - (a·b)²`` the reference computes (up to summation order).

Importing this module needs ``triton``; :mod:`smdm_plugin.core.kernels.vw` imports it lazily.
"""
from __future__ import annotations

from typing import Optional

import torch
import triton
import triton.language as tl


@triton.jit
def vw_row(X, KEYBUF, LEN, KEEP, FORCED, ACTIVE, b, N, F, sxb, sxn, sxf,
           HAS_FORCED: tl.constexpr, HAS_ACTIVE: tl.constexpr,
           BLOCK_N: tl.constexpr, BLOCK_F: tl.constexpr, ROWS: tl.constexpr):
    """Sample ``b``'s keyframes: ``[BLOCK_N]`` int8, 1 = kept (0 past ``N``, and everywhere for an
    inactive sample)."""
    L = tl.load(LEN + b).to(tl.int32)
    K = tl.load(KEEP + b).to(tl.int32)
    i = tl.arange(0, BLOCK_N)
    f = tl.arange(0, BLOCK_F)
    fm = f < F
    xrow = X + b * sxb
    prot = (i == 0) | (i >= L - 1)
    if HAS_FORCED:
        prot = prot | (tl.load(FORCED + b * N + i, mask=i < N, other=0) != 0)
    nprot = tl.sum((prot & (i < L)).to(tl.int32), 0)
    nrem = tl.maximum(L - tl.maximum(K, nprot), 0)
    act = 1
    if HAS_ACTIVE:
        act = (tl.load(ACTIVE + b) != 0).to(tl.int32)   # an inactive sample does no work at all
    nrem = nrem * act
    INF: tl.constexpr = float("inf")
    # initial keys, ROWS frames at a time (a = x_{j-1} - x_j, c = x_{j+1} - x_j)
    kb = KEYBUF + b * BLOCK_N
    r = tl.arange(0, ROWS)
    for c0 in range(0, BLOCK_N * act, ROWS):
        j = c0 + r
        ok = (j >= 1) & (j < L - 1)
        m2 = ok[:, None] & fm[None, :]
        xm = tl.load(xrow + (j - 1)[:, None] * sxn + f[None, :] * sxf, mask=m2, other=0.0).to(tl.float64)
        x0 = tl.load(xrow + j[:, None] * sxn + f[None, :] * sxf, mask=m2, other=0.0).to(tl.float64)
        xp = tl.load(xrow + (j + 1)[:, None] * sxn + f[None, :] * sxf, mask=m2, other=0.0).to(tl.float64)
        a = xm - x0
        c = xp - x0
        aa = tl.sum(a * a, 1)
        cc = tl.sum(c * c, 1)
        ac = tl.sum(a * c, 1)
        tl.store(kb + j, tl.maximum(aa * cc - ac * ac, 0.0), mask=j < BLOCK_N)
    tl.debug_barrier()
    key = tl.load(kb + i)
    key = tl.where(prot | (i >= L), INF, key)
    prev = i - 1
    nxt = i + 1
    for _ in range(0, nrem):
        rr = tl.argmin(key, 0, tie_break_left=True)
        sel = i == rr
        p = tl.sum(tl.where(sel, prev, 0), 0)
        n = tl.sum(tl.where(sel, nxt, 0), 0)
        pp = tl.maximum(tl.sum(tl.where(i == p, prev, 0), 0), 0)
        nn = tl.minimum(tl.sum(tl.where(i == n, nxt, 0), 0), N - 1)
        nxt = tl.where(i == p, n, nxt)
        prev = tl.where(i == n, p, prev)
        key = tl.where(sel, INF, key)
        xpp = tl.load(xrow + pp * sxn + f * sxf, mask=fm, other=0.0).to(tl.float64)
        xp = tl.load(xrow + p * sxn + f * sxf, mask=fm, other=0.0).to(tl.float64)
        xn = tl.load(xrow + n * sxn + f * sxf, mask=fm, other=0.0).to(tl.float64)
        xnn = tl.load(xrow + nn * sxn + f * sxf, mask=fm, other=0.0).to(tl.float64)
        a = xpp - xp
        c = xn - xp
        e = xnn - xn
        aa = tl.sum(a * a, 0)
        cc = tl.sum(c * c, 0)
        ee = tl.sum(e * e, 0)
        ac = tl.sum(a * c, 0)
        ce = tl.sum(c * e, 0)
        key = tl.where((i == p) & ~prot, tl.maximum(aa * cc - ac * ac, 0.0), key)
        key = tl.where((i == n) & ~prot, tl.maximum(cc * ee - ce * ce, 0.0), key)
    keep = ((key < INF) | prot) & (i < L)
    return tl.where(keep, act, 0).to(tl.int8)


@triton.jit
def _vw_kernel(X, KEYBUF, LEN, KEEP, FORCED, ACTIVE, OUT,
               N, F, sxb, sxn, sxf,
               HAS_FORCED: tl.constexpr, HAS_ACTIVE: tl.constexpr,
               BLOCK_N: tl.constexpr, BLOCK_F: tl.constexpr, ROWS: tl.constexpr):
    b = tl.program_id(0).to(tl.int64)
    i = tl.arange(0, BLOCK_N)
    keep = vw_row(X, KEYBUF, LEN, KEEP, FORCED, ACTIVE, b, N, F, sxb, sxn, sxf, HAS_FORCED, HAS_ACTIVE,
                  BLOCK_N, BLOCK_F, ROWS)
    tl.store(OUT + b * N + i, keep, mask=i < N)


def launch_config(N: int, F: int):
    """``(BLOCK_N, BLOCK_F, ROWS, num_warps)`` for ``N`` frames of ``F`` features: one warp up to
    256 frames x 128 features (the HumanML3D case, [196, 64]: 93 registers, no spills on sm_90),
    more warps for longer motions or wider features."""
    block_n = triton.next_power_of_2(max(N, 2))
    block_f = triton.next_power_of_2(max(F, 1))
    warps = max(1, min(8, max(block_n // 256, block_f // 128)))
    rows = max(1, min(8, block_n, 2048 // block_f))
    return block_n, block_f, rows, warps


def vw_triton(features: torch.Tensor, lengths: torch.Tensor, counts: torch.Tensor,
              forced: Optional[torch.Tensor] = None, active: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Keyframe mask ``[B, N]`` bool; arguments as :func:`smdm_plugin.core.kernels.vw.vw_keyframes`."""
    B, N, F = features.shape
    x = features if features.dtype in (torch.float32, torch.float64) else features.float()
    out = torch.zeros(B, N, dtype=torch.int8, device=x.device)
    if B == 0 or N == 0:
        return out.bool()
    block_n, block_f, rows, warps = launch_config(N, F)
    keybuf = torch.empty(B, block_n, dtype=torch.float64, device=x.device)
    f8 = forced.to(torch.bool).contiguous().view(torch.uint8) if forced is not None else out
    a8 = active.to(torch.bool).contiguous().view(torch.uint8) if active is not None else out
    _vw_kernel[(B,)](x, keybuf, lengths.to(torch.int64).contiguous(), counts.to(torch.int64).contiguous(),
                     f8, a8, out, N, F, x.stride(0), x.stride(1), x.stride(2),
                     HAS_FORCED=forced is not None, HAS_ACTIVE=active is not None,
                     BLOCK_N=block_n, BLOCK_F=block_f, ROWS=rows, num_warps=warps,
                     enable_fp_fusion=False)
    return out.view(torch.bool)
