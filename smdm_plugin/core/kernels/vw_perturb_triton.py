"""The Triton kernel of ``smdm::vw_perturb_mask`` and of the eager training plan (the ``cuda`` kernel;
see :mod:`.vw_perturb`): one program per sample runs VW (:func:`.vw_triton.vw_row`), writes its
keyframes, then their mask noise (:func:`.perturb_triton.perturb_row`, which reads them back by
column blocks) over them, and with ``PLAN`` the keyframe plan of ``[P always-kept frames | mask]``
(:func:`.plan_triton.plan_row`): one launch where a training step took three. Core ``tl`` ops only:
Triton's interpreter runs it on the CPU (the tests). Importing this module needs ``triton``."""
from __future__ import annotations

from typing import Optional, Tuple, Union

import torch
import triton
import triton.language as tl

from .perturb_triton import perturb_row
from .plan_tensors import Plan
from .plan_triton import plan_outputs, plan_row
from .vw_triton import launch_config, vw_row


@triton.jit
def _vw_perturb_kernel(X, KEYBUF, LEN, KEEP, FORCED, U, OUT, PMASK, INDEX, VALID, COUNT, SLOTS, WEIGHT, ROWS, BIAS,
                       B, N, F, sxb, sxn, sxf, amount, P, K,
                       HAS_FORCED: tl.constexpr, BLOCK_N: tl.constexpr, BLOCK_F: tl.constexpr,
                       KEY_ROWS: tl.constexpr, BLOCK_J: tl.constexpr, PLAN: tl.constexpr, BLOCK_P: tl.constexpr):
    b = tl.program_id(0).to(tl.int64)
    i = tl.arange(0, BLOCK_N)
    inb = i < N
    keep = vw_row(X, KEYBUF, LEN, KEEP, FORCED, FORCED, b, N, F, sxb, sxn, sxf, HAS_FORCED, False,
                  BLOCK_N, BLOCK_F, KEY_ROWS)
    row = OUT + b * N
    tl.store(row + i, keep, mask=inb)
    tl.debug_barrier()                            # the keyframes, as the rank loop reads them back
    L = tl.load(LEN + b).to(tl.int32)
    out = perturb_row(row, U + b * (N + 1), FORCED + b * N, keep != 0, L, N, amount, HAS_FORCED, BLOCK_N, BLOCK_J)
    tl.debug_barrier()                            # every read of the keyframes done before they are replaced
    tl.store(row + i, out.to(tl.int8), mask=inb)
    if PLAN:
        tl.debug_barrier()                        # the noisy mask, read back after the prefix
        n = tl.arange(0, BLOCK_P)
        src = n - P
        m = tl.where(n < P, 1, tl.load(row + src, mask=(n >= P) & (src < N), other=0).to(tl.int32))
        tl.store(PMASK + b * (N + P) + n, m.to(tl.int8), mask=n < N + P)
        plan_row(m, b, B, N + P, K, INDEX, VALID, COUNT, SLOTS, WEIGHT, ROWS, BIAS, BLOCK_P)


def rank_block(block_n: int, warps: int) -> int:
    """``BLOCK_J``: the rank loop's ``[BLOCK_N, BLOCK_J]`` comparisons at 32 per thread of VW's warps
    (VW's launch config keeps one warp up to 256 frames)."""
    return max(1, min(block_n, 32 * 32 * warps // block_n))


def vw_perturb_triton(features: torch.Tensor, lengths: torch.Tensor, counts: torch.Tensor,
                      forced: Optional[torch.Tensor], u: torch.Tensor, amount: float,
                      slots: Optional[int] = None, prefix: int = 0
                      ) -> Union[torch.Tensor, Tuple[torch.Tensor, torch.Tensor, Plan]]:
    """The noisy training mask ``[B, N]`` bool; with ``slots``, ``(mask, plan mask [B, prefix + N],
    plan tensors)``: the plan of ``prefix`` kept frames then the mask with ``slots`` slots. Arguments
    as :func:`.vw_perturb.vw_perturb_mask` / :func:`.vw_perturb.vw_perturb_plan`."""
    B, N, F = features.shape
    x = features if features.dtype in (torch.float32, torch.float64) else features.float()
    dev = x.device
    out = torch.zeros(B, N, dtype=torch.int8, device=dev)
    plan = slots is not None
    P = int(prefix)
    pmask = torch.empty(B, N + P, dtype=torch.int8, device=dev) if plan and P else out
    outputs = plan_outputs(B, N + P, int(slots), dev) if plan else (out,) * 7
    if B and N:
        block_n, block_f, rows, warps = launch_config(N, F)
        keybuf = torch.empty(B, block_n, dtype=torch.float64, device=dev)
        f8 = forced.to(torch.bool).contiguous().view(torch.uint8) if forced is not None else out
        _vw_perturb_kernel[(B,)](x, keybuf, lengths.to(torch.int64).contiguous(), counts.to(torch.int64).contiguous(),
                                 f8, u.float().contiguous(), out, pmask, *outputs, B, N, F, x.stride(0), x.stride(1),
                                 x.stride(2), float(amount), P, int(slots or 0),
                                 HAS_FORCED=forced is not None, BLOCK_N=block_n, BLOCK_F=block_f, KEY_ROWS=rows,
                                 BLOCK_J=rank_block(block_n, warps), PLAN=plan,
                                 BLOCK_P=triton.next_power_of_2(N + P) if plan else 1,
                                 num_warps=warps, enable_fp_fusion=False)
    mask = out.view(torch.bool)
    return (mask, pmask.view(torch.bool), outputs) if plan else mask
