"""Count the kernels a block would launch on a CUDA device, by running it on the CPU."""
from __future__ import annotations

import collections
import dataclasses
import inspect
from typing import Any, Callable, Iterable

import torch
import torch.nn.functional as F
from torch.optim.optimizer import register_optimizer_step_pre_hook
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves
from torch.utils.weak import WeakTensorKeyDictionary

from ..core.kernels.dispatch import OBSERVERS

__all__ = ["LaunchCounter", "LaunchCount", "count_launches", "SYNC_OPS", "AUTOCAST_DIFFERENCES"]

_aten = torch.ops.aten

#: ops that make the host wait for the device (or build device tensors from host data)
SYNC_OPS = frozenset({
    "aten._local_scalar_dense.default", "aten.item.default", "aten.is_nonzero.default",
    "aten.nonzero.default", "aten.nonzero_static.default", "aten.masked_select.default",
    "aten.repeat_interleave.Tensor", "aten._unique2.default", "aten.unique_dim.default",
    "aten.unique_consecutive.default", "aten.lift_fresh.default", "aten.lift_fresh_copy.default"})

#: metadata-only ops (no kernel) that are not views by their schema
_FREE = frozenset({
    _aten.empty.memory_format, _aten.empty_like.default, _aten.empty_strided.default,
    _aten.new_empty.default, _aten.new_empty_strided.default, _aten._unsafe_view.default,
    _aten.lift_fresh.default, _aten.lift_fresh_copy.default, _aten.set_.source_Storage,
    _aten.set_.source_Storage_storage_offset, _aten.set_.source_Tensor, _aten.resize_.default,
    _aten.empty_permuted.default})

#: ops whose outputs are host data (``scalar_tensor``: a Python scalar wrapped by an op such as
#: ``torch.where(c, x, 0.0)`` or an autograd formula; CUDA passes it to the kernel by value)
_HOST_SOURCES = frozenset({_aten.lift_fresh.default, _aten.lift_fresh_copy.default,
                           _aten.scalar_tensor.default})

_BOOL_INDEX_OPS = frozenset({_aten.index.Tensor, _aten.index_put_.default, _aten.index_put.default})

#: where ``torch.autocast("cpu", torch.bfloat16)`` (what is counted) and CUDA's bf16 autocast
#: differ for the ops these models use (torch 2.13's lists): CUDA inserts a cast where the text says
#: so and the CPU does not, so a bf16 count here is a lower bound by one cast per such op on a bf16
#: input. In MDM's layers the norms and softmaxes see float32 inputs (the residual stream stays
#: float32 under autocast, SDPA's softmax is inside its kernel), so dense and sparse counts move
#: alike.
AUTOCAST_DIFFERENCES: dict[str, str] = {
    "layer_norm": "CUDA: fp32 list (a bf16 input is cast to fp32, output fp32); CPU: no cast "
                  "(runs in the input dtype)",
    "softmax / log_softmax / sum / cumsum / prod": "CUDA: fp32_set_opt_dtype (a bf16 input runs with "
                  "dtype=float32: one cast for bf16); CPU: in the input dtype",
    "exp / log / pow / rsqrt / reciprocal / erfinv / softplus": "CUDA: fp32 list (a cast per bf16 "
                  "input); CPU: in the input dtype",
    "mse_loss / l1_loss / smooth_l1_loss": "both: fp32 lists (the same casts)",
    "addmm / mm / bmm / baddbmm / matmul / linear / SDPA": "both: bf16 (the same casts)",
    "cat / stack / index_put / addcmul / addcdiv": "both: promote to the widest input dtype",
}


@dataclasses.dataclass(frozen=True)
class LaunchCount:
    """One counted run: ``count`` kernels CUDA would launch, ``ops`` by op name (launches per op),
    ``syncs`` host syncs by op name."""
    count: int
    ops: collections.Counter
    syncs: collections.Counter


