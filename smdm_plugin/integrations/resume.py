"""An upstream run resumed from an optimizer state that a 0.9 sparse run wrote (FSQ key maps held per
layer) goes on with the key maps banked: ``TrainLoop._load_optimizer_state`` (MDM, DiP, priorMDM)
hands ``load_state_dict`` the state in today's layout
(:func:`~smdm_plugin.core.fsq_bank.upgrade_optimizer_state`). A model without banks (a dense run:
the flag off) and a state that already fits load as upstream loads them."""
from __future__ import annotations

import functools
from typing import Any, Callable

from torch import nn

from ..core.fsq_bank import upgrade_optimizer_state

__all__ = ["optimizer_state_upgraded", "install_hooks"]

_MARK = "_smdm_optimizer_resume"


def optimizer_state_upgraded(original: Callable[..., Any]) -> Callable[..., Any]:
    """``original`` (a training loop's ``_load_optimizer_state(self)``, which loads into ``self.opt``
    what it read for ``self.model``) with the loaded state upgraded on its way into ``self.opt``."""
    @functools.wraps(original)
    def _load_optimizer_state(self: Any, *args: Any, **kwargs: Any) -> Any:
        opt, model = getattr(self, "opt", None), getattr(self, "model", None)
        if opt is None or not isinstance(model, nn.Module) or "load_state_dict" in vars(opt):
            return original(self, *args, **kwargs)
        load = opt.load_state_dict

        def load_state_dict(state_dict: Any) -> Any:
            return load(upgrade_optimizer_state(state_dict, model, opt) if isinstance(state_dict, dict)
                        else state_dict)

        opt.load_state_dict = load_state_dict
        try:
            return original(self, *args, **kwargs)
        finally:
            del opt.load_state_dict
    return _load_optimizer_state


def _hook(mod: Any) -> None:
    from ._hooks import wrap_once

    loop = getattr(mod, "TrainLoop", None)
    if isinstance(loop, type):
        wrap_once(loop, "_load_optimizer_state", optimizer_state_upgraded, marker=_MARK)


def install_hooks(module: str = "train.training_loop") -> None:
    """Wrap ``module``'s ``TrainLoop._load_optimizer_state`` as it is imported (idempotent)."""
    from ._hooks import on_import

    on_import(module, _hook)
