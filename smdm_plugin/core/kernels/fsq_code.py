"""The key codes of FSQ attention's folded path, with their straight-through gradient.

``fsq_code(z, neg_offset, half_l) = round(tanh(z) · half_l + neg_offset)`` per channel (the last
dimension's ``C`` channels), in float32, returned in ``z``'s dtype (small integers: exact in bf16);
gradient ``g · half_l · (1 - tanh(z)²)``. Eager mode runs the composite of torch ops on every device
(tanh, a fused multiply-add, round; under autograd the rounding's straight-through term detached, two
ops backward; plus bf16's casts): on the H200 its Triton kernels (:mod:`.fsq_triton`, :data:`CODE` /
:data:`GRAD`) cost the host more per call (120 µs forward, 340 µs backward) than those few ops
(docs/gpu.md); ``use_triton_kernels(True, ["FSQ code", "FSQ code gradient"])`` switches them on.
Under ``torch.compile`` the composite is traced. All give the composite's values (float32 maths,
round half to even).
"""
from __future__ import annotations

from typing import Callable, Tuple

import torch

from .dispatch import FusedOp, TritonKernel

Tensor = torch.Tensor

__all__ = ["fsq_code", "code_functions", "fsq_code_composite", "fsq_code_grad_composite", "CODE", "GRAD"]


def fsq_code_composite(z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
    """``round(tanh(z) · half_l + neg_offset)`` in float32, in ``z``'s dtype (no gradient).
    ``z [..., C]``, ``neg_offset, half_l [C]`` float32."""
    return torch.round(torch.addcmul(neg_offset, torch.tanh(z.float()), half_l)).to(z.dtype)


def fsq_code_grad_composite(grad: Tensor, z: Tensor, half_l: Tensor) -> Tensor:
    """``grad · half_l · (1 - tanh(z)²)`` in float32, in ``grad``'s dtype."""
    return torch.ops.aten.tanh_backward(grad.float() * half_l, torch.tanh(z.float())).to(grad.dtype)


CODE = FusedOp("fsq_code", fsq_code_composite,
               cuda=TritonKernel(".fsq_triton", "fsq_code_triton", "FSQ code", enabled=False))
GRAD = FusedOp("fsq_code_backward", fsq_code_grad_composite,
               cuda=TritonKernel(".fsq_triton", "fsq_code_backward_triton", "FSQ code gradient", enabled=False))


class _CodeSTE(torch.autograd.Function):
    """The codes with the straight-through gradient as one kernel each way (:data:`CODE`,
    :data:`GRAD`), where those kernels run."""

    @staticmethod
    def forward(ctx, z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
        ctx.save_for_backward(z, half_l)
        return CODE(z, neg_offset, half_l)

    @staticmethod
    def backward(ctx, grad: Tensor):
        z, half_l = ctx.saved_tensors
        return GRAD(grad, z, half_l), None, None


def straight_through_codes(z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
    """The composite under autograd: ``b + (round(b) - b)`` with the rounding's term detached, ``b =
    tanh(z)·half_l + neg_offset`` in float32 (the sum is ``round(b)`` exactly: ``|round(b) - b| <=
    1/2`` is a multiple of ``b``'s last place), so autograd's own nodes give the straight-through
    gradient ``g·half_l·(1 - tanh(z)²)`` (the same two ops as written out, no Python in the backward:
    a Python autograd function cost 4% of a sparse trans_enc training step's host time, docs/gpu.md)."""
    b = torch.addcmul(neg_offset, torch.tanh(z.float()), half_l)
    bd = b.detach()
    return (b + (torch.round(bd) - bd)).to(z.dtype)


def code_functions(like: Tensor) -> Tuple[Callable[..., Tensor], Callable[..., Tensor]]:
    """``(with autograd, without)``: what :func:`fsq_code` runs for pre-codes on ``like``'s device
    outside tracing, looked up once (a stack's run calls them per layer, without the lookups)."""
    ste = _CodeSTE.apply if CODE.fused_on(like) and GRAD.fused_on(like) else straight_through_codes
    return ste, CODE.eager


def fsq_code(z: Tensor, neg_offset: Tensor, half_l: Tensor) -> Tensor:
    """FSQ key codes ``[..., C]`` of pre-codes ``z [..., C]`` (any float dtype), with the bound's
    ``neg_offset`` and ``half_l`` ``[C]`` float32 on ``z``'s device; straight-through gradient in
    ``z``. The composite (module docstring; under autograd :func:`straight_through_codes`); one
    Triton kernel each way on CUDA where switched on."""
    if torch.is_grad_enabled() and z.requires_grad:
        if CODE.fused_on(z) and GRAD.fused_on(z):
            return _CodeSTE.apply(z, neg_offset, half_l)
        return straight_through_codes(z, neg_offset, half_l)
    return CODE(z, neg_offset, half_l)
