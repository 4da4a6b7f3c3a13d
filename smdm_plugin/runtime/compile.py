"""Graph capture with one flag: ``--sparse_compile {none,default,reduce-overhead}`` (docs/compile.md).

One place compiles every model the integrations build (MDM / DiP, priorMDM's DoubleTake,
MotionDiffuse, ``smdm train``, ``smdm bench``), dense or sparse alike, so an A/B compares each
side at its best:

* :func:`compile_model` compiles the module **in place** (as ``nn.Module.compile`` does: the call,
  forward hooks included, goes through ``torch.compile``; ``dynamic=False``; ``fullgraph=True``
  for sparse models): parameter and buffer names do not change, so a checkpoint of a compiled
  model loads into an uncompiled one and back (no ``_orig_mod.`` prefix), ``copy.deepcopy`` gives
  an uncompiled copy (torch drops the compiled call; MDM's EMA model evaluates eagerly),
  ``DistributedDataParallel`` wraps the compiled module as usual
  (compile inside DDP).
* Each call is first *prepared* eagerly (:data:`PREPARERS`): what cannot be captured runs
  before the graph — text encoding (CLIP tokenises Python strings), strings dropped from ``y``,
  tensors moved to the motion's device (no CPU tensor becomes a changing graph input), and,
  at sampling, classifier-free guidance's unconditional pass folded into zeroed text features
  (exact in eval mode), so both guidance passes share one graph.
* **Static batch** (CUDA graphs replay fixed shapes): per phase (train / eval, grad on / off,
  autocast, motion shape without the batch) the first batch size seen is the static one; a call
  with another batch size (an epoch's last partial batch) runs **eagerly**, never recompiling, and
  is counted in :attr:`CompileSetting.eager_calls` (warned once).
* **The first call of a phase runs eagerly** (on the static-shape path the graph takes:
  :func:`~smdm_plugin.core.checks.static_mode`), counted in :attr:`CompileSetting.warm_calls`: it
  fills every per-device cache the sparse path keeps (the schedule's plan and count tables, the
  selection constants, the noise table on the device), so the trace that follows only reads them:
  no constant table, and no tensor of another device, is ever built inside a graph (issue 36's
  ``cuda:0, cpu`` crash), and no cache write fails a guard afterwards.
* :func:`compile_function` compiles more than the model call in the same way (``smdm train``'s
  whole training loss, ``smdm bench``'s guided sampling call and sampling step): the model's own
  compiled call is then traced inline (one graph for the whole function).
* ``reduce-overhead`` (CUDA graphs): ``torch.compiler.cudagraph_mark_step_begin()`` before
  every call and the outputs cloned, so the second guidance pass never overwrites the first
  pass's output. Without CUDA it cannot apply: a warning, and the run compiles with ``default``
  (stated in :attr:`CompileSetting.mode` / ``note``, which the runs write to their config).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Tuple

import torch
import torch.nn as nn

__all__ = ["COMPILE_MODES", "CompileSetting", "CompiledFunction", "add_compile_options", "check_compile_mode",
           "compile_function", "compile_model", "compile_setting", "compile_stats", "uncompile", "compile_from_args",
           "fused_optimizer_kwargs", "prepare_call", "PREPARERS"]

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
def _split_call(args: tuple, kwargs: dict) -> Tuple[Any, Any, Any]:
    x = args[0] if args else kwargs.get("x")
    t = args[1] if len(args) > 1 else kwargs.get("timesteps")
    y = args[2] if len(args) > 2 else kwargs.get("y")
    return x, t, y


def _join_call(args: tuple, kwargs: dict, x: Any, t: Any, y: Any) -> Tuple[tuple, dict]:
    args, kwargs = list(args), dict(kwargs)
    for i, (key, value) in enumerate((("x", x), ("timesteps", t), ("y", y))):
        if len(args) > i:
            args[i] = value
        elif key in kwargs:
            kwargs[key] = value
    return tuple(args), kwargs


def _to(value: Any, device: torch.device) -> Any:
    """A tensor on ``device``, contiguous (a slice's strides would be guarded: DiP's prefix is the
    previous window's tail); anything else as it is."""
    if isinstance(value, torch.Tensor):
        if value.device != device:
            value = value.to(device, non_blocking=True)
        return value.contiguous()
    return value


def _is_strings(value: Any) -> bool:
    return isinstance(value, str) or (isinstance(value, (list, tuple)) and len(value) > 0
                                      and all(isinstance(v, str) for v in value))


def _zeros_like_text(enc: Any) -> Any:
    if isinstance(enc, tuple):          # DiP's BERT encoder: (features, padding mask); only features zeroed
        return (torch.zeros_like(enc[0]),) + tuple(enc[1:])
    return torch.zeros_like(enc)


class _PassThroughEncoder:
    """``model.encode_text`` that returns features already computed (tensor or tuple of tensors) and
    encodes anything else (strings) with the original encoder."""

    def __init__(self, original: Callable) -> None:
        self.original = original

    def __call__(self, raw: Any, *a: Any, **kw: Any) -> Any:
        if isinstance(raw, torch.Tensor) or (isinstance(raw, tuple) and raw and isinstance(raw[0], torch.Tensor)):
            return raw
        return self.original(raw, *a, **kw)


#: DiP's DistilBERT features are padded (masked tokens) to a multiple of this many tokens
TEXT_TOKEN_BUCKET = 64


def pad_text_tokens(enc: Tuple[torch.Tensor, ...], bucket: int = TEXT_TOKEN_BUCKET) -> Tuple[torch.Tensor, ...]:
    """DiP's BERT text features ``(features [L, B, d], padding mask [B, L] bool, True = no token)``
    padded with masked tokens to the next multiple of ``bucket`` tokens: the batch's longest
    caption no longer sets a shape (one graph for every batch up to ``bucket`` tokens). Exact:
    masked keys get zero attention weight."""
    if len(enc) != 2 or not all(isinstance(t, torch.Tensor) for t in enc) or enc[0].dim() != 3 or enc[1].dim() != 2:
        return enc
    feats, mask = enc
    L = feats.shape[0]
    target = max(bucket, -(-L // bucket) * bucket)
    if target == L or mask.shape[1] != L:
        return enc
    feats = torch.cat([feats, feats.new_zeros(target - L, *feats.shape[1:])], dim=0)
    mask = torch.cat([mask, mask.new_ones(mask.shape[0], target - L)], dim=1)
    return feats, mask


def _mdm_text_encoder(model: nn.Module) -> Optional[Callable]:
    enc = getattr(model, "encode_text", None)
    if isinstance(enc, _PassThroughEncoder):
        return enc.original
    if enc is not None:
        return enc
    return getattr(model, "text_encoder", None)   # TinyMDM


def prepare_mdm(model: nn.Module, args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
    """MDM / DiP / doubleTake_MDM / TinyMDM calls ``(x [B, J, F, N], timesteps [B], y)``: text
    encoded before the graph (``y['text_embed']``; for ``doubleTake_MDM`` also ``y['text']``),
    strings dropped, tensors on ``x``'s device, and in eval mode ``y['uncond']`` folded into zeroed
    text features (MDM's ``mask_cond(force_mask=True)`` is exactly that)."""
    x, t, y = _split_call(args, kwargs)
    if not isinstance(x, torch.Tensor):
        return args, kwargs
    device = x.device
    x = x.contiguous()                               # x_t's strides change between steps: one graph
    t = _to(t, device)
    if isinstance(y, dict):
        y = dict(y)                                  # never write into the caller's dict
        cond_mode = str(getattr(model, "cond_mode", ""))
        text_cond = "text" in cond_mode and "action" not in cond_mode
        if text_cond and "text_embed" not in y and _is_strings(y.get("text")):
            encoder = _mdm_text_encoder(model)
            if encoder is not None:
                enc = encoder(list(y["text"]) if isinstance(y["text"], tuple) else y["text"])
                if getattr(model, "encode_text", None) is None:       # TinyMDM: [B, dim] -> [1, B, dim]
                    enc = enc.reshape(1, x.shape[0], -1)
                y["text_embed"] = enc
        if isinstance(y.get("text_embed"), tuple):
            y["text_embed"] = pad_text_tokens(y["text_embed"])
        uncond = y.get("uncond", False)   # True, or priorMDM's second take: 1.0
        if text_cond and isinstance(uncond, (bool, int, float)) and not model.training and "text_embed" in y:
            if uncond:
                y["text_embed"] = _zeros_like_text(y["text_embed"])
            y.pop("uncond", None)
        if "text_embed" in y and isinstance(getattr(model, "encode_text", None), _PassThroughEncoder):
            y["text"] = y["text_embed"]               # forwards that always call encode_text(y['text'])
        y = {k: (tuple(_to(v, device) for v in val) if isinstance(val, tuple) and not _is_strings(val)
                 else _to(val, device))
             for k, val in y.items() if not _is_strings(val)}
    return _join_call(args, kwargs, x, t, y)


def prepare_motiondiffuse(model: nn.Module, args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
    """MotionDiffuse's ``forward(x [B, T, D], timesteps, length=, text=, xf_proj=, xf_out=)``: the
    text encoded before the graph (``xf_proj``, ``xf_out``; upstream encodes inside forward when
    they are absent), ``text`` dropped, tensors on ``x``'s device."""
    x = args[0] if args else kwargs.get("x")
    if not isinstance(x, torch.Tensor):
        return args, kwargs
    kwargs = dict(kwargs)
    x = x.contiguous()
    names = ("timesteps", "length", "text", "xf_proj", "xf_out")
    for name, value in zip(names, args[1:]):
        kwargs[name] = value
    args = (x,)
    if (kwargs.get("xf_proj") is None or kwargs.get("xf_out") is None) and kwargs.get("text") is not None:
        text = kwargs["text"]
        B = x.shape[0]
        if len(text) != B:                           # upstream's DataParallel slice
            index = x.device.index or 0
            text = text[index * B: index * B + B]
        kwargs["xf_proj"], kwargs["xf_out"] = model.encode_text(text, x.device)
    kwargs.pop("text", None)
    length = kwargs.get("length")
    if isinstance(length, (list, tuple)) and all(isinstance(v, int) for v in length):
        kwargs["length"] = torch.tensor(length, dtype=torch.long)   # Python ints would be guarded one by one
    return args, {k: _to(v, x.device) for k, v in kwargs.items()}


def _is_motiondiffuse(model: nn.Module) -> bool:
    return hasattr(model, "temporal_decoder_blocks") and hasattr(model, "encode_text")


#: (which models, how their calls are prepared before the graph), first match wins
PREPARERS: List[Tuple[Callable[[nn.Module], bool], Callable]] = [
    (_is_motiondiffuse, prepare_motiondiffuse),
    (lambda m: hasattr(m, "cond_mode") or hasattr(m, "input_process"), prepare_mdm),
]


def _preparer(model: nn.Module) -> Callable:
    for matches, prepare in PREPARERS:
        if matches(model):
            return prepare
    return lambda model, args, kwargs: (args, kwargs)


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


def _has_forced(args: tuple, kwargs: dict) -> bool:
    """Whether a call carries forced keyframes (a :class:`KeyframeRequest` with ``forced``), in
    MDM's ``y`` or MotionDiffuse's keyword arguments."""
    from ..adapters.request import KEYFRAMES_KEY

    for container in [kwargs] + [a for a in args if isinstance(a, dict)] + \
            [v for v in kwargs.values() if isinstance(v, dict)]:
        if getattr(container.get(KEYFRAMES_KEY), "forced", None) is not None:
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
    * called while an outer compiled function traces, ``fn`` is traced inline (one graph).

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

    def _phase(self, x: torch.Tensor, fullgraph: bool) -> tuple:
        training = None if self.model is None else self.model.training
        return (training, torch.is_grad_enabled(), _autocast_key(x.device), x.device.type, tuple(x.shape[1:]),
                fullgraph)

    def _function(self, device: torch.device, fullgraph: bool) -> Tuple[Callable, bool]:
        """The compiled ``fn`` (made on the first compiled call; one per ``fullgraph``) and whether
        CUDA graphs apply."""
        s = self.setting
        if self._mode is None:
            self._mode = s.mode
            if s.mode == "reduce-overhead" and device.type != "cuda":
                self._mode = s.mode = "default"
                s.note = (s.note + "; " if s.note else "") + \
                    f"reduce-overhead needs CUDA graphs; the model runs on {device.type}: compiled with default"
                warnings.warn(f"{_WARN}: {s.note}", stacklevel=4)
        if fullgraph not in self._compiled:
            kwargs: Dict[str, Any] = dict(fullgraph=fullgraph, dynamic=False, backend=s.backend)
            if s.backend == "inductor":
                kwargs["mode"] = None if self._mode == "default" else self._mode
            run = self._run

            def call(*args: Any, **kw: Any) -> Any:    # traced as one frame, the hooks inlined
                return run(*args, **kw)

            self._compiled[fullgraph] = torch.compile(call, **kwargs)
        return self._compiled[fullgraph], self._mode == "reduce-overhead" and device.type == "cuda"

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        from ..core.checks import compiling, static_mode   # here: a flag-off run loads only the options

        if compiling():                              # inside an outer compiled function: one graph
            return self._run(*args, **kwargs)
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
                return self._run(*args, **kwargs)
        if x.shape[0] != batch:                      # outside the static batch: eager, no recompile
            self.setting.eager_calls += 1
            if not self._warned_eager:
                self._warned_eager = True
                warnings.warn(f"{_WARN}: a call with batch {x.shape[0]} (static batch {batch} for this "
                              f"shape) runs eagerly; the compiled graph keeps its static batch", stacklevel=3)
            return self._run(*args, **kwargs)
        fn, graphs = self._function(x.device, fullgraph)
        self.setting.compiled_calls += 1
        before = _graph_count()
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


class _CompiledCall(CompiledFunction):
    """What ``model.__call__`` runs once compiled (``nn.Module._compiled_call_impl``): the module's
    ``_call_impl`` (hooks included), each call prepared by the model's :data:`PREPARERS` entry;
    calls carrying forced keyframes are a phase of their own, traced with a graph break."""

    def __init__(self, model: nn.Module, setting: CompileSetting) -> None:
        super().__init__(model._call_impl, setting, model, prepare_call(model))

    def _fullgraph(self, args: tuple, kwargs: dict) -> bool:
        # forced keyframes (sample.edit, in-betweening) are counted on the host once per call, as in
        # eager: such calls trace with a graph break there (a phase of their own, same guarantee)
        return self.setting.fullgraph and not _has_forced(args, kwargs)


# --------------------------------------------------------------------------- entry points
def _fullgraph_default(model: nn.Module) -> bool:
    """Sparse models trace whole (fullgraph), except DoubleTake's: its forced keyframes are read
    from ``y`` on the host once per call (as in eager), which breaks the graph there."""
    from ..families.doubletake.model import has_doubletake_forcing
    from ..adapters.surgery import is_sparse

    return is_sparse(model) and not has_doubletake_forcing(model)


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
    encoder = getattr(model, "encode_text", None)
    if encoder is not None and not _is_motiondiffuse(model):    # uncompile() put the original back
        model.encode_text = _PassThroughEncoder(encoder)
    model._compiled_call_impl = _CompiledCall(model, setting)
    return setting


def prepare_call(model: nn.Module) -> Callable[[tuple, dict], Tuple[tuple, dict]]:
    """``prepare(args, kwargs)`` of a call whose arguments are ``model``'s own (``(x, timesteps, y)``
    / MotionDiffuse's): its :data:`PREPARERS` entry (for :func:`compile_function`'s ``prepare``:
    e.g. a guidance wrapper's call, prepared as the model's)."""
    model = _inner(model)
    prepare = _preparer(model)
    return lambda args, kwargs: prepare(model, args, kwargs)


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
    enc = model.__dict__.get("encode_text")
    if isinstance(enc, _PassThroughEncoder):
        model.encode_text = enc.original
    return model


#: environment: the torch.compile backend of the integrations (default inductor; aot_eager / eager
#: trace the same graphs without generating code: quick checks on a CPU)
BACKEND_ENV = "SMDM_COMPILE_BACKEND"
#: environment: a JSON file the process writes at exit (``{rank}`` in it: torchrun's rank): per
#: compiled model its setting, calls, phases (static shapes), recompiles, and Dynamo's graph count
STATS_ENV = "SMDM_COMPILE_STATS"
_COMPILED: List[Tuple[str, CompileSetting, "_CompiledCall"]] = []


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
    """The integrations' entry point: compile ``model`` for ``args.sparse_compile`` (absent or
    ``none``: nothing happens, upstream runs bit for bit) with the backend of ``SMDM_COMPILE_BACKEND``
    (default inductor) and record what applies on ``args`` (``sparse_compile_applied``:
    ``args.json`` / ``opt.txt`` carry it). With ``SMDM_COMPILE_STATS=FILE`` the process writes
    :func:`compile_stats` there at exit. Returns the setting."""
    import atexit
    import os

    mode = getattr(args, "sparse_compile", None)
    if mode in (None, "none"):
        return None
    setting = compile_model(model, mode, device=device, backend=os.environ.get(BACKEND_ENV, "inductor"))
    if os.environ.get(STATS_ENV):
        if not _COMPILED:
            atexit.register(_write_stats)
        _COMPILED.append((type(model).__name__, setting, model._compiled_call_impl))
    if hasattr(args, "__dict__"):
        args.sparse_compile_applied = setting.describe()
    return setting
