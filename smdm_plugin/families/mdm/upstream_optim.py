"""The step after the loss of a captured upstream MDM / DiP / priorMDM training run
(``--sparse_compile``, one process or ``torchrun``), where the fused optimizer applies (CUDA:
:func:`~smdm_plugin.runtime.compile.fused_optimizer_kwargs`): upstream's ``AdamW`` fused and kept
fused across a resume (:class:`~smdm_plugin.runtime.fused_optim.FusedAdamW`); the norms that
``MixedPrecisionTrainer._compute_norms`` logs (a ``.item()`` per tensor, frozen CLIP included: 478
per step at the paper's size) in a few multi-tensor ops, read with the log (:mod:`.upstream_loop`)
or in one sync; ``--use_ema``'s average (two ops per tensor) in two multi-tensor ops. Dense and
sparse runs alike; the counts and why: docs/modules.md."""
from __future__ import annotations

import functools
import sys
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from ...runtime.fused_optim import FusedAdamW
from .upstream_loop import (Later, batches_on_device, deferred_logger, deferring, log_loss_dict_later,
                            sample_without_sync)

__all__ = ["norms_in_one_sync", "average_in_two_ops", "fast_optimizer_step", "train_device", "OPTIMIZER_NOTE",
           "UPSTREAM_BATCHES"]

#: what a hooked run records beside its compile setting (``args.json``)
OPTIMIZER_NOTE = ("optimizer step: AdamW fused, EMA in two ops; losses and norms logged without a sync, "
                  "batches and timesteps copied without one")
#: what the note adds where the batches stay upstream's (:func:`~.upstream_loop.batches_on_device`)
UPSTREAM_BATCHES = " (batches: upstream's copies, --multi_target_cond)"
_MARK = "_smdm_fast_optimizer"
_EMA_LISTS = "_smdm_ema_lists"      # a TrainLoop's (key, parameters, averages), listed once
_LOOP_MODULE, _FP16_MODULE = "train.training_loop", "diffusion.fp16_util"
_LOGGER_MODULE, _SAMPLER_MODULE = "diffusion.logger", "diffusion.resample"


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


def _sums(values: List[float], n: int, grad_scale: float) -> Tuple[Any, Any]:
    """Upstream's return value from the norms read back (``n`` parameters', then the gradients'):
    ``(sqrt(sum grad_norm^2) / grad_scale, sqrt(sum param_norm^2))``, summed in upstream's order."""
    grad_norm = param_norm = 0.0
    for v in values[:n]:
        param_norm += v ** 2
    for v in values[n:]:
        grad_norm += v ** 2
    return np.sqrt(grad_norm) / grad_scale, np.sqrt(param_norm)


def _grad_norm(n: int, grad_scale: float, host: torch.Tensor) -> Any:
    return _sums(host.tolist(), n, grad_scale)[0]


def _param_norm(n: int, host: torch.Tensor) -> Any:
    return _sums(host.tolist(), n, 1.0)[1]


def norms_in_one_sync(original: Callable) -> Callable:
    """``original`` (upstream's ``MixedPrecisionTrainer._compute_norms(self, grad_scale=1.0)``: the
    L2 norms of ``self.master_params`` and of their gradients, each read with ``.item()`` and
    summed in Python) with every norm computed in a few multi-tensor ops (:func:`_norms`), stacked,
    and read back in one ``tolist``, or, where upstream's logger keeps its calls
    (:mod:`.upstream_loop`) and nothing but the log reads them (``use_fp16`` off: the fp16 path
    checks the norm for overflow), returned as two :class:`~.upstream_loop.Later` values read with
    the log. The sums and values as upstream's (``(sqrt(sum grad_norm^2) / grad_scale, sqrt(sum
    param_norm^2))``, numpy floats): bit for bit on the CPU; on CUDA the multi-tensor norm may
    round differently in the last bit (logged values only: MDM's ``use_fp16`` is off)."""

    @functools.wraps(original)
    def _compute_norms(self: Any, grad_scale: float = 1.0) -> Tuple[Any, Any]:
        params = list(self.master_params)
        if not params or len({p.device for p in params}) != 1:
            return original(self, grad_scale)
        with torch.no_grad():
            norms = _norms(params)
            grads = _norms([p.grad for p in params if p.grad is not None])
            stacked = torch.stack(norms + grads)
        n = len(norms)
        if not getattr(self, "use_fp16", False) and deferring(sys.modules.get(_LOGGER_MODULE)):
            return (Later((stacked,), functools.partial(_grad_norm, n, grad_scale)),
                    Later((stacked,), functools.partial(_param_norm, n)))
        return _sums(stacked.tolist(), n, grad_scale)                  # the one sync

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
        wrap_once(loop, "__init__", batches_on_device, marker=_MARK)
    wrap_once(mod, "log_loss_dict", log_loss_dict_later, marker=_MARK)


def _hook_logger(mod: Any) -> None:
    cls = getattr(mod, "Logger", None)
    if isinstance(cls, type):
        deferred_logger(cls)


def _hook_sampler(mod: Any) -> None:
    from ...integrations._hooks import wrap_once

    sampler = getattr(mod, "ScheduleSampler", None)
    if sampler is not None:
        wrap_once(sampler, "sample", sample_without_sync, marker=_MARK)


def _hook_fp16_util(mod: Any) -> None:
    from ...integrations._hooks import wrap_once

    trainer = getattr(mod, "MixedPrecisionTrainer", None)
    if trainer is not None:
        wrap_once(trainer, "_compute_norms", norms_in_one_sync, marker=_MARK)


def fast_optimizer_step(device: Any, mode: Any, args: Any = None) -> Optional[str]:
    """Hook upstream's training loop (now, or when it is imported) for a run compiled with
    ``mode`` on ``device``: :class:`~smdm_plugin.runtime.fused_optim.FusedAdamW` for its ``AdamW``,
    :func:`norms_in_one_sync` for its norms, :func:`average_in_two_ops` for its EMA, its log read
    when it is read (:mod:`.upstream_loop`: ``Logger``, ``log_loss_dict``), its timesteps and
    batches copied without a sync, when :func:`~smdm_plugin.runtime.compile.fused_optimizer_kwargs`
    says the fused optimizer applies there. Returns :data:`OPTIMIZER_NOTE` (with
    :data:`UPSTREAM_BATCHES` when the run's ``args`` ask for MDM's ``--multi_target_cond``, whose
    batches the loop copies as upstream), or None (nothing hooked)."""
    from ...integrations._hooks import on_import
    from ...runtime import compile as compile_mod

    if not compile_mod.fused_optimizer_kwargs(device, mode).get("fused"):
        return None
    on_import(_LOGGER_MODULE, _hook_logger)
    on_import(_SAMPLER_MODULE, _hook_sampler)
    on_import(_LOOP_MODULE, _hook_training_loop)
    on_import(_FP16_MODULE, _hook_fp16_util)
    return OPTIMIZER_NOTE + (UPSTREAM_BATCHES if getattr(args, "multi_target_cond", False) else "")
