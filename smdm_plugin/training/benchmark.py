"""Dense and sparse side by side in one process: the measurements behind ``smdm bench``.

:func:`run_bench` times, for one family's :class:`~smdm_plugin.training.workloads.Workload`, the
dense model and every reduction rate, interleaved (every repeat runs every variant in turn, so
machine load hits all alike), at each compile mode: ``train`` (one training step with the sparse
diffusion wrapper + backward + ``AdamW.step``), ``sample`` (one guided sampling call at a late
step, dynamic update forced on), ``loop`` (the whole sampling loop). Compiled, each step is
captured whole (:func:`training_loss`, :func:`guided_call`, :func:`sampling_step`; docs/compile.md). Each result row is a JSON-ready dict
(wall and CPU medians, speed-ups against dense at the same compile mode, peak memory, kernel
launches, and for sparse steps the share spent in keyframe selection and interpolation).
:func:`bench_keyframes` times VW selection alone.
"""
from __future__ import annotations

import contextlib
import statistics
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, ContextManager, Dict, List, Optional, Sequence, Tuple

import torch

from ..adapters.state import sparse_config_of
from ..runtime.distributed import resolve_device
from .timing import PeakMemory, device_name, launches, load_averages, pin_malloc, sync, time_it
from .workloads import WORKLOADS, Workload, WorkloadBatch, build

__all__ = ["TARGETS", "MODES", "run_bench", "compile_modes_of", "step_fn", "overhead_fns", "bench_keyframes"]

TARGETS = {"train": 4.0, "sample": 3.5, "loop": 3.0, "overhead": 0.10}  # at 80% reduction
MODES = ("train", "sample", "loop")

Step = Callable[[], Any]


class TimedStep:
    """One cell's timed callable: ``run()`` (returns what the step made: the training loss, the
    sampling call's output, the sample), and ``compiled``, the function inside it that the compile
    helper made (:func:`~smdm_plugin.runtime.compile.compile_setting` says how it ran). Its
    inputs are drawn on the CPU with fixed seeds (the same on every device)."""

    def __init__(self, run: Callable[[], Any], compiled: Callable) -> None:
        self.run, self.compiled = run, compiled

    def __call__(self) -> Any:
        return self.run()


def autocast(device: torch.device, amp: str) -> ContextManager[Any]:
    """``torch.autocast`` to bfloat16 for ``amp="bf16"``, else nothing."""
    if amp == "bf16":
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def _compile(fn: Callable, model: torch.nn.Module, compile_mode: str, device: torch.device, backend: Any,
             captures: str, prepare: Optional[Callable] = None) -> Callable:
    """``fn`` compiled whole by the helper every integration uses (docs/compile.md), dense or
    sparse alike; ``none``: ``fn`` itself."""
    from ..runtime.compile import compile_function

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")            # reduce-overhead off CUDA: stated in the table instead
        return compile_function(fn, compile_mode, model=model, backend=backend, device=device, name="--compile",
                                captures=captures, prepare=prepare)


def _applied(fn: Callable) -> str:
    """How a timed callable ran: ``eager`` or the compile mode that applied (reduce-overhead falls
    back to default without CUDA)."""
    from ..runtime.compile import compile_setting

    s = compile_setting(fn)
    return "eager" if s is None else s.mode


# ----------------------------------------------------------------------------------------- steps
def training_loss(work: Workload, model: torch.nn.Module, diffusion: Any, device: torch.device,
                  compile_mode: str = "none", backend: Any = "inductor") -> Callable[..., torch.Tensor]:
    """``loss(x, t, kwargs, noise)``: the mean training loss of one batch (the sparse diffusion
    wrapper's keyframe selection included), compiled whole for ``compile_mode``: its forward and
    backward are one graph each (AOTAutograd)."""
    from ..runtime.compile import CAPTURES_TRAIN

    def loss(x: torch.Tensor, t: torch.Tensor, kwargs: Dict[str, Any], noise: torch.Tensor) -> torch.Tensor:
        return diffusion.training_losses(model, x, t, kwargs, noise=noise)["loss"].mean()

    return _compile(loss, model, compile_mode, device, backend, CAPTURES_TRAIN)


