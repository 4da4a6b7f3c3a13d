"""Whether a training batch can fit at all: a lower bound of the memory one optimiser step of the
in-package trainer needs, against the memory the device has free (``smdm train --batch``)."""
from __future__ import annotations

import os
from typing import Any, Mapping, Optional

import torch

from ..core.config import SparseConfig
from ..core.selection import keyframe_count

__all__ = ["step_bytes", "available_bytes", "check_batch_fits"]

_F32 = 4
_GIB = float(1 << 30)


def model_parameters(model: Mapping[str, Any], features: int) -> int:
    """A lower bound of TinyMDM's parameter count (``model``: its size options, ``features`` D):
    pose in and out, and per layer the attention's four projections and the feed-forward."""
    d, ff, layers = int(model["latent_dim"]), int(model["ff_size"]), int(model["num_layers"])
    return 2 * features * d + layers * (4 * d * d + 2 * d * ff)


def step_bytes(batch: int, frames: int, features: int, model: Mapping[str, Any],
               sparse: Optional[SparseConfig] = None) -> int:
    """Lower bound of the bytes one training step of ``batch`` samples of ``frames`` frames and
    ``features`` features holds (module doc); ``sparse`` runs the transformer on keyframes only."""
    d, ff, layers = int(model["latent_dim"]), int(model["ff_size"]), int(model["num_layers"])
    tokens = (keyframe_count(frames, float(sparse.reduction)) if sparse is not None else frames) + 1
    per_sample = 4 * frames * features + layers * tokens * (5 * d + ff)
    return _F32 * (4 * model_parameters(model, features) + batch * per_sample)


def available_bytes(device: torch.device) -> Optional[int]:
    """Memory a new allocation can get on ``device``: CUDA's free device memory, on the CPU the
    available RAM (Linux ``MemAvailable``, else free pages); None where unknown (MPS, others)."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    if device.type != "cpu":
        return None
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def check_batch_fits(batch: int, frames: int, features: int, model: Mapping[str, Any],
                     sparse: Optional[SparseConfig], device: torch.device, processes: int = 1,
                     available: Optional[int] = None) -> None:
    """``ValueError`` naming ``--batch`` when ``batch`` samples per process cannot fit in the memory
    ``device`` has free (:func:`available_bytes`, or ``available``), ``processes`` processes sharing
    it (on the CPU: the processes of this machine); nothing when the free memory is unknown."""
    free = available_bytes(device) if available is None else available
    if free is None:
        return
    need = processes * step_bytes(batch, frames, features, model, sparse)
    if need <= free:
        return
    fixed = processes * step_bytes(0, frames, features, model, sparse)
    per_sample = processes * step_bytes(1, frames, features, model, sparse) - fixed
    most = max(0, (free - fixed) // per_sample)
    where = f"{device}" + (f", shared by {processes} processes" if processes > 1 else "")
    raise ValueError(f"argument --batch: {batch} samples per step need at least {need / _GIB:,.1f} GiB "
                     f"({frames} frames x {features} features, TinyMDM {model['latent_dim']}-D x "
                     f"{model['num_layers']} layer(s)), more than the {free / _GIB:,.1f} GiB free on {where}; "
                     f"at most about {most} can fit")
