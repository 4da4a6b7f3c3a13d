"""Motion metrics: End-Effector Speed (EES) and the motion/transition split of DoubleTake.

EES is the mean speed of the end effectors (both feet and both hands/wrists) in centimetres per
frame: for every valid frame ``n >= 1`` the displacement ``|p_j(n) - p_j(n-1)|`` of each end
effector ``j``, averaged over end effectors and frames. Jittery or "skating" transitions show up
as an EES far from the one of the motion around them; the paper's Table 3 reports it separately on
the transition windows of DoubleTake (the handshake frames shared between neighbouring segments)
and on the rest of the long sequence.

Inputs are either joint positions ``[B, N, J, 3]`` in metres (HumanML3D stores metres) or
HumanML3D 263-D feature vectors ``[B, N, 263]`` (un-normalised, or normalised with ``mean``/``std``
given), converted with :func:`recover_from_ric`.
"""
from __future__ import annotations

from typing import Optional, Sequence, Tuple, Union

import numpy as np
import torch

ArrayLike = Union[torch.Tensor, np.ndarray]

#: HumanML3D 22-joint (SMPL order) end effectors: l_foot, r_foot, l_wrist, r_wrist.
HUMANML3D_END_EFFECTORS: Tuple[int, ...] = (10, 11, 20, 21)
#: KIT-ML 21-joint end effectors: l_foot, r_foot (toes), l_wrist, r_wrist.
KIT_END_EFFECTORS: Tuple[int, ...] = (15, 20, 7, 10)


# --------------------------------------------------------------------------- quaternions
def _qinv(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (inverse of a unit quaternion), ``(w, x, y, z)`` convention."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def _qrot(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors ``v [..., 3]`` by unit quaternions ``q [..., 4]`` (broadcast)."""
    q, v = torch.broadcast_tensors(q, torch.cat([v[..., :1], v], dim=-1))
    v = v[..., 1:]
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * torch.cross(u, v, dim=-1)
    return v + w * t + torch.cross(u, t, dim=-1)


# --------------------------------------------------------------------------- recover_from_ric
def recover_root(data: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Root rotation (quaternion about +Y) and root position per frame from HumanML3D features.

    Feature 0 is the root's angular velocity about Y (rad/frame), features 1-2 its XZ velocity
    expressed in the root's facing frame, feature 3 its height. The heading and the XZ path are
    integrated from the velocities of the *previous* frames, so frame 0 faces +Z at the origin.
    Returns ``quat [..., N, 4]`` and ``pos [..., N, 3]``.
    """
    ang_vel = data[..., 0]
    heading = torch.zeros_like(ang_vel)
    heading[..., 1:] = ang_vel[..., :-1]
    heading = torch.cumsum(heading, dim=-1)
    quat = torch.zeros(data.shape[:-1] + (4,), dtype=data.dtype, device=data.device)
    quat[..., 0] = torch.cos(heading)
    quat[..., 2] = torch.sin(heading)

    step = torch.zeros(data.shape[:-1] + (3,), dtype=data.dtype, device=data.device)
    step[..., 1:, 0] = data[..., :-1, 1]
    step[..., 1:, 2] = data[..., :-1, 2]
    step = _qrot(_qinv(quat), step)  # local -> world
    pos = torch.cumsum(step, dim=-2)
    pos[..., 1] = data[..., 3]
    return quat, pos


def recover_from_ric(data: ArrayLike, joints_num: int = 22) -> ArrayLike:
    """Global joint positions ``[..., N, joints_num, 3]`` from HumanML3D/KIT features
    ``[..., N, D]`` (D = 263 for 22 joints, 251 for 21).

    Features ``4 : 4 + 3 (J - 1)`` hold the non-root joints relative to the root, in the root's
    facing frame and without the root's XZ translation; they are rotated back to the world frame
    and shifted by the root's XZ position. Returns the same type (numpy or torch) as ``data``.
    """
    is_np = isinstance(data, np.ndarray)
    x = torch.from_numpy(data) if is_np else data
    need = 4 + 3 * (joints_num - 1)
    if x.shape[-1] < need:
        raise ValueError(f"recover_from_ric: data must be [..., N, D] with D >= {need} for "
                         f"joints_num={joints_num}, got shape {tuple(x.shape)}")
    if not torch.is_floating_point(x):
        x = x.float()
    quat, root = recover_root(x)
    local = x[..., 4:need].reshape(x.shape[:-1] + (joints_num - 1, 3))
    world = _qrot(_qinv(quat)[..., None, :], local)
    world = world + torch.stack([root[..., 0], torch.zeros_like(root[..., 0]), root[..., 2]],
                                dim=-1)[..., None, :]
    out = torch.cat([root[..., None, :], world], dim=-2)
    return out.numpy() if is_np else out


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