def guided_call(work: Workload, model: torch.nn.Module, device: torch.device, compile_mode: str = "none",
                backend: Any = "inductor") -> Callable[..., torch.Tensor]:
    """``call(x_t, t, **kwargs)``: one sampling call of the family (MDM: classifier-free guidance,
    both passes), ``model`` in eval mode, compiled whole for ``compile_mode`` (one graph: the
    guidance wrapper included)."""
    from ..runtime.compile import CAPTURES_GUIDED, prepare_call

    return _compile(work.denoiser(model), model, compile_mode, device, backend, CAPTURES_GUIDED, prepare_call(model))


def sampling_step(work: Workload, model: torch.nn.Module, diffusion: Any, device: torch.device,
                  compile_mode: str = "none", backend: Any = "inductor") -> Callable[..., torch.Tensor]:
    """``step(x_t, tt, noise, kwargs) -> x_{t-1}``: one whole ancestral step (the guided call and
    the posterior update, :meth:`~smdm_plugin.reference.simple_diffusion.SimpleDiffusion.sample_step`),
    compiled whole for ``compile_mode``: one graph replayed at every step of a loop."""
    from ..runtime.compile import CAPTURES_SAMPLE_STEP

    den = work.denoiser(model)

    def step(x_t: torch.Tensor, tt: torch.Tensor, noise: torch.Tensor, kwargs: Dict[str, Any]) -> torch.Tensor:
        return diffusion.sample_step(den, x_t, tt, noise, kwargs)

    return _compile(step, model, compile_mode, device, backend, CAPTURES_SAMPLE_STEP)


def sample_loop(step: Callable[..., torch.Tensor], shape: Tuple[int, ...], steps: int, kwargs: Dict[str, Any],
                device: torch.device, generator: torch.Generator) -> torch.Tensor:
    """The whole sampling loop with :func:`sampling_step`'s ``step``: ``steps`` steps from noise
    drawn with ``generator`` (the draws of ``SimpleDiffusion.p_sample_loop``, so equal to it; a
    generator on another device than ``device`` draws there: a CPU one gives every device the
    same noise)."""
    def draw() -> torch.Tensor:                      # on the generator's device (a CPU one: any device alike)
        return torch.randn(shape, generator=generator, device=generator.device).to(device)

    x = draw()
    zeros = torch.zeros_like(x)
    tts = [torch.full((shape[0],), t, dtype=torch.long, device=device) for t in range(steps)]
    for t in range(steps - 1, -1, -1):
        x = step(x, tts[t], draw() if t > 0 else zeros, kwargs)
    return x


def _train_step(work: Workload, model: torch.nn.Module, diffusion: Any, batch: WorkloadBatch,
                device: torch.device, amp: str, compile_mode: str, backend: Any = "inductor", seed: int = 0) -> TimedStep:
    from ..runtime.compile import fused_optimizer_kwargs

    model.train()
    loss_fn = training_loss(work, model, diffusion, device, compile_mode, backend)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, **fused_optimizer_kwargs(device, compile_mode))
    g = torch.Generator(device="cpu").manual_seed(seed)
    # made ahead of time: no host-to-device copy in the step
    ts = [torch.randint(0, diffusion.num_timesteps, (batch.size,), generator=g).to(device) for _ in range(8)]
    noises = [torch.randn(batch.x.shape, generator=g).to(device) for _ in range(2)]
    step_no = [0]

    def step() -> torch.Tensor:
        i = step_no[0]
        step_no[0] += 1
        with autocast(device, amp):
            loss = loss_fn(batch.x, ts[i % len(ts)], work.kwargs(batch), noises[i % len(noises)])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss.detach()

    return TimedStep(step, loss_fn)


def _sample_step(work: Workload, model: torch.nn.Module, diffusion: Any, batch: WorkloadBatch,
                 device: torch.device, amp: str, compile_mode: str, backend: Any = "inductor",
                 seed: int = 0) -> TimedStep:
    from ..core.schedule import MaskSchedule

    model.eval()
    call = guided_call(work, model, device, compile_mode, backend)
    config = sparse_config_of(model)  # the public accessor, not the model's private state
    late = MaskSchedule(config).late_steps if config is not None else 1
    t = torch.full((batch.size,), max(0, late - 1), dtype=torch.long, device=device)
    noise = torch.randn(batch.x.shape, generator=torch.Generator().manual_seed(seed)).to(device)
    x_t = diffusion.q_sample(batch.x, t, noise)

    def step() -> torch.Tensor:
        with torch.no_grad(), autocast(device, amp):
            x_t.add_(0)                              # a new x_t every time
            return call(x_t, t, **work.sample_kwargs(batch))

    return TimedStep(step, call)


