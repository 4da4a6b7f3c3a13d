"""Every output token of a keyframe-only pass: the lead tokens as they are, each frame linearly
interpolated between the keyframe rows around it (:func:`fill_frames`)."""
from __future__ import annotations

import torch

from . import consts
from .checks import compiling as static_compiling
from .plan import KeyframePlan
from .rows import gather_rows, lerp_row_pairs, lerp_rows


def _lead_rows(h: torch.Tensor, rows: torch.Tensor, lead: int, B: int) -> torch.Tensor:
    """``[lead, B, d]``: the lead tokens' output rows; a view when they are ``h``'s first rows (the
    compact backend's rows: its cached arange)."""
    if not static_compiling() and rows.is_contiguous() and rows.numel() == h.shape[0] \
            and rows.data_ptr() == consts.arange(rows.numel(), rows.device).data_ptr():
        return h[:lead * B].view(lead, B, -1)
    return gather_rows(h, rows[:lead].reshape(-1)).view(lead, B, h.shape[-1])


def fill_frames(h: torch.Tensor, rows: torch.Tensor, plan: KeyframePlan, lead: int,
                interpolate: bool = True) -> torch.Tensor:
    """Every output token ``[lead + N, B, d]`` from a backend's rows: lead tokens as they are,
    frames linearly interpolated between the keyframe rows around them (or, with
    ``interpolate=False``, keyframes as they are and zeros elsewhere)."""
    d = h.shape[-1]
    B, N = plan.mask.shape
    frame_rows = rows[lead:]                                           # [K, B]
    if interpolate and plan.slots is not None:                         # both ends in one gather
        pairs = frame_rows.gather(0, plan.slots.t())                   # [2N, B]: prev rows, next rows
        out = lerp_row_pairs(h, pairs.reshape(-1), plan.weight.t().unsqueeze(-1).to(h.dtype))
        out = out.view(N, B, d)
        if lead:
            out = torch.cat([_lead_rows(h, rows, lead, B), out], 0)
        return out
    prev = frame_rows.gather(0, plan.prev_slot.t())                    # [N, B]
    if interpolate:
        out = lerp_rows(h, prev.reshape(-1), frame_rows.gather(0, plan.next_slot.t()).reshape(-1),
                        plan.weight.t().unsqueeze(-1).to(h.dtype))
    else:
        out = h.index_select(0, prev.reshape(-1)) * plan.mask.t().reshape(-1, 1).to(h.dtype)
    out = out.view(N, B, d)
    if lead:
        out = torch.cat([_lead_rows(h, rows, lead, B), out], 0)
    return out
