"""Upstream MDM's / DiP's / priorMDM's training loop without a host sync per step
(``--sparse_compile`` where the fused optimizer applies: CUDA; with :mod:`.upstream_optim`).
``log_loss_dict`` read each loss back three times per step and the norms once: they go to the
logger as :class:`Later` values, which ``diffusion.logger.Logger`` keeps, in call order, until its
values are read (``dumpkvs``, ``name2val``) or :data:`LIMIT` calls wait; then one copy per dtype
and upstream's calls replayed in order: the same values, keys and order. The timestep sampler
draws as upstream and each batch reaches the device before the loop's ``.to(device)`` (which then
copies nothing), both copied from pinned memory without a sync. Counts and why: docs/modules.md."""
from __future__ import annotations

import functools
import sys
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch

from ...integrations.host_copies import DeviceBatches as _DeviceBatches, pin_batches, sample_without_sync, \
    to_device_without_sync

__all__ = ["Later", "DeviceBatches", "deferred_logger", "log_loss_dict_later", "sample_without_sync",
           "batches_on_device", "LIMIT"]

#: calls a logger keeps before it reads them back by itself (one host sync per this many)
LIMIT = 4096
_MARK = "_smdm_log_later"
_PENDING, _FLUSHING = "_smdm_pending", "_smdm_flushing"
_FIELDS = ("name2val", "name2cnt")       # the logger's values: reading either replays what waits


class Later:
    """A value logged now and read later: ``make(*host)``, ``host`` the host copies of ``tensors``
    (device tensors computed when logged, read when the log is)."""

    __slots__ = ("tensors", "make")

    def __init__(self, tensors: Sequence[torch.Tensor], make: Callable[..., Any]) -> None:
        self.tensors, self.make = tuple(tensors), make


class _Many(Later):
    """Several ``logkv_mean`` calls whose keys depend on device values: ``make(*host)`` returns
    their ``[(key, value), ...]`` in call order."""

    __slots__ = ()


def _to_host(tensors: List[torch.Tensor]) -> Dict[int, torch.Tensor]:
    """``id(t) -> t`` on the host, each distinct tensor once: one copy per (device, dtype)."""
    groups: Dict[Tuple[torch.device, torch.dtype], List[torch.Tensor]] = {}
    seen = set()
    for t in tensors:
        if id(t) not in seen:
            seen.add(id(t))
            groups.setdefault((t.device, t.dtype), []).append(t)
    out: Dict[int, torch.Tensor] = {}
    for group in groups.values():
        flat = torch.cat([t.detach().reshape(-1) for t in group]).cpu()     # the one read of the group
        for t, part in zip(group, flat.split([t.numel() for t in group])):
            out[id(t)] = part.reshape(t.shape)
    return out


def _flush(logger: Any, logkv: Callable, logkv_mean: Callable) -> None:
    """Replay what ``logger`` keeps, in order, through upstream's ``logkv`` / ``logkv_mean``."""
    state = vars(logger)
    pending = state.get(_PENDING)
    if not pending or state.get(_FLUSHING):
        return
    state[_FLUSHING] = True
    try:
        calls, state[_PENDING] = pending, []
        host = _to_host([t for _, _, v in calls if isinstance(v, Later) for t in v.tensors])
        for mean, key, val in calls:
            if isinstance(val, _Many):
                for k, v in val.make(*(host[id(t)] for t in val.tensors)):
                    logkv_mean(logger, k, v)
                continue
            if isinstance(val, Later):
                val = val.make(*(host[id(t)] for t in val.tensors))
            (logkv_mean if mean else logkv)(logger, key, val)
    finally:
        state[_FLUSHING] = False


