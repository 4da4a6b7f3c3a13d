"""Graph capture with one flag: ``--sparse_compile {none,default,reduce-overhead}`` (docs/compile.md)."""
from __future__ import annotations

import threading
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Tuple

import torch
import torch.nn as nn

__all__ = ["COMPILE_MODES", "CompileSetting", "CompiledFunction", "add_compile_options", "check_compile_mode",
           "compile_function", "compile_model", "compile_setting", "compile_stats", "uncompile", "compile_from_args",
           "compile_training_losses", "compile_losses_from_args", "compile_wrapper_call", "register_stats",
           "fused_optimizer_kwargs", "prepare_call", "CallPreparer", "preparer_of", "to_device"]

#: the values of ``--sparse_compile`` / ``smdm train --compile`` / ``smdm bench --compile``
COMPILE_MODES = ("none", "default", "reduce-overhead")
#: what one graph covers (:attr:`CompileSetting.captures`), as runs and tables state it
CAPTURES_MODEL = "model call"
CAPTURES_TRAIN = "training step: loss forward and backward"
CAPTURES_GUIDED = "guided sampling call: every guidance pass"
CAPTURES_SAMPLE_STEP = "sampling step: guided call and ancestral update"
#: the argparse option the upstream integrations add (``smdm train`` / ``bench`` call it ``--compile``)
FLAG = "--sparse_compile"
_WARN = "smdm compile"


def check_compile_mode(mode: Any, name: str = FLAG) -> str:
    """``mode`` as one of :data:`COMPILE_MODES` (``None``/``False`` = ``none``, ``True`` = ``default``);
    ``ValueError`` naming ``name`` otherwise."""
    if mode is None or mode is False:
        return "none"
    if mode is True:
        return "default"
    if not isinstance(mode, str) or mode not in COMPILE_MODES:
        raise ValueError(f"{name} must be one of {', '.join(COMPILE_MODES)}, got {mode!r}")
    return mode


@dataclass
class CompileSetting:
    """How a model runs: ``requested`` (what was asked), ``mode`` (what applies: ``none`` /
    ``default`` / ``reduce-overhead``), ``backend``, ``fullgraph``, ``note`` (why ``mode`` differs
    from ``requested``), ``captures`` (what one graph covers: ``model call``, ``training step``,
    ...); counters: ``compiled_calls``, ``warm_calls`` (each phase's first call, run eagerly to
    fill the caches the graph reads), ``eager_calls`` (calls outside the static batch, run
    eagerly), ``recompiles`` (graphs captured after a phase's first compiled call; 0 is the
    guarantee)."""

    requested: str
    mode: str
    backend: str = "inductor"
    fullgraph: bool = True
    note: str = ""
    captures: str = CAPTURES_MODEL
    compiled_calls: int = 0
    warm_calls: int = 0
    eager_calls: int = 0
    recompiles: int = 0

    def to_dict(self) -> Dict[str, Any]:
        """What a run records (``args.json``'s ``sparse_compile_applied``, ``train_config.json``...)."""
        return {"requested": self.requested, "mode": self.mode, "backend": self.backend,
                "fullgraph": self.fullgraph, "captures": self.captures, "note": self.note}

    def describe(self) -> str:
        if self.mode == "none":
            return "eager" + (f" ({self.note})" if self.note else "")
        s = f"torch.compile {self.mode} ({self.backend}, fullgraph={self.fullgraph}; {self.captures})"
        return s + (f"; {self.note}" if self.note else "")


def add_compile_options(parser: Any, flag: str = FLAG) -> Any:
    """Add ``flag {none,default,reduce-overhead}`` (default none) to an argparse parser or group;
    idempotent (the patch and the launcher may both call it)."""
    if flag in getattr(parser, "_option_string_actions", {}):
        return parser
    parser.add_argument(flag, default="none", choices=COMPILE_MODES,
                        help="smdm-plugin: torch.compile the model (dense or sparse) once before the loop; "
                             "reduce-overhead adds CUDA graphs (CUDA only; elsewhere: default, with a warning). "
                             "See smdm-plugin docs/compile.md")
    return parser