def _sample_loop(work: Workload, model: torch.nn.Module, diffusion: Any, batch: WorkloadBatch,
                 device: torch.device, amp: str, compile_mode: str, backend: Any = "inductor") -> TimedStep:
    model.eval()
    step_fn_ = sampling_step(work, model, diffusion, device, compile_mode, backend)
    shape = tuple(batch.x.shape)
    g = torch.Generator(device=device).manual_seed(0)

    def loop() -> torch.Tensor:
        with torch.no_grad(), autocast(device, amp):
            return sample_loop(step_fn_, shape, diffusion.num_timesteps, work.sample_kwargs(batch), device, g)

    return TimedStep(loop, step_fn_)


#: what each ``--modes`` entry times: ``maker(work, model, diffusion, batch, device, amp, compile_mode, backend)``
STEP_MAKERS: Dict[str, Callable[..., TimedStep]] = {"train": _train_step, "sample": _sample_step,
                                                    "loop": _sample_loop}


def step_fn(mode: str, work: Workload, model: torch.nn.Module, diffusion: Any, batch: WorkloadBatch,
            device: torch.device, amp: str = "fp32", compile_mode: str = "none",
            compile_backend: Any = None) -> TimedStep:
    """The timed callable of one cell: ``mode`` one of :data:`MODES`; with ``compile_mode`` the
    whole step compiled (``train``: the loss forward and backward, AdamW fused on CUDA; ``sample``:
    the guided call, every guidance pass; ``loop``: the sampling step, replayed at every step) with
    ``compile_backend`` (a ``torch.compile`` backend; None: ``SMDM_COMPILE_BACKEND``, else inductor)."""
    if compile_backend is None:
        from ..runtime.compile import default_backend

        compile_backend = default_backend()
    return STEP_MAKERS[mode](work, model, diffusion, batch, device, amp, compile_mode, compile_backend)


def overhead_fns(work: Workload, model: torch.nn.Module, batch: WorkloadBatch, device: torch.device,
                 train: bool) -> Tuple[Step, Step]:
    """Keyframe selection and the interpolation back to all frames, alone, with the step's
    shapes: ``(select, interp)`` callables."""
    from ..adapters.diffusion_wrapper import model_noise
    from ..adapters.state import get_state
    from ..core.fill import fill_frames

    state = get_state(model)
    frames = batch.frames
    lengths = batch.lengths.to(device)
    B, N = frames.shape[:2]
    if train:
        def select():
            return state.schedule.training_mask(frames, lengths, None, model_noise(model), checked=True)
    else:
        late = torch.zeros(B, dtype=torch.long, device=device)

        def select():
            return state.schedule.sampling_mask(frames, late, lengths, checked=True)
    args, kwargs = work.call_args(batch, select(), state.schedule.capacity(N, training=train))
    plan = state.family.read_call(state, args, kwargs).plan(state)
    lead = work.lead(model)
    K = plan.capacity
    width = getattr(model, "latent_dim")
    h = torch.randn((lead + K) * B, width, device=device, requires_grad=train)
    rows = torch.arange((lead + K) * B, device=device).view(lead + K, B)

    def interp():
        if train:
            fill_frames(h, rows, plan, lead).sum().backward()
        else:
            with torch.no_grad():
                fill_frames(h, rows, plan, lead)

    return select, interp


# ----------------------------------------------------------------------------------------- run
@dataclass
class BenchSettings:
    """What :func:`run_bench` was asked, checked: the workload, its variants and the grid."""

    work: Workload
    archs: List[str]
    reductions: List[float]
    batch: int
    frames: int
    repeats: int
    warmup: int
    device: str
    quick: bool
    backend: str
    steps: int
    fastpath: bool
    modes: List[str]
    amp: str
    compile_modes: List[str]
    fsq: str
    root: Optional[str]


