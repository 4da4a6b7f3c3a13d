"""What VW measures: per-frame selection features from a motion representation.

* ``humanml3d``: ``x [B, N, 263]`` -> the 21 root-relative joint positions (features ``4:67``,
  metres) + frame index × ``frame_index_scale`` (metres per frame) -> ``[B, N, 64]``.
* ``kit``: ``x [B, N, 251]`` -> 20 × 3 positions (features ``4:64``, KIT's mm-scale units as
  stored) + index column -> ``[B, N, 61]``.
* ``raw``: ``x [B, N, D]`` itself + index column -> ``[B, N, D + 1]``.

HumanML3D layout per frame: root rotation velocity (1), root linear velocity xz (2), root y (1),
ric positions ((joints - 1) × 3), 6-D rotations ((joints - 1) × 6), local velocities
(joints × 3), foot contacts (4).
"""
from __future__ import annotations

from typing import Optional, Union

import numpy as np
import torch

KINDS = {"humanml3d": (263, 22), "kit": (251, 21)}  # kind -> (feature dim D, joints)
ArrayLike = Union[torch.Tensor, np.ndarray]


def ric_slice(kind: str) -> slice:
    """Slice of the root-relative joint positions in a ``kind`` feature vector."""
    _, joints = KINDS[kind]
    return slice(4, 4 + (joints - 1) * 3)


def from_mdm_layout(x: ArrayLike) -> torch.Tensor:
    """MDM layout ``[B, D, 1, N]`` -> batch-major ``[B, N, D]``."""
    x = torch.as_tensor(x)
    if x.dim() != 4 or x.shape[2] != 1:
        raise ValueError(f"from_mdm_layout: x must have MDM layout [B, D, 1, N], "
                         f"got shape {tuple(x.shape)}")
    return x[:, :, 0, :].permute(0, 2, 1)


def to_mdm_layout(x: ArrayLike) -> torch.Tensor:
    """Batch-major ``[B, N, D]`` -> MDM layout ``[B, D, 1, N]``."""
    x = torch.as_tensor(x)
    if x.dim() != 3:
        raise ValueError(f"to_mdm_layout: x must be [B, N, D], got shape {tuple(x.shape)}")
    return x.permute(0, 2, 1)[:, :, None, :]


def _stat(v: Optional[ArrayLike], name: str, D: int, ref: torch.Tensor) -> Optional[torch.Tensor]:
    if v is None:
        return None
    t = torch.as_tensor(v).to(device=ref.device, dtype=ref.dtype)
    if tuple(t.shape) != (D,):
        raise ValueError(f"extract_selection_features: {name} must have shape [D={D}], "
                         f"got {tuple(t.shape)}")
    return t


def extract_selection_features(x: ArrayLike, kind: str = "humanml3d",
                               mean: Optional[ArrayLike] = None, std: Optional[ArrayLike] = None,
                               frame_index_scale: float = 0.1) -> torch.Tensor:
    """Selection features ``[B, N, F]`` from motion ``x [B, N, D]`` (batch-major; use
    :func:`from_mdm_layout` for ``[B, D, 1, N]``). ``mean``/``std`` (``[D]``) de-normalise
    ``x`` first (``x * std + mean``); None means ``x`` is already un-normalised. The last
    column is ``frame index × frame_index_scale`` (metres per frame)."""
    if kind not in ("humanml3d", "kit", "raw"):
        raise ValueError(f"extract_selection_features: unknown kind {kind!r}; "
                         f"known: ('humanml3d', 'kit', 'raw')")
    x = torch.as_tensor(x)
    if x.dim() != 3:
        hint = " (MDM layout [B, D, 1, N]? use from_mdm_layout)" if x.dim() == 4 else ""
        raise ValueError(f"extract_selection_features: x must be 3-D [B, N, D], "
                         f"got shape {tuple(x.shape)}{hint}")
    if not x.dtype.is_floating_point:
        x = x.float()
    if not float(frame_index_scale) >= 0.0:
        raise ValueError(f"extract_selection_features: frame_index_scale must be >= 0 "
                         f"(metres per frame), got {frame_index_scale!r}")
    B, N, D = x.shape
    if kind != "raw" and D != KINDS[kind][0]:
        raise ValueError(f"extract_selection_features: x must have D={KINDS[kind][0]} features "
                         f"for kind={kind!r}, got D={D} (shape {tuple(x.shape)})")
    s, m = _stat(std, "std", D, x), _stat(mean, "mean", D, x)
    if s is not None:
        x = x * s
    if m is not None:
        x = x + m
    pos = x if kind == "raw" else x[..., ric_slice(kind)]
    idx = torch.arange(N, device=x.device, dtype=x.dtype) * float(frame_index_scale)
    return torch.cat([pos, idx[None, :, None].expand(B, N, 1)], dim=-1)
