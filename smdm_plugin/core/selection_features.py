"""What VW measures: per-frame selection features from a motion representation."""
from __future__ import annotations

from typing import NamedTuple, Optional, Union

import numpy as np
import torch

KINDS = {"humanml3d": (263, 22), "kit": (251, 21)}  # kind -> (feature dim D, joints)
FEATURE_KINDS = ("humanml3d", "kit", "raw", "joints")
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


def _stat(v: Optional[ArrayLike], name: str, D: int) -> Optional[torch.Tensor]:
    if v is None:
        return None
    t = torch.as_tensor(np.asarray(v) if not isinstance(v, torch.Tensor) else v)
    if tuple(t.shape) != (D,):
        raise ValueError(f"extract_selection_features: {name} must have shape [D={D}], "
                         f"got {tuple(t.shape)}")
    return t


class SelectionConstants(NamedTuple):
    """What :func:`apply_selection_constants` needs for one ``(kind, N, D, device, dtype)``: the
    feature columns read, their ``mean``/``std`` (None: not de-normalised), whether positions are
    made root-relative (``joints``), and the frame-index column ``[1, N, 1]``."""

    cols: slice
    mean: Optional[torch.Tensor]
    std: Optional[torch.Tensor]
    root_relative: bool
    index: torch.Tensor


def selection_constants(kind: str, N: int, D: int, mean: Optional[ArrayLike] = None, std: Optional[ArrayLike] = None,
                        frame_index_scale: float = 0.1, device: Union[torch.device, str] = "cpu",
                        dtype: torch.dtype = torch.float32) -> SelectionConstants:
    """The constants of the selection features of ``kind`` for motions ``[*, N, D]`` on ``device``
    in ``dtype`` (``mean``/``std`` ``[D]``: de-normalise the columns read; None: as stored). Made
    once, outside the traced call (a host-to-device copy per call would synchronise)."""
    if kind not in FEATURE_KINDS:
        raise ValueError(f"extract_selection_features: unknown kind {kind!r}; known: {FEATURE_KINDS}")
    if not float(frame_index_scale) >= 0.0:
        raise ValueError(f"extract_selection_features: frame_index_scale must be >= 0 "
                         f"(metres per frame), got {frame_index_scale!r}")
    if kind in KINDS and D != KINDS[kind][0]:
        raise ValueError(f"extract_selection_features: x must have D={KINDS[kind][0]} features "
                         f"for kind={kind!r}, got D={D}")
    if kind == "joints" and (D % 3 or D < 6):
        raise ValueError(f"extract_selection_features: kind='joints' needs x [B, N, 3J] joint positions "
                         f"(J >= 2), got D={D}")
    cols = ric_slice(kind) if kind in KINDS else slice(0, D)
    s, m = _stat(std, "std", D), _stat(mean, "mean", D)
    s = None if s is None else s[cols].to(device=device, dtype=dtype)
    m = None if m is None else m[cols].to(device=device, dtype=dtype)
    index = (torch.arange(N, dtype=dtype) * float(frame_index_scale)).view(1, N, 1).to(device)
    return SelectionConstants(cols, m, s, kind == "joints", index)


def apply_selection_constants(x: torch.Tensor, c: SelectionConstants) -> torch.Tensor:
    """Selection features ``[B, N, F]`` of ``x [B, N, D]`` (shape and dtype as the constants were
    made for): the columns read, de-normalised, root-relative for ``joints``, plus the index column."""
    pos = x[..., c.cols]
    if c.std is not None:
        pos = pos * c.std
    if c.mean is not None:
        pos = pos + c.mean
    if c.root_relative:
        B, N, D = pos.shape
        pos = (pos.view(B, N, D // 3, 3)[:, :, 1:] - pos.view(B, N, D // 3, 3)[:, :, :1]).reshape(B, N, D - 3)
    return torch.cat([pos, c.index.expand(x.shape[0], x.shape[1], 1)], dim=-1)


def extract_selection_features(x: ArrayLike, kind: str = "humanml3d",
                               mean: Optional[ArrayLike] = None, std: Optional[ArrayLike] = None,
                               frame_index_scale: float = 0.1) -> torch.Tensor:
    """Selection features ``[B, N, F]`` from motion ``x [B, N, D]`` (batch-major; use
    :func:`from_mdm_layout` for ``[B, D, 1, N]``); ``kind`` as in the module docstring.
    ``mean``/``std`` (``[D]``) de-normalise ``x`` first (``x * std + mean``); None means ``x`` is
    already un-normalised. The last column is ``frame index × frame_index_scale`` (metres per frame)."""
    if kind not in FEATURE_KINDS:
        raise ValueError(f"extract_selection_features: unknown kind {kind!r}; known: {FEATURE_KINDS}")
    x = torch.as_tensor(x)
    if x.dim() != 3:
        hint = " (MDM layout [B, D, 1, N]? use from_mdm_layout)" if x.dim() == 4 else ""
        raise ValueError(f"extract_selection_features: x must be 3-D [B, N, D], "
                         f"got shape {tuple(x.shape)}{hint}")
    if not x.dtype.is_floating_point:
        x = x.float()
    B, N, D = x.shape
    return apply_selection_constants(x, selection_constants(kind, N, D, mean, std, frame_index_scale, x.device,
                                                            x.dtype))