@dataclass
class Cell:
    """One timed variant of a (arch, mode) group: dense (``reduction`` None) or sparse, at one
    compile mode; its wall and CPU times per repeat and its peak memory rise (bytes)."""

    reduction: Optional[float]
    compile_mode: str
    model: torch.nn.Module
    fn: Step
    applied: str
    wall: List[float] = field(default_factory=list)
    cpu: List[float] = field(default_factory=list)
    mem: int = 0
    launches: Optional[int] = None

    def run_timed(self, device: torch.device) -> None:
        """One timed call: wall, process CPU time, peak memory."""
        with PeakMemory(device) as mem:
            sync(device)
            w0, c0 = time.perf_counter(), time.process_time()
            self.fn()
            sync(device)
            self.wall.append(time.perf_counter() - w0)
            self.cpu.append(time.process_time() - c0)
        self.mem = max(self.mem, mem.peak)


def run_bench(archs: Optional[Sequence[str]] = None, reductions: Sequence[float] = (0.6, 0.7, 0.8, 0.9),
              batch: int = 64, frames: int = 196, repeats: int = 3, warmup: int = 1, device: str = "auto",
              quick: bool = False, backend: str = "auto", steps: int = 50, fastpath: bool = False,
              modes: Sequence[str] = ("train", "sample"), amp: str = "fp32", compile_mode: Any = "none",
              on_row: Optional[Callable[[Dict[str, Any]], None]] = None, fsq: str = "paper", family: str = "mdm",
              root: Optional[str] = None) -> Dict[str, Any]:
    """Dense and sparse, interleaved per repeat; wall-clock, process CPU time, peak memory.
    ``family``: a registered model family with a :class:`~smdm_plugin.training.workloads.Workload`
    (:func:`~smdm_plugin.training.workloads.family_choices`); ``archs``: its variants (None = all of
    them); ``root``: an upstream checkout whose model class to time (None = the in-package one);
    ``on_row``: called with each result row as it is measured. Returns the JSON-ready result."""
    work = WORKLOADS.get(family)
    archs = list(work.default_archs if archs is None else archs)
    bad = [a for a in archs if a not in work.archs]
    if bad:
        raise ValueError(f"run_bench: arch {bad[0]!r} is not a {family} variant; expected one of {list(work.archs)}")
    s = BenchSettings(work, archs, list(reductions), batch, frames, repeats, warmup, device, quick, backend, steps,
                      fastpath, list(modes), amp, compile_modes_of(compile_mode), fsq if work.fsq else "off", root)
    mha = getattr(torch.backends, "mha", None)
    has_fp = mha is not None and hasattr(mha, "set_fastpath_enabled")
    before = mha.get_fastpath_enabled() if has_fp else None
    if has_fp:
        mha.set_fastpath_enabled(bool(fastpath))
    try:
        return _run_bench(s, on_row or (lambda row: None))
    finally:
        if has_fp:
            mha.set_fastpath_enabled(before)


def _run_bench(s: BenchSettings, on_row: Callable[[Dict[str, Any]], None]) -> Dict[str, Any]:
    work, dev = s.work, resolve_device(s.device)
    if dev.type == "cpu":
        pin_malloc()
    rows: List[Dict[str, Any]] = []
    lengths: Dict[str, List[int]] = {}
    for arch in s.archs:
        data = work.batch(s.batch, s.frames, dev, s.quick, arch)
        lengths[arch] = [int(v) for v in data.lengths]
        for mode in s.modes:
            cells = _cells(s, arch, mode, data, dev)
            for _ in range(s.warmup):
                for c in cells:
                    c.fn()
            for _ in range(s.repeats):
                for c in cells:
                    c.run_timed(dev)
            for c in cells:
                c.launches = launches(c.fn, dev, c.compile_mode != "none")
            for c in cells:
                row = _row(s, arch, mode, c, cells, data, dev)
                rows.append(row)
                on_row(row)
            del cells
    return {
        "family": work.family, "model_source": work.source(s.root), "device": str(dev),
        "device_name": device_name(dev), "torch": torch.__version__,
        "threads": torch.get_num_threads(), "batch": s.batch, "frames": s.frames,
        "lengths": lengths[s.archs[0]], "model": work.size(s.quick), "quick": bool(s.quick),
        "repeats": s.repeats, "warmup": s.warmup, "backend": s.backend,
        "sparse_backend": " / ".join(dict.fromkeys(work.backend(s.backend, dev, m) for m in s.compile_modes)),
        "amp": s.amp, "compile": ", ".join(s.compile_modes), "compile_modes": s.compile_modes,
        "fastpath": bool(s.fastpath), "diffusion_steps": s.steps, "fsq": s.fsq,
        "load_average": load_averages(), "rows": rows, "targets": TARGETS,
    }


