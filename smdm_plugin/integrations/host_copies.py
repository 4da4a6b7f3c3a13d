"""Host-to-device copies of upstream training loops without a host sync (``--sparse_compile`` runs on
CUDA): PyTorch's blocking copy from pageable memory synchronizes the stream after it, so each made the
host wait for the device once per step. Here: pinned memory and ``non_blocking=True`` (the same
values); the timestep samplers' draws stay upstream's (numpy, on the host); a loader's batches reach
the device before the loop's own ``.to(device)``, which then copies nothing."""
from __future__ import annotations

import functools
from typing import Any, Callable, Tuple

import torch

__all__ = ["to_device_without_sync", "sample_without_sync", "DeviceBatches", "pin_batches"]


def to_device_without_sync(t: torch.Tensor, device: torch.device) -> torch.Tensor:
    """``t`` on ``device``: from pinned memory without blocking on CUDA (a batch the loader pinned
    is not copied again on the host), else ``t.to(device)``."""
    if device.type == "cuda":
        return t.pin_memory().to(device, non_blocking=True)
    return t.to(device)


def sample_without_sync(original: Callable) -> Callable:
    """``original`` (upstream's ``ScheduleSampler.sample(self, batch_size, device)`` of MDM and
    MotionDiffuse: numpy draws, then two blocking host-to-device copies) drawing the same on the
    host, copied to a CUDA ``device`` from pinned memory without a sync; other devices: ``original``."""

    @functools.wraps(original)
    def sample(self: Any, batch_size: int, device: Any) -> Tuple[torch.Tensor, torch.Tensor]:
        dev = torch.device(device)
        if dev.type != "cuda":
            return original(self, batch_size, device)
        indices, weights = original(self, batch_size, "cpu")
        return to_device_without_sync(indices, dev), to_device_without_sync(weights, dev)

    return sample


class DeviceBatches:
    """An upstream data loader whose batches come with the tensors its loop moves to ``device``
    already there (:meth:`_moved`, per family); ``len`` and every other name are the loader's."""

    def __init__(self, loader: Any, device: torch.device) -> None:
        self.loader, self.device = loader, device

    def __iter__(self) -> Any:
        for batch in self.loader:
            yield self._moved(batch)

    def _moved(self, batch: Any) -> Any:
        """``batch`` with the tensors the loop moves on ``device`` (any other batch as it is)."""
        return batch

    def __len__(self) -> int:
        return len(self.loader)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.loader, name)


def pin_batches(loader: Any, device: torch.device) -> None:
    """Ask a ``DataLoader`` that feeds ``device`` (CUDA) to pin its batches (in its own thread, with
    workers), so that :func:`to_device_without_sync` copies them as they are."""
    if device.type == "cuda" and isinstance(loader, torch.utils.data.DataLoader):
        loader.pin_memory = True
