"""How the fused operators of :mod:`smdm_plugin.core.kernels` run: :class:`FusedOp`."""
from __future__ import annotations

import importlib
import warnings
from typing import Any, Callable, Dict, List, Optional

from ..checks import compiling

__all__ = ["TritonKernel", "FusedOp", "OBSERVERS", "TRITON_KERNELS", "use_triton_kernels"]

#: who watches fused ops (innermost last): ``observer(name, kernel, args)`` runs ``kernel(*args)``
#: and returns its result (:class:`~smdm_plugin.runtime.launches.LaunchCounter` counts one launch)
OBSERVERS: List[Callable[[str, Callable[..., Any], list], Any]] = []

#: every Triton kernel of the package, by what it computes (``TritonKernel.what``)
TRITON_KERNELS: Dict[str, "TritonKernel"] = {}


class TritonKernel:
    """``kernel(fallback, *args)``: the function ``name`` of ``module`` (a module of this package named
    relatively, ``.vw_triton``, so that the architecture test sees the import; it imports ``triton``)
    on ``args``, or ``fallback(*args)`` where it cannot run or is switched off. ``what`` names the
    kernel in the warning (and in :data:`TRITON_KERNELS`), ``slower`` what the fallback costs.

    ``enabled``: whether eager mode uses it (:func:`use_triton_kernels` switches it). A Triton launch
    from Python costs the host 80-340 µs on the H200 that measured it (docs/gpu.md), several aten
    ops' worth: a kernel that replaces only a few elementwise ops is off by default
    (``enabled=False``: the composite, cheaper on the host at MDM's size)."""

    def __init__(self, module: str, name: str, what: str, slower: str = "the composite (more kernels)",
                 enabled: bool = True) -> None:
        if what in TRITON_KERNELS:
            raise ValueError(f"TritonKernel: a kernel named {what!r} exists already")
        self.module, self.name, self.what, self.slower = module, name, what, slower
        self.default = self.enabled = bool(enabled)
        self.broken: Optional[str] = None          # why the kernel cannot be used (None: not known yet)
        self._fn: Optional[Callable[..., Any]] = None
        TRITON_KERNELS[what] = self

    @property
    def runs(self) -> bool:
        """Whether a CUDA call runs this kernel (switched on, not found broken)."""
        return self.enabled and self.broken is None

    def __call__(self, fallback: Callable[..., Any], *args: Any) -> Any:
        if not self.enabled:
            return fallback(*args)
        fn = self._fn
        if fn is None and self.broken is None:
            try:
                fn = self._fn = getattr(importlib.import_module(self.module, __package__), self.name)
            except ImportError as e:  # no triton (e.g. Windows): the fallback, quietly
                self.broken = f"triton is not importable ({e})"
        if fn is not None:
            try:
                return fn(*args)
            except Exception as e:  # a kernel that cannot be built here must not stop training
                self._fn, self.broken = None, f"{type(e).__name__}: {e}"
                warnings.warn(f"smdm: the Triton {self.what} kernel failed on this GPU ({self.broken}); "
                              f"using {self.slower}", RuntimeWarning, stacklevel=2)
        return fallback(*args)


def use_triton_kernels(on: Optional[bool] = None, names: Optional[List[str]] = None) -> Dict[str, bool]:
    """Switch the package's Triton kernels (``names``: keys of :data:`TRITON_KERNELS`, default all)
    on (``True``), off (``False``: the composite on CUDA) or back to their defaults (``None``), for
    eager calls from now on; returns each kernel's previous setting (pass it back one by one to
    restore). Values are the composite's either way (docs/gpu.md)."""
    chosen = list(TRITON_KERNELS) if names is None else list(names)
    unknown = [n for n in chosen if n not in TRITON_KERNELS]
    if unknown:
        raise ValueError(f"use_triton_kernels: names must be among {sorted(TRITON_KERNELS)}, got {unknown}")
    before = {n: TRITON_KERNELS[n].enabled for n in chosen}
    for n in chosen:
        k = TRITON_KERNELS[n]
        k.enabled = k.default if on is None else bool(on)
    return before