def deferred_logger(cls: type) -> bool:
    """Make upstream's ``Logger`` class keep its ``logkv`` / ``logkv_mean`` calls until its values
    are read (``name2val`` / ``name2cnt``, which ``dumpkvs`` reads) or :data:`LIMIT` wait; every
    instance, once. Returns whether it changed ``cls``."""
    if getattr(cls, _MARK, False) or not all(callable(getattr(cls, m, None)) for m in ("logkv", "logkv_mean")):
        return False
    logkv, logkv_mean = cls.logkv, cls.logkv_mean

    def keep(mean: bool) -> Callable:
        def call(self: Any, key: Any, val: Any) -> None:
            if mean and isinstance(val, torch.Tensor):     # upstream averages it now: its value now
                val = val.detach().clone()
            pending = vars(self).setdefault(_PENDING, [])
            pending.append((mean, key, val))
            if len(pending) >= LIMIT:
                _flush(self, logkv, logkv_mean)
        return functools.wraps(logkv_mean if mean else logkv)(call)

    def field(name: str) -> property:
        def get(self: Any) -> Any:
            _flush(self, logkv, logkv_mean)
            return vars(self)[name]

        def put(self: Any, value: Any) -> None:
            vars(self)[name] = value
        return property(get, put, doc=f"upstream's ``{name}``, with the calls that wait replayed first")

    cls.logkv, cls.logkv_mean = keep(False), keep(True)
    for name in _FIELDS:
        setattr(cls, name, field(name))
    setattr(cls, _MARK, True)
    return True


def deferring(logger_module: Any) -> bool:
    """Whether upstream's logger (``diffusion.logger``) keeps its calls (:func:`deferred_logger`)."""
    return bool(getattr(getattr(logger_module, "Logger", None), _MARK, False))


def _item(x: torch.Tensor) -> float:
    return x.item()


def _quartiles(key: str, num_timesteps: int, ts: torch.Tensor, values: torch.Tensor) -> List[Tuple[str, Any]]:
    """Upstream's per-sample quartile log: ``(f"{key}_q{int(4 t / T)}", loss)`` per sample, numpy
    scalars as ``.cpu().numpy()`` gives them."""
    return [(f"{key}_q{int(4 * t / num_timesteps)}", v) for t, v in zip(ts.numpy(), values.numpy())]


def log_loss_dict_later(original: Callable) -> Callable:
    """``original`` (upstream's ``log_loss_dict(diffusion, ts, losses)``: per loss ``logkv_mean(key,
    values.mean().item())``, then per sample ``logkv_mean(f"{key}_q{quartile}", loss)``) logging
    :class:`Later` values: the means computed now on the device, read with the log. ``original``
    runs where the logger does not keep its calls."""

    @functools.wraps(original)
    def log_loss_dict(diffusion: Any, ts: torch.Tensor, losses: Dict[str, torch.Tensor]) -> None:
        log = getattr(sys.modules.get(original.__module__), "logger", None)
        if not deferring(log):
            return original(diffusion, ts, losses)
        for key, values in losses.items():
            v = values.detach()            # kept until read: without the step's autograd graph
            log.logkv_mean(key, Later((v.mean(),), _item))
            log.logkv_mean(key, _Many((ts, v), functools.partial(_quartiles, key, diffusion.num_timesteps)))

    return log_loss_dict


class DeviceBatches(_DeviceBatches):
    """Upstream's data loader (``TrainLoop.data``) whose batches ``(motion, {"y": {...}})`` come
    with ``motion`` and the tensors of ``y`` on ``device`` (what upstream's loop moves there
    itself, with a blocking copy each: on CUDA a stream sync per step); any other batch as the
    loader gives it. ``len`` and every other name are the loader's."""

    def _moved(self, batch: Any) -> Any:
        if not (isinstance(batch, (tuple, list)) and len(batch) == 2 and torch.is_tensor(batch[0])
                and isinstance(batch[1], dict) and isinstance(batch[1].get("y"), dict)):
            return batch
        motion, cond = batch
        y = {k: to_device_without_sync(v, self.device) if torch.is_tensor(v) else v for k, v in cond["y"].items()}
        return type(batch)((to_device_without_sync(motion, self.device), {**cond, "y": y}))


def batches_on_device(original: Callable) -> Callable:
    """``original`` (upstream's ``TrainLoop.__init__``) then its ``data`` as :class:`DeviceBatches`
    on the loop's ``device`` (a loader asked to pin its batches, on CUDA). Not with MDM's
    ``--multi_target_cond``, whose goal sampling draws on the batch's device before the loop moves it."""

    @functools.wraps(original)
    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        device, data = getattr(self, "device", None), getattr(self, "data", None)
        if (not isinstance(device, torch.device) or data is None or isinstance(data, DeviceBatches)
                or getattr(getattr(self, "args", None), "multi_target_cond", False)):
            return
        pin_batches(data, device)
        self.data = DeviceBatches(data, device)

    return __init__
