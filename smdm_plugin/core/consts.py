"""Per-device constants made once: a constant rebuilt in every call is a kernel launch per call
(and a host-to-device copy when it is made from host data). Not filled while ``torch.compile``
traces (the traced graph makes its own; a cache write would fail its guards)."""
from __future__ import annotations

from typing import Dict, Tuple

import torch

from .checks import compiling

_ARANGES: Dict[Tuple[int, torch.device], torch.Tensor] = {}


def arange(n: int, device: torch.device) -> torch.Tensor:
    """``torch.arange(n)`` (long) on ``device``, made once per ``(n, device)``. Read-only: never
    write to it."""
    if compiling():
        return torch.arange(n, device=device)
    key = (int(n), torch.device(device))
    out = _ARANGES.get(key)
    if out is None:
        if len(_ARANGES) > 256:
            _ARANGES.clear()
        out = _ARANGES[key] = torch.arange(n, device=device)
    return out
