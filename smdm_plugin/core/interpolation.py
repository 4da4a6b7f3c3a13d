"""Interpolation of per-frame features between keyframes (vectorised, differentiable): linear (the
paper) and C¹ Catmull-Rom (``cubic``, smoother motion at sampling)."""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from .checks import require
from .config import INTERPOLATIONS  # linear (the paper), cubic (C¹ Catmull-Rom)


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


def _checked(features: torch.Tensor, mask: torch.Tensor, fn: str) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(features [B, N, D], mask [B, N] bool on features' device)``, shapes checked."""
    if features.dim() != 3:
        raise ValueError(f"{fn}: features must be [B, N, D], got shape {tuple(features.shape)}")
    B, N, D = features.shape
    if mask.shape != (B, N):
        raise ValueError(f"{fn}: mask must be [B, N]=[{B}, {N}], got {tuple(mask.shape)}")
    mask = mask.to(device=features.device, dtype=torch.bool)
    require(mask.any(dim=1), f"{fn}: every row of mask needs at least one keyframe")
    return features, mask


def interpolate_keyframes(features: torch.Tensor, mask: torch.Tensor, method: str = "linear") -> torch.Tensor:
    """Fill every frame by interpolation in time between neighbouring keyframes.

    Args:
        features: ``[B, N, D]``; values at non-keyframes are ignored (they get no gradient).
        mask: bool ``[B, N]``, True = keyframe; at least one per row (two for interpolation).
        method: ``"linear"`` (the paper) or ``"cubic"`` (C¹ Catmull-Rom,
            :func:`interpolate_keyframes_cubic`).
    Returns:
        ``[B, N, D]``, equal to ``features`` at keyframes, piecewise linear (cubic) in between,
        constant before the first and after the last keyframe.
    """
    if method not in INTERPOLATIONS:
        raise ValueError(f"interpolate_keyframes: method must be one of {INTERPOLATIONS}, got {method!r}")
    if method == "cubic":
        return interpolate_keyframes_cubic(features, mask)
    features, mask = _checked(features, mask, "interpolate_keyframes")
    B, N, D = features.shape
    prev, nxt, w = neighbour_keyframes(mask, features.dtype)
    f_prev = features.gather(1, prev.unsqueeze(-1).expand(B, N, D))
    f_next = features.gather(1, nxt.unsqueeze(-1).expand(B, N, D))
    w = w.unsqueeze(-1)
    return torch.lerp(f_prev, f_next, w)


def catmull_rom_taps(index: torch.Tensor, count: torch.Tensor, prev_slot: torch.Tensor,
                     next_slot: torch.Tensor, weight: torch.Tensor, dtype: torch.dtype = torch.float32
                     ) -> Tuple[torch.Tensor, torch.Tensor]:
    """The four keyframe slots and weights of C¹ Catmull-Rom interpolation at every frame.

    A cubic Hermite curve on each gap between keyframes ``t1 = frame(k) < t2 = frame(k+1)`` with
    tangents ``m1 = (p2 - p0) / (t2 - t0)`` and ``m2 = (p3 - p1) / (t3 - t1)`` from the keyframes
    around them (non-uniform Catmull-Rom; at the first / last keyframe the missing neighbour is the
    keyframe itself, a one-sided difference). Exact at keyframes, C¹ in between, constant before the
    first and after the last keyframe (as the linear fill). Static shapes, no host sync.

    Args (a :class:`~smdm_plugin.core.plan.KeyframePlan`'s tensors):
        index: ``[B, K]`` long, frame of each slot (slots ``< count`` hold the keyframes in order).
        count: ``[B]`` long, keyframes per sample (>= 1).
        prev_slot, next_slot: ``[B, N]`` long, the slots of the keyframes around each frame.
        weight: ``[B, N]`` float in [0, 1], the linear blend weight ``s = (n - t1) / (t2 - t1)``.
    Returns:
        ``slots [B, N, 4]`` long (slots of p0, p1, p2, p3) and ``weights [B, N, 4]`` in ``dtype``:
        ``f(n) = sum_i weights[..., i] * f(slot slots[..., i])``; the weights of a frame sum to 1.
    """
    last = (count - 1).clamp_min(0)[:, None]                            # [B, 1]
    s0 = (prev_slot - 1).clamp_min(0)
    s3 = torch.minimum(next_slot + 1, last)
    slots = torch.stack([s0, prev_slot, next_slot, s3], dim=-1)         # [B, N, 4]
    t = index.gather(1, slots.flatten(1)).view(slots.shape).to(torch.float32)   # frames: exact
    t0, t1, t2, t3 = t.unbind(-1)
    s = weight.to(torch.float32)
    h = t2 - t1                                                         # 0 at a keyframe
    s2, s3_ = s * s, s * s * s
    h00, h10 = 2 * s3_ - 3 * s2 + 1, s3_ - 2 * s2 + s
    h01, h11 = -2 * s3_ + 3 * s2, s3_ - s2
    a = h10 * h / (t2 - t0).clamp_min(1)                                # weight of m1's difference
    b = h11 * h / (t3 - t1).clamp_min(1)                                # weight of m2's difference
    w = torch.stack([-a, h00 - b, h01 + a, b], dim=-1)
    return slots, w.to(dtype)


def interpolate_keyframes_cubic(features: torch.Tensor, mask: torch.Tensor,
                                cubic: Optional[torch.Tensor] = None) -> torch.Tensor:
    """:func:`interpolate_keyframes` with C¹ Catmull-Rom curves (:func:`catmull_rom_taps`) in place
    of straight lines. ``features [B, N, D]``, bool ``mask [B, N]`` (>= 1 keyframe per row),
    ``cubic`` bool ``[B]`` (None: every sample; the others are filled linearly) -> ``[B, N, D]``,
    equal to ``features`` at keyframes. Static shapes, no host sync."""
    from .plan import KeyframePlan

    features, mask = _checked(features, mask, "interpolate_keyframes_cubic")
    B, N, D = features.shape
    plan = KeyframePlan.build(mask, None, check=False)
    slots, w = catmull_rom_taps(plan.index, plan.count, plan.prev_slot, plan.next_slot, plan.weight,
                                features.dtype)
    if cubic is not None:
        s = plan.weight.to(features.dtype)
        z = torch.zeros_like(s)
        cubic = torch.as_tensor(cubic, device=features.device).to(torch.bool).reshape(-1).expand(B)
        w = torch.where(cubic.view(B, 1, 1), w, torch.stack([z, 1 - s, s, z], dim=-1))
    frames = plan.index.gather(1, slots.flatten(1))                     # [B, N*4]
    taps = features.gather(1, frames.unsqueeze(-1).expand(B, N * 4, D)).view(B, N, 4, D)
    return (taps * w.unsqueeze(-1)).sum(2)
