"""Motion metrics on joint positions: End-Effector Speed (EES).

EES is the mean speed of the end effectors (both feet and both hands/wrists) in centimetres per
frame: for every valid frame ``n >= 1`` the displacement ``|p_j(n) - p_j(n-1)|`` of each end
effector ``j``, averaged over end effectors and frames. Jittery or "skating" transitions show up
as an EES far from the one of the motion around them; the paper's Table 3 reports it separately on
the transition windows of DoubleTake (see :mod:`smdm_plugin.metrics.doubletake`).

Inputs are either joint positions ``[B, N, J, 3]`` in metres (HumanML3D stores metres) or
HumanML3D 263-D feature vectors ``[B, N, 263]`` (un-normalised, or normalised with ``mean``/``std``
given), converted with :func:`smdm_plugin.io.humanml3d.recover_from_ric`.
"""
from __future__ import annotations

from typing import Optional, Sequence, Tuple, Union

import numpy as np
import torch

from ..io.humanml3d import recover_from_ric

ArrayLike = Union[torch.Tensor, np.ndarray]

#: HumanML3D 22-joint (SMPL order) end effectors: l_foot, r_foot, l_wrist, r_wrist.
HUMANML3D_END_EFFECTORS: Tuple[int, ...] = (10, 11, 20, 21)
#: KIT-ML 21-joint end effectors: l_foot, r_foot (toes), l_wrist, r_wrist.
KIT_END_EFFECTORS: Tuple[int, ...] = (15, 20, 7, 10)

# --------------------------------------------------------------------------- helpers
def _as_tensor(x: ArrayLike) -> torch.Tensor:
    if isinstance(x, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, torch.Tensor):
        return torch.as_tensor(np.asarray(x))
    return x


def to_joint_positions(motion: ArrayLike, mean: Optional[ArrayLike] = None,
                       std: Optional[ArrayLike] = None, joints_num: Optional[int] = None
                       ) -> torch.Tensor:
    """Joint positions ``[B, N, J, 3]`` (float) from positions ``[B, N, J, 3]`` / ``[N, J, 3]`` or
    features ``[B, N, D]`` / ``[N, D]`` (D = 263 or 251; normalised ones need ``mean``/``std``)."""
    x = _as_tensor(motion)
    x = x.float() if not torch.is_floating_point(x) else x
    if x.dim() >= 3 and x.shape[-1] == 3 and x.dim() in (3, 4):
        return x if x.dim() == 4 else x.unsqueeze(0)
    if x.dim() in (2, 3):
        if x.dim() == 2:
            x = x.unsqueeze(0)
        D = x.shape[-1]
        if joints_num is None:
            joints_num = {263: 22, 251: 21}.get(D)
            if joints_num is None:
                raise ValueError(f"to_joint_positions: cannot infer the joint count from D={D}; "
                                 "pass joints_num or give positions [B, N, J, 3]")
        if std is not None:
            x = x * _as_tensor(std).to(x)
        if mean is not None:
            x = x + _as_tensor(mean).to(x)
        return recover_from_ric(x, joints_num)
    raise ValueError(f"to_joint_positions: motion must be positions [B, N, J, 3] or features "
                     f"[B, N, D], got shape {tuple(x.shape)}")


# --------------------------------------------------------------------------- EES
def end_effector_speed(motion: ArrayLike, lengths: Optional[ArrayLike] = None,
                       frame_mask: Optional[ArrayLike] = None,
                       joints: Sequence[int] = HUMANML3D_END_EFFECTORS,
                       mean: Optional[ArrayLike] = None, std: Optional[ArrayLike] = None,
                       unit_scale: float = 100.0, reduce: str = "mean") -> torch.Tensor:
    """End-Effector Speed in cm/frame (with the default ``unit_scale=100`` for metres).

    Args:
        motion: joint positions ``[B, N, J, 3]`` (metres) or HumanML3D/KIT features ``[B, N, D]``.
        lengths: ``[B]`` valid frames per sample (None: all ``N``).
        frame_mask: bool ``[B, N]`` or ``[N]``: frames whose speed counts. The speed of frame
            ``n`` is the displacement from ``n - 1`` to ``n``, so frame 0 never counts.
        joints: end-effector joint indices (default HumanML3D feet 10, 11 and wrists 20, 21).
        mean, std: de-normalisation of feature input.
        reduce: ``"mean"`` (one number over all counted frames of the batch) or ``"none"``
            (per sample ``[B]``; NaN where a sample has no counted frame).
    """
    pos = to_joint_positions(motion, mean, std)
    B, N = pos.shape[:2]
    if max(joints) >= pos.shape[2]:
        raise ValueError(f"end_effector_speed: joints {tuple(joints)} out of range for "
                         f"J={pos.shape[2]} joints")
    ee = pos[:, :, list(joints)]
    speed = torch.zeros(B, N, dtype=pos.dtype, device=pos.device)
    speed[:, 1:] = (ee[:, 1:] - ee[:, :-1]).norm(dim=-1).mean(dim=-1) * unit_scale
    valid = torch.zeros(B, N, dtype=torch.bool, device=pos.device)
    valid[:, 1:] = True
    if lengths is not None:
        L = _as_tensor(lengths).to(pos.device).long().reshape(-1)
        if L.shape[0] != B:
            raise ValueError(f"end_effector_speed: lengths must be [B]=[{B}], got {tuple(L.shape)}")
        valid &= torch.arange(N, device=pos.device)[None] < L[:, None]
    if frame_mask is not None:
        fm = _as_tensor(frame_mask).to(pos.device).bool()
        if fm.dim() == 1:
            fm = fm.unsqueeze(0).expand(B, -1)
        if fm.shape != (B, N):
            raise ValueError(f"end_effector_speed: frame_mask must be [B, N]=[{B}, {N}] or [N], "
                             f"got {tuple(fm.shape)}")
        valid &= fm
    w = valid.to(speed.dtype)
    if reduce == "none":
        return (speed * w).sum(1) / w.sum(1)
    if reduce != "mean":
        raise ValueError(f"end_effector_speed: reduce must be 'mean' or 'none', got {reduce!r}")
    return (speed * w).sum() / w.sum().clamp_min(1.0)
