"""``smdm::vw_keyframes``: Visvalingam–Whyatt keyframe selection as one registered operator.

``torch.compile`` sees one op (a ``torch.library.custom_op`` with a fake implementation for its
output shape), eager mode launches one kernel per call, and the implementation is chosen by device:

* ``cuda`` — a Triton kernel, one program per motion (:mod:`.vw_triton`), when ``triton`` imports;
  otherwise (or if that kernel cannot be built on this GPU, with one warning) the portable loop;
* ``cpu`` — numpy, samples batched per removal step (:mod:`.vw_numpy`);
* ``mps`` — the CPU kernel on a copy (exact float64 keys; MPS has no float64);
* anything else — the portable loop of small torch ops (:mod:`.vw_torch`).

All give the frames of :func:`smdm_plugin.core.selection.vw_reference` (the heap algorithm):
key ``(2·area)² = max(0, |a|²|b|² - (a·b)²)`` in float64, the smallest key removed first (ties: the
lowest frame), until ``max(count, protected frames)`` frames remain, where protected = the first
and last valid frame and the ``forced`` frames. On torch < 2.4 (no ``custom_op``) the same
dispatch runs as a plain function (no ``torch.compile`` support).
"""
from __future__ import annotations

from typing import Optional

import torch

from .dispatch import TritonKernel
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


_KERNEL = TritonKernel("vw_triton", "vw_triton", "VW", "the portable implementation (slower)")


def _cuda(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor],
          active: Optional[Tensor]) -> Tensor:
    return _KERNEL(vw_torch, features.detach(), lengths, counts, forced, active)


def _mps(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor],
         active: Optional[Tensor]) -> Tensor:
    return _cpu(features, lengths, counts, forced, active)


if hasattr(torch.library, "custom_op"):
    @torch.library.custom_op("smdm::vw_keyframes", mutates_args=())
    def _vw_op(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor],
               active: Optional[Tensor]) -> Tensor:
        return vw_torch(features.detach(), lengths, counts, forced, active)

    _vw_op.register_kernel("cpu")(_cpu)
    _vw_op.register_kernel("cuda")(_cuda)
    _vw_op.register_kernel("mps")(_mps)

    @_vw_op.register_fake
    def _vw_fake(features: Tensor, lengths: Tensor, counts: Tensor, forced: Optional[Tensor],
                 active: Optional[Tensor]) -> Tensor:
        return features.new_empty(features.shape[:2], dtype=torch.bool)

    OP = torch.ops.smdm.vw_keyframes.default
else:  # pragma: no cover - torch < 2.4
    def _vw_op(features, lengths, counts, forced, active):
        kernel = {"cpu": _cpu, "cuda": _cuda, "mps": _mps}.get(features.device.type, vw_torch)
        return kernel(features, lengths, counts, forced, active)

    OP = _vw_op


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
    return _vw_op(features.detach(), lengths, counts, forced, active)
