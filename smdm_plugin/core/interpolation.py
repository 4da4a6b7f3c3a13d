"""Linear interpolation of per-frame features between keyframes (vectorised, differentiable)."""
from __future__ import annotations

from typing import Tuple

import torch

from .checks import require


def neighbour_keyframes(mask: torch.Tensor, dtype: torch.dtype = torch.float32
                        ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For every frame, the previous and next keyframe and the blend weight.

    Args:
        mask: bool ``[B, N]``, True = keyframe; every row needs at least one keyframe.
    Returns:
        ``prev [B, N]`` long, ``next [B, N]`` long and ``w [B, N]`` float in [0, 1], so that
        ``f(n) = (1 - w) f(prev) + w f(next)``. At a keyframe prev = next = n, w = 0. Before the
        first keyframe (after the last) both indices are the first (last) keyframe.
    """
    B, N = mask.shape
    idx = torch.arange(N, device=mask.device).expand(B, N)
    prev = torch.where(mask, idx, torch.full_like(idx, -1)).cummax(dim=1).values
    nxt = torch.where(mask, idx, torch.full_like(idx, N)).flip(1).cummin(dim=1).values.flip(1)
    prev = torch.where(prev < 0, nxt, prev)
    nxt = torch.where(nxt >= N, prev, nxt)
    gap = (nxt - prev).clamp_min(1)
    w = (idx - prev).to(dtype) / gap.to(dtype)
    return prev, nxt, w


def interpolate_keyframes(features: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Fill every frame by linear interpolation in time between neighbouring keyframes.

    Args:
        features: ``[B, N, D]``; values at non-keyframes are ignored (they get no gradient).
        mask: bool ``[B, N]``, True = keyframe; at least one per row (two for interpolation).
    Returns:
        ``[B, N, D]``, equal to ``features`` at keyframes, piecewise linear in between,
        constant before the first and after the last keyframe.
    """
    if features.dim() != 3:
        raise ValueError(f"interpolate_keyframes: features must be [B, N, D], got shape {tuple(features.shape)}")
    B, N, D = features.shape
    if mask.shape != (B, N):
        raise ValueError(f"interpolate_keyframes: mask must be [B, N]=[{B}, {N}], got {tuple(mask.shape)}")
    mask = mask.to(device=features.device, dtype=torch.bool)
    require(mask.any(dim=1), "interpolate_keyframes: every row of mask needs at least one keyframe")
    prev, nxt, w = neighbour_keyframes(mask, features.dtype)
    f_prev = features.gather(1, prev.unsqueeze(-1).expand(B, N, D))
    f_next = features.gather(1, nxt.unsqueeze(-1).expand(B, N, D))
    w = w.unsqueeze(-1)
    return torch.lerp(f_prev, f_next, w)
