"""Upstream's sampling loops (MDM's, DiP's, priorMDM's ``p_sample_loop_progressive`` and its DDIM
and in-betweening kin) make each step's timesteps with ``th.tensor([i] * B, device=device)``, and
``respace._WrappedModel`` maps them through ``th.tensor(self.timestep_map, device=...)`` at every
call: on CUDA each a blocking copy from pageable memory, after which PyTorch synchronizes the
stream, so the host waits for the device twice per step. With the hook the modules that define the
diffusion's classes see a ``th`` (:class:`TorchView`) whose ``tensor`` makes such int lists on the
device (a fill, or a copy of the device tensor made for the same list before): the same values and
dtype, a tensor of the caller's own; every other name and call is torch's."""
from __future__ import annotations

import sys
import types
from collections import OrderedDict
from typing import Any, Optional, Tuple

import torch

__all__ = ["TorchView", "timesteps_without_copy"]


#: int lists kept on the device per hooked process (upstream's ``timestep_map``: one per diffusion)
MAX_LISTS = 16
_LISTS: "OrderedDict[Tuple[int, torch.device, Optional[torch.dtype]], Tuple[list, tuple, torch.Tensor]]" = OrderedDict()


def _ints(data: Any) -> bool:
    """Whether ``data`` is a non-empty list of Python ``int`` (not ``bool``)."""
    return type(data) is list and bool(data) and all(type(v) is int for v in data)


def tensor(data: Any, *args: Any, **kwargs: Any) -> torch.Tensor:
    """``torch.tensor``. A list of ints with only ``device`` (and ``dtype``) given is made on that
    device: ``[i] * B`` as ``torch.full((B,), i, ...)``; another list as a copy (on the device) of
    the tensor made for the same list, with the same contents, the last time (:data:`MAX_LISTS`
    lists kept). The dtype is torch's (int64 unless ``dtype``); the result is the caller's own."""
    device = kwargs.get("device")
    if args or device is None or set(kwargs) - {"device", "dtype"} or torch.compiler.is_compiling() \
            or not _ints(data):
        return torch.tensor(data, *args, **kwargs)
    dtype = kwargs.get("dtype")
    first = data[0]
    if data.count(first) == len(data):
        return torch.full((len(data),), first, dtype=dtype or torch.int64, device=device)
    key = (id(data), torch.device(device), dtype)
    entry = _LISTS.get(key)
    if entry is None or entry[0] is not data or entry[1] != tuple(data):
        entry = _LISTS[key] = (data, tuple(data), torch.tensor(data, device=device, dtype=dtype))
        while len(_LISTS) > MAX_LISTS:
            _LISTS.popitem(last=False)
    return entry[2].clone()


class TorchView(types.ModuleType):
    """``torch`` as an upstream module sees it: :func:`tensor` in place of ``torch.tensor``, every
    other name read from torch at each use (a name torch gains or a test patches later included;
    ``torch.compile`` reads a module's names the same way)."""

    def __init__(self) -> None:
        super().__init__("torch", torch.__doc__)
        self.tensor = tensor

    def __getattr__(self, name: str) -> Any:
        return getattr(torch, name)


def timesteps_without_copy(diffusion: Any) -> int:
    """Give the modules that define ``diffusion``'s classes and name torch ``th`` a
    :class:`TorchView` (once per module); returns how many modules see it."""
    hooked = 0
    for cls in type(diffusion).__mro__:
        module = sys.modules.get(cls.__module__)
        th = getattr(module, "th", None) if module is not None else None
        if th is torch:
            module.th = TorchView()
            th = module.th
        hooked += isinstance(th, TorchView)
    return hooked
