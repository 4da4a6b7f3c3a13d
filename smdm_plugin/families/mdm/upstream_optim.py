"""The step after the loss of a captured upstream MDM / DiP / priorMDM training run
(``--sparse_compile``, one process or ``torchrun``), where the fused optimizer applies (CUDA:
:func:`~smdm_plugin.runtime.compile.fused_optimizer_kwargs`): upstream's ``AdamW`` fused and kept
fused across a resume (:class:`~smdm_plugin.runtime.fused_optim.FusedAdamW`); the norms that
``MixedPrecisionTrainer._compute_norms`` logs (a ``.item()`` per tensor, frozen CLIP included: 478
per step at the paper's size) in a few multi-tensor ops read back in one sync, the same values;
``--use_ema``'s average (two ops per tensor) in two multi-tensor ops. Dense and sparse runs alike;
the counts and why: docs/modules.md."""
from __future__ import annotations

import functools
import sys
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from ...runtime.fused_optim import FusedAdamW

__all__ = ["norms_in_one_sync", "average_in_two_ops", "fast_optimizer_step", "train_device", "OPTIMIZER_NOTE"]

#: what a hooked run records beside its compile setting (``args.json``)
OPTIMIZER_NOTE = "optimizer step: AdamW fused, norms read in one sync, EMA in two ops"
_MARK = "_smdm_fast_optimizer"
_EMA_LISTS = "_smdm_ema_lists"      # a TrainLoop's (key, parameters, averages), listed once
_LOOP_MODULE, _FP16_MODULE = "train.training_loop", "diffusion.fp16_util"


def _norms(tensors: List[torch.Tensor]) -> List[torch.Tensor]:
    """The float32 L2 norm of each tensor, in order (upstream's ``th.norm(t, p=2,
    dtype=th.float32)``): one multi-tensor op per dtype (MDM's frozen CLIP is float16), asking for
    float32 where the tensors are not (a torch without ``_foreach_norm``'s ``dtype``: the op per
    tensor). On the CPU torch runs ``linalg.vector_norm`` per tensor: upstream's op."""
    out: List[Any] = [None] * len(tensors)
    groups: Dict[torch.dtype, List[int]] = {}
    for i, t in enumerate(tensors):
        groups.setdefault(t.dtype, []).append(i)
    for dtype, index in groups.items():
        group = [tensors[i] for i in index]
        if dtype == torch.float32:
            res = list(torch._foreach_norm(group, 2))
        else:
            try:
                res = list(torch._foreach_norm(group, 2, dtype=torch.float32))
            except (TypeError, RuntimeError):
                res = [torch.linalg.vector_norm(t, 2, dtype=torch.float32) for t in group]
        for i, r in zip(index, res):
            out[i] = r
    return out


def norms_in_one_sync(original: Callable) -> Callable:
    """``original`` (upstream's ``MixedPrecisionTrainer._compute_norms(self, grad_scale=1.0)``: the
    L2 norms of ``self.master_params`` and of their gradients, each read with ``.item()`` and
    summed in Python) with every norm read back in one host sync: the norms in a few multi-tensor
    ops (:func:`_norms`), stacked, one ``tolist``; the sums and the return value as upstream's
    (``(sqrt(sum grad_norm^2) / grad_scale, sqrt(sum param_norm^2))``, numpy floats). The same
    values bit for bit on the CPU; on CUDA the multi-tensor norm may round differently in the last
    bit (logged values only: MDM's ``use_fp16`` is off)."""

    @functools.wraps(original)
    def _compute_norms(self: Any, grad_scale: float = 1.0) -> Tuple[Any, Any]:
        params = list(self.master_params)
        if not params or len({p.device for p in params}) != 1:
            return original(self, grad_scale)
        with torch.no_grad():
            norms = _norms(params)
            grads = _norms([p.grad for p in params if p.grad is not None])
            values = torch.stack(norms + grads).tolist()          # the one sync
        grad_norm = param_norm = 0.0
        for v in values[:len(norms)]:
            param_norm += v ** 2
        for v in values[len(norms):]:
            grad_norm += v ** 2
        return np.sqrt(grad_norm) / grad_scale, np.sqrt(param_norm)

    return _compute_norms


