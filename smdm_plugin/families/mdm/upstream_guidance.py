"""``--sparse_compile`` in MDM's and priorMDM's sampling: classifier-free guidance's two passes and
their combination as one graph (upstream's ``ClassifierFreeSampleModel`` deep-copies ``y`` per call,
which no graph captures, so its passes ran as two compiled model calls and eager arithmetic)."""
from __future__ import annotations

import functools
from typing import Any, Callable, Optional, Tuple

import torch
import torch.nn as nn

from .prepare import _split_call, prepare_mdm

__all__ = ["guided", "guided_preparer", "compile_guidance", "patch_cfg_sampler", "install_hooks"]


def guided(model: nn.Module) -> Callable[..., torch.Tensor]:
    """Upstream's ``ClassifierFreeSampleModel.forward`` over calls already prepared:
    ``(x [B, J, F, N], timesteps [B], y, y_uncond) -> out_uncond + scale * (out - out_uncond)``,
    the same operations in the same order."""
    def call(x: torch.Tensor, timesteps: torch.Tensor, y: dict, y_uncond: dict) -> torch.Tensor:
        out = model(x, timesteps, y)
        out_uncond = model(x, timesteps, y_uncond)
        return out_uncond + (y["scale"].view(-1, 1, 1, 1) * (out - out_uncond))
    return call


def guided_preparer(model: nn.Module) -> Callable[[tuple, dict], Tuple[tuple, dict]]:
    """``(x, timesteps, y)`` of a guided call -> ``(x, timesteps, y, y_uncond)``: ``y`` prepared as
    ``model``'s call (:func:`~.prepare.prepare_mdm`: text encoded once), ``y_uncond`` its copy with
    ``uncond`` (upstream's ``deepcopy(y)`` + ``['uncond'] = True``; in eval mode folded into zeroed
    text features)."""
    def prepare(args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
        x, t, y = _split_call(args, kwargs)
        (x, t, y), _ = prepare_mdm(model, (x, t, y), {})
        (_, _, y_uncond), _ = prepare_mdm(model, (x, t, {**y, "uncond": True}), {})
        return (x, t, y, y_uncond), {}
    return prepare


def _wrapped(wrapper: nn.Module) -> Optional[nn.Module]:
    """The model a guidance wrapper runs (MDM registers it as a submodule, priorMDM keeps it in
    ``vars``)."""
    model = vars(wrapper).get("model")
    if model is None:
        model = getattr(wrapper, "_modules", {}).get("model")
    return model if isinstance(model, nn.Module) else None


def compile_guidance(wrapper: nn.Module) -> Any:
    """When the model ``wrapper`` guides was compiled (``--sparse_compile``), compile ``wrapper``'s
    call whole, in place (:func:`~smdm_plugin.runtime.compile.compile_wrapper_call`: ``captures``
    "guided sampling call: every guidance pass"), counted by ``SMDM_COMPILE_STATS``. Otherwise
    nothing happens (a flag-off run: upstream's wrapper as it is). Returns the setting or None."""
    from ...runtime.compile import CAPTURES_GUIDED, compile_setting, compile_wrapper_call, register_stats

    done = getattr(wrapper, "_compiled_call_impl", None)
    if done is not None:                  # the patch's line and the launcher's hook both ran
        return compile_setting(done)
    model = _wrapped(wrapper)
    if model is None:
        return None
    setting = compile_wrapper_call(wrapper, model, guided(model), guided_preparer(model), CAPTURES_GUIDED)
    if setting is not None:
        register_stats(type(wrapper).__name__, wrapper._compiled_call_impl)
    return setting


def patch_cfg_sampler(mod: Any) -> None:
    """Wrap ``mod.ClassifierFreeSampleModel.__init__`` (MDM's ``utils.sampler_util``, priorMDM's
    ``model.cfg_sampler``): a wrapper built around a compiled model is compiled whole."""
    from ...integrations._hooks import wrap_once

    cls = getattr(mod, "ClassifierFreeSampleModel", None)
    if cls is None:
        return

    def make(original):
        @functools.wraps(original)
        def __init__(self, model, *a, **kw):
            original(self, model, *a, **kw)
            compile_guidance(self)
        return __init__

    wrap_once(cls, "__init__", make)


def install_hooks(module: str) -> None:
    """Hook ``module``'s ``ClassifierFreeSampleModel`` as it is imported (idempotent)."""
    from ...integrations._hooks import on_import

    on_import(module, patch_cfg_sampler)