class _OneKernel(torch.autograd.Function):
    """Runs ``fn`` (its CPU graph uncounted) and counts one kernel forward and one backward; the
    gradient is the CPU graph's."""

    @staticmethod
    def forward(ctx, counter: "LaunchCounter", name: str, fn: Callable, *inputs):
        with counter._silent(), torch.enable_grad():
            leaves = [i.detach().requires_grad_(i.requires_grad) if isinstance(i, torch.Tensor) else i
                      for i in inputs]
            out = fn(*leaves)
            result = out.detach()
        ctx.counter, ctx.name, ctx.out = counter, name, out
        ctx.leaves = leaves
        counter._launch(name)
        return result

    @staticmethod
    def backward(ctx, grad):
        wanted = [i for i, t in enumerate(ctx.leaves) if isinstance(t, torch.Tensor) and t.requires_grad]
        grads = [None] * len(ctx.leaves)
        with ctx.counter._silent():
            got = torch.autograd.grad(ctx.out, [ctx.leaves[i] for i in wanted], grad, allow_unused=True)
        for i, g in zip(wanted, got):
            grads[i] = g
        ctx.counter._launch(ctx.name + ".backward")
        ctx.out = ctx.leaves = None
        return (None, None, None, *grads)


def _autocast_inputs(tensors: list) -> list:
    """The casts autocast inserts before a lower-precision op (counted: they run outside the silence)."""
    if not torch.is_autocast_enabled("cpu"):
        return tensors
    dtype = torch.get_autocast_dtype("cpu")
    return [t.to(dtype) if isinstance(t, torch.Tensor) and t.is_floating_point()
            and t.dtype not in (dtype, torch.float64) else t for t in tensors]


_SDPA_SIGNATURE = inspect.Signature([
    inspect.Parameter(n, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=d) for n, d in (
        ("query", inspect.Parameter.empty), ("key", inspect.Parameter.empty),
        ("value", inspect.Parameter.empty), ("attn_mask", None), ("dropout_p", 0.0),
        ("is_causal", False), ("scale", None), ("enable_gqa", False))])


def _sdpa(counter: "LaunchCounter", func: Callable, args: tuple, kwargs: dict):
    bound = _SDPA_SIGNATURE.bind(*args, **kwargs)
    bound.apply_defaults()
    a = bound.arguments
    tensors = _autocast_inputs([a["query"], a["key"], a["value"], a["attn_mask"]])

    def fn(q, k, v, m):
        with torch.autocast("cpu", enabled=False):         # its casts were made (and counted) above
            return func(q, k, v, attn_mask=m, dropout_p=a["dropout_p"], is_causal=a["is_causal"],
                        scale=a["scale"], **({"enable_gqa": True} if a["enable_gqa"] else {}))
    return counter._one_kernel("aten.scaled_dot_product_attention", fn, tensors)


_DROPOUT_SIGNATURE = inspect.signature(F.dropout)


def _dropout(counter: "LaunchCounter", func: Callable, args: tuple, kwargs: dict):
    a = _DROPOUT_SIGNATURE.bind(*args, **kwargs)
    a.apply_defaults()
    x, p, train = (a.arguments[k] for k in ("input", "p", "training"))
    if not train or p == 0 or x.numel() == 0:
        return func(*args, **kwargs)
    with counter._silent():                                # native_dropout: 1 kernel forward ...
        out = func(*args, **kwargs)
    counter._launch("aten.native_dropout")
    return out                                             # ... its backward (the CPU's mul): 1


_ORIGINAL = {"scaled_dot_product_attention": F.scaled_dot_product_attention, "dropout": F.dropout}
_RULES = {"scaled_dot_product_attention": _sdpa, "dropout": _dropout}
_ACTIVE: list["LaunchCounter"] = []          # counters entered, innermost last


def _patched(name: str) -> Callable:
    original, rule = _ORIGINAL[name], _RULES[name]

    def wrapper(*args, **kwargs):
        counter = _ACTIVE[-1] if _ACTIVE else None
        if counter is None or counter._quiet:
            return original(*args, **kwargs)
        return rule(counter, original, args, kwargs)
    wrapper.__name__ = wrapper.__qualname__ = name
    wrapper.__doc__ = original.__doc__
    return wrapper


def _install() -> None:
    """While a counter is active, ``torch.nn.functional.scaled_dot_product_attention`` / ``dropout``
    (looked up at call time by ``nn.MultiheadAttention``, ``nn.Dropout`` and this package) count as
    CUDA's single kernels. (A ``TorchFunctionMode`` cannot do it: it is off inside the Python
    functions it intercepts, e.g. ``F.multi_head_attention_forward``.) Code that bound the functions
    at import time is counted by the CPU's dispatch: ``_scaled_dot_product_flash_attention_for_cpu``
    is 1 + 1 as well; the math path (dropout in training) is its decomposition."""
    for name in _ORIGINAL:
        setattr(F, name, _patched(name))


