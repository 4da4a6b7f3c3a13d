"""Host time per call, measured on the CPU (:func:`host_times`) and counted (:func:`host_work`): what
decides eager speed on a GPU at MDM's size."""
from __future__ import annotations

import sys
import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from types import CodeType
from typing import TYPE_CHECKING, Callable, Dict, Iterator, List, Optional, Set

import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode

from ..core.kernels.dispatch import OBSERVERS

if TYPE_CHECKING:
    from ..core.config import SparseConfig

__all__ = ["HOST_SIZE", "TRITON_LAUNCH_OPS", "HostTime", "HostWork", "host_times", "host_work", "launch_charge",
           "charging_kernels"]

#: the model size of the measurement: MDM's depth and heads, tiny tensors
HOST_SIZE = dict(latent_dim=16, ff_size=32, num_layers=8, num_heads=4, batch=2, frames=24)

#: what one Triton launch from Python costs the host, in small aten ops: the H200's profile
#: (results/gpu_h200_2026-11-28/profile_train_sparse.txt) showed each Triton-launching autograd
#: function costing the host 204 µs per call (mean over a training step's 24 calls), where a dense
#: bf16 step took 4.2x its meter time; 204 µs / 4.2 / 1.4 µs (a small op on the meter) ≈ 34
#: (docs/gpu.md, 0.9.2)
TRITON_LAUNCH_OPS = 34


#: ``charge(fn, *args, ops=n, **kwargs) -> fn(*args, **kwargs)``: runs a call that CUDA launches
#: as ``n`` kernels, charging it ``n`` launches (the timer times it apart, the counter counts ``n``)
Charge = Callable[..., object]


class _OneEachWay(torch.autograd.Function):
    """``fn(*inputs)`` (run within its caller's charge) whose gradient, the CPU graph's, runs in
    one ``charge`` of its own: one launch each way, as CUDA's SDPA runs (one kernel forward, one
    backward, where the CPU's math composite runs a dozen ops forward and about twenty backward)."""

    @staticmethod
    def forward(ctx, charge: Charge, fn: Callable, *inputs):
        with torch.enable_grad():
            leaves = [t.detach().requires_grad_(t.requires_grad) if isinstance(t, torch.Tensor) else t
                      for t in inputs]
            out = fn(*leaves)
        ctx.charge, ctx.leaves, ctx.out = charge, leaves, out
        return out.detach()

    @staticmethod
    def backward(ctx, grad):
        wanted = [i for i, t in enumerate(ctx.leaves) if isinstance(t, torch.Tensor) and t.requires_grad]
        got = ctx.charge(torch.autograd.grad, ctx.out, [ctx.leaves[i] for i in wanted], grad, allow_unused=True)
        grads = [None] * len(ctx.leaves)
        for i, g in zip(wanted, got):
            grads[i] = g
        ctx.leaves = ctx.out = None
        return (None, None, *grads)


def _attention_as_cuda(charge: Charge, sdpa: Callable) -> Callable:
    """``F.scaled_dot_product_attention`` charged as CUDA runs it: one launch forward (and one per
    cast autocast makes of its inputs), one backward under autograd (:class:`_OneEachWay`)."""
    def attention(query, key, value, attn_mask=None, dropout_p=0.0, is_causal=False, scale=None, **kw):
        tensors = (query, key, value, attn_mask)
        kind = query.device.type
        autocast = kind in ("cpu", "cuda") and torch.is_autocast_enabled(kind)
        dtype = torch.get_autocast_dtype(kind) if autocast else None
        casts: Dict[int, torch.Tensor] = {}          # what autocast casts, each tensor once (its cache)
        for t in tensors:
            if autocast and t is not None and t.is_floating_point() and t.dtype not in (dtype, torch.float64):
                casts[id(t)] = t

        def fn(q, k, v, m):
            with torch.autocast(kind, enabled=False) if autocast else nullcontext():   # (cast below)
                return sdpa(q, k, v, attn_mask=m, dropout_p=dropout_p, is_causal=is_causal, scale=scale, **kw)

        def run():
            cast = {i: t.to(dtype) for i, t in casts.items()}
            q, k, v, m = [cast.get(id(t), t) for t in tensors]
            if torch.is_grad_enabled() and (q.requires_grad or k.requires_grad or v.requires_grad
                                            or m is not None and m.requires_grad):
                return _OneEachWay.apply(charge, fn, q, k, v, m)
            return fn(q, k, v, m)
        return charge(run, ops=1 + len(casts))
    attention.__name__ = attention.__qualname__ = "scaled_dot_product_attention"
    return attention


