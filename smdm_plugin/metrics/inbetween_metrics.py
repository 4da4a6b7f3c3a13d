"""In-betweening metrics on joint positions (metres), built on :mod:`.quality` (no metric math of
their own): where the transitions between given and generated frames are, and one dict of keyframe
error, jitter (overall and at the transitions), foot skating and the in-between error."""
from __future__ import annotations

from typing import Dict, Optional, Sequence

import numpy as np
import torch

from .quality import foot_skating_ratio, jitter, keyframe_error

__all__ = ["transition_frames", "keyframe_metrics"]


def transition_frames(given: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """bool ``[B, N]``: the frames on both sides of every change between given and generated frames
    within the length — where the transitions are. An isolated keyframe: it and its two neighbours."""
    B, N = given.shape
    valid = torch.arange(N)[None] < lengths[:, None]
    change = (given[:, 1:] != given[:, :-1]) & valid[:, 1:]
    out = torch.zeros_like(given)
    out[:, 1:] |= change
    out[:, :-1] |= change
    return out & valid


def keyframe_metrics(joints: np.ndarray, target: np.ndarray, given: np.ndarray, fps: float = 20.0,
                     lengths: Optional[Sequence[int]] = None, reference: bool = False,
                     global_error: bool = True) -> Dict[str, float]:
    """Metrics of in-betweens ``joints [S, N, J, 3]`` (metres) with keyframes ``given`` (bool ``[N]``
    or ``[S, N]``) taken from ``target`` (``[N, J, 3]`` or ``[S, N, J, 3]``), over ``lengths`` valid
    frames (None: all): keyframe error (mm, CondMDI's, global — unless ``global_error`` is False,
    when the target's global positions are unknown — and root-relative), jitter at the transitions
    (:func:`transition_frames`) and overall (m/s³, DNO's), foot skating ratio (GMD's). With
    ``reference`` (the target is the real motion everywhere): the in-between frames' mean joint
    error (mm) and the target's own jitter and foot skating."""
    S, N = joints.shape[:2]
    j = torch.as_tensor(np.asarray(joints, np.float64))
    t = torch.as_tensor(np.asarray(target, np.float64)).expand_as(j)
    g = torch.as_tensor(np.asarray(given, bool)).expand(S, N)
    L = torch.full((S,), N, dtype=torch.long) if lengths is None else torch.as_tensor(lengths).long().reshape(S)
    rel = lambda x: x - x[:, :, :1]  # noqa: E731
    kf = [row.nonzero().flatten().tolist() for row in g]
    m = {"keyframe_error_root_relative_mm": 1000 * float(keyframe_error(rel(j), rel(t), kf, fps=fps, lengths=L))}
    if global_error:
        m["keyframe_error_mm"] = 1000 * float(keyframe_error(j, t, kf, fps=fps, lengths=L))
    if int(L.min()) >= 4:
        trans = transition_frames(g, L)
        m["jitter_transitions"] = float(jitter(j, fps=fps, lengths=L, frame_mask=trans))
        m["jitter"] = float(jitter(j, fps=fps, lengths=L))
        if reference:
            m["reference_jitter_transitions"] = float(jitter(t, fps=fps, lengths=L, frame_mask=trans))
            m["reference_jitter"] = float(jitter(t, fps=fps, lengths=L))
    m["foot_skating"] = float(foot_skating_ratio(j, fps=fps, lengths=L))
    if reference:
        m["reference_foot_skating"] = float(foot_skating_ratio(t, fps=fps, lengths=L))
        between = (torch.arange(N)[None] < L[:, None]) & ~g
        if bool(between.any()):
            m["inbetween_error_mm"] = 1000 * float((j - t).norm(dim=-1).mean(-1)[between].mean())
    return m
