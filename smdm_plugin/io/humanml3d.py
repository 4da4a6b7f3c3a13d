"""HumanML3D / KIT-ML: the folder layout (:func:`load_humanml3d`, the one reader of it) and the
feature vectors (decoding joint positions, ``recover_from_ric``).

Folder layout: ``Mean.npy`` / ``Std.npy`` ``[D]``, ``<split>.txt`` (motion ids),
``new_joint_vecs/<id>.npy`` ``[T, D]`` features, optionally ``new_joints/<id>.npy`` ``[T, 22, 3]``
(metres) and ``texts/<id>.txt`` (captions, io/captions.py), all at 20 fps.

HumanML3D layout per frame (263-D for 22 joints, 251-D for KIT's 21): root rotation velocity (1),
root linear velocity xz (2), root y (1), ric positions ((joints - 1) x 3), 6-D rotations
((joints - 1) x 6), local velocities (joints x 3), foot contacts (4).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Tuple, Union

import numpy as np
import torch

from .captions import Caption, read_captions

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


# --------------------------------------------------------------------------- the folder layout
@dataclass
class HumanML3DSplit:
    """One split of a HumanML3D-format folder as read (features not normalised): ``ids`` (M names),
    ``motions`` (per motion ``[L_i, D]`` float32, cut to ``max_frames``), ``mean``/``std`` ``[D]``,
    ``joints`` (``joints=True``: per motion ``[L_i, 22, 3]`` metres, None where ``new_joints/<id>.npy``
    is absent), ``captions`` (``captions=True``: per motion its :class:`Caption` s, empty where
    ``texts/<id>.txt`` is absent), ``files`` (every file read, for a fingerprint)."""

    root: str
    split: str
    ids: List[str]
    motions: List[np.ndarray]
    mean: np.ndarray
    std: np.ndarray
    max_frames: Optional[int]
    joints: Optional[List[Optional[np.ndarray]]] = None
    captions: Optional[List[List[Caption]]] = None
    files: List[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.ids)


def load_humanml3d(root: str, split: str = "train", max_frames: Optional[int] = 196, min_frames: int = 40,
                   joints: bool = False, captions: bool = False) -> HumanML3DSplit:
    """The ``split`` (``<root>/<split>.txt``) of a HumanML3D-format folder, every file checked
    (shape ``[T, D]`` with ``D`` from ``Mean.npy``, finite values, std > 0): ids whose
    ``new_joint_vecs/<id>.npy`` is absent or shorter than ``min_frames`` are skipped, longer motions
    cut to their first ``max_frames`` frames (None: kept whole). Errors name the file:
    ``FileNotFoundError`` (not such a folder), ``ValueError`` (a bad file, no motion left)."""
    from .validate import check_array, check_magnitude, check_stats, load_npy

    base = Path(root)
    missing = [n for n in ("Mean.npy", "Std.npy", "new_joint_vecs", f"{split}.txt") if not (base / n).exists()]
    if missing:
        raise FileNotFoundError(f"data: {root} is not a HumanML3D-format folder (missing {', '.join(missing)})")
    if not 2 <= min_frames <= (min_frames if max_frames is None else max_frames):
        raise ValueError(f"load_humanml3d: need 2 <= min_frames <= max_frames, got {min_frames}, {max_frames}")

    def npy(path: Path, what: str) -> np.ndarray:
        try:
            return load_npy(str(path), what)
        except ValueError as e:
            raise ValueError(f"data: {e}") from None

    mean = npy(base / "Mean.npy", "feature mean")
    std = npy(base / "Std.npy", "feature std")
    if mean.ndim != 1:
        raise ValueError(f"data: {base / 'Mean.npy'}: expected a vector [D], got shape {list(mean.shape)}")
    D = mean.shape[0]
    mean, _ = check_stats(mean, np.ones(D), D, f"data: {base / 'Mean.npy'}")
    _, std = check_stats(mean, std, D, f"data: {base / 'Std.npy'}")
    listing = base / f"{split}.txt"
    try:
        names = listing.read_bytes().decode("utf-8-sig").split()
    except UnicodeDecodeError as e:
        raise ValueError(f"data: {listing}: not UTF-8 text (byte {e.start}: {e.reason})") from None
    except IsADirectoryError:
        raise ValueError(f"data: {listing}: is a folder, expected a text file") from None
    files = [str(base / "Mean.npy"), str(base / "Std.npy"), str(listing)]
    out = HumanML3DSplit(str(root), split, [], [], mean.astype(np.float32), std.astype(np.float32), max_frames,
                         [] if joints else None, [] if captions else None, files)
    cut = slice(None, max_frames)
    for name in names:
        path = base / "new_joint_vecs" / f"{name}.npy"
        if not path.exists():
            continue
        files.append(str(path))
        # checked before the first step: a bad file is one line naming it, not a nan loss later
        motion = check_magnitude(check_array(npy(path, "motion features [T, D]"), f"data: {path}", "motion", (-1, D)),
                                 f"data: {path}", "motion features")
        if len(motion) < min_frames:
            continue
        out.ids.append(name)
        out.motions.append(np.asarray(motion, np.float32)[cut])
        if joints:
            jpath = base / "new_joints" / f"{name}.npy"
            if jpath.exists():
                files.append(str(jpath))
            out.joints.append(check_magnitude(check_array(npy(jpath, "joint positions [T, J, 3]"), f"data: {jpath}",
                                                          "joints"), f"data: {jpath}", "joint positions")[cut]
                              .astype(np.float32) if jpath.exists() else None)
        if captions:
            tpath = base / "texts" / f"{name}.txt"
            if tpath.is_file():
                files.append(str(tpath))
            out.captions.append(read_captions(str(tpath)) if tpath.is_file() else [])
    if not out.ids:
        raise ValueError(f"data: split {split!r} of {root} has no motion of >= {min_frames} frames")
    return out
