"""The tensors of a :class:`~smdm_plugin.core.plan.KeyframePlan` as one fused op (a training call
builds its plan from a fresh keyframe mask: ~20 small kernels as torch ops, one Triton kernel on CUDA).

For ``mask [B, N]`` bool and ``K`` slots: ``index [B, K]`` long (keyframes first, then the other
frames, each in frame order), ``valid [B, K]`` bool, ``count [B]`` long, ``slots [B, 2N]`` long
(``prev_slot | next_slot``), ``weight [B, N]`` float32 (the interpolation weight), ``rows [K, B]``
long (``b + B · index[b, k]``) and ``key_bias [B, 1 + K]`` float32 (0, then 0 / -inf per slot: the
additive key padding mask of one lead token and the slots). On CUDA a Triton kernel
(:mod:`.plan_triton`, one program per sample) when ``triton`` imports (else, or if it cannot be built
on this GPU, with one warning, the composite); elsewhere the composite (:func:`keyframe_plan_composite`),
whose values every kernel gives. Under ``torch.compile`` the composite is traced instead.
"""
from __future__ import annotations

import torch

from .. import consts
from .dispatch import FusedOp, TritonKernel
from .plan_tensors import Plan

Tensor = torch.Tensor

__all__ = ["keyframe_plan", "keyframe_plan_composite"]


def keyframe_plan_composite(mask: Tensor, capacity: int) -> Plan:
    """``(index, valid, count, slots, weight, rows, key_bias)`` of bool ``mask [B, N]`` with
    ``capacity`` slots (see the module docstring), in torch ops. A sample with more keyframes than
    ``capacity`` has no valid plan (callers check ``count``)."""
    B, N = mask.shape
    K = int(capacity)
    idx = consts.arange(N, mask.device)
    seen = torch.cumsum(mask, 1)                                   # keyframes at or before n
    count = seen[:, -1]
    # keyframes first (frame order), then the other frames (frame order): one stable sort
    index = torch.sort(mask, dim=1, descending=True, stable=True).indices[:, :K]
    valid = idx[:K] < count[:, None]
    before = seen - 1
    slots = torch.cat([before.clamp_min(0),
                       torch.minimum(torch.where(mask, before, seen), before[:, -1:].clamp_min(0))], 1)
    ends = index.gather(1, slots.clamp_max(K - 1))                 # frames of both ends at once
    prev_f, next_f = ends[:, :N], ends[:, N:]
    # a true division of ints: float32 (exact frame differences, one rounding)
    weight = torch.div(idx[None] - prev_f, (next_f - prev_f).clamp_min(1)).to(torch.float32).clamp(0.0, 1.0)
    rows = torch.add(consts.arange(B, mask.device)[:, None], index, alpha=B).t().contiguous()
    key_bias = torch.zeros(B, 1 + K, device=mask.device).masked_fill_(
        torch.cat([valid.new_ones(B, 1), valid], 1).logical_not(), float("-inf"))
    return index, valid, count, slots, weight, rows, key_bias


#: the op: a Triton kernel on CUDA (one program per sample), the composite elsewhere and under compile
OP = FusedOp("keyframe_plan", keyframe_plan_composite,
             cuda=TritonKernel(".plan_triton", "keyframe_plan_triton", "keyframe plan"))


def keyframe_plan(mask: Tensor, capacity: int) -> Plan:
    """:func:`keyframe_plan_composite` of bool ``mask [B, N]``: one kernel on CUDA in eager mode,
    the composite elsewhere and under ``torch.compile``."""
    return OP(mask, int(capacity))
