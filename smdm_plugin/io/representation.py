"""Motion representations of the in-package models: what one frame's feature vector holds, and the
way to and from joint positions (HumanML3D's 22 joints, metres, y up)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Union

import numpy as np
import torch

from .humanml3d import recover_from_ric

ArrayLike = Union[np.ndarray, torch.Tensor]

JOINTS = 22
REPRESENTATIONS = ("joints66", "humanml3d")


def _check_joints(fn: str, joints: ArrayLike) -> None:
    if joints.ndim < 2 or tuple(joints.shape[-2:]) != (JOINTS, 3):
        raise ValueError(f"{fn}: joints must be [..., N, {JOINTS}, 3] (metres), got {tuple(joints.shape)}")


def joints_to_joints66(joints: ArrayLike) -> ArrayLike:
    """``[..., N, 22, 3]`` joint positions -> ``[..., N, 66]`` ``joints66`` features (same type)."""
    _check_joints("joints_to_joints66", joints)
    cat = np.concatenate if isinstance(joints, np.ndarray) else torch.cat
    root = joints[..., 0, :]
    rel = (joints[..., 1:, :] - root[..., None, :]).reshape(*joints.shape[:-2], 63)
    return cat([rel, root[..., 1:2], root[..., 0:1], root[..., 2:3]], -1)


def joints66_to_joints(features: ArrayLike) -> ArrayLike:
    """``[..., N, 66]`` ``joints66`` features -> ``[..., N, 22, 3]`` joint positions (exact inverse)."""
    if features.shape[-1] != 66:
        raise ValueError(f"joints66_to_joints: features must be [..., N, 66], got {tuple(features.shape)}")
    stack = np.stack if isinstance(features, np.ndarray) else torch.stack
    cat = np.concatenate if isinstance(features, np.ndarray) else torch.cat
    root = stack([features[..., 64], features[..., 63], features[..., 65]], -1)
    rel = features[..., :63].reshape(*features.shape[:-1], 21, 3)
    return cat([root[..., None, :], rel + root[..., None, :]], -2)


def canonical_xz(joints: ArrayLike, frame: int = 0) -> ArrayLike:
    """``joints`` ``[..., N, 22, 3]`` moved on the floor so that the root's x, z at ``frame`` is 0."""
    _check_joints("canonical_xz", joints)
    offset = joints[..., frame:frame + 1, 0:1, :] * 1.0
    offset[..., 1] = 0.0
    return joints - offset


@dataclass(frozen=True)
class Representation:
    """A model's per-frame features: ``name`` (one of :data:`REPRESENTATIONS`) and ``dim``."""

    name: str

    def __post_init__(self) -> None:
        if self.name not in REPRESENTATIONS:
            raise ValueError(f"Representation: name must be one of {REPRESENTATIONS}, got {self.name!r}")

    @property
    def dim(self) -> int:
        return {"joints66": 66, "humanml3d": 263}[self.name]

    def to_joints(self, features: ArrayLike) -> ArrayLike:
        """Un-normalised features ``[..., N, dim]`` -> joint positions ``[..., N, 22, 3]`` (metres)."""
        if features.shape[-1] != self.dim:
            raise ValueError(f"{self.name} features must be [..., N, {self.dim}], got {tuple(features.shape)}")
        if self.name == "joints66":
            return joints66_to_joints(features)
        return recover_from_ric(features, JOINTS)

    def from_joints(self, joints: ArrayLike) -> ArrayLike:
        """Joint positions ``[..., N, 22, 3]`` -> features ``[..., N, dim]``, where possible."""
        if self.name == "joints66":
            return joints_to_joints66(joints)
        raise ValueError("HumanML3D 263-D features cannot be computed from joint positions here (HumanML3D's "
                         "processing fits rotations and foot contacts); give the keyframes as 263-D features "
                         "(.npy [N, 263], e.g. new_joint_vecs/<id>.npy) or use a joints66 model "
                         "(smdm demo trains one from BVH files)")
