"""The Triton kernel of ``smdm::keyframe_plan`` (the ``cuda`` kernel; see :mod:`.plan_op`): one
program per sample holds its ``N`` frames (``N <= 2^16``): a cumulative sum gives each frame's slot
(keyframes first, then the others), a max-scan / reverse min-scan the keyframes around each frame.
Core ``tl`` ops only, so Triton's interpreter runs it on the CPU (the tests). Needs ``triton``."""
from __future__ import annotations

import torch
import triton
import triton.language as tl

from .plan_tensors import Plan


@triton.jit
def _max(a, b):
    return tl.maximum(a, b)


@triton.jit
def _min(a, b):
    return tl.minimum(a, b)


@triton.jit
def plan_row(m, b, B, N, K, INDEX, VALID, COUNT, SLOTS, WEIGHT, ROWS, BIAS, BLOCK: tl.constexpr):
    """Sample ``b``'s plan tensors from its keyframes ``m`` (``[BLOCK]`` int32, 1 = keyframe; 0 past
    ``N``), written to the outputs."""
    n = tl.arange(0, BLOCK)
    inb = n < N
    key = m > 0
    seen = tl.cumsum(m, 0)                                          # keyframes at or before n
    count = tl.sum(m, 0)
    before = seen - 1
    pos = tl.where(key, before, count + n - seen)                   # the slot order (a permutation)
    put = inb & (pos < K)
    tl.store(INDEX + b * K + pos, n.to(tl.int64), mask=put)
    tl.store(ROWS + pos.to(tl.int64) * B + b, b + B * n.to(tl.int64), mask=put)
    tl.store(VALID + b * K + n, n < count, mask=n < K)
    tl.store(BIAS + b * (K + 1) + n + 1, tl.where(n < count, 0.0, float("-inf")), mask=n < K)
    tl.store(BIAS + b * (K + 1), 0.0)
    tl.store(COUNT + b, count.to(tl.int64))
    prev_slot = tl.maximum(before, 0)
    next_slot = tl.minimum(tl.where(key, before, seen), tl.maximum(count - 1, 0))
    tl.store(SLOTS + b * 2 * N + n, prev_slot.to(tl.int64), mask=inb)
    tl.store(SLOTS + b * 2 * N + N + n, next_slot.to(tl.int64), mask=inb)
    # the frames of both ends: the last keyframe at or before n (else the first), the next at or
    # after n (else the last); no keyframe at all: frame 0 (the composite's index[0])
    big = 1 << 30
    first = tl.where(count > 0, tl.min(tl.where(key, n, big), 0), 0)
    last = tl.where(count > 0, tl.max(tl.where(key, n, -1), 0), 0)
    prev_f = tl.associative_scan(tl.where(key, n, -1), 0, _max)
    prev_f = tl.where(prev_f < 0, first, prev_f)
    next_f = tl.associative_scan(tl.where(key, n, big), 0, _min, reverse=True)
    next_f = tl.where(next_f >= big, last, next_f)
    w = tl.math.div_rn((n - prev_f).to(tl.float32), tl.maximum(next_f - prev_f, 1).to(tl.float32))
    tl.store(WEIGHT + b * N + n, tl.minimum(tl.maximum(w, 0.0), 1.0), mask=inb)


@triton.jit
def _plan_kernel(MASK, INDEX, VALID, COUNT, SLOTS, WEIGHT, ROWS, BIAS, B, N, K, ms, BLOCK: tl.constexpr):
    b = tl.program_id(0).to(tl.int64)
    n = tl.arange(0, BLOCK)
    m = tl.load(MASK + b * ms + n, mask=n < N, other=0).to(tl.int32)
    plan_row(m, b, B, N, K, INDEX, VALID, COUNT, SLOTS, WEIGHT, ROWS, BIAS, BLOCK)

def plan_outputs(B: int, N: int, K: int, device: torch.device) -> Plan:
    """The plan tensors of ``B`` samples of ``N`` frames with ``K`` slots, uninitialised (a kernel
    writes every element)."""
    if N > 1 << 16:
        raise ValueError(f"keyframe_plan_triton: at most 65536 frames, got {N}")
    return (torch.empty(B, K, dtype=torch.long, device=device), torch.empty(B, K, dtype=torch.bool, device=device),
            torch.empty(B, dtype=torch.long, device=device), torch.empty(B, 2 * N, dtype=torch.long, device=device),
            torch.empty(B, N, dtype=torch.float32, device=device), torch.empty(K, B, dtype=torch.long, device=device),
            torch.empty(B, 1 + K, dtype=torch.float32, device=device))


def keyframe_plan_triton(mask: torch.Tensor, capacity: int) -> Plan:
    B, N = mask.shape
    K = int(capacity)
    out = plan_outputs(B, N, K, mask.device)
    m = mask if mask.stride(1) == 1 else mask.contiguous()
    if B and N:
        _plan_kernel[(B,)](m, *out, B, N, K, m.stride(0), BLOCK=triton.next_power_of_2(N))
    return out
