"""Upstream's diffusion tables on the model's device, made once: MDM's / priorMDM's /
MotionDiffuse's ``_extract_into_tensor(arr, timesteps, shape)`` copies a 1-D numpy array to
``timesteps``' device at every call: on CUDA a copy from pageable memory, which waits for the
device (PyTorch synchronizes the stream after a blocking host-to-device copy), six times per
sampling step of MDM's ``p_sample``; inside a compiled training step that array is a CPU tensor
in the graph (a copy per step, and no CUDA graph). With the hook the copy is made once per array
and device, eagerly, and a step (or its graph) reads the device table."""
from __future__ import annotations

import functools
import sys
from typing import Any, Callable, Dict, Tuple

import numpy as np
import torch

__all__ = ["tables_on_device", "extract_from_device_table"]

_MARK = "_smdm_device_tables"
#: tables kept per hooked module (upstream's schedules: about 15 arrays, per device)
MAX_TABLES = 64


def extract_from_device_table(original: Callable) -> Callable:
    """``original`` (upstream's ``_extract_into_tensor``) with its numpy table kept on each device
    it is read on: ``table[timesteps]`` as float32, broadcast to ``broadcast_shape`` (the values of
    ``original``'s ``from_numpy(arr).to(device)[timesteps].float()``, expanded). The table is made
    on an eager call; a traced call that meets a table not made yet runs ``original``, and so does
    a call once :data:`MAX_TABLES` tables are kept (an array made anew at every call, as upstream's
    ``FIXED_LARGE`` variances are, is not kept for ever)."""
    tables: Dict[Tuple[int, torch.device], Tuple[np.ndarray, torch.Tensor]] = {}

    @functools.wraps(original)
    def extract(arr: Any, timesteps: torch.Tensor, broadcast_shape: Any) -> torch.Tensor:
        if not isinstance(arr, np.ndarray) or not isinstance(timesteps, torch.Tensor):
            return original(arr, timesteps, broadcast_shape)
        key = (id(arr), timesteps.device)
        entry = tables.get(key)
        if entry is None:
            if torch.compiler.is_compiling() or len(tables) >= MAX_TABLES:
                return original(arr, timesteps, broadcast_shape)
            entry = tables[key] = (arr, torch.from_numpy(arr).to(device=timesteps.device))   # arr kept: its id stays its own
        res = entry[1][timesteps].float()
        return res.reshape(tuple(res.shape) + (1,) * (len(broadcast_shape) - res.dim())).expand(broadcast_shape)

    setattr(extract, _MARK, True)
    return extract


def tables_on_device(diffusion: Any) -> int:
    """Hook ``_extract_into_tensor`` in the modules that define ``diffusion``'s classes (once per
    module); returns how many modules carry the hook."""
    hooked = 0
    for cls in type(diffusion).__mro__:
        module = sys.modules.get(cls.__module__)
        fn = getattr(module, "_extract_into_tensor", None) if module is not None else None
        if not callable(fn):
            continue
        if not getattr(fn, _MARK, False):
            setattr(module, "_extract_into_tensor", extract_from_device_table(fn))
        hooked += 1
    return hooked
