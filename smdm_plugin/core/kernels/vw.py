"""``smdm::vw_keyframes``: Visvalingam–Whyatt keyframe selection as one registered operator.

Eager mode calls one kernel per call, chosen by device (a :class:`~.dispatch.FusedOp`: no
``torch.library`` dispatch on the hot path); ``torch.compile`` sees one opaque op (a
``torch.library.custom_op`` with a fake implementation for its output shape):

* ``cuda`` — a Triton kernel, one program per motion (:mod:`.vw_triton`), when ``triton`` imports;
  otherwise (or if that kernel cannot be built on this GPU, with one warning) the portable loop;
* ``cpu`` — numpy, samples batched per removal step (:mod:`.vw_numpy`);
* ``mps`` — the CPU kernel on a copy (exact float64 keys; MPS has no float64);
* anything else — the portable loop of small torch ops (:mod:`.vw_torch`).

All give the frames of :func:`smdm_plugin.core.selection.vw_reference` (the heap algorithm):
key ``(2·area)² = max(0, |a|²|b|² - (a·b)²)`` in float64, the smallest key removed first (ties: the
lowest frame), until ``max(count, protected frames)`` frames remain, where protected = the first
and last valid frame and the ``forced`` frames.
"""
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
