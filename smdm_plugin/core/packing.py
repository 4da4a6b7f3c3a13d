"""Kept tokens packed with no padding: where each packed row ``[T, ...]`` sits in the batch, and the
way to the padded ``[B, max, ...]`` layout the attention needs and back."""
from __future__ import annotations

from typing import Dict, Optional

import torch
import torch.nn.functional as F

from .rows import gather_rows, scatter_rows


class Packing:
    """Where the packed rows ``[T, ...]`` (batch-major, the order of ``keep.nonzero()``) sit.

    ``counts [B]``, ``cu [B+1]`` (cumulative), ``max`` (largest count), ``seg [T]`` (sample of
    each row), ``src [T]`` (its position in the sequence), ``valid [B, max]`` and ``flat [T]``
    (padded slot ``b * max + j`` of each row).
    """

    def __init__(self, keep: torch.Tensor) -> None:
        B, S = keep.shape
        self.B = B
        self.counts = keep.sum(1)
        self.cu = F.pad(self.counts.cumsum(0), (1, 0))
        self.max = int(self.counts.max()) if B else 0
        self.seg, self.src = keep.nonzero(as_tuple=True)
        self.T = int(self.seg.shape[0])
        slot = torch.arange(self.T, device=keep.device) - self.cu[self.seg]
        self.flat = self.seg * self.max + slot
        self.valid = torch.arange(self.max, device=keep.device) < self.counts.unsqueeze(1)
        self.full = self.T == B * self.max
        self._padding: Dict[torch.dtype, torch.Tensor] = {}

    def key_padding(self, dtype: torch.dtype) -> Optional[torch.Tensor]:
        """Additive key padding mask ``[B, max]`` (0 / -inf), None when nothing is padded; made
        once per call and dtype (a float mask goes through every layer's attention as it is)."""
        if self.full:
            return None
        if dtype not in self._padding:
            pad = torch.zeros(self.B, self.max, dtype=dtype, device=self.valid.device)
            self._padding[dtype] = pad.masked_fill_(~self.valid, float("-inf"))
        return self._padding[dtype]

    def pad(self, t: torch.Tensor) -> torch.Tensor:
        """``[T, ...]`` -> ``[B, max, ...]`` (padded slots hold zeros)."""
        if not self.full:
            t = scatter_rows(t, self.flat, self.B * self.max)
        return t.view(self.B, self.max, *t.shape[1:])

    def unpad(self, t: torch.Tensor) -> torch.Tensor:
        """``[B, max, ...]`` -> ``[T, ...]``."""
        t = t.reshape(self.B * self.max, *t.shape[2:])
        return t if self.full else gather_rows(t, self.flat)
