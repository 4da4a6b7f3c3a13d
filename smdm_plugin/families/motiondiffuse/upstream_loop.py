"""MotionDiffuse's training step without its Python mask loop or a host sync per step.
``generate_src_mask`` filled ``[B, T]`` one element at a time (B * (T - length) tensor writes, ~6 ms
of host time at B = 32, T = 196; on CUDA lengths one read of the device each), once in the trainer's
``forward`` and once per dense denoiser call: flagged runs (``--sparse`` or ``--sparse_compile``)
make it in two ops (:func:`src_mask`). Under ``--sparse_compile`` where the fused optimizer applies
(CUDA), :func:`loop_without_sync` also removes the step's host syncs: batches, lengths and timesteps
copied from pinned memory without one, the loss logged as a :class:`LossValue` read when printed.
Every value is upstream's (the loss the same ops; the printed means the same float sums)."""
from __future__ import annotations

import contextlib
import sys
import threading
import types
from collections import OrderedDict
from typing import Any, Iterator, List, Optional, Sequence, Union

import torch

from ...integrations._hooks import WRAPPED
from ...integrations.host_copies import DeviceBatches, pin_batches, sample_without_sync, to_device_without_sync

__all__ = ["src_mask", "mask_without_loop", "LossValue", "upstream_loss", "deferring", "log_of", "MotionBatches",
           "TrainerTorch", "loop_without_sync", "LIMIT"]

#: device values a :class:`LossValue` keeps before it reads them by itself (one sync per this many)
LIMIT = 4096
_MARK = "_smdm_loop_without_sync"


def src_mask(T: int, length: Any) -> torch.Tensor:
    """Upstream's ``MotionTransformer.generate_src_mask(T, length)``: ``[B, T]`` in the default
    float dtype, 1 before each sample's ``length`` and 0 from it on; on ``length``'s device (a
    tensor; a list of ints or 0-d tensors: the CPU), where upstream's is always on the CPU (its
    callers move it to the motion's device)."""
    lengths = (length if torch.is_tensor(length) else torch.as_tensor(length)).reshape(-1)
    return (torch.arange(T, device=lengths.device) < lengths[:, None]).to(torch.get_default_dtype())


def mask_without_loop(model: Any) -> bool:
    """``model`` (upstream's ``MotionTransformer``, the core inside DDP / DataParallel) makes its
    padding mask with :func:`src_mask` (an instance attribute: the class stays upstream's). Returns
    whether it does."""
    if not hasattr(model, "generate_src_mask"):
        return False
    vars(model)["generate_src_mask"] = src_mask
    return True


class LossValue:
    """A loss logged per step and read when printed: the sum of the logged values, in order, as
    Python floats (upstream's ``logs[k] += loss.item()``), over ``divisor``. ``parts``: device
    scalars not read yet (after :data:`LIMIT` of them, read in one copy); ``total``: the sum of
    those read."""

    __slots__ = ("total", "parts", "divisor")

    def __init__(self, parts: Sequence[torch.Tensor] = (), total: float = 0.0, divisor: float = 1.0) -> None:
        self.total, self.parts, self.divisor = total, list(parts), divisor
        if len(self.parts) >= LIMIT:
            self.total, self.parts = self._read(), []

    @classmethod
    def of(cls, loss: torch.Tensor) -> "LossValue":
        """The value of a 0-d ``loss`` tensor, not read yet."""
        return cls([loss.detach()])

    def _read(self) -> float:
        total = self.total
        if self.parts:
            for v in torch.stack(self.parts).tolist():   # one copy to the host
                total += v
        return total

    def __float__(self) -> float:
        return self._read() / self.divisor if self.divisor != 1.0 else self._read()

    def __add__(self, other: Any) -> Union["LossValue", float]:
        """``self + other``; a step's value (one part) added to a sum waits with it: the same float
        additions, in the same order, when read. Anything else: a float now."""
        if isinstance(other, LossValue) and self.divisor == other.divisor == 1.0 and not other.total \
                and len(other.parts) == 1:
            return LossValue(self.parts + other.parts, self.total)
        return float(self) + float(other)

    def __radd__(self, other: Any) -> float:
        return float(other) + float(self)

    def __truediv__(self, other: Any) -> Union["LossValue", float]:
        if isinstance(other, (int, float)) and not isinstance(other, bool) and self.divisor == 1.0:
            return LossValue(self.parts, self.total, float(other))
        return float(self) / other

    def __format__(self, spec: str) -> str:
        return format(float(self), spec)

    def __repr__(self) -> str:
        return repr(float(self))


def upstream_loss(trainer: Any) -> torch.Tensor:
    """``DDPMTrainer.backward_G``'s loss, the same ops: the trainer's ``mse_criterion`` between its
    predicted and real noise, averaged over features, weighted by ``src_mask`` over its sum."""
    loss = trainer.mse_criterion(trainer.fake_noise, trainer.real_noise).mean(dim=-1)
    return (loss * trainer.src_mask).sum() / trainer.src_mask.sum()


