"""A training mask as one op: VW keyframes, then their mask noise (``smdm::vw_perturb_mask``), and in
eager mode with the keyframe plan made from them (:func:`vw_perturb_plan`).

``vw_perturb_mask(features, lengths, counts, forced, u, amount)`` is
``perturb_mask_op(vw_keyframes(features, lengths, counts, forced), lengths, u, amount, forced)`` (the
forced frames are protected from the noise), value for value; :func:`vw_perturb_plan` adds
``keyframe_plan`` of ``[prefix kept frames | mask]``. On CUDA one Triton kernel
(:mod:`.vw_perturb_triton`) where the separate ops launch two or three (a launch from Python costs
the host more than a few small ops, docs/gpu.md); switched off or failing on this GPU (one warning),
the separate ops; elsewhere their kernels (numpy VW on the CPU), which stand in for one launch where
:data:`~.dispatch.OBSERVERS` count them. ``vw_perturb_mask`` is one opaque node under ``torch.compile``.
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from .dispatch import FusedOp, TritonKernel
from .perturb import OP as PERTURB
from .plan_op import OP as PLAN
from .plan_tensors import Plan
from .vw import OP as VW

Tensor = torch.Tensor
#: ``(mask [B, N], plan mask [B, prefix + N], plan tensors)``: what :func:`vw_perturb_plan` returns
MaskAndPlan = Tuple[Tensor, Tensor, Plan]

__all__ = ["vw_perturb_mask", "vw_perturb_plan", "MaskAndPlan"]


def _two_ops(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor], u: Tensor,
             amount: float) -> Tensor:
    """The two ops, each as it runs on the device (a launch each for an observer)."""
    return PERTURB(VW(features, lengths, counts, forced, None), lengths, u, amount, forced)


def _two_kernels(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor], u: Tensor,
                 amount: float) -> Tensor:
    """The two ops' kernels for the device, unobserved: inside this op's one launch (the CPU's
    stand-in for the CUDA kernel)."""
    mask = VW.kernel(features)(features, lengths, counts, forced, None)
    return PERTURB.kernel(mask)(mask, lengths, u, amount, forced)


def _with_prefix(mask: Tensor, prefix: int) -> Tensor:
    return torch.cat([mask.new_ones(mask.shape[0], prefix), mask], 1) if prefix else mask


def _three_ops(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor], u: Tensor,
               amount: float, slots: int, prefix: int) -> MaskAndPlan:
    """The mask op and the plan op, each as it runs on the device."""
    mask = MASK_OP(features, lengths, counts, forced, u, amount)
    pmask = _with_prefix(mask, prefix)
    return mask, pmask, PLAN(pmask, slots)


def _three_kernels(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor], u: Tensor,
                   amount: float, slots: int, prefix: int) -> MaskAndPlan:
    """The three ops' kernels for the device, unobserved (as :func:`_two_kernels`)."""
    mask = _two_kernels(features, lengths, counts, forced, u, amount)
    pmask = _with_prefix(mask, prefix)
    return mask, pmask, PLAN.kernel(pmask)(pmask, slots)


def _fake(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor], u: Tensor,
          amount: float) -> Tensor:
    return features.new_empty(features.shape[:2], dtype=torch.bool)


#: the CUDA kernel of both ops (one switch: ``use_triton_kernels(False, ["VW with mask noise"])``)
KERNEL = TritonKernel(".vw_perturb_triton", "vw_perturb_triton", "VW with mask noise",
                      "the separate VW, mask-noise and plan kernels (a launch each)")
#: the mask: one Triton kernel on CUDA, the two ops' kernels elsewhere; one opaque node
#: (``smdm::vw_perturb_mask``) under ``torch.compile``
MASK_OP = FusedOp("vw_perturb_mask", _two_ops, cuda=KERNEL, kernels={"cpu": _two_kernels, "mps": _two_kernels},
                  fake=_fake, opaque=True)
#: the mask and its plan (eager training): one Triton kernel on CUDA, the three ops' kernels elsewhere
PLAN_OP = FusedOp("vw_perturb_plan", _three_ops, cuda=KERNEL, kernels={"cpu": _three_kernels, "mps": _three_kernels})


def vw_perturb_mask(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor], u: Tensor,
                    amount: float) -> Tensor:
    """The noisy VW keyframe mask ``[B, N]`` bool (no validation: callers validate once).

    Args:
        features: ``[B, N, F]`` float, what VW measures; lengths: ``[B]`` long, ``2 <= L <= N``;
        counts: ``[B]`` long, VW's keyframes per sample; forced: ``[B, N]`` bool (kept by VW,
        never dropped by the noise) or None; u: ``[B, N + 1]`` float32 uniforms in ``[0, 1)`` (the
        noise's count, then its frames); amount: the noise's share of the keyframes (> 0).
    """
    return MASK_OP(features.detach(), lengths, counts, forced, u, float(amount))


def vw_perturb_plan(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor], u: Tensor,
                    amount: float, slots: int, prefix: int = 0) -> MaskAndPlan:
    """:func:`vw_perturb_mask` with the plan of ``prefix`` always-kept frames followed by it:
    ``(mask [B, N], plan mask [B, prefix + N], keyframe_plan(plan mask, slots))`` (``slots`` counts
    the prefix's too). Eager mode (under ``torch.compile``: the separate ops, traced)."""
    return PLAN_OP(features.detach(), lengths, counts, forced, u, float(amount), int(slots), int(prefix))