class FusedOp:
    """One fused operation ``op(*args)`` (first argument a tensor).

    Args:
        name: the op's name (``smdm::<name>`` when it is registered as an opaque custom op).
        composite: the op in torch ops: its reference values, traced under ``torch.compile``, and
            run in eager mode where no kernel is given for the device.
        cuda: the CUDA kernel (a :class:`TritonKernel`, falling back to ``fallback`` or the composite).
        kernels: other eager kernels by device type (e.g. ``{"cpu": numpy_kernel}``).
        fallback: what a CUDA kernel that cannot run falls back to (default: the composite).
        fake: output shapes (for tracing with ``opaque=True``, and the kernel on ``meta`` tensors).
        opaque: under ``torch.compile`` call a registered ``torch.library.custom_op`` (one graph
            node running the eager kernels) instead of tracing the composite.
    """

    def __init__(self, name: str, composite: Callable[..., Any], cuda: Optional[TritonKernel] = None,
                 kernels: Optional[Dict[str, Callable[..., Any]]] = None, fallback: Optional[Callable[..., Any]] = None,
                 fake: Optional[Callable[..., Any]] = None, opaque: bool = False) -> None:
        self.name, self.composite, self.cuda = name, composite, cuda
        self.kernels: Dict[str, Callable[..., Any]] = dict(kernels or {})
        self.fallback = fallback or composite
        if cuda is not None:
            fb = self.fallback
            self.kernels["cuda"] = lambda *args: cuda(fb, *args)
        if fake is not None:                  # meta tensors hold no values: the output's shape only
            self.kernels.setdefault("meta", fake)
        self.traced: Callable[..., Any] = composite
        if opaque:
            self.traced = self._register(fake)

    def kernel(self, t: Any) -> Callable[..., Any]:
        """The eager kernel for tensors on ``t``'s device (else the composite), unobserved: what a
        fused op of fused ops runs inside its own launch."""
        return self.kernels.get(t.device.type, self.composite)

    def eager(self, *args: Any) -> Any:
        """The op outside tracing: the kernel of the first argument's device, else the composite.
        While an observer models CUDA (:data:`OBSERVERS`): one observed launch where CUDA runs its
        kernel, else what CUDA runs instead (the fallback)."""
        kernel = self.kernel(args[0])
        if OBSERVERS and self.cuda is not None:
            if self.cuda.enabled:                    # a launch counter: CUDA runs it as one kernel
                return OBSERVERS[-1](f"smdm.{self.name}", kernel, list(args))
            return self.fallback(*args)
        return kernel(*args)

    def fused_on(self, t: Any) -> bool:
        """Whether eager mode runs a kernel of its own (not the composite) for tensors on ``t``'s
        device: a CUDA kernel that is on, or another device's kernel; while an observer models CUDA
        (:data:`OBSERVERS`), what CUDA runs; False while tracing."""
        if compiling():
            return False
        if OBSERVERS and self.cuda is not None:
            return self.cuda.enabled
        kind = t.device.type
        if kind not in self.kernels or kind == "meta":
            return False
        return kind != "cuda" or self.cuda is None or self.cuda.runs

    def __call__(self, *args: Any) -> Any:
        return self.traced(*args) if compiling() else self.eager(*args)

    def _register(self, fake: Optional[Callable[..., Any]]) -> Callable[..., Any]:
        """``smdm::<name>`` as a ``torch.library.custom_op`` running :meth:`eager` (torch >= 2.4;
        older: the eager function, which ``torch.compile`` cannot trace)."""
        import torch

        if not hasattr(torch.library, "custom_op"):  # pragma: no cover - torch < 2.4
            return self.eager
        op = torch.library.custom_op(f"smdm::{self.name}", mutates_args=())(self.composite)
        for device, kernel in self.kernels.items():
            if device != "meta" or fake is None:     # register_fake is the meta kernel (torch 2.11 refuses both)
                op.register_kernel(device)(kernel)
        if fake is not None:
            op.register_fake(fake)
        return op