def _dropout_as_cuda(charge: Charge, dropout: Callable) -> Callable:
    """The op under ``F.dropout`` (``torch._VF.dropout``) charged as CUDA runs it in training: one
    launch (``native_dropout``; the CPU runs four ops); ``F.dropout``'s Python runs and counts as it
    does on a GPU; the backward is one op on both (a multiply)."""
    def vf_dropout(input, p, train):
        return charge(dropout, input, p, train) if train and p > 0.0 else dropout(input, p, train)
    return vf_dropout


@contextmanager
def _stand_ins(charge: Charge) -> Iterator[Set[CodeType]]:
    """Within the block, SDPA and dropout charged as CUDA runs them (:func:`_attention_as_cuda`,
    :func:`_dropout_as_cuda`); yields the stand-ins' code objects (their frames are not the
    measured call's: :func:`_stand_in_frame`)."""
    sdpa, vf = F.scaled_dot_product_attention, torch._VF
    own = vf.__dict__.get("dropout")                  # (normally none: _VF looks ops up by name)
    attention, drop = _attention_as_cuda(charge, sdpa), _dropout_as_cuda(charge, vf.dropout)
    F.scaled_dot_product_attention, vf.dropout = attention, drop
    try:
        yield {attention.__code__, drop.__code__}
    finally:
        F.scaled_dot_product_attention = sdpa
        if own is None:
            del vf.dropout
        else:
            vf.dropout = own


#: the Python frame that runs a custom autograd function's backward (its own, before ``backward``)
_BACKWARD_APPLY = torch.autograd.function.BackwardCFunction.apply.__code__


def _stand_in_frame(frame, own: Set[CodeType]) -> bool:
    """Whether ``frame`` runs one of the ``own`` stand-ins (:func:`_stand_ins`), or is (or runs
    within) the backward call of :class:`_OneEachWay`: not the measured call's frames (their
    charged calls' frames are not counted anyway)."""
    if frame.f_code in own:
        return True
    while frame is not None:
        if frame.f_code is _BACKWARD_APPLY and getattr(frame.f_locals.get("self"), "_forward_cls", None) is _OneEachWay:
            return True
        frame = frame.f_back
    return False


@dataclass(frozen=True)
class HostTime:
    """Host milliseconds per call of each measured callable (``ms``), and what one charged launch
    counts (``charge_us``)."""

    ms: Dict[str, float]
    charge_us: float

    def ratio(self, a: str, b: str) -> float:
        """``ms[a] / ms[b]``."""
        return self.ms[a] / self.ms[b]


