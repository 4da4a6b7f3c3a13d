"""DoubleTake's long sequences: the motion/transition frame split and EES on each part (the
paper's Table 3 reports EES separately on the transition windows, the handshake frames shared by
neighbouring segments, and on the rest of the sequence)."""
from __future__ import annotations

from typing import Optional, Sequence, Tuple

import numpy as np
import torch

from .motion import ArrayLike, end_effector_speed, to_joint_positions

# --------------------------------------------------------------------------- DoubleTake split
def unfolded_step_sizes(segment_lengths: Sequence[int], handshake_size: int) -> np.ndarray:
    """End frame (exclusive) of every segment in DoubleTake's unfolded sequence.

    Segment ``i > 0`` shares its first ``handshake_size`` frames with the last ones of segment
    ``i - 1``, so ``step[0] = len_0`` and ``step[i] = step[i-1] + len_i - handshake_size``; the
    unfolded length is ``step[-1]``.
    """
    lens = [int(v) for v in segment_lengths]
    if not lens:
        raise ValueError("unfolded_step_sizes: segment_lengths must not be empty")
    if any(v <= 2 * handshake_size for v in lens[1:-1]) or any(v <= handshake_size for v in lens):
        raise ValueError(f"unfolded_step_sizes: every segment must be longer than the handshake "
                         f"(2x for inner segments); got lengths {lens}, handshake {handshake_size}")
    steps = np.zeros(len(lens), dtype=np.int64)
    steps[0] = lens[0]
    for i in range(1, len(lens)):
        steps[i] = steps[i - 1] + lens[i] - handshake_size
    return steps


def motion_transition_masks(segment_lengths: Sequence[int], handshake_size: int,
                            margin: int = 0, total_frames: Optional[int] = None
                            ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Frame masks ``(motion [T], transition [T])`` of DoubleTake's unfolded sequence.

    The transition window between segment ``i`` and ``i + 1`` is the handshake they share,
    ``[step_i - handshake, step_i)``, widened by ``margin // 2`` frames on each side (as
    priorMDM's ``--transition_margins`` does for its transition evaluation). Motion frames are
    all other frames of the sequence. ``T`` is ``total_frames`` or the unfolded length.
    """
    steps = unfolded_step_sizes(segment_lengths, handshake_size)
    T = int(steps[-1]) if total_frames is None else int(total_frames)
    transition = torch.zeros(T, dtype=torch.bool)
    for s in steps[:-1]:
        a = max(0, int(s) - handshake_size - margin // 2)
        b = min(T, int(s) + margin // 2)
        transition[a:b] = True
    motion = torch.zeros(T, dtype=torch.bool)
    motion[: min(T, int(steps[-1]))] = True
    motion &= ~transition
    return motion, transition


def doubletake_ees(motion: ArrayLike, segment_lengths: Sequence[int], handshake_size: int,
                   margin: int = 0, **kwargs) -> dict:
    """EES on the motion frames and on the transition frames of unfolded DoubleTake samples.

    ``motion``: ``[B, T, J, 3]`` / ``[B, T, D]`` unfolded sequences that all follow the
    ``segment_lengths`` layout (or ``[T, ...]`` for one). Returns
    ``{"motion": EES, "transition": EES, "all": EES}`` (cm/frame, floats).
    """
    pos = to_joint_positions(motion, kwargs.pop("mean", None), kwargs.pop("std", None))
    T = pos.shape[1]
    m, t = motion_transition_masks(segment_lengths, handshake_size, margin, total_frames=T)
    return {"motion": float(end_effector_speed(pos, frame_mask=m, **kwargs)),
            "transition": float(end_effector_speed(pos, frame_mask=t, **kwargs)),
            "all": float(end_effector_speed(pos, frame_mask=m | t, **kwargs))}
