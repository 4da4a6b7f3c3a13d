"""Training mask noise without torch's global RNG and without a generator in the traced call."""
from __future__ import annotations

from typing import Tuple

import torch

from . import consts

#: the sparse model's persistent int64 buffer holding the mask-noise step (saved with the weights)
NOISE_STEP = "smdm_mask_noise_step"
#: the sparse model's non-persistent buffer holding the noise table (moves with the model), as the
#: int32 bit patterns of its float32 numbers, so that ``model.half()`` / ``.double()`` leave it alone
NOISE_TABLE = "smdm_mask_noise_table"
#: uniforms in a table (a prime: every stride visits every offset); 4 MiB in float32
TABLE_SIZE = 1048573
#: the offset between two steps' windows (≈ TABLE_SIZE / golden ratio)
STRIDE = 648054
#: the offset between two ranks' windows (≈ TABLE_SIZE · (√2 - 1))
RANK_STRIDE = 434334


def default_noise_seed() -> int:
    """torch's current seed (``torch.initial_seed()``: what ``torch.manual_seed`` set; reading it
    draws nothing)."""
    return torch.initial_seed()


def default_noise_salt() -> int:
    """Where this process's windows start: ``rank · RANK_STRIDE`` under ``torch.distributed`` (ranks
    draw different numbers from the same table and step, so their buffers stay equal), else 0."""
    dist = getattr(torch, "distributed", None)
    if dist is not None and dist.is_available() and dist.is_initialized():
        return dist.get_rank() * RANK_STRIDE % TABLE_SIZE
    return 0


def noise_table(seed: int) -> torch.Tensor:
    """float32 ``[TABLE_SIZE]`` uniforms in ``[0, 1)`` from a private CPU generator seeded with
    ``seed`` (torch's global stream is not touched)."""
    g = torch.Generator().manual_seed(int(seed) % (1 << 64))
    return torch.rand(TABLE_SIZE, generator=g)


class CounterNoise:
    """Uniform ``[0, 1)`` float32 numbers for one mask: windows of ``table`` at ``step``.

    Args:
        step: int64 tensor on the table's device: 0-d (one step for the call) or ``[B]`` (a step
            per row, e.g. sampling steps); read here, advanced only by :meth:`advance`.
        table: the ``[TABLE_SIZE]`` uniforms (:func:`noise_table`) on the device of the numbers:
            float32, or their int32 bit patterns (the model's buffer :data:`NOISE_TABLE`).
        salt: where the windows start (host int; :func:`default_noise_salt`: the rank's offset).

    Successive :meth:`uniform` calls of one object read successive parts of the window (so two
    draws of one mask differ); a new object for the same step reads the same numbers again.
    """

    def __init__(self, step: torch.Tensor, table: torch.Tensor, salt: int = 0) -> None:
        self.step, self.used = step, int(salt)
        self.table = table.view(torch.float32) if table.dtype == torch.int32 else table

    def uniform(self, shape: Tuple[int, ...]) -> torch.Tensor:
        """float32 ``shape`` (``[B]`` or ``[B, N]``) in ``[0, 1)``."""
        numel = 1
        for n in shape:
            numel *= int(n)
        start, self.used = self.used, self.used + numel
        device = self.table.device
        if self.step.dim() == 0:                             # start + i + step * STRIDE: one op
            pos = torch.add(consts.arange(start + numel, device)[start:], self.step, alpha=STRIDE)
        else:                                                # a window per row, at the row's step
            rows = int(shape[0])
            cols = numel // max(rows, 1)
            base = self.step.reshape(rows, 1) * STRIDE + torch.arange(rows, device=device)[:, None] * cols
            pos = torch.arange(start, start + cols, device=device)[None] + base
        return self.table.take(pos % TABLE_SIZE).reshape(shape)

    def advance(self) -> None:
        """``step += 1`` in place (on the device, no sync): the next mask's numbers."""
        self.step.add_(1)
