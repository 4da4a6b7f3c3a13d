"""The key codes of FSQ attention's folded path as one fused op each way (:class:`~.dispatch.FusedOp`).

``fsq_code(z, neg_offset, half_l) = round(tanh(z) · half_l + neg_offset)`` per channel (the last
dimension's ``C`` channels), computed in float32 and returned in ``z``'s dtype (the codes are small
integers: exact in bfloat16/float16); its gradient is the straight-through one,
``g · half_l · (1 - tanh(z)²)``. Eager mode launches one kernel each
way: on CUDA a Triton kernel (:mod:`.fsq_triton`) when ``triton`` imports (else, or if it cannot be
built on this GPU, with one warning, the composite); elsewhere the composite of torch ops
(:func:`fsq_code_composite`). Under ``torch.compile`` the composite is traced instead (inductor
fuses it). All give the composite's values (float32 maths, round half to even).
"""
from __future__ import annotations

import torch

from .dispatch import FusedOp, TritonKernel

Tensor = torch.Tensor

__all__ = ["fsq_code", "fsq_code_composite", "fsq_code_grad_composite", "CODE", "GRAD"]


def fsq_code_composite(z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
    """``round(tanh(z) · half_l + neg_offset)`` in float32, in ``z``'s dtype (no gradient).
    ``z [..., C]``, ``neg_offset, half_l [C]`` float32."""
    return torch.round(torch.addcmul(neg_offset, torch.tanh(z.float()), half_l)).to(z.dtype)


def fsq_code_grad_composite(grad: Tensor, z: Tensor, half_l: Tensor) -> Tensor:
    """``grad · half_l · (1 - tanh(z)²)`` in float32, in ``grad``'s dtype."""
    return torch.ops.aten.tanh_backward(grad.float() * half_l, torch.tanh(z.float())).to(grad.dtype)


CODE = FusedOp("fsq_code", fsq_code_composite, cuda=TritonKernel(".fsq_triton", "fsq_code_triton", "FSQ code"))
GRAD = FusedOp("fsq_code_backward", fsq_code_grad_composite,
               cuda=TritonKernel(".fsq_triton", "fsq_code_backward_triton", "FSQ code gradient"))


class _CodeSTE(torch.autograd.Function):
    """The codes with the straight-through gradient: one op each way (:data:`CODE`, :data:`GRAD`)."""

    @staticmethod
    def forward(ctx, z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
        ctx.save_for_backward(z, half_l)
        return CODE(z, neg_offset, half_l)

    @staticmethod
    def backward(ctx, grad: Tensor):
        z, half_l = ctx.saved_tensors
        return GRAD(grad, z, half_l), None, None


def fsq_code(z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
    """FSQ key codes ``[..., C]`` of pre-codes ``z [..., C]`` (any float dtype), with the bound's
    ``neg_offset`` and ``half_l`` ``[C]`` float32 on ``z``'s device; straight-through gradient in
    ``z``. One kernel each way on CUDA in eager mode; the composite elsewhere and under compile."""
    if torch.is_grad_enabled() and z.requires_grad:
        return _CodeSTE.apply(z, neg_offset, half_l)
    return CODE(z, neg_offset, half_l)