def deferring(trainer: Any) -> bool:
    """Whether ``trainer``'s loss is logged as a :class:`LossValue` (:func:`loop_without_sync`)."""
    return bool(vars(trainer).get(_MARK))


class MotionBatches(DeviceBatches):
    """MotionDiffuse's loader: batches ``[caption, motions, m_lens]`` with ``motions`` on the
    device (lengths stay on the host: the trainer reads them there)."""

    def _moved(self, batch: Any) -> Any:
        if not (isinstance(batch, (list, tuple)) and len(batch) == 3 and torch.is_tensor(batch[1])):
            return batch
        caption, motions, m_lens = batch
        return type(batch)((caption, to_device_without_sync(motions, self.device), m_lens))


_LOCAL = threading.local()


def _long_tensor(*args: Any, **kwargs: Any) -> torch.Tensor:
    """``torch.LongTensor``; inside a hooked trainer's ``forward``, a list (the lengths) is made on
    the host and copied to the trainer's device from pinned memory without a sync."""
    device: Optional[torch.device] = getattr(_LOCAL, "device", None)
    if device is None or kwargs or len(args) != 1 or not isinstance(args[0], (list, tuple)):
        return torch.LongTensor(*args, **kwargs)
    return to_device_without_sync(torch.tensor([int(v) for v in args[0]], dtype=torch.long), device)


class TrainerTorch(types.ModuleType):
    """``torch`` as ``trainers/ddpm_trainer.py`` sees it: torch, but for ``LongTensor``
    (:func:`_long_tensor`)."""

    def __init__(self) -> None:
        super().__init__("torch", torch.__doc__)
        self.LongTensor = _long_tensor

    def __getattr__(self, name: str) -> Any:
        return getattr(torch, name)


@contextlib.contextmanager
def _lengths_on(device: torch.device) -> Iterator[None]:
    previous = getattr(_LOCAL, "device", None)
    _LOCAL.device = device
    try:
        yield
    finally:
        _LOCAL.device = previous


def loop_without_sync(trainer: Any, device: Any = None) -> List[str]:
    """Hook ``trainer`` (upstream's ``DDPMTrainer``, on CUDA) and its module: the loader that
    ``train`` builds pins its batches and hands ``motions`` on the device (:class:`MotionBatches`),
    ``forward``'s lengths copied without a sync (:class:`TrainerTorch`), the timestep sampler's
    copies too (:func:`~smdm_plugin.integrations.host_copies.sample_without_sync`), the loss logged
    as a :class:`LossValue` (by the hooks' ``backward_G``: :func:`deferring`; the patch route's is
    upstream's, which reads it); ``device``: the
    trainer's (``trainer.device`` when None). Once per trainer; returns what is hooked."""
    device = torch.device(trainer.device if device is None else device)
    module = sys.modules.get(type(trainer).__module__)
    done = []
    if module is not None and getattr(module, "torch", None) is torch:
        module.torch = TrainerTorch()
    forward = getattr(trainer, "forward", None)
    if forward is not None and isinstance(getattr(module, "torch", None), TrainerTorch):
        if not getattr(forward, _MARK, False):
            def forward_hooked(*args: Any, **kwargs: Any) -> Any:
                with _lengths_on(device):
                    return forward(*args, **kwargs)

            setattr(forward_hooked, _MARK, True)
            vars(trainer)["forward"] = forward_hooked
        done.append("lengths")
    build = getattr(module, "build_dataloader", None)
    if build is not None and not getattr(build, _MARK, False):
        def build_dataloader(*args: Any, **kwargs: Any) -> Any:
            loader = build(*args, **kwargs)
            pin_batches(loader, device)
            return MotionBatches(loader, device)

        setattr(build_dataloader, _MARK, True)
        module.build_dataloader = build_dataloader
    if build is not None:
        done.append("batches")
    sampler = getattr(trainer, "sampler", None)
    if sampler is not None:
        if "sample" not in vars(sampler):
            vars(sampler)["sample"] = types.MethodType(sample_without_sync(type(sampler).sample), sampler)
        done.append("timesteps")
    if getattr(getattr(type(trainer), "backward_G", None), WRAPPED, False):   # the hooks' (not the patch's)
        vars(trainer)[_MARK] = True
        done.append("loss")
    return done


def log_of(trainer: Any, loss: torch.Tensor) -> "OrderedDict[str, Any]":
    """``backward_G``'s return: ``{"loss_mot_rec": ...}``, a :class:`LossValue` when the trainer is
    hooked, else the float (one read)."""
    return OrderedDict(loss_mot_rec=LossValue.of(loss) if deferring(trainer) else loss.item())