def average_in_two_ops(original: Callable) -> Callable:
    """``original`` (upstream's ``TrainLoop.update_average_model(self)``: with ``--use_ema``, per
    parameter ``avg.mul_(beta).add_(param, alpha=1 - beta)``, two ops per tensor) as two
    multi-tensor ops over every tensor (``_foreach_mul_``, ``_foreach_add_``; the two lists of
    tensors made once per loop): the same arithmetic per element (bit for bit on the CPU, where
    foreach runs those ops per tensor). Without ``--use_ema``, or when the two lists do not pair
    up (lengths, devices, dtypes), ``original`` runs."""

    @functools.wraps(original)
    def update_average_model(self: Any) -> None:
        args = getattr(self, "args", None)
        if not getattr(args, "use_ema", False) or getattr(self, "model_avg", None) is None:
            return original(self)
        key = (id(self.model), id(self.model_avg), id(self.mp_trainer))
        cached = vars(self).get(_EMA_LISTS)
        if cached is None or cached[0] != key:      # the tensors are the same every step: listed once
            params = list(self.model.parameters() if self.use_fp16 else self.mp_trainer.master_params)
            averages = list(self.model_avg.parameters())
            pair = (bool(params) and len(params) == len(averages)
                    and all(p.device == a.device and p.dtype == a.dtype for p, a in zip(params, averages)))
            cached = vars(self)[_EMA_LISTS] = (key, params, averages) if pair else (key, None, None)
        _, params, averages = cached
        if params is None:
            return original(self)
        beta = args.avg_model_beta
        with torch.no_grad():                     # upstream writes through .data: outside autograd too
            torch._foreach_mul_(averages, beta)
            torch._foreach_add_(averages, params, alpha=1 - beta)

    return update_average_model


def train_device() -> torch.device:
    """The device upstream trains on: its ``utils.dist_util.dev()`` (set up before the model is
    built), else CUDA when there is one."""
    dist_util = sys.modules.get("utils.dist_util")
    dev = getattr(dist_util, "dev", None)
    if callable(dev):
        return torch.device(dev())
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _hook_training_loop(mod: Any) -> None:
    from ...integrations._hooks import wrap_once

    if getattr(mod, "AdamW", None) is torch.optim.AdamW:
        mod.AdamW = FusedAdamW
    loop = getattr(mod, "TrainLoop", None)
    if loop is not None:
        wrap_once(loop, "update_average_model", average_in_two_ops, marker=_MARK)


def _hook_fp16_util(mod: Any) -> None:
    from ...integrations._hooks import wrap_once

    trainer = getattr(mod, "MixedPrecisionTrainer", None)
    if trainer is not None:
        wrap_once(trainer, "_compute_norms", norms_in_one_sync, marker=_MARK)


def fast_optimizer_step(device: Any, mode: Any) -> Optional[str]:
    """Hook upstream's training loop (now, or when it is imported) for a run compiled with
    ``mode`` on ``device``: :class:`~smdm_plugin.runtime.fused_optim.FusedAdamW` for its ``AdamW``,
    :func:`norms_in_one_sync` for its norms and :func:`average_in_two_ops` for its EMA, when
    :func:`~smdm_plugin.runtime.compile.fused_optimizer_kwargs` says the fused optimizer applies
    there. Returns :data:`OPTIMIZER_NOTE`, or None (nothing hooked)."""
    from ...integrations._hooks import on_import
    from ...runtime import compile as compile_mod

    if not compile_mod.fused_optimizer_kwargs(device, mode).get("fused"):
        return None
    on_import(_LOOP_MODULE, _hook_training_loop)
    on_import(_FP16_MODULE, _hook_fp16_util)
    return OPTIMIZER_NOTE