def _uninstall() -> None:
    for name, original in _ORIGINAL.items():
        setattr(F, name, original)


class LaunchCounter(TorchDispatchMode):
    """Context manager: the kernels a CUDA device would launch for the ops run inside it (module
    docstring: the rules). ``count``: total; ``ops``: launches by op name; ``syncs``: host syncs by
    op name. ``host``: extra tensors to treat as host data (e.g. a custom optimizer's CPU steps)."""

    def __init__(self, host: Iterable[torch.Tensor] = ()):
        super().__init__()
        self.ops: collections.Counter = collections.Counter()
        self.syncs: collections.Counter = collections.Counter()
        self._host = WeakTensorKeyDictionary()
        for t in host:
            self._host[t] = True
        self._quiet = 0
        self._hook = None

    @property
    def count(self) -> int:
        return sum(self.ops.values())

    def result(self) -> LaunchCount:
        return LaunchCount(self.count, collections.Counter(self.ops), collections.Counter(self.syncs))

    # -- context
    def __enter__(self):
        self._hook = register_optimizer_step_pre_hook(self._optimizer_steps_on_host)
        if not _ACTIVE:
            _install()
        _ACTIVE.append(self)
        OBSERVERS.append(self._fused)
        return super().__enter__()

    def __exit__(self, *exc):
        try:
            return super().__exit__(*exc)
        finally:
            OBSERVERS.remove(self._fused)
            _ACTIVE.remove(self)
            if not _ACTIVE:
                _uninstall()
            self._hook.remove()

    def _fused(self, name: str, kernel: Callable, args: list):
        """A fused op of the package (:class:`~smdm_plugin.core.kernels.dispatch.FusedOp`) that
        CUDA runs as one kernel: counted as one (its CPU composite silent)."""
        if self._quiet:
            return kernel(*args)
        with torch.no_grad():
            return self._one_kernel(name, kernel, args)

    def _optimizer_steps_on_host(self, optimizer, args, kwargs):
        """torch keeps a non-capturable, non-fused optimizer's ``step`` tensors on the CPU."""
        for group in optimizer.param_groups:
            if group.get("capturable") or group.get("fused"):
                continue
            for p in group["params"]:
                step = optimizer.state.get(p, {}).get("step")
                if isinstance(step, torch.Tensor):
                    self._host[step] = True

    # -- counting
    def _silent(self):
        counter = self

        class _Quiet:
            def __enter__(self):
                counter._quiet += 1

            def __exit__(self, *exc):
                counter._quiet -= 1
        return _Quiet()

    def _launch(self, name: str, n: int = 1) -> None:
        self.ops[name] += n

    def _one_kernel(self, name: str, fn: Callable, tensors: list):
        needs_grad = torch.is_grad_enabled() and any(
            isinstance(t, torch.Tensor) and t.requires_grad for t in tensors)
        if needs_grad:
            return _OneKernel.apply(self, name, fn, *tensors)
        with self._silent():
            out = fn(*tensors)
        self._launch(name)
        return out

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        if self._quiet:
            return out
        inputs = [t for t in tree_leaves((args, kwargs)) if isinstance(t, torch.Tensor)]
        host = func in _HOST_SOURCES or (bool(inputs) and all(t in self._host for t in inputs))
        if host:
            for t in tree_leaves(out):
                if isinstance(t, torch.Tensor):
                    self._host[t] = True
        name = str(func)
        if not host:
            bool_index = func in _BOOL_INDEX_OPS and any(
                isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] or ()))
            if name in SYNC_OPS or bool_index:
                self.syncs[name] += 1
            if any(t.dim() and t in self._host for t in inputs):   # host data fed to the device
                self.syncs["aten.lift_fresh.default"] += 1             # (0-d host scalars: by value)
        if not host and not func.is_view and func not in _FREE and func.namespace != "profiler":
            self.ops[name] += 1
        return out


def count_launches(fn: Callable[[], Any], *, warmup: int = 1) -> LaunchCount:
    """Run ``fn`` ``warmup`` times (caches, optimizer state, per-device tables), then count one run."""
    for _ in range(warmup):
        fn()
    with LaunchCounter() as counter:
        fn()
    return counter.result()
