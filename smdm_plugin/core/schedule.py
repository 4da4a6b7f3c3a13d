"""When and how keyframes are chosen: from x0 during training, from (x_t, t) during sampling."""
from __future__ import annotations

from typing import Optional, Sequence, Union

import numpy as np
import torch

from .config import SparseConfig
from .features import extract_selection_features
from .selection import perturb_mask, select_keyframes

ArrayLike = Union[torch.Tensor, np.ndarray, Sequence[float], None]


def resolve_lengths(lengths, B: int, N: int, device: torch.device) -> torch.Tensor:
    """``lengths`` (tensor, list or None) as a long tensor ``[B]`` on ``device``, validated."""
    if lengths is None:
        return torch.full((B,), N, dtype=torch.long, device=device)
    lengths = torch.as_tensor(lengths, device=device).long().reshape(-1)
    if lengths.shape[0] != B:
        raise ValueError(f"lengths must have shape [B]=[{B}], got {tuple(lengths.shape)}")
    if bool((lengths > N).any()):
        raise ValueError(f"lengths must be <= N={N} (frames in the tensor), got max {int(lengths.max())}")
    if bool((lengths < 2).any()):
        raise ValueError(f"lengths must be >= 2 (two keyframes at least), got min {int(lengths.min())}")
    return lengths


def apply_forced(mask: torch.Tensor, forced: Optional[torch.Tensor]) -> torch.Tensor:
    """OR the forced keyframes ``[B, N]`` into ``mask`` ``[B, N]``."""
    if forced is None:
        return mask
    forced = forced.to(device=mask.device, dtype=torch.bool)
    if forced.shape != mask.shape:
        raise ValueError(f"forced keyframes must have shape [B, N]={list(mask.shape)}, got {list(forced.shape)}")
    return mask | forced


class MaskSchedule:
    """Keyframe masks for training and sampling.

    Args:
        config: the sparse config (reduction, selector, feature, gamma, dynamic_update, ...).
        mean, std: ``[D]`` dataset statistics to de-normalise features before VW (optional).
    """

    def __init__(self, config: SparseConfig, mean: ArrayLike = None, std: ArrayLike = None) -> None:
        self.config = config
        self.mean = None if mean is None else torch.as_tensor(np.asarray(mean), dtype=torch.float32)
        self.std = None if std is None else torch.as_tensor(np.asarray(std), dtype=torch.float32)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """What VW measures, ``[B, N, F]``, from motion ``x [B, N, D]``."""
        kind = self.config.feature
        if kind == "auto":
            kind = {263: "humanml3d", 251: "kit"}.get(x.shape[-1], "raw")
        if kind == "raw":
            mean = std = None
        else:
            mean, std = self.mean, self.std
        return extract_selection_features(x.detach().float(), kind=kind, mean=mean, std=std,
                                          frame_index_scale=self.config.frame_index_scale)

    def training_mask(self, x0: torch.Tensor, lengths=None, forced: Optional[torch.Tensor] = None,
                      generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """bool ``[B, N]`` from the clean motion ``x0 [B, N, D]``: selector + mask noise + forced."""
        B, N, _ = x0.shape
        lengths = resolve_lengths(lengths, B, N, x0.device)
        c = self.config
        with torch.no_grad():
            mask = select_keyframes(self.features(x0), lengths, c.reduction, c.selector, generator)
            if c.mask_noise > 0:
                mask = perturb_mask(mask, lengths, c.mask_noise, generator)
        return apply_forced(mask, forced)

    def sampling_mask(self, x_t: torch.Tensor, t: torch.Tensor, lengths=None,
                      forced: Optional[torch.Tensor] = None) -> torch.Tensor:
        """bool ``[B, N]`` at sampling step ``t [B]``: uniform while ``t > gamma*T``, else the
        selector (VW) on ``x_t`` (when ``config.dynamic``); forced frames OR-ed in."""
        B, N, _ = x_t.shape
        lengths = resolve_lengths(lengths, B, N, x_t.device)
        c = self.config
        with torch.no_grad():
            dummy = x_t.new_zeros(B, N, 1)
            mask = select_keyframes(dummy, lengths, c.reduction, "uniform")
            if c.dynamic and c.reduction > 0:
                t = torch.as_tensor(t, device=x_t.device).reshape(-1).expand(B)
                late = t.float() <= c.gamma * c.diffusion_steps
                if bool(late.any()):
                    rows = late.nonzero(as_tuple=True)[0]
                    sel = select_keyframes(self.features(x_t[rows]), lengths[rows], c.reduction, c.selector)
                    mask = mask.clone()
                    mask[rows] = sel
        return apply_forced(mask, forced)