def _cells(s: BenchSettings, arch: str, mode: str, data: WorkloadBatch, dev: torch.device) -> List[Cell]:
    """Dense and every reduction at each compile mode (one table), built and ready to time."""
    sparse_kw = {"dynamic_update": True} if mode == "sample" else {}
    cells = []
    for cmode in s.compile_modes:
        for red in [None] + s.reductions:
            model, diffusion = build(arch, red, dev, s.quick, s.steps, s.backend, fsq=s.fsq, family=s.work.family,
                                     frames=s.frames, root=s.root, **sparse_kw)
            fn = step_fn(mode, s.work, model, diffusion, data, dev, s.amp, cmode)
            cells.append(Cell(red, cmode, model, fn, _applied(fn.compiled)))
    return cells


def _row(s: BenchSettings, arch: str, mode: str, c: Cell, cells: List[Cell], data: WorkloadBatch,
         dev: torch.device) -> Dict[str, Any]:
    """The result row of cell ``c``: against the dense cell at its compile mode; sparse steps add
    the selection and interpolation times (alone, with the step's shapes)."""
    dense = next(d for d in cells if d.reduction is None and d.compile_mode == c.compile_mode)
    d_wall, d_cpu = statistics.median(dense.wall), statistics.median(dense.cpu)
    red, wall, cpu = c.reduction, statistics.median(c.wall), statistics.median(c.cpu)
    row: Dict[str, Any] = {
        "family": s.work.family, "arch": arch, "mode": mode, "reduction": 0.0 if red is None else red,
        "compile": c.compile_mode, "compile_applied": c.applied, "launches": c.launches,
        "sparse_backend": s.work.backend(s.backend, dev, c.compile_mode),
        "variant": "dense" if red is None else f"sparse {int(round(red * 100))}%",
        "median_s": wall, "cpu_s": cpu, "times_s": c.wall, "cpu_times_s": c.cpu,
        "speedup": d_wall / wall, "cpu_speedup": d_cpu / cpu, "peak_mem_mib": c.mem / 2 ** 20,
        "mem_ratio": c.mem / dense.mem if dense.mem > 0 else None,
    }
    if red is not None and mode != "loop":
        sel, interp = overhead_fns(s.work, c.model, data, dev, mode == "train")
        with autocast(dev, s.amp):
            t_sel = statistics.median(time_it(sel, dev, s.repeats, 1))
            t_int = statistics.median(time_it(interp, dev, s.repeats, 1))
        n = 1 if mode == "train" else s.work.passes   # CFG: two passes, two selections
        row.update(select_s=t_sel * n, interp_s=t_int * n, overhead_share=(t_sel * n + t_int * n) / wall)
    return row


def compile_modes_of(compile_mode: Any) -> List[str]:
    """``--compile``'s modes as a list (one mode or several; each checked, duplicates dropped)."""
    from ..runtime.compile import check_compile_mode

    modes = [compile_mode] if isinstance(compile_mode, str) else list(compile_mode)
    if not modes:
        raise ValueError("run_bench: compile_mode: give at least one of none, default, reduce-overhead")
    return list(dict.fromkeys(check_compile_mode(m, "--compile") for m in modes))


# ----------------------------------------------------------------------------------------- keyframes
def bench_keyframes(batch: int = 64, frames: int = 196, dims: int = 64, reduction: float = 0.8,
                    repeats: int = 5, device: str = "auto") -> Dict[str, Any]:
    """VW selection (the fused op) on ``[batch, frames, dims]`` (random-walk features, full lengths)."""
    from ..core.selection import select_keyframes

    dev = resolve_device(device)
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(batch, frames, dims, generator=g).cumsum(1).to(dev)
    times = time_it(lambda: select_keyframes(feats, None, reduction, "vw"), dev, repeats, 1)
    return {"shape": [batch, frames, dims], "reduction": reduction, "device": str(dev),
            "median_s": statistics.median(times), "times_s": times}
