"""Small BVH reader and forward kinematics (tests, demo, keyframe studies on real motion).

Conventions: BVH rotation channels are Euler angles in degrees, applied intrinsically in the
order listed (``Zrotation Yrotation Xrotation`` -> ``R = Rz @ Ry @ Rx``). A joint's world
position is ``parent_pos + parent_R @ (offset + translation)``; its world rotation is
``parent_R @ R``. Lengths are in file units unless scaled (CMU: × 0.056444 = metres).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Sequence, Tuple, Union

import numpy as np

CMU_TO_METRES = 0.056444  # (1 / 0.45) * 2.54 / 100, CMU's FAQ

# HumanML3D 22-joint order; a tuple of CMU names is a synthesised midpoint
HUMANML22_FROM_CMU: Tuple[Union[str, Tuple[str, str]], ...] = (
    "Hips", "LeftUpLeg", "RightUpLeg", "Spine", "LeftLeg", "RightLeg", ("Spine", "Spine1"),
    "LeftFoot", "RightFoot", "Spine1", "LeftToeBase", "RightToeBase", "Neck1",
    ("Spine1", "LeftArm"), ("Spine1", "RightArm"), "Head", "LeftArm", "RightArm",
    "LeftForeArm", "RightForeArm", "LeftHand", "RightHand",
)


@dataclass
class BVH:
    """Parsed BVH. ``offsets [J, 3]`` (file units), ``channels[j]`` the channel names of joint
    ``j`` (e.g. ``["Zrotation", "Yrotation", "Xrotation"]``), ``motion [T, C]`` with the
    channels of all joints in hierarchy order, ``frame_time`` in seconds. ``end_sites`` lists
    ``(parent joint, offset [3])``; End Sites are not joints."""

    names: List[str]
    parents: List[int]
    offsets: np.ndarray
    channels: List[List[str]]
    frame_time: float
    motion: np.ndarray
    end_sites: List[Tuple[int, np.ndarray]] = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time


_VALID_CHANNELS = {"Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation"}


def read_bvh(path: Union[str, Path]) -> BVH:
    """Read a BVH file (LF or CRLF line endings, End Sites)."""
    text = Path(path).read_text()
    head, sep, motion_text = text.partition("MOTION")
    if not sep:
        raise ValueError(f"read_bvh: {path}: no MOTION section")
    tok = head.split()
    if not tok or tok[0] != "HIERARCHY":
        raise ValueError(f"read_bvh: {path}: file must start with HIERARCHY")
    names: List[str] = []
    parents: List[int] = []
    offsets: List[List[float]] = []
    channels: List[List[str]] = []
    end_sites: List[Tuple[int, np.ndarray]] = []
    stack: List[int] = []          # joint index per open brace (-2 for an End Site)
    pending: int = -1              # joint / End Site opened by the next "{"
    i = 1
    while i < len(tok):
        t = tok[i]
        if t in ("ROOT", "JOINT"):
            if t == "ROOT" and stack:
                raise ValueError(f"read_bvh: {path}: ROOT inside another joint")
            parent = next((s for s in reversed(stack) if s >= 0), -1)
            names.append(tok[i + 1])
            parents.append(parent)
            offsets.append([0.0, 0.0, 0.0])
            channels.append([])
            pending = len(names) - 1
            i += 2
        elif t == "End":
            if i + 1 >= len(tok) or tok[i + 1] != "Site":
                raise ValueError(f"read_bvh: {path}: expected 'End Site'")
            parent = next((s for s in reversed(stack) if s >= 0), -1)
            end_sites.append((parent, np.zeros(3)))
            pending = -2
            i += 2
        elif t == "{":
            stack.append(pending)
            i += 1
        elif t == "}":
            if not stack:
                raise ValueError(f"read_bvh: {path}: unbalanced braces in HIERARCHY")
            stack.pop()
            i += 1
        elif t == "OFFSET":
            vals = [float(v) for v in tok[i + 1:i + 4]]
            if not stack:
                raise ValueError(f"read_bvh: {path}: OFFSET outside a joint")
            if stack[-1] == -2:
                end_sites[-1] = (end_sites[-1][0], np.array(vals))
            else:
                offsets[stack[-1]] = vals
            i += 4
        elif t == "CHANNELS":
            n = int(tok[i + 1])
            ch = tok[i + 2:i + 2 + n]
            bad = [c for c in ch if c not in _VALID_CHANNELS]
            if bad or not stack or stack[-1] < 0:
                raise ValueError(f"read_bvh: {path}: bad CHANNELS {ch}")
            channels[stack[-1]] = ch
            i += 2 + n
        else:
            raise ValueError(f"read_bvh: {path}: unexpected token {t!r} in HIERARCHY")
    if stack:
        raise ValueError(f"read_bvh: {path}: unbalanced braces in HIERARCHY")
    if not names:
        raise ValueError(f"read_bvh: {path}: no joints")

    mtok = motion_text.split()
    try:
        fi = mtok.index("Frames:")
        n_frames = int(mtok[fi + 1])
        if mtok[fi + 2:fi + 4] != ["Frame", "Time:"]:
            raise ValueError
        frame_time = float(mtok[fi + 4])
    except (ValueError, IndexError):
        raise ValueError(f"read_bvh: {path}: MOTION needs 'Frames: n' and 'Frame Time: t'")
    n_ch = sum(len(c) for c in channels)
    values = np.array(mtok[fi + 5:], dtype=np.float64)
    if values.size != n_frames * n_ch:
        raise ValueError(f"read_bvh: {path}: expected {n_frames} frames × {n_ch} channels = "
                         f"{n_frames * n_ch} values, got {values.size}")
    return BVH(names, parents, np.array(offsets, dtype=np.float64), channels, frame_time,
               values.reshape(n_frames, n_ch), end_sites)


def _axis_rotation(axis: str, deg: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[T, 3, 3]`` about ``axis`` ('X', 'Y' or 'Z') by ``deg`` degrees."""
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    if axis == "X":
        m = [[o, z, z], [z, c, -s], [z, s, c]]
    elif axis == "Y":
        m = [[c, z, s], [z, o, z], [-s, z, c]]
    else:
        m = [[c, -s, z], [s, c, z], [z, z, o]]
    return np.stack([np.stack(r, -1) for r in m], -2)


