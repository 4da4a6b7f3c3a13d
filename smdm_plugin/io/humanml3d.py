"""HumanML3D / KIT-ML feature vectors: decoding joint positions (``recover_from_ric``).

HumanML3D layout per frame (263-D for 22 joints, 251-D for KIT's 21): root rotation velocity (1),
root linear velocity xz (2), root y (1), ric positions ((joints - 1) x 3), 6-D rotations
((joints - 1) x 6), local velocities (joints x 3), foot contacts (4).
"""
from __future__ import annotations

from typing import Tuple, Union

import numpy as np
import torch

ArrayLike = Union[torch.Tensor, np.ndarray]

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
