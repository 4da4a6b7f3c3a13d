"""Adam / AdamW that stay fused across a resume: what a captured upstream training run's
optimizer step is (``families/mdm/upstream_optim.py``, ``families/motiondiffuse/upstream.py``).

torch's ``load_state_dict`` takes a loaded state's param-group settings as they were saved, so a
state saved by a ``foreach`` optimizer (upstream's default) would turn a fused one back into
``foreach`` with its ``step`` counters on the host. :class:`FusedAdam` and :class:`FusedAdamW`
keep their groups fused and move each ``step`` to its parameter's device as float32 (where a fused
optimizer keeps it). A state they save says ``fused``; torch's own optimizer loads it and steps
fused (on a device torch has the fused kernel for)."""
from __future__ import annotations

from typing import Any, Dict

import torch

__all__ = ["FusedAdam", "FusedAdamW", "FUSED_OF"]


class _StaysFused:
    """Mixin over a torch optimizer with a ``fused`` option: built fused, fused after loading."""

    def __init__(self, params: Any, *args: Any, **kwargs: Any) -> None:
        if kwargs.get("foreach"):
            raise ValueError(f"{type(self).__name__}: foreach=True cannot be fused (pass foreach=None or leave it out)")
        kwargs["fused"] = True
        super().__init__(params, *args, **kwargs)   # type: ignore[call-arg]

    def load_state_dict(self, state_dict: Dict[str, Any]) -> None:
        super().load_state_dict(state_dict)         # type: ignore[misc]
        for group in self.param_groups:             # type: ignore[attr-defined]
            group["fused"], group["foreach"] = True, None
            for p in group["params"]:
                state = self.state.get(p)           # type: ignore[attr-defined]
                if state and torch.is_tensor(state.get("step")):
                    state["step"] = state["step"].to(device=p.device, dtype=torch.float32)


class FusedAdam(_StaysFused, torch.optim.Adam):
    """``torch.optim.Adam(..., fused=True)``, fused after :meth:`load_state_dict` too."""


class FusedAdamW(_StaysFused, torch.optim.AdamW):
    """``torch.optim.AdamW(..., fused=True)``, fused after :meth:`load_state_dict` too."""


#: torch's optimizer -> the fused one that replaces it
FUSED_OF = {torch.optim.Adam: FusedAdam, torch.optim.AdamW: FusedAdamW}
