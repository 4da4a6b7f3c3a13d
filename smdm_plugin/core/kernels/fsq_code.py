"""``smdm::fsq_code``: the key codes of FSQ attention's folded path as one registered operator.

``fsq_code(z, neg_offset, half_l) = round(tanh(z) · half_l + neg_offset)`` per channel (the last
dimension's ``C`` channels), computed in float32 and returned in ``z``'s dtype (the codes are small
integers: exact in bfloat16/float16); its gradient is the straight-through one,
``g · half_l · (1 - tanh(z)²)`` (``smdm::fsq_code_backward``). Eager mode launches one kernel each
way: on CUDA a Triton kernel (:mod:`.fsq_triton`) when ``triton`` imports (else, or if it cannot be
built on this GPU, with one warning, the composite); elsewhere the composite of torch ops
(:func:`fsq_code_composite`). Under ``torch.compile`` the composite is traced instead (inductor
fuses it). All give the composite's values (float32 maths, round half to even).
"""
from __future__ import annotations

from typing import Tuple

import torch

from .dispatch import TritonKernel, register_op

Tensor = torch.Tensor

__all__ = ["fsq_code", "fsq_code_composite", "fsq_code_grad_composite"]


def fsq_code_composite(z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
    """``round(tanh(z) · half_l + neg_offset)`` in float32, in ``z``'s dtype (no gradient).
    ``z [..., C]``, ``neg_offset, half_l [C]`` float32."""
    return torch.round(torch.addcmul(neg_offset, torch.tanh(z.float()), half_l)).to(z.dtype)


def fsq_code_grad_composite(grad: Tensor, z: Tensor, half_l: Tensor) -> Tensor:
    """``grad · half_l · (1 - tanh(z)²)`` in float32, in ``grad``'s dtype."""
    return torch.ops.aten.tanh_backward(grad.float() * half_l, torch.tanh(z.float())).to(grad.dtype)


if hasattr(torch.library, "custom_op"):
    def _code_fake(z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
        return torch.empty_like(z, memory_format=torch.contiguous_format)

    def _grad_fake(grad: Tensor, z: Tensor, half_l: Tensor) -> Tensor:
        return torch.empty_like(z, dtype=grad.dtype, memory_format=torch.contiguous_format)

    _code_op = register_op("fsq_code", fsq_code_composite, TritonKernel("fsq_triton", "fsq_code_triton", "FSQ code"),
                           _code_fake)
    _grad_op = register_op("fsq_code_backward", fsq_code_grad_composite,
                           TritonKernel("fsq_triton", "fsq_code_backward_triton", "FSQ code gradient"), _grad_fake)

    def _setup(ctx, inputs: Tuple[Tensor, Tensor, Tensor], output: Tensor) -> None:
        z, _, half_l = inputs
        ctx.save_for_backward(z, half_l)

    def _backward(ctx, grad: Tensor):
        z, half_l = ctx.saved_tensors
        return _grad_op(grad, z, half_l), None, None

    _code_op.register_autograd(_backward, setup_context=_setup)
    OP = torch.ops.smdm.fsq_code.default
else:  # pragma: no cover - torch < 2.4: the composite with a straight-through gradient
    OP = None


class _CodeSTE(torch.autograd.Function):
    """The composite with the straight-through gradient (traced under ``torch.compile``)."""

    @staticmethod
    def forward(ctx, z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
        ctx.save_for_backward(z, half_l)
        return fsq_code_composite(z, neg_offset, half_l)

    @staticmethod
    def backward(ctx, grad: Tensor):
        z, half_l = ctx.saved_tensors
        return fsq_code_grad_composite(grad, z, half_l), None, None


def fsq_code(z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
    """FSQ key codes ``[..., C]`` of pre-codes ``z [..., C]`` (any float dtype), with the bound's
    ``neg_offset`` and ``half_l`` ``[C]`` float32 on ``z``'s device; straight-through gradient in
    ``z``. One op each way in eager mode; the composite under ``torch.compile``."""
    from ..checks import compiling

    if OP is None or compiling():
        return _CodeSTE.apply(z, neg_offset, half_l) if torch.is_grad_enabled() and z.requires_grad \
            else fsq_code_composite(z, neg_offset, half_l)
    return _code_op(z, neg_offset, half_l)
