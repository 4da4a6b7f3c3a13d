"""One Lipschitz-normalised weight: the composite's ops under autograd, or one fused op each way.

``lipschitz_weight(W, c) = W · min(1, softplus(c) / rowsum|W|)`` (``W [out, in]``, ``c`` a 0-d
tensor, rowsum per output row), the value of :class:`~smdm_plugin.core.lipschitz.LipschitzWeight`
bit for bit. With autograd, eager mode runs the composite's five ops on every device (no Python in
the backward: less host time per training step than the Triton pair in its Python autograd
function, which the H200 profiled at 93 µs forward and 217 µs backward per weight; docs/gpu.md).
``use_triton_kernels(True, ["Lipschitz weight", "Lipschitz weight gradient"])`` switches the pair on
for CUDA (:mod:`.lipschitz_triton`, one program per row; the gradient written out: ``dW = g·scale -
sign(W)·r``, ``r = [ratio <= 1][rowsum >= eps]·ratio/rowsum·Σ_j g·W``, ``dc = Σ_rows
softplus'(c)·[ratio <= 1]/rowsum·Σ_j g·W``). Values are the composite's either way.
"""
from __future__ import annotations

from typing import Tuple

import torch
import torch.nn.functional as F

from .dispatch import FusedOp, TritonKernel

Tensor = torch.Tensor

__all__ = ["lipschitz_weight", "lipschitz_weight_composite", "lipschitz_weight_grad_composite", "WEIGHT", "GRAD"]


def row_abs_sum(weight: Tensor) -> Tensor:
    """``[out, in] -> [out, 1]``: absolute row sums (each row's contribution to the ∞-norm), as
    one reduction (the 1-norm of each row)."""
    return torch.linalg.vector_norm(weight, 1, dim=1, keepdim=True)


def lipschitz_weight_composite(weight: Tensor, c: Tensor) -> Tensor:
    """``W · min(1, softplus(c) / rowsum|W|)`` (``weight [out, in]``, ``c`` 0-d), no gradient. A
    zero row keeps its scale 1 (the ratio is inf)."""
    return weight * (F.softplus(c) / row_abs_sum(weight)).clamp(max=1.0)


def lipschitz_weight_grad_composite(grad: Tensor, weight: Tensor, c: Tensor) -> Tuple[Tensor, Tensor]:
    """``(dW [out, in], dc per row [out])`` of :func:`lipschitz_weight_composite` for ``grad [out,
    in]``: ``dc = dc_rows.sum()``."""
    eps = torch.finfo(weight.dtype).eps
    rowsum = row_abs_sum(weight)
    ratio = F.softplus(c) / rowsum
    gw = (grad * weight).sum(1, keepdim=True)                              # Σ_j g·W per row
    g_bound = torch.where(ratio <= 1.0, gw / rowsum, 0.0)                  # d/d softplus(c), per row
    r = torch.where(rowsum >= eps, g_bound * ratio, 0.0)                   # -d/d rowsum
    grad_w = torch.addcmul(grad * ratio.clamp(max=1.0), torch.sign(weight), r, value=-1.0)
    rows = torch.ops.aten.softplus_backward(g_bound.squeeze(1), c.expand(weight.shape[0]), 1.0, 20.0)
    return grad_w, rows


WEIGHT = FusedOp("lipschitz_weight", lipschitz_weight_composite,
                 cuda=TritonKernel(".lipschitz_triton", "lipschitz_weight_triton", "Lipschitz weight", enabled=False))
GRAD = FusedOp("lipschitz_weight_backward", lipschitz_weight_grad_composite,
               cuda=TritonKernel(".lipschitz_triton", "lipschitz_weight_backward_triton", "Lipschitz weight gradient",
                                 enabled=False))


class _Weight(torch.autograd.Function):
    """The normalised weight with its written-out gradient: one op forward, two backward (where the
    Triton kernels are switched on)."""

    @staticmethod
    def forward(ctx, weight: Tensor, c: Tensor) -> Tensor:
        ctx.save_for_backward(weight, c)
        return WEIGHT(weight, c)

    @staticmethod
    def backward(ctx, grad: Tensor):
        weight, c = ctx.saved_tensors
        grad_w, rows = GRAD(grad, weight, c)
        return grad_w, rows.sum().reshape(c.shape)


def lipschitz_weight(weight: Tensor, c: Tensor) -> Tensor:
    """The normalised weight ``[out, in]`` of ``weight [out, in]`` and the 0-d bound parameter ``c``,
    differentiable in both: the composite under autograd (five ops, no Python in the backward: less
    host time than a Python function's backward); with the Triton kernels switched on, on CUDA one
    kernel forward and two backward (:class:`_Weight`)."""
    if torch.is_grad_enabled() and (weight.requires_grad or c.requires_grad):
        if WEIGHT.fused_on(weight) and GRAD.fused_on(weight):
            return _Weight.apply(weight, c)
        # the parametrization's own operations (rows summing to < eps clamped: finite gradients)
        rowsum = row_abs_sum(weight).clamp_min(torch.finfo(weight.dtype).eps)
        return weight * torch.clamp(F.softplus(c) / rowsum, max=1.0)
    return WEIGHT(weight, c)