def bvh_joint_positions(bvh: BVH, scale: float = 1.0) -> np.ndarray:
    """World joint positions ``[T, J, 3]`` (file units × ``scale``) by forward kinematics."""
    T = bvh.num_frames
    J = len(bvh.names)
    pos = np.zeros((T, J, 3))
    rot = np.zeros((T, J, 3, 3))
    col = 0
    for j in range(J):
        R = np.broadcast_to(np.eye(3), (T, 3, 3))
        trans = np.zeros((T, 3))
        for c in bvh.channels[j]:
            v = bvh.motion[:, col]
            col += 1
            if c.endswith("rotation"):
                R = R @ _axis_rotation(c[0], v)
            else:
                trans[:, "XYZ".index(c[0])] = v
        local = bvh.offsets[j][None] + trans
        p = bvh.parents[j]
        if p < 0:
            pos[:, j], rot[:, j] = local, R
        else:
            pos[:, j] = pos[:, p] + np.einsum("tij,tj->ti", rot[:, p], local)
            rot[:, j] = rot[:, p] @ R
    return pos * scale


def cmu_to_humanml22(positions: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """CMU (cgspeed MotionBuilder-friendly) joints ``[T, J, 3]`` -> HumanML3D 22-joint order
    ``[T, 22, 3]``; spine2 and the two collars are midpoints (see the cmu-humanml3d README)."""
    positions = np.asarray(positions)
    if positions.ndim != 3 or positions.shape[1:] != (len(names), 3):
        raise ValueError(f"cmu_to_humanml22: positions must be [T, J={len(names)}, 3], "
                         f"got {positions.shape}")
    where = {n: k for k, n in enumerate(names)}
    missing = sorted({n for e in HUMANML22_FROM_CMU for n in ((e,) if isinstance(e, str) else e)}
                     - set(where))
    if missing:
        raise ValueError(f"cmu_to_humanml22: names lack CMU joints {missing}")
    out = [positions[:, where[e]] if isinstance(e, str)
           else 0.5 * (positions[:, where[e[0]]] + positions[:, where[e[1]]])
           for e in HUMANML22_FROM_CMU]
    return np.stack(out, 1)


def load_cmu_clip(path: Union[str, Path], fps: int = 20, drop_first: bool = True) -> np.ndarray:
    """A CMU BVH clip as HumanML3D-ordered joints ``[T, 22, 3]`` in metres at ``fps``: frame 0
    (the converter's synthetic T-pose) dropped, then every ``round(file_fps / fps)``-th frame
    (120 -> 20 fps: file frames 1, 7, 13, ...)."""
    bvh = read_bvh(path)
    step = max(1, int(round(bvh.fps / fps)))
    pos = bvh_joint_positions(bvh, scale=CMU_TO_METRES)
    pos = pos[1:] if drop_first else pos
    return cmu_to_humanml22(pos[::step], bvh.names)


def root_relative_features(joints22: np.ndarray, frame_index_scale: float = 0.1) -> np.ndarray:
    """Selection features ``[..., T, 64]`` from joints ``[..., T, 22, 3]`` (metres): joints
    1..21 minus the root, flattened (63), plus ``frame index × frame_index_scale`` (m/frame)."""
    j = np.asarray(joints22, dtype=np.float64)
    if j.ndim < 3 or j.shape[-2:] != (22, 3):
        raise ValueError(f"root_relative_features: joints22 must be [..., T, 22, 3], "
                         f"got {j.shape}")
    rel = (j[..., 1:, :] - j[..., :1, :]).reshape(*j.shape[:-2], 63)
    T = j.shape[-3]
    idx = np.broadcast_to((np.arange(T) * float(frame_index_scale))[:, None],
                          (*j.shape[:-3], T, 1))
    return np.concatenate([rel, idx], -1)
