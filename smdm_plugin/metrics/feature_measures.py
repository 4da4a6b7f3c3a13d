"""Measures of normalised HumanML3D features ``[B, N, 263]`` (what a model trained on them
outputs): End-Effector Speed, jitter and foot skating of the decoded joints, and the error of
interpolating joints from the keyframes a sparse config picks (``smdm ablate``'s columns)."""
from __future__ import annotations

from typing import Any, Dict, Optional, Sequence

import numpy as np
import torch

from .motion import ArrayLike, end_effector_speed, to_joint_positions
from .quality import foot_skating_ratio, jitter, mean_speed


def feature_quality(motion: torch.Tensor, lengths: torch.Tensor, mean: ArrayLike, std: ArrayLike,
                    fps: float = 20.0) -> Dict[str, float]:
    """``{'ees': cm/frame, 'jitter': m/s³, 'foot_skating': ratio}`` of normalised features
    ``motion [B, N, 263]`` with ``lengths [B]`` valid frames, on the joints ``recover_from_ric`` gives
    after de-normalising with ``mean``/``std`` ``[263]``."""
    ees = float(end_effector_speed(motion, lengths, mean=mean, std=std))
    j = to_joint_positions(motion.float(), mean, std)
    L = lengths.long().cpu()
    return {"ees": ees, "jitter": float(jitter(j, fps=fps, lengths=L)),
            "foot_skating": float(foot_skating_ratio(j, fps=fps, lengths=L))}


def per_motion_quality(norm: torch.Tensor, lengths: torch.Tensor, mean: ArrayLike, std: ArrayLike,
                       fps: float = 20.0) -> Dict[str, np.ndarray]:
    """Per motion ``[M]``: jitter (m/s³), mean joint speed (m/s), jitter per unit speed (1/s²) and
    foot skating ratio (``smdm ablate --config quality_compute``) of normalised features ``norm [M, N, 263]`` with valid ``lengths [M]``."""
    j = to_joint_positions(norm.float(), mean, std)  # [M, N, 22, 3]
    L = lengths.long()
    jit = jitter(j, fps=fps, lengths=L, reduce="none").double()
    speed = mean_speed(j, fps=fps, lengths=L, reduce="none").double()
    skate = foot_skating_ratio(j, fps=fps, lengths=L, reduce="none").double()
    return {"jitter": jit.numpy(), "speed": speed.numpy(), "jitter_per_speed": (jit / speed.clamp_min(1e-6)).numpy(),
            "foot_skating": skate.numpy()}


def keyframe_interpolation_error_mm(motion: torch.Tensor, lengths: torch.Tensor,
                                    joints: Sequence[Optional[np.ndarray]], mean: ArrayLike, std: ArrayLike,
                                    config: Any, limit: Optional[int] = None, seed: int = 0) -> Optional[float]:
    """Mean joint position error (mm) of linearly interpolating each motion's joints
    (``joints[b]``: ``[L_b, 22, 3]`` metres, None: skipped) from the keyframes ``config`` (a
    ``SparseConfig``; its selector and reduction, no mask noise) picks on the normalised features
    ``motion [M, N, 263]`` (``lengths [M]``); the first ``limit`` motions (None: all). None when
    ``config`` is None (dense) or no motion has joints."""
    if config is None:
        return None
    from ..core.interpolation import interpolate_keyframes
    from ..core.schedule import MaskSchedule
    from ..core.selection import select_keyframes

    sched = MaskSchedule(config.replace(mask_noise=0.0), mean, std)
    n = len(lengths) if limit is None else min(limit, len(lengths))
    errs = []
    g = torch.Generator().manual_seed(seed)
    for b in range(n):
        j = joints[b]
        if j is None:
            continue
        L = int(lengths[b])
        mask = select_keyframes(sched.features(motion[b:b + 1, :L]), torch.tensor([L]), config.reduction,
                                config.selector, generator=g)
        rec = interpolate_keyframes(torch.from_numpy(j).reshape(1, L, -1).double(), mask).reshape(L, -1, 3)
        errs.append(float((rec.numpy() - j).__pow__(2).sum(-1).__pow__(0.5).mean() * 1000.0))
    return float(np.mean(errs)) if errs else None
