"""The one way the fused operators of :mod:`smdm_plugin.core.kernels` run their CUDA kernels: a
Triton kernel when ``triton`` imports and the kernel builds on this GPU, else a fallback (the op's
composite of torch ops, or a portable implementation), chosen once per kernel: no triton falls back
quietly, a kernel that fails on this GPU warns once and falls back from then on (a kernel that
cannot be built must not stop training)."""
from __future__ import annotations

import importlib
import warnings
from typing import Any, Callable, Optional

__all__ = ["TritonKernel", "register_op"]


class TritonKernel:
    """``kernel(fallback, *args)``: the function ``name`` of this package's module ``module`` (which
    imports ``triton``) on ``args``, or ``fallback(*args)`` where it cannot run. ``what`` names the
    kernel in the warning, ``slower`` what the fallback costs."""

    def __init__(self, module: str, name: str, what: str, slower: str = "the composite (more kernels)") -> None:
        self.module, self.name, self.what, self.slower = module, name, what, slower
        self.broken: Optional[str] = None          # why the kernel is not used (None: not known yet)

    def __call__(self, fallback: Callable[..., Any], *args: Any) -> Any:
        if self.broken is None:
            try:
                fn = getattr(importlib.import_module(f"{__package__}.{self.module}"), self.name)
            except ImportError as e:  # no triton (e.g. Windows): the fallback, quietly
                self.broken = f"triton is not importable ({e})"
            else:
                try:
                    return fn(*args)
                except Exception as e:  # a kernel that cannot be built here must not stop training
                    self.broken = f"{type(e).__name__}: {e}"
                    warnings.warn(f"smdm: the Triton {self.what} kernel failed on this GPU ({self.broken}); "
                                  f"using {self.slower}", RuntimeWarning, stacklevel=2)
        return fallback(*args)


def register_op(name: str, composite: Callable[..., Any], kernel: TritonKernel, fake: Callable[..., Any]):
    """``smdm::<name>`` (a ``torch.library.custom_op``, torch >= 2.4): ``composite`` on every device,
    ``kernel`` (falling back to ``composite``) on CUDA, ``fake`` for tracing."""
    import torch

    op = torch.library.custom_op(f"smdm::{name}", mutates_args=())(composite)
    op.register_kernel("cuda")(lambda *args: kernel(composite, *args))
    op.register_fake(fake)
    return op
