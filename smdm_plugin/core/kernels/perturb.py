"""``smdm::perturb_mask``: the training mask noise as one registered operator.

Per sample with ``K`` keyframes in ``mask [B, N]``: ``m = round(amount · K)``, ``c = min(floor(u_0 ·
(2m + 1)) - m, m)`` from the first of the sample's ``N + 1`` uniforms ``u [B, N + 1]``; ``c > 0``
adds the ``c`` non-keyframes of the valid frames with the smallest ``u_{1+i}``, ``c < 0`` drops
``min(-c, K - 2)`` interior keyframes (not ``protected``) the same way (ties: the lower frame; fewer
when there are not enough candidates). One kernel in eager mode: on CUDA a Triton kernel
(:mod:`.perturb_triton`) when ``triton`` imports (else, or if it cannot be built on this GPU, with one
warning, the composite); elsewhere the composite of torch ops (:func:`perturb_composite`), whose
values every kernel gives.
"""
from __future__ import annotations

from typing import Optional

import torch

from .. import consts
from .dispatch import FusedOp, TritonKernel

Tensor = torch.Tensor

__all__ = ["perturb_mask_op", "perturb_composite", "rank_select"]


def rank_select(cand: Tensor, count: Tensor, u: Tensor) -> Tensor:
    """``[B, N]`` bool: the ``count[b]`` entries of ``cand[b]`` with the smallest ``u [B, N]`` (ties:
    the lower index; fewer if not enough candidates)."""
    N = cand.shape[1]
    order = torch.where(cand, u, 2.0).argsort(dim=1, stable=True)
    take = (consts.arange(N, cand.device)[None] < count[:, None]) & cand.gather(1, order)
    return torch.zeros_like(cand).scatter_(1, order, take)


def perturb_composite(mask: Tensor, lengths: Tensor, u: Tensor, amount: float,
                      protected: Optional[Tensor] = None) -> Tensor:
    """The mask noise of the module docstring in torch ops: ``mask [B, N]`` bool (keyframes in the
    valid frames), ``lengths [B]`` long, ``u [B, N + 1]`` float32 in ``[0, 1)``, ``protected [B, N]``
    bool or None."""
    B, N = mask.shape
    device = mask.device
    i = consts.arange(N, device)[None]
    valid = i < lengths[:, None]
    m = mask.to(torch.bool)
    k = m.sum(1, dtype=torch.float32)
    mmax = torch.round(k * float(amount))                          # exact: k <= N << 2^24
    c = torch.minimum((u[:, 0] * (2 * mmax + 1)).floor() - mmax, mmax)
    # interior frames 0 < i < L - 1: i >= 1 is the cached arange's tail, i < L - 1 is i + 1 < L
    after_first = consts.arange(N + 1, device)[None, 1:]            # i + 1
    droppable = m & (after_first > 1) & (after_first < lengths[:, None])
    if protected is not None:
        droppable &= ~protected
    add = c > 0
    cand = torch.where(add[:, None], valid & ~m, droppable)
    # (no more than the candidates: rank_select takes all of them when count exceeds them)
    count = torch.where(add, c, torch.minimum(-c, k - 2))
    return m ^ rank_select(cand, count, u[:, 1:])


def _composite(mask: Tensor, lengths: Tensor, u: Tensor, amount: float, protected: Optional[Tensor]) -> Tensor:
    return perturb_composite(mask, lengths, u, amount, protected)


def _fake(mask: Tensor, lengths: Tensor, u: Tensor, amount: float, protected: Optional[Tensor]) -> Tensor:
    return torch.empty(mask.shape, dtype=torch.bool, device=mask.device)


#: the op: a Triton kernel on CUDA, the composite elsewhere; one opaque node under ``torch.compile``
OP = FusedOp("perturb_mask", _composite, cuda=TritonKernel(".perturb_triton", "perturb_triton", "mask-noise"),
             fake=_fake, opaque=True)


def perturb_mask_op(mask: Tensor, lengths: Tensor, u: Tensor, amount: float,
                    protected: Optional[Tensor] = None) -> Tensor:
    """:func:`perturb_composite` as one op (no validation: callers validate once)."""
    return OP(mask.to(torch.bool), lengths, u, float(amount), protected)
