"""The Triton kernel of ``smdm::perturb_mask`` (the ``cuda`` kernel; see :mod:`.perturb`). One
program per sample; a candidate's rank is the number of candidates with a smaller uniform (ties: the
lower frame), counted over a ``[BLOCK_N, BLOCK_N]`` comparison, so no sort is needed; the same
float32 arithmetic as the composite. Only core ``tl`` ops: Triton's interpreter runs it on the CPU
(the tests). Importing this module needs ``triton``."""
from __future__ import annotations

from typing import Optional

import torch
import triton
import triton.language as tl


@triton.jit
def _perturb_kernel(MASK, LEN, U, PROT, OUT, N, amount,
                    HAS_PROT: tl.constexpr, BLOCK_N: tl.constexpr):
    b = tl.program_id(0).to(tl.int64)
    i = tl.arange(0, BLOCK_N)
    inb = i < N
    L = tl.load(LEN + b).to(tl.int32)
    m = tl.load(MASK + b * N + i, mask=inb, other=0) != 0
    k = tl.sum(m.to(tl.float32), 0)
    x = k * amount
    mmax = tl.floor(x + 0.5)                                         # torch.round: ties to even
    mmax = tl.where((mmax - x == 0.5) & (mmax - 2.0 * tl.floor(mmax * 0.5) != 0.0), mmax - 1.0, mmax)
    u0 = tl.load(U + b * (N + 1))
    c = tl.minimum(tl.floor(u0 * (2.0 * mmax + 1.0)) - mmax, mmax)
    valid = i < L
    droppable = m & (i >= 1) & (i + 1 < L)
    if HAS_PROT:
        droppable = droppable & (tl.load(PROT + b * N + i, mask=inb, other=0) == 0)
    add = c > 0
    cand = tl.where(add, valid & (m == 0), droppable) & inb
    count = tl.where(add, c, tl.minimum(-c, k - 2.0))
    key = tl.where(cand, tl.load(U + b * (N + 1) + 1 + i, mask=inb, other=2.0), 2.0)
    # rank_i = #{j candidate: key_j < key_i or (key_j == key_i and j < i)}
    kj = key[None, :]
    ki = key[:, None]
    before = (kj < ki) | ((kj == ki) & (i[None, :] < i[:, None]))
    rank = tl.sum((before & cand[None, :]).to(tl.float32), 1)
    take = cand & (rank < count)
    tl.store(OUT + b * N + i, (m ^ take).to(tl.int8), mask=inb)


def perturb_triton(mask: torch.Tensor, lengths: torch.Tensor, u: torch.Tensor, amount: float,
                   protected: Optional[torch.Tensor]) -> torch.Tensor:
    B, N = mask.shape
    out = torch.empty((B, N), dtype=torch.int8, device=mask.device)
    if B and N:
        m8 = mask.to(torch.int8).contiguous()
        p8 = protected.to(torch.int8).contiguous() if protected is not None else m8
        _perturb_kernel[(B,)](m8, lengths.contiguous(), u.float().contiguous(), p8, out, N, float(amount),
                              HAS_PROT=protected is not None, BLOCK_N=triton.next_power_of_2(N))
    return out.view(torch.bool)