# --------------------------------------------------------------------------- call preparation
def to_device(value: Any, device: torch.device) -> Any:
    """A tensor on ``device``, contiguous (a slice's strides would be guarded: DiP's prefix is the
    previous window's tail); anything else as it is."""
    if isinstance(value, torch.Tensor):
        if value.device != device:
            value = value.to(device, non_blocking=True)
        return value.contiguous()
    return value


class CallPreparer:
    """How one model family's calls are made ready for graph capture (its ``FamilySpec.preparer``):
    :meth:`prepare` runs eagerly before every compiled call (what cannot be captured: text
    encoding, strings, tensors on other devices); :meth:`attach` / :meth:`detach` when a model is
    compiled / uncompiled. The base class leaves a call as it is."""

    def prepare(self, model: nn.Module, args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
        return args, kwargs

    def attach(self, model: nn.Module) -> None:
        """Before the model's first compiled call (e.g. a text encoder that passes features through)."""

    def detach(self, model: nn.Module) -> None:
        """Undo :meth:`attach` (:func:`uncompile`)."""

    def __call__(self, model: nn.Module, args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
        return self.prepare(model, args, kwargs)


class _FunctionPreparer(CallPreparer):
    """A ``FamilySpec.preparer`` given as a function ``prepare(model, args, kwargs)``."""

    def __init__(self, fn: Callable[[nn.Module, tuple, dict], Tuple[tuple, dict]]) -> None:
        self.fn = fn

    def prepare(self, model: nn.Module, args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
        return self.fn(model, args, kwargs)


def preparer_of(model: nn.Module) -> CallPreparer:
    """The call preparer of ``model``'s family (found once, by the family registry: the family that
    converted a sparse model, else the first that matches); a preparer that changes nothing for a
    model of no registered family, or of a family registered without one."""
    from ..adapters.families import FAMILY_SPECS, family_of, family_part

    family = family_of(model)
    if family is None or family.name not in FAMILY_SPECS:
        return CallPreparer()
    preparer = family_part(FAMILY_SPECS.get(family.name), "preparer")
    if preparer is None:
        return CallPreparer()
    return preparer if isinstance(preparer, CallPreparer) else _FunctionPreparer(preparer)


# --------------------------------------------------------------------------- the compiled call
def _first_tensor(args: tuple, kwargs: dict) -> Optional[torch.Tensor]:
    for v in list(args) + list(kwargs.values()):
        if isinstance(v, torch.Tensor):
            return v
    return None


def _clone_outputs(out: Any) -> Any:
    if isinstance(out, torch.Tensor):
        return out.clone()
    if isinstance(out, (tuple, list)):
        return type(out)(_clone_outputs(o) for o in out)
    if isinstance(out, dict):
        return {k: _clone_outputs(v) for k, v in out.items()}
    return out


def _reads_forced(args: tuple, kwargs: dict) -> bool:
    """Whether a call carries forced keyframes (a :class:`KeyframeRequest` with ``forced``), in
    MDM's ``y`` or MotionDiffuse's keyword arguments, without a ``forced_bound``: its plan is sized
    by counting them on the host (with a bound nothing is read, and the call traces whole)."""
    from ..adapters.request import KEYFRAMES_KEY

    for container in [kwargs] + [a for a in args if isinstance(a, dict)] + \
            [v for v in kwargs.values() if isinstance(v, dict)]:
        request = container.get(KEYFRAMES_KEY)
        if getattr(request, "forced", None) is not None and getattr(request, "forced_bound", None) is None:
            return True
    return False


def _graph_count() -> int:
    from torch._dynamo.utils import counters

    return int(counters["stats"]["unique_graphs"])


def _autocast_key(device: torch.device) -> Optional[Tuple[bool, torch.dtype]]:
    """``(enabled, dtype)`` of autocast on ``device``'s type (a phase of its own: another dtype is
    another graph); None where autocast has no state (``meta``)."""
    try:
        return torch.is_autocast_enabled(device.type), torch.get_autocast_dtype(device.type)
    except RuntimeError:
        return None


def _contiguous(value: Any) -> Any:
    """Tensors (top level, and in a top-level dict) made contiguous: a graph guards on strides, and
    a model's output fed back (a sampling loop's ``x_t``) may come back in another layout."""
    if isinstance(value, torch.Tensor):
        return value.contiguous()
    if isinstance(value, dict):
        return {k: v.contiguous() if isinstance(v, torch.Tensor) else v for k, v in value.items()}
    return value


def _none() -> None:
    return None


class _Holder(nn.Module):
    """``run`` as a module's forward, ``model`` its submodule: what ``torch.func.functional_call``
    reparametrizes for a compiled call that reads the model's matmul weights from their casts
    (parameter names ``model.<name>``)."""

    def __init__(self, model: nn.Module, run: Callable) -> None:
        super().__init__()
        self._modules["model"] = model               # (not a registration: no structure change)
        self.run = run

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        return self.run(*args, **kwargs)


class _EagerDepth(threading.local):
    """How many compiled functions are running eagerly (a phase's first call, a call outside the
    static batch) on this thread's stack: compiled functions they call run eagerly as well."""

    depth = 0


_EAGER_OUTER = _EagerDepth()


class CompiledFunction:
    """A function ``fn`` compiled for ``setting`` (:func:`compile_function`; the model call of
    :func:`compile_model` is one too), with the guarantees of docs/compile.md:

    * per *phase* (``model``'s train / eval, grad on / off, autocast, device, the first tensor's
      shape without the batch, fullgraph) the **first call runs eagerly** on the static-shape path
      (:func:`~smdm_plugin.core.checks.static_mode`; it fills the per-device caches the trace
      then only reads) and fixes the phase's static batch; the next call captures the graph, and
      no later call captures another (``recompiles`` counts any that does);
    * a call with another batch size (a last partial batch) runs eagerly (``eager_calls``);
    * ``reduce-overhead`` on CUDA: ``cudagraph_mark_step_begin()`` before each call and the
      outputs cloned (a later replay never overwrites what a caller holds);
    * called while an outer compiled function traces, ``fn`` is traced inline (one graph); called
      while one runs eagerly (its warm call), ``fn`` runs eagerly (no graph of its own);
    * a call without autograd of a ``model`` reads what its modules make from parameters alone
      (FSQ's folded projections, Lipschitz weights) from their stores, refreshed in place before
      the call (:mod:`~smdm_plugin.core.products`), instead of remaking them in its graph.

    ``prepare(args, kwargs) -> (args, kwargs)`` runs first, eagerly, on every call (text encoded,
    tensors on the motion's device: what cannot be captured)."""

    def __init__(self, fn: Callable, setting: CompileSetting, model: Optional[nn.Module] = None,
                 prepare: Optional[Callable[[tuple, dict], Tuple[tuple, dict]]] = None) -> None:
        self.fn, self.setting, self.model, self.prepare = fn, setting, model, prepare
        self._compiled: Dict[bool, Callable] = {}
        self._mode: Optional[str] = None
        self._static: Dict[tuple, int] = {}
        self._traced: set = set()
        self._warned_eager = False

    def _run(self, *args: Any, **kwargs: Any) -> Any:
        """``fn`` itself (eager, or traced)."""
        return self.fn(*args, **kwargs)

    def _fullgraph(self, args: tuple, kwargs: dict) -> bool:
        return self.setting.fullgraph

    def _eager(self, args: tuple, kwargs: dict) -> Any:
        """``fn`` run eagerly, and compiled functions it calls (a compiled model) eagerly too: their
        calls belong to this one's graph, and would otherwise capture one of their own."""
        _EAGER_OUTER.depth += 1
        try:
            return self._run(*args, **kwargs)
        finally:
            _EAGER_OUTER.depth -= 1

    def _phase(self, x: torch.Tensor, fullgraph: bool) -> tuple:
        training = None if self.model is None else self.model.training
        return (training, torch.is_grad_enabled(), _autocast_key(x.device), x.device.type, tuple(x.shape[1:]),
                fullgraph)

    def _function(self, device: torch.device, fullgraph: bool, casts: bool = False) -> Tuple[Callable, bool]:
        """The compiled ``fn`` (made on the first compiled call; one per ``fullgraph`` and ``casts``:
        called as ``fn(casts, *args)``, the model's matmul parameters read from ``casts``,
        :mod:`~smdm_plugin.core.weight_casts`) and whether CUDA graphs apply."""
        s = self.setting
        if self._mode is None:
            self._mode = s.mode
            if s.mode == "reduce-overhead" and device.type != "cuda":
                self._mode = s.mode = "default"
                s.note = (s.note + "; " if s.note else "") + \
                    f"reduce-overhead needs CUDA graphs; the model runs on {device.type}: compiled with default"
                warnings.warn(f"{_WARN}: {s.note}", stacklevel=4)
        key = (fullgraph, casts)
        if key not in self._compiled:
            kwargs: Dict[str, Any] = dict(fullgraph=fullgraph, dynamic=False, backend=s.backend)
            if s.backend == "inductor":
                kwargs["mode"] = None if self._mode == "default" else self._mode
            run = self._run
            if casts:
                holder = _Holder(self.model, run)

                def call(over: Dict[str, torch.Tensor], *args: Any, **kw: Any) -> Any:
                    return torch.func.functional_call(holder, over, args, kw)
            else:
                def call(*args: Any, **kw: Any) -> Any:    # traced as one frame, the hooks inlined
                    return run(*args, **kw)

            self._compiled[key] = torch.compile(call, **kwargs)
        return self._compiled[key], self._mode == "reduce-overhead" and device.type == "cuda"

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        from ..core.checks import compiling, static_mode   # here: a flag-off run loads only the options
        from ..core.products import armed_products, refresh_products
        from ..core.weight_casts import refresh_casts

        if compiling() or _EAGER_OUTER.depth:        # inside an outer compiled function: one graph
            return self._run(*args, **kwargs)        # (or that function's eager call: eager too)
        if self.prepare is not None:
            args, kwargs = self.prepare(args, kwargs)
        args, kwargs = tuple(map(_contiguous, args)), {k: _contiguous(v) for k, v in kwargs.items()}
        x = _first_tensor(args, kwargs)
        if x is None:
            return self._run(*args, **kwargs)
        fullgraph = self._fullgraph(args, kwargs)
        phase = self._phase(x, fullgraph)
        batch = self._static.get(phase)
        if batch is None:                            # the phase's first call: eager, caches filled
            self._static[phase] = x.shape[0]
            self.setting.warm_calls += 1
            with static_mode():
                return self._eager(args, kwargs)
        if x.shape[0] != batch:                      # outside the static batch: eager, no recompile
            self.setting.eager_calls += 1
            if not self._warned_eager:
                self._warned_eager = True
                warnings.warn(f"{_WARN}: a call with batch {x.shape[0]} (static batch {batch} for this "
                              f"shape) runs eagerly; the compiled graph keeps its static batch", stacklevel=3)
            return self._eager(args, kwargs)
        armed = self.model is not None and not torch.is_grad_enabled()
        casts = None
        if armed:                                    # what the graph reads instead of remaking
            refresh_products(self.model)
            casts = refresh_casts(self.model, x.device.type, "model.")
        fn, graphs = self._function(x.device, fullgraph, casts is not None)
        if casts is not None:
            args = (casts,) + args
        self.setting.compiled_calls += 1
        before = _graph_count()
        with armed_products(armed):
            if graphs:
                torch.compiler.cudagraph_mark_step_begin()
                out = _clone_outputs(fn(*args, **kwargs))
            else:
                out = fn(*args, **kwargs)
        if phase in self._traced and _graph_count() > before:
            self.setting.recompiles += 1
        self._traced.add(phase)
        return out

    def __reduce__(self):                            # torch.save(model): saved uncompiled
        return (_none, ())


class _ModelCalls(CompiledFunction):
    """A compiled function over a model's calls: calls carrying forced keyframes without a bound
    are a phase of their own, traced with a graph break (their count is read on the host)."""

    def _fullgraph(self, args: tuple, kwargs: dict) -> bool:
        # forced keyframes (sample.edit, in-betweening) without a bound are counted on the host once
        # per call, as in eager: such calls trace with a graph break there (a phase of their own)
        return self.setting.fullgraph and not _reads_forced(args, kwargs)


class _CompiledCall(_ModelCalls):
    """What ``model.__call__`` runs once compiled (``nn.Module._compiled_call_impl``): the module's
    ``_call_impl`` (hooks included), each call prepared by its family's :class:`CallPreparer`."""

    def __init__(self, model: nn.Module, setting: CompileSetting, preparer: CallPreparer) -> None:
        self.preparer = preparer
        super().__init__(model._call_impl, setting, model,
                         lambda args, kwargs: preparer.prepare(model, args, kwargs))


# --------------------------------------------------------------------------- entry points
def _fullgraph_default(model: nn.Module) -> bool:
    """Sparse models trace whole (fullgraph) when their family says so
    (:meth:`~smdm_plugin.adapters.family.ModelFamily.traces_whole`: not DoubleTake's without a
    forced bound, whose forced keyframes are counted on the host once per call, as in eager); dense
    ones do not."""
    from ..adapters.state import get_state

    state = get_state(model)
    return state is not None and state.family.traces_whole(model)


def _setting(mode: Any, backend: Any, fullgraph: bool, device: Any, name: str, captures: str) -> CompileSetting:
    """The :class:`CompileSetting` of ``mode`` (checked, named ``name``) as it can apply with
    ``backend`` on ``device`` (default: CUDA when available): ``reduce-overhead`` needs inductor and
    CUDA, else a warning and ``default``."""
    mode = check_compile_mode(mode, name)
    setting = CompileSetting(requested=mode, mode=mode, backend=backend, fullgraph=fullgraph, captures=captures)
    if mode == "none":
        return setting
    if backend != "inductor" and mode == "reduce-overhead":
        setting.mode = "default"
        setting.note = f"reduce-overhead needs the inductor backend, got {backend!r}: compiled without CUDA graphs"
        warnings.warn(f"{_WARN}: {setting.note}", stacklevel=3)
    dev = torch.device(device) if device is not None else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if setting.mode == "reduce-overhead" and dev.type != "cuda":
        setting.mode = "default"
        setting.note = f"reduce-overhead needs CUDA graphs; no CUDA device here ({dev.type}): compiled with default"
        warnings.warn(f"{_WARN}: {setting.note}", stacklevel=3)
    return setting


def _inner(model: nn.Module) -> nn.Module:
    """The module inside DDP / DataParallel wrappers (what is compiled)."""
    if isinstance(model, (nn.parallel.DistributedDataParallel, nn.DataParallel)):
        return model.module
    return model


def compile_model(model: nn.Module, mode: Any, *, backend: Any = "inductor", fullgraph: Optional[bool] = None,
                  device: Any = None, name: str = FLAG) -> CompileSetting:
    """Compile ``model`` in place for ``mode`` (:data:`COMPILE_MODES`); returns its
    :class:`CompileSetting` (also on ``compile_setting(model)``). ``none`` leaves the model
    untouched (bit for bit). ``fullgraph``: default True for sparse models (DoubleTake's excepted: its
    forced keyframes are read on the host), False for dense ones (upstream's dense MotionDiffuse
    builds its padding mask in a Python loop). ``device``: where
    the model will run (default: CUDA when available), to decide now whether ``reduce-overhead``
    can apply (else a warning and ``default``). Compiling again replaces the previous setting."""
    if not isinstance(model, nn.Module):
        check_compile_mode(mode, name)
        raise TypeError(f"compile_model: expected an nn.Module, got {type(model).__name__}")
    model = _inner(model)                            # compile inside DDP / DataParallel wrappers
    uncompile(model)
    fullgraph = _fullgraph_default(model) if fullgraph is None else bool(fullgraph)
    setting = _setting(mode, backend, fullgraph, device, name, CAPTURES_MODEL)
    if setting.requested == "none":
        return setting
    preparer = preparer_of(model)
    preparer.attach(model)                           # uncompile() detaches it
    model._compiled_call_impl = _CompiledCall(model, setting, preparer)
    return setting


def prepare_call(model: nn.Module) -> Callable[[tuple, dict], Tuple[tuple, dict]]:
    """``prepare(args, kwargs)`` of a call whose arguments are ``model``'s own (``(x, timesteps, y)``
    / MotionDiffuse's): its family's :class:`CallPreparer` (for :func:`compile_function`'s
    ``prepare``: e.g. a guidance wrapper's call, prepared as the model's)."""
    model = _inner(model)
    preparer = preparer_of(model)
    return lambda args, kwargs: preparer.prepare(model, args, kwargs)


def compile_function(fn: Callable, mode: Any, *, model: Optional[nn.Module] = None, backend: Any = "inductor",
                     fullgraph: Optional[bool] = None, device: Any = None, name: str = FLAG,
                     captures: str = "function", prepare: Optional[Callable] = None) -> Callable:
    """``fn`` compiled for ``mode`` with the guarantees of :class:`CompiledFunction` (first call of
    each phase eager, static batch, no recompiles, CUDA graphs under ``reduce-overhead``): a
    whole training loss (its backward compiled with it by AOTAutograd), a guided sampling call,
    a sampling step. ``model``: the module ``fn`` runs (its train / eval mode is part of the phase;
    ``fullgraph`` defaults as :func:`compile_model`'s); ``captures``: what the graph covers, as the
    run records it. ``none``: ``fn`` itself. The setting is on ``compile_setting(result)``."""
    if fullgraph is None:
        fullgraph = _fullgraph_default(_inner(model)) if model is not None else True
    setting = _setting(mode, backend, bool(fullgraph), device, name, captures)
    if setting.requested == "none":
        return fn
    return CompiledFunction(fn, setting, None if model is None else _inner(model), prepare)


def compile_wrapper_call(wrapper: nn.Module, model: nn.Module, fn: Callable,
                         prepare: Callable[[tuple, dict], Tuple[tuple, dict]], captures: str) -> Optional[CompileSetting]:
    """A module that wraps a compiled ``model`` (a guidance wrapper: several calls of ``model`` per
    call of its own) compiled in place as ``model`` is (mode, backend, fullgraph of
    ``compile_setting(model)``): ``wrapper(*args)`` runs ``fn(*prepare(args))`` as one graph, the
    model's calls traced inline (``captures`` says what it covers). Nothing happens, and None is
    returned, when ``model`` is not compiled."""
    inner = compile_setting(model)
    if inner is None or inner.requested == "none":
        return None
    setting = CompileSetting(requested=inner.requested, mode=inner.mode, backend=inner.backend,
                             fullgraph=inner.fullgraph, note=inner.note, captures=captures)
    wrapper._compiled_call_impl = _ModelCalls(fn, setting, _inner(model), prepare)
    return setting


def fused_optimizer_kwargs(device: Any, mode: Any) -> Dict[str, Any]:
    """AdamW's keyword arguments for a captured run: ``fused=True`` (the whole update in a few
    multi-tensor kernels, no host sync) on CUDA when ``mode`` compiles; ``{}`` (torch's default,
    ``foreach``) otherwise."""
    if check_compile_mode(mode) != "none" and torch.device(device).type == "cuda":
        return {"fused": True}
    return {}


def compile_setting(model: Any) -> Optional[CompileSetting]:
    """The :class:`CompileSetting` of a model :func:`compile_model` compiled, or of a function
    :func:`compile_function` compiled (None: eager)."""
    if isinstance(model, CompiledFunction):
        return model.setting
    call = getattr(_inner(model), "_compiled_call_impl", None)
    return call.setting if isinstance(call, _CompiledCall) else None


def uncompile(model: nn.Module) -> nn.Module:
    """Undo :func:`compile_model` (the model runs eagerly again)."""
    call = getattr(model, "_compiled_call_impl", None)
    if isinstance(call, _CompiledCall):
        model._compiled_call_impl = None
        call.preparer.detach(model)
    return model


#: environment: the torch.compile backend of the integrations (default inductor; aot_eager / eager
#: trace the same graphs without generating code: quick checks on a CPU)
BACKEND_ENV = "SMDM_COMPILE_BACKEND"
#: environment: a JSON file the process writes at exit (``{rank}`` in it: torchrun's rank): per
#: compiled model its setting, calls, phases (static shapes), recompiles, and Dynamo's graph count
STATS_ENV = "SMDM_COMPILE_STATS"
_COMPILED: List[Tuple[str, CompileSetting, CompiledFunction]] = []


def compile_stats() -> Dict[str, Any]:
    """What the integrations compiled in this process: ``graphs`` (Dynamo's unique graphs, all
    models), ``models`` (name, setting, ``compiled_calls``, ``eager_calls``, ``phases``: the distinct
    (train/eval, grad, device, shape) combinations that ran compiled)."""
    from torch._dynamo.utils import counters

    return {"graphs": int(counters["stats"]["unique_graphs"]),
            "models": [{"name": name, **s.to_dict(), "compiled_calls": s.compiled_calls,
                        "warm_calls": s.warm_calls, "eager_calls": s.eager_calls, "recompiles": s.recompiles,
                        "phases": len(call._static)}
                       for name, s, call in _COMPILED]}


def _write_stats() -> None:
    import json
    import os

    path = os.environ.get(STATS_ENV)
    if path:
        path = path.replace("{rank}", os.environ.get("RANK", "0"))    # torchrun: a file per process
        with open(path, "w") as f:
            json.dump(compile_stats(), f, indent=2)


def compile_from_args(model: nn.Module, args: Any, device: Any = None) -> Optional[CompileSetting]:
    """The upstream integrations' entry point: compile ``model`` for ``args.sparse_compile`` (absent
    or ``none``: nothing happens, upstream runs bit for bit; returns None) with the backend of
    ``SMDM_COMPILE_BACKEND`` (default inductor). Returns the :class:`CompileSetting` that applies
    (the caller records it: ``args.json`` / ``opt.txt``). With ``SMDM_COMPILE_STATS=FILE`` the
    process writes :func:`compile_stats` there at exit."""
    mode = getattr(args, "sparse_compile", None)
    if mode in (None, "none"):
        return None
    setting = compile_model(model, mode, device=device, backend=default_backend())
    register_stats(type(model).__name__, _inner(model)._compiled_call_impl)
    return setting


def compile_training_losses(diffusion: Any, model: nn.Module, mode: Any, *, prepare: Callable[[tuple, dict], Tuple[tuple, dict]],
                            backend: Any = "inductor", device: Any = None, name: str = FLAG) -> Optional[CompiledFunction]:
    """``diffusion.training_losses`` compiled whole for ``mode``, in place on the instance (the
    sparse wrapper, when there is one, inside): a training step's loss forward, upstream's
    diffusion arithmetic around the model included, and its backward by AOTAutograd: one graph,
    what ``smdm train --compile`` captures (``captures``: :data:`CAPTURES_TRAIN`). ``model``: the
    module it trains (its mode is part of the phase); ``prepare``: the call made ready, eagerly
    (text encoded; upstream's noise drawn as upstream draws it). Compiling again replaces the
    previous function. Returns the :class:`CompiledFunction` (None for ``none``: nothing changes)."""
    current = diffusion.training_losses
    if isinstance(current, CompiledFunction):
        current = current.fn
    compiled = compile_function(current, mode, model=model, backend=backend, device=device, name=name,
                                captures=CAPTURES_TRAIN, prepare=prepare)
    if not isinstance(compiled, CompiledFunction):
        return None
    diffusion.training_losses = compiled
    return compiled


def register_stats(name: str, compiled: CompiledFunction) -> None:
    """Count ``compiled`` in what ``SMDM_COMPILE_STATS`` writes at exit (when it is set)."""
    import atexit
    import os

    if os.environ.get(STATS_ENV):
        if not _COMPILED:
            atexit.register(_write_stats)
        _COMPILED.append((name, compiled.setting, compiled))


def compile_losses_from_args(diffusion: Any, model: nn.Module, args: Any, prepare: Callable[[tuple, dict], Tuple[tuple, dict]],
                             device: Any = None) -> Optional[CompileSetting]:
    """:func:`compile_training_losses` for ``args.sparse_compile`` with :func:`default_backend`, as
    :func:`compile_from_args` compiles the model (``SMDM_COMPILE_STATS`` counts it too, after the
    model). Returns its setting, or None (``none`` / absent)."""
    mode = getattr(args, "sparse_compile", None)
    if mode in (None, "none"):
        return None
    inner = compile_setting(model)                # the model's, as it applies (its warning said why)
    backend = inner.backend if inner is not None else default_backend()
    with warnings.catch_warnings():
        if inner is not None:
            warnings.simplefilter("ignore")
        compiled = compile_training_losses(diffusion, _inner(model), mode if inner is None else inner.mode,
                                           prepare=prepare, backend=backend, device=device)
    if compiled is None:
        return None
    if inner is not None:
        compiled.setting.requested, compiled.setting.note = inner.requested, inner.note
    register_stats("training_losses", compiled)
    return compiled.setting


def default_backend() -> str:
    """The torch.compile backend when none is named: ``SMDM_COMPILE_BACKEND``, else ``inductor``
    (``--sparse_compile`` in upstream scripts, the default of ``smdm train / bench --compile-backend``)."""
    import os

    return os.environ.get(BACKEND_ENV) or "inductor"
