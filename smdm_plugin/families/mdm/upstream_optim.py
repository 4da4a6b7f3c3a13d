"""The optimizer step of a captured upstream MDM / DiP / priorMDM training run (``--sparse_compile``,
one process): upstream's ``train.training_loop`` builds ``torch.optim.AdamW`` (torch's ``foreach``
default: about a dozen multi-tensor ops per step, ``step`` counters on the host) and its
``MixedPrecisionTrainer._compute_norms`` (``diffusion.fp16_util``) logs the gradient and parameter
norms with two host syncs per parameter (``.item()``: ~200 per step at MDM's size). Where the run
compiles on a device with torch's fused AdamW (:func:`~smdm_plugin.runtime.compile.fused_optimizer_kwargs`):

* ``AdamW`` is :class:`~smdm_plugin.runtime.fused_optim.FusedAdamW` (the update in a few fused
  kernels, no host sync, ``step`` on the device), kept fused across a resume (upstream's
  ``_load_optimizer_state``);
* the norms are read back in one sync: the same op per parameter (``th.norm(p, p=2, dtype=float32)``
  is ``linalg.vector_norm``), the same Python sums in the same order: the same logged values.

Dense and sparse runs alike; nothing changes without ``--sparse_compile`` or where the fused
optimizer does not apply."""
from __future__ import annotations

import functools
import sys
from typing import Any, Callable, Optional, Tuple

import numpy as np
import torch

from ...runtime.fused_optim import FusedAdamW

__all__ = ["norms_in_one_sync", "fast_optimizer_step", "train_device", "OPTIMIZER_NOTE"]

#: what a run that takes both hooks records beside its compile setting (``args.json``)
OPTIMIZER_NOTE = "optimizer step: AdamW fused, norms read in one sync"
_MARK = "_smdm_fast_optimizer"
_LOOP_MODULE, _FP16_MODULE = "train.training_loop", "diffusion.fp16_util"


def norms_in_one_sync(original: Callable) -> Callable:
    """``original`` (upstream's ``MixedPrecisionTrainer._compute_norms(self, grad_scale=1.0)``: the
    L2 norms of ``self.master_params`` and of their gradients, each read with ``.item()`` and
    summed in Python) with every norm read back in one host sync: per parameter the op upstream
    runs, stacked, one ``tolist``; the sums and the return value as upstream's
    (``(sqrt(sum grad_norm^2) / grad_scale, sqrt(sum param_norm^2))``, numpy floats)."""

    @functools.wraps(original)
    def _compute_norms(self: Any, grad_scale: float = 1.0) -> Tuple[Any, Any]:
        params = list(self.master_params)
        if not params or len({p.device for p in params}) != 1:
            return original(self, grad_scale)
        with torch.no_grad():
            norms = [torch.linalg.vector_norm(p, 2, dtype=torch.float32) for p in params]
            grads = [torch.linalg.vector_norm(p.grad, 2, dtype=torch.float32) for p in params if p.grad is not None]
            values = torch.stack(norms + grads).tolist()          # the one sync
        grad_norm = param_norm = 0.0
        for v in values[:len(norms)]:
            param_norm += v ** 2
        for v in values[len(norms):]:
            grad_norm += v ** 2
        return np.sqrt(grad_norm) / grad_scale, np.sqrt(param_norm)

    return _compute_norms


def train_device() -> torch.device:
    """The device upstream trains on: its ``utils.dist_util.dev()`` (set up before the model is
    built), else CUDA when there is one."""
    dist_util = sys.modules.get("utils.dist_util")
    dev = getattr(dist_util, "dev", None)
    if callable(dev):
        return torch.device(dev())
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _hook_training_loop(mod: Any) -> None:
    if getattr(mod, "AdamW", None) is torch.optim.AdamW:
        mod.AdamW = FusedAdamW


def _hook_fp16_util(mod: Any) -> None:
    from ...integrations._hooks import wrap_once

    trainer = getattr(mod, "MixedPrecisionTrainer", None)
    if trainer is not None:
        wrap_once(trainer, "_compute_norms", norms_in_one_sync, marker=_MARK)


def fast_optimizer_step(device: Any, mode: Any) -> Optional[str]:
    """Hook upstream's training loop (now, or when it is imported) for a run compiled with
    ``mode`` on ``device``: :class:`~smdm_plugin.runtime.fused_optim.FusedAdamW` for its ``AdamW`` and :func:`norms_in_one_sync`
    for its norms, when :func:`~smdm_plugin.runtime.compile.fused_optimizer_kwargs` says the fused
    optimizer applies there. Returns :data:`OPTIMIZER_NOTE`, or None (nothing hooked)."""
    from ...integrations._hooks import on_import
    from ...runtime import compile as compile_mod

    if not compile_mod.fused_optimizer_kwargs(device, mode).get("fused"):
        return None
    on_import(_LOOP_MODULE, _hook_training_loop)
    on_import(_FP16_MODULE, _hook_fp16_util)
    return OPTIMIZER_NOTE
