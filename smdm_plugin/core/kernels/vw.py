"""``smdm::vw_keyframes``: Visvalingam–Whyatt keyframe selection as one registered operator."""
from __future__ import annotations

from typing import Optional

import torch

from .dispatch import FusedOp, TritonKernel
from .vw_numpy import vw_numpy
from .vw_torch import vw_torch

Tensor = torch.Tensor


def _cpu(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor],
         active: Optional[Tensor]) -> Tensor:
    x = features.detach()
    if x.dtype not in (torch.float32, torch.float64):
        x = x.float()
    x = x.cpu().contiguous().numpy()
    mask = vw_numpy(x, lengths.cpu().numpy(), counts.cpu().numpy(),
                    None if forced is None else forced.cpu().numpy(),
                    None if active is None else active.cpu().numpy())
    return torch.from_numpy(mask).to(features.device)


_KERNEL = TritonKernel(".vw_triton", "vw_triton", "VW", "the portable implementation (slower)")


def _mps(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor],
         active: Optional[Tensor]) -> Tensor:
    return _cpu(features, lengths, counts, forced, active)


def _composite(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor],
               active: Optional[Tensor]) -> Tensor:
    return vw_torch(features.detach(), lengths, counts, forced, active)


def _fake(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor],
          active: Optional[Tensor]) -> Tensor:
    return features.new_empty(features.shape[:2], dtype=torch.bool)


#: the op: numpy on the CPU, Triton on CUDA, the CPU kernel on a copy on MPS, the portable loop
#: elsewhere; one opaque node (``smdm::vw_keyframes``) under ``torch.compile``
OP = FusedOp("vw_keyframes", _composite, cuda=_KERNEL, kernels={"cpu": _cpu, "mps": _mps}, fake=_fake, opaque=True)


def vw_keyframes(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor] = None,
                 active: Optional[Tensor] = None) -> Tensor:
    """VW keyframe mask ``[B, N]`` bool (no validation of values; callers validate once).

    Args:
        features: ``[B, N, F]`` float, what VW measures (e.g. joints + frame index).
        lengths: ``[B]`` integer, valid frames per sample, ``2 <= L <= N``.
        counts: ``[B]`` integer, frames to keep (``keyframe_count(L, reduction)``).
        forced: ``[B, N]`` bool, frames that are always kept (they count towards ``counts``).
        active: ``[B]`` bool; inactive samples cost nothing and get an all-False row.
    """
    return OP(features.detach(), lengths, counts, forced, active)
