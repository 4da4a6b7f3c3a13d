"""Interpolation of per-frame features between keyframes (vectorised, differentiable): linear (the
paper) and C¹ Catmull-Rom (``cubic``, smoother motion at sampling)."""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from .checks import require
from .config import INTERPOLATIONS  # linear (the paper), cubic (C¹ Catmull-Rom)
from .plan import KeyframePlan


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
    """The four keyframes and weights of C¹ Catmull-Rom interpolation at every frame.

    A cubic Hermite curve on each gap between keyframes ``t1 = frame(k) < t2 = frame(k+1)`` with
    tangents ``m1 = (p2 - p0) / (t2 - t0)`` and ``m2 = (p3 - p1) / (t3 - t1)`` from the keyframes
    around them (non-uniform Catmull-Rom; at the first / last keyframe the missing neighbour is the
    keyframe itself, a one-sided difference). Exact at keyframes, C¹ in between, constant before the
    first and after the last keyframe (as the linear fill). Static shapes, no host sync; about 20
    small ``[B, N]``-sized ops (one elementwise kernel under ``torch.compile``).

    Args (a :class:`~smdm_plugin.core.plan.KeyframePlan`'s tensors):
        index: ``[B, K]`` long, frame of each slot (slots ``< count`` hold the keyframes in order).
        count: ``[B]`` long, keyframes per sample (>= 1).
        prev_slot, next_slot: ``[B, N]`` long, the slots of the keyframes around each frame.
        weight: ``[B, N]`` float in [0, 1], the linear blend weight ``s = (n - t1) / (t2 - t1)``.
    Returns:
        ``frames [B, N, 4]`` long (frames of p0, p1, p2, p3) and ``weights [B, N, 4]`` in ``dtype``:
        ``f(n) = sum_i weights[..., i] * f(frames[..., i])``; the weights of a frame sum to 1.
    """
    slots = torch.stack([(prev_slot - 1).clamp_min(0), prev_slot, next_slot,
                         torch.minimum(next_slot + 1, count[:, None] - 1)], dim=-1)     # [B, N, 4]
    t = index.gather(1, slots.flatten(1)).view(slots.shape)            # frames t0..t3: exact ints
    # h / (t2 - t0) and h / (t3 - t1) with h = t2 - t1 (0 at a keyframe): a true division of ints
    ratio = torch.div((t[..., 2] - t[..., 1]).unsqueeze(-1), (t[..., 2:] - t[..., :2]).clamp_min(1))
    s = weight.to(ratio.dtype)
    u = s - 1
    s2 = s * s
    h11 = s2 * u                                                        # Hermite basis: s³ - s²
    ab = torch.stack([s * u * u, h11], dim=-1) * ratio                  # h10 = s(1-s)²; (a, b)
    p = torch.add(s2, h11, alpha=-2).unsqueeze(-1) + ab                 # h01 = 3s² - 2s³; h01 + (a, b)
    a, b = ab.unbind(-1)
    w = torch.stack([-a, 1 - p[..., 1], p[..., 0], b], dim=-1)          # h00 = 1 - h01
    return t, w.to(dtype)


def catmull_rom_fill(features: torch.Tensor, plan: KeyframePlan) -> torch.Tensor:
    """``features [B, N, D]`` refilled between the keyframes of ``plan`` (over the same ``N`` frames)
    along C¹ Catmull-Rom curves (:func:`catmull_rom_taps`): equal at keyframes, constant before the
    first and after the last. Reuses the plan's slots (or its looked-up ``taps``): no mask is
    scanned again."""
    B, N, D = features.shape
    if plan.taps is not None:
        frames, w = plan.taps
        w = w.to(features.dtype)
    else:
        frames, w = catmull_rom_taps(plan.index, plan.count, plan.prev_slot, plan.next_slot, plan.weight,
                                     features.dtype)
    taps = features.gather(1, frames.view(B, N * 4, 1).expand(B, N * 4, D)).view(B, N, 4, D)
    return (taps * w.unsqueeze(-1)).sum(2)


def catmull_rom_refill(features: torch.Tensor, plan: KeyframePlan) -> torch.Tensor:
    """``features [B, N, D]`` with the samples in ``plan.cubic`` (``True``: every sample) refilled by
    :func:`catmull_rom_fill`, the others as they are."""
    filled = catmull_rom_fill(features, plan)
    if plan.cubic is True:
        return filled
    return torch.where(plan.cubic.view(-1, 1, 1), filled, features)


def interpolate_keyframes_cubic(features: torch.Tensor, mask: torch.Tensor,
                                cubic: Optional[torch.Tensor] = None) -> torch.Tensor:
    """:func:`interpolate_keyframes` with C¹ Catmull-Rom curves (:func:`catmull_rom_taps`) in place
    of straight lines. ``features [B, N, D]``, bool ``mask [B, N]`` (>= 1 keyframe per row),
    ``cubic`` bool ``[B]`` (None: every sample; the others are filled linearly) -> ``[B, N, D]``,
    equal to ``features`` at keyframes. Static shapes, no host sync."""
    features, mask = _checked(features, mask, "interpolate_keyframes_cubic")
    out = catmull_rom_fill(features, KeyframePlan.build(mask, None, check=False))
    if cubic is None:
        return out
    cubic = torch.as_tensor(cubic, device=features.device).to(torch.bool).reshape(-1)
    return torch.where(cubic.view(-1, 1, 1), out, interpolate_keyframes(features, mask))