def launch_charge(repeats: int = 2000) -> float:
    """Seconds of host time of one small op (a launch's worth): the 10th percentile of an add of
    two one-element tensors."""
    a, b = torch.ones(1), torch.ones(1)
    for _ in range(200):
        a + b
    ts = []
    for _ in range(repeats):
        t0 = time.thread_time()
        a + b
        ts.append(time.thread_time() - t0)
    ts.sort()
    return ts[len(ts) // 10]


class _Charges:
    """Thread time spent in charged kernels and how many launches' worth they cost (``count``: one
    per SDPA call and its backward, dropout or foreach call, :data:`TRITON_LAUNCH_OPS` per fused op
    that CUDA runs as a Triton kernel), since the last :meth:`reset`."""

    def __init__(self) -> None:
        self.seconds, self.count = 0.0, 0

    def reset(self) -> None:
        self.seconds, self.count = 0.0, 0

    def run(self, fn: Callable, *args, ops: int = 1, **kwargs):
        t0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            self.seconds += time.thread_time() - t0
            self.count += ops


def _timed(charges: "_Charges", fn: Callable) -> Callable:
    def timed(*args, **kwargs):
        return charges.run(fn, *args, **kwargs)
    return timed


@contextmanager
def charging_kernels() -> Iterator[_Charges]:
    """Within the block, what CUDA runs as one kernel where the CPU runs several ops is timed apart
    (:class:`_Charges`) and charged at what it costs a GPU's host: the package's fused ops that CUDA
    runs as Triton kernels :data:`TRITON_LAUNCH_OPS` small ops each; ``F.scaled_dot_product_attention``
    one launch forward and, under autograd, one backward (:class:`_OneEachWay`); dropout in training
    one (``native_dropout``; ``F.dropout``'s own Python is measured); ``torch._foreach_*`` one. (They
    are looked up at call time by ``nn.MultiheadAttention``, ``F.dropout``, this package and
    ``torch.optim``.)"""
    charges = _Charges()
    originals = [(torch, n, getattr(torch, n)) for n in dir(torch) if n.startswith("_foreach_")]

    def observer(name: str, kernel: Callable, args: list):
        return charges.run(kernel, *args, ops=TRITON_LAUNCH_OPS)

    OBSERVERS.append(observer)
    for owner, name, fn in originals:
        setattr(owner, name, _timed(charges, fn))
    try:
        with _stand_ins(charges.run):
            yield charges
    finally:
        for owner, name, fn in originals:
            setattr(owner, name, fn)
        OBSERVERS.remove(observer)


def host_times(fns: Dict[str, Callable[[], object]], repeats: int = 100, warmup: int = 3,
               quantile: float = 0.2) -> HostTime:
    """Host milliseconds per call of each callable in ``fns`` (run interleaved, ``repeats`` times
    after ``warmup`` calls each): thread CPU time, what CUDA runs as one kernel charged at its launch
    (:func:`charging_kernels`: SDPA one launch each way, dropout and foreach ops one, Triton-launching
    fused ops :data:`TRITON_LAUNCH_OPS`); the ``quantile`` of the repeats. Run on the CPU, one
    thread."""
    if repeats < 1:
        raise ValueError(f"host_times: repeats must be >= 1, got {repeats}")
    charge = launch_charge()
    times: Dict[str, List[float]] = {name: [] for name in fns}
    with charging_kernels() as charges:
        for fn in fns.values():
            for _ in range(warmup):
                fn()
        for _ in range(repeats):
            for name, fn in fns.items():
                charges.reset()
                t0 = time.thread_time()
                fn()
                t = time.thread_time() - t0
                times[name].append(t - charges.seconds + charges.count * charge)
    ms = {}
    for name, ts in times.items():
        ts.sort()
        ms[name] = ts[min(len(ts) - 1, int(len(ts) * quantile))] * 1e3
    return HostTime(ms, charge * 1e6)


@dataclass(frozen=True)
class HostWork:
    """The host work of one call, counted: ``ops``, the aten ops the dispatcher runs (forward,
    backward, optimizer; a fused op that CUDA runs as a Triton kernel counts
    :data:`TRITON_LAUNCH_OPS`, as :func:`host_times` charges it) and ``calls``, the Python frames
    entered. Unlike :class:`HostTime` it does not depend on the machine or its load."""

    ops: int
    calls: int

    def ratio(self, other: "HostWork") -> Dict[str, float]:
        """``{"ops": ..., "calls": ...}``: this call's counts over ``other``'s."""
        return {"ops": self.ops / max(other.ops, 1), "calls": self.calls / max(other.calls, 1)}


class _OpCounter(TorchDispatchMode):
    """Counts the aten ops that reach the dispatcher's Python key, except while ``inside`` (a charged
    fused op or SDPA: :func:`host_work` counts those itself)."""

    def __init__(self) -> None:
        super().__init__()
        self.ops, self.inside = 0, 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if not self.inside:
            self.ops += 1
        return func(*args, **(kwargs or {}))


def host_work(fn: Callable[[], object], warmup: int = 2) -> HostWork:
    """The :class:`HostWork` of a call of ``fn`` after ``warmup`` calls (caches filled, as in a loop):
    its Python frames in one call, its aten ops in the next (the op counter's own frames are not
    counted), what CUDA runs as one kernel counted as :func:`host_times` charges it (a fused op that
    CUDA runs as a Triton kernel :data:`TRITON_LAUNCH_OPS`, its CPU composite not counted; SDPA one
    op forward and one backward, where the CPU runs its math composite wherever a mask or unequal
    head sizes rule out its flash kernel, ~13 ops forward and ~20 backward; dropout in training one,
    the CPU's four ops not counted; ``F.dropout``'s own Python frame counts, as a GPU runs it), the
    stand-ins no frame of their own. The same call counts the same on any
    machine: what a test can budget (time is what :func:`host_times` and ``scripts/host_time.py``
    measure)."""
    for _ in range(warmup):
        fn()
    counter, frames, launches = _OpCounter(), [0], [0]

    def observer(name: str, kernel: Callable, args: list):
        counter.inside += 1
        try:
            return kernel(*args)
        finally:
            counter.inside -= 1
            launches[0] += 1

    def charge(f: Callable, *args, ops: int = 1, **kwargs):
        counter.inside += 1
        try:
            return f(*args, **kwargs)
        finally:
            counter.inside -= 1
            if not counter.inside:
                counter.ops += ops

    own: Set[CodeType] = {charge.__code__}

    def profile(frame, event, arg):
        if event == "call" and not counter.inside and not _stand_in_frame(frame, own):
            frames[0] += 1

    OBSERVERS.append(observer)
    try:
        with _stand_ins(charge) as stand_ins:
            own.update(stand_ins)
            previous = sys.getprofile()
            sys.setprofile(profile)
            try:
                fn()
            finally:
                sys.setprofile(previous)
            launches[0] = 0
            counter.ops = 0
            with counter:
                fn()
    finally:
        OBSERVERS.remove(observer)
    return HostWork(counter.ops + TRITON_LAUNCH_OPS * launches[0], frames[0])


#: the model variants :func:`host_cells` builds: MDM's three, DoubleTake's sampling (trans_enc with
#: forced frames) and MotionDiffuse's denoiser
HOST_VARIANTS = ("trans_enc", "trans_dec", "dip", "doubletake", "motiondiffuse")
_MDM = {"trans_enc": dict(arch="trans_enc"), "trans_dec": dict(arch="trans_dec"),
        "dip": dict(arch="trans_dec", emb_trans_dec=True, context_len=20, pred_len=20),
        "doubletake": dict(arch="trans_enc")}
#: DoubleTake's first-take handshake at :data:`HOST_SIZE`'s 24 frames (priorMDM's 20 of 196, scaled)
HOST_HANDSHAKE = 3


def host_cells(variant: str, sparse: bool, precision: str, config: Optional["SparseConfig"] = None
               ) -> Dict[str, Callable[[], object]]:
    """The calls whose host time counts, for ``variant`` (:data:`HOST_VARIANTS`) at
    :data:`HOST_SIZE`, dense (the upstream model, no FSQ) or sparse (the paper's recipe,
    ``SparseConfig()``; MotionDiffuse: no FSQ, its attention is linear), ``precision`` ``fp32`` or
    ``bf16`` (CPU autocast): ``train`` (``training_losses`` + backward + ``AdamW(foreach=True)``)
    and ``sample`` (one sampling call: both classifier-free-guidance passes for MDM's models, one
    pass for MotionDiffuse; DoubleTake's with its handshake frames forced; ``config``: another
    sparse config); ``step``: the training step's optimizer step alone (run after ``train``: its
    gradients). Each sets the model's mode only when it changes, as a loop does (0.9.5 and
    before: every call, which charged a sparse model its larger module tree). Run them under
    :func:`~smdm_plugin.core.checks.static_mode`."""
    from ..adapters.surgery import sparsify
    from ..core.config import SparseConfig
    from ..reference.simple_diffusion import ClassifierFreeGuidance, SimpleDiffusion

    if variant not in HOST_VARIANTS:
        raise ValueError(f"host_cells: variant must be one of {HOST_VARIANTS}, got {variant!r}")
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"host_cells: precision must be fp32 or bf16, got {precision!r}")
    s = HOST_SIZE
    B, N = s["batch"], s["frames"]
    g = torch.Generator().manual_seed(0)
    lengths = torch.linspace(N // 2, N, B).round().long()
    torch.manual_seed(0)
    if variant == "motiondiffuse":
        from ..reference.motiondiffuse_denoiser import MotionDiffuseDenoiser

        model = MotionDiffuseDenoiser(input_feats=263, num_frames=N, latent_dim=s["latent_dim"], ff_size=s["ff_size"],
                                      num_layers=s["num_layers"], num_heads=s["num_heads"], text_latent_dim=8)
        x = torch.randn(B, N, 263, generator=g)
        kw = {"length": lengths, "xf_proj": torch.randn(B, 4 * s["latent_dim"], generator=g),
              "xf_out": torch.randn(B, 4, 8, generator=g)}
        recipe = SparseConfig(fsq=False)
    else:
        from ..reference.backbone import TinyMDM

        spec = _MDM[variant]
        model = TinyMDM(latent_dim=s["latent_dim"], ff_size=s["ff_size"], num_layers=s["num_layers"],
                        num_heads=s["num_heads"], dropout=0.1, cond_mask_prob=0.1, **spec)
        if variant == "dip":
            lengths = torch.full((B,), N)
        x = torch.randn(B, 263, 1, N, generator=g)
        y = {"mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N), "lengths": lengths,
             "text_embed": torch.randn(1, B, 512, generator=g)}
        if variant == "dip":
            y["prefix"] = torch.randn(B, 263, 1, spec["context_len"], generator=g)
        recipe = SparseConfig()
        sample_y = _doubletake_y(y, lengths, N, sparse) if variant == "doubletake" else y
    diffusion = SimpleDiffusion(50)
    if sparse:
        sparsify(model, recipe if config is None else config, diffusion=diffusion)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, foreach=True)
    t = torch.arange(B) * 6
    bf16 = precision == "bf16"
    md = variant == "motiondiffuse"
    guided = model if md else ClassifierFreeGuidance(model)

    def train() -> None:
        if not model.training:  # a training loop sets the mode once, not per step (MDM: around its evaluations)
            model.train()
        opt.zero_grad(set_to_none=True)
        with torch.autocast("cpu", torch.bfloat16, enabled=bf16):
            terms = diffusion.training_losses(model, x, t, dict(kw) if md else {"y": dict(y)})
            loss = terms["loss"].mean()
        loss.backward()
        opt.step()

    def sample() -> None:
        if model.training:  # once per sampling loop
            model.eval()
        with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=bf16):
            if md:
                guided(x, torch.full((B,), 40), **kw)
            else:
                guided(x, torch.full((B,), 40), dict(sample_y))

    return {"train": train, "sample": sample, "step": opt.step}


def _doubletake_y(y: Dict[str, object], lengths: torch.Tensor, N: int, sparse: bool) -> Dict[str, object]:
    """A DoubleTake first take's sampling ``y``: its handshake frames (``is_transition``, which
    the dense model ignores), for the sparse model forced keyframes with the run's bound, as
    priorMDM's forcing hook hands them on (``with_forced``; the same tensors at every call, as in a
    sampling loop)."""
    from ..adapters.request import with_forced
    from .workloads import handshake_frames

    forced = handshake_frames(lengths, N, HOST_HANDSHAKE)
    y = {**y, "is_transition": forced}
    return with_forced(y, forced, 2 * HOST_HANDSHAKE) if sparse else y
