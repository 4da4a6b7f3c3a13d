"""The Triton kernel of ``smdm::perturb_mask`` (the ``cuda`` kernel; see :mod:`.perturb`). One
program per sample; a candidate's rank is the number of candidates with a smaller uniform (ties: the
lower frame), counted over ``[BLOCK_N, BLOCK_J]`` comparisons (column blocks), so no sort is needed; the same
float32 arithmetic as the composite. Only core ``tl`` ops: Triton's interpreter runs it on the CPU
(the tests). Importing this module needs ``triton``."""
from __future__ import annotations

from typing import Optional

import torch
import triton
import triton.language as tl


@triton.jit
def perturb_row(MASK, U, PROT, m, L, N, amount, HAS_PROT: tl.constexpr, BLOCK_N: tl.constexpr,
                BLOCK_J: tl.constexpr):
    """One sample's noisy mask ``[BLOCK_N]`` bool from its keyframes ``m`` (``[BLOCK_N]`` bool, also
    readable at ``MASK``: the rank loop reads them by column blocks), its ``N + 1`` uniforms at ``U``,
    ``L`` valid frames, protected frames at ``PROT`` (``HAS_PROT``)."""
    i = tl.arange(0, BLOCK_N)
    inb = i < N
    k = tl.sum(m.to(tl.float32), 0)
    x = k * amount
    mmax = tl.floor(x + 0.5)                                         # torch.round: ties to even
    mmax = tl.where((mmax - x == 0.5) & (mmax - 2.0 * tl.floor(mmax * 0.5) != 0.0), mmax - 1.0, mmax)
    u0 = tl.load(U)
    c = tl.minimum(tl.floor(u0 * (2.0 * mmax + 1.0)) - mmax, mmax)
    valid = i < L
    droppable = m & (i >= 1) & (i + 1 < L)
    if HAS_PROT:
        droppable = droppable & (tl.load(PROT + i, mask=inb, other=0) == 0)
    add = c > 0
    cand = tl.where(add, valid & (m == 0), droppable) & inb
    count = tl.where(add, c, tl.minimum(-c, k - 2.0))
    key = tl.where(cand, tl.load(U + 1 + i, mask=inb, other=2.0), 2.0)
    # rank = candidates with a smaller key (ties: the lower frame), over column blocks of BLOCK_J
    # frames ([BLOCK_N, BLOCK_J] comparisons at a time: registers, no spills)
    rank = tl.zeros([BLOCK_N], dtype=tl.float32)
    for j0 in range(0, N, BLOCK_J):
        j = j0 + tl.arange(0, BLOCK_J)
        inj = j < N
        mj = tl.load(MASK + j, mask=inj, other=0) != 0
        dj = mj & (j >= 1) & (j + 1 < L)
        if HAS_PROT:
            dj = dj & (tl.load(PROT + j, mask=inj, other=0) == 0)
        cj = tl.where(add, (j < L) & (mj == 0), dj) & inj
        kj = tl.where(cj, tl.load(U + 1 + j, mask=inj, other=2.0), 2.0)[None, :]
        ki = key[:, None]
        before = (kj < ki) | ((kj == ki) & (j[None, :] < i[:, None]))
        rank += tl.sum((before & cj[None, :]).to(tl.float32), 1)
    take = cand & (rank < count)
    return m ^ take


@triton.jit
def _perturb_kernel(MASK, LEN, U, PROT, OUT, N, amount,
                    HAS_PROT: tl.constexpr, BLOCK_N: tl.constexpr, BLOCK_J: tl.constexpr):
    b = tl.program_id(0).to(tl.int64)
    i = tl.arange(0, BLOCK_N)
    inb = i < N
    L = tl.load(LEN + b).to(tl.int32)
    m = tl.load(MASK + b * N + i, mask=inb, other=0) != 0
    out = perturb_row(MASK + b * N, U + b * (N + 1), PROT + b * N, m, L, N, amount, HAS_PROT, BLOCK_N, BLOCK_J)
    tl.store(OUT + b * N + i, out, mask=inb)

def perturb_triton(mask: torch.Tensor, lengths: torch.Tensor, u: torch.Tensor, amount: float,
                   protected: Optional[torch.Tensor]) -> torch.Tensor:
    # bool tensors are read and written as they are (no cast kernels: the op is one launch); the
    # inputs are contiguous as the selection makes them (a copy only if a caller's are not)
    B, N = mask.shape
    out = torch.empty((B, N), dtype=torch.bool, device=mask.device)
    if B and N:
        block = triton.next_power_of_2(N)
        m = mask.contiguous()
        p = protected.contiguous() if protected is not None else m
        _perturb_kernel[(B,)](m, lengths.contiguous(), u.float().contiguous(), p, out, N, float(amount),
                              HAS_PROT=protected is not None, BLOCK_N=block, BLOCK_J=max(1, min(block, 4096 // block)))
    return out
