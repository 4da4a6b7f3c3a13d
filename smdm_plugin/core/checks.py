"""Input checks that never stall a GPU.

A check on data (not shapes) needs the data's values. Where they are on the CPU (eager mode) the
check runs on the host and raises a ``ValueError`` naming the argument; on an accelerator, or while
``torch.compile`` traces, it becomes ``torch._assert_async`` with the same message: no host
synchronisation, the error surfaces at the next synchronising call. Shapes and dtypes are metadata
and are always checked on the host.
"""
from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Iterator, Optional, Sequence, Union

import numpy as np
import torch

LengthsLike = Union[torch.Tensor, Sequence[int], np.ndarray, None]

_STATIC = threading.local()


_IS_COMPILING = getattr(getattr(torch, "compiler", None), "is_compiling", None)


def compiling() -> bool:
    """True while ``torch.compile`` traces (data-dependent Python branches are not allowed then)."""
    return bool(_IS_COMPILING()) if _IS_COMPILING is not None else False


@contextmanager
def static_mode(enabled: bool = True) -> Iterator[None]:
    """Within the block, CPU tensors are treated as if they lived on an accelerator: no host reads
    of values (checks become ``torch._assert_async``), static shapes everywhere (the ``compact``
    backend, fixed-size embedding rows). The CPU proxy of the GPU code path, for tests and
    benchmarks; thread-local."""
    before = getattr(_STATIC, "on", False)
    _STATIC.on = enabled
    try:
        yield
    finally:
        _STATIC.on = before


def static_shapes() -> bool:
    """True under ``torch.compile`` or :func:`static_mode`: take the static-shape, sync-free path."""
    return compiling() or getattr(_STATIC, "on", False)


def host_checkable(t: torch.Tensor) -> bool:
    """Whether ``t``'s values can be read without a device sync or a graph break."""
    return t.device.type == "cpu" and not static_shapes()


def module_device(module: "torch.nn.Module") -> torch.device:
    """The device of ``module``'s first parameter (else buffer; the CPU when it has neither)."""
    for t in module.parameters():
        return t.device
    for t in module.buffers():
        return t.device
    return torch.device("cpu")


def require(cond: torch.Tensor, message: str) -> None:
    """Raise ``ValueError(message)`` unless every element of bool ``cond`` is True (host check on
    the CPU in eager mode; ``torch._assert_async`` otherwise)."""
    if host_checkable(cond):
        if not bool(cond.all()):
            raise ValueError(message)
    else:
        torch._assert_async(cond.all(), message)


class LengthsTypeError(TypeError, ValueError):
    """Lengths that are not integers (a ``TypeError`` that callers catching ``ValueError`` for bad
    lengths also catch)."""


def as_lengths(lengths: LengthsLike, B: int, N: int, device: torch.device, fn: str,
               clip: bool = False, minimum: int = 2, broadcast: bool = False) -> torch.Tensor:
    """``lengths`` as a long tensor ``[B]`` on ``device`` (None: all ``N``), checked: integers of
    shape ``[B]`` with ``minimum <= L <= N`` (``clip``: values above ``N`` cut to ``N``;
    ``broadcast``: a Python int or a single value stands for every sample). The one validation of
    per-sample frame counts; errors name ``fn``. On an accelerator the range is asserted on the
    device (no host sync)."""
    if lengths is None:
        if N < minimum:
            raise ValueError(f"{fn}: N must be >= {minimum} frames, got N={N}")
        return torch.full((B,), N, dtype=torch.long, device=device)
    if not isinstance(lengths, torch.Tensor):
        arr = np.asarray(lengths)
        if arr.dtype.kind not in "iu":
            raise LengthsTypeError(f"{fn}: lengths must be an integer tensor [B={B}], got dtype {arr.dtype}")
        lengths = torch.as_tensor(arr)
    if lengths.dtype.is_floating_point or lengths.dtype.is_complex or lengths.dtype == torch.bool:
        raise LengthsTypeError(f"{fn}: lengths must be an integer tensor [B={B}], got dtype {lengths.dtype}")
    if lengths.device.type == "meta":
        raise ValueError(f"{fn}: lengths is a 'meta' tensor (no values); pass the frame counts [B={B}] on the CPU"
                         + ("" if torch.device(device).type in ("cpu", "meta") else f" or on {device}"))
    if broadcast and lengths.numel() == 1:
        lengths = lengths.reshape(1).expand(B)
    if tuple(lengths.shape) != (B,):
        raise ValueError(f"{fn}: lengths must have shape [B={B}]{' (or be one int)' if broadcast else ''}, "
                         f"got {tuple(lengths.shape)}")
    if host_checkable(lengths) and B:
        lo, hi = int(lengths.min()), int(lengths.max())
        if lo < minimum:
            raise ValueError(f"{fn}: lengths must be >= {minimum}, got min {lo}")
        if hi > N and not clip:
            raise ValueError(f"{fn}: lengths must be <= N={N}, got max {hi}")
    elif B and clip:
        torch._assert_async((lengths >= minimum).all(), f"{fn}: lengths must be >= {minimum}")
    elif B:
        torch._assert_async(((lengths >= minimum) & (lengths <= N)).all(),
                            f"{fn}: lengths must be in [{minimum}, N={N}]")
    lengths = lengths.to(device=device, dtype=torch.long)
    return lengths.clamp(max=N) if clip else lengths


def as_mask(mask, B: int, N: int, device: torch.device, what: str) -> "Optional[torch.Tensor]":
    """A per-frame mask (e.g. forced keyframes) as bool ``[B, N]`` on ``device``; None stays None.
    The error names ``what`` (the argument) and the expected shape."""
    if mask is None:
        return None
    mask = torch.as_tensor(mask)
    if tuple(mask.shape) != (B, N):
        raise ValueError(f"{what} must be a bool tensor [B, N]=[{B}, {N}], got shape {tuple(mask.shape)}")
    return mask.to(device=device, dtype=torch.bool)
