"""Dense and sparse side by side in one process: the measurements behind ``smdm bench``.

:func:`run_bench` times, for one family's :class:`~smdm_plugin.training.workloads.Workload`, the
dense model and every reduction rate, interleaved (every repeat runs every variant in turn, so
machine load hits all alike), at each compile mode: ``train`` (one training step with the sparse
diffusion wrapper + backward + ``AdamW.step``), ``sample`` (one sampling step at a late step,
dynamic update forced on), ``loop`` (the whole sampling loop). Each result row is a JSON-ready dict
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
from ..integrations.distributed import resolve_device
from .timing import PeakMemory, device_name, launches, load_averages, pin_malloc, sync, time_it
from .workloads import WORKLOADS, Workload, WorkloadBatch, build

__all__ = ["TARGETS", "MODES", "run_bench", "compile_modes_of", "step_fn", "overhead_fns", "bench_keyframes"]

TARGETS = {"train": 4.0, "sample": 3.5, "loop": 3.0, "overhead": 0.10}  # at 80% reduction
MODES = ("train", "sample", "loop")

Step = Callable[[], None]


def autocast(device: torch.device, amp: str) -> ContextManager[Any]:
    """``torch.autocast`` to bfloat16 for ``amp="bf16"``, else nothing."""
    if amp == "bf16":
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def _compiled(model: torch.nn.Module, compile_mode: str) -> torch.nn.Module:
    """``model`` compiled in place by the helper every integration uses (``--sparse_compile``,
    ``smdm train --compile``; docs/compile.md): the denoiser, guidance wrapper around it eager."""
    from ..integrations.compile import compile_model

    if compile_mode != "none":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")        # reduce-overhead off CUDA: stated in the table instead
            compile_model(model, compile_mode)
    return model


def _applied(model: torch.nn.Module) -> str:
    """How ``model`` ran: ``eager`` or the compile mode that applied (reduce-overhead falls back to
    default without CUDA)."""
    from ..integrations.compile import compile_setting

    s = compile_setting(model)
    return "eager" if s is None else s.mode


# ----------------------------------------------------------------------------------------- steps
def _train_step(work: Workload, model: torch.nn.Module, diffusion: Any, batch: WorkloadBatch,
                device: torch.device, amp: str, compile_mode: str, seed: int = 0) -> Step:
    model.train()
    run = _compiled(model, compile_mode)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    g = torch.Generator(device="cpu").manual_seed(seed)
    ts = [torch.randint(0, diffusion.num_timesteps, (batch.size,), generator=g).to(device) for _ in range(16)]
    step_no = [0]

    def step() -> None:
        t = ts[step_no[0] % len(ts)]                 # made ahead of time: no host-to-device copy
        step_no[0] += 1
        with autocast(device, amp):
            loss = diffusion.training_losses(run, batch.x, t, work.kwargs(batch))["loss"].mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


def _sample_step(work: Workload, model: torch.nn.Module, diffusion: Any, batch: WorkloadBatch,
                 device: torch.device, amp: str, compile_mode: str) -> Step:
    from ..core.schedule import MaskSchedule

    den = work.denoiser(_compiled(model, compile_mode))
    config = sparse_config_of(model)  # the public accessor, not the model's private state
    late = MaskSchedule(config).late_steps if config is not None else 1
    t = torch.full((batch.size,), max(0, late - 1), dtype=torch.long, device=device)
    x_t = diffusion.q_sample(batch.x, t)

    def step() -> None:
        with torch.no_grad(), autocast(device, amp):
            x_t.add_(0)                              # a new x_t every time
            den(x_t, t, **work.kwargs(batch))

    return step


def _sample_loop(work: Workload, model: torch.nn.Module, diffusion: Any, batch: WorkloadBatch,
                 device: torch.device, amp: str, compile_mode: str) -> Step:
    den = work.denoiser(_compiled(model, compile_mode))
    shape = tuple(batch.x.shape)
    g = torch.Generator(device=device).manual_seed(0)

    def loop() -> None:
        with torch.no_grad(), autocast(device, amp):
            diffusion.p_sample_loop(den, shape, work.kwargs(batch), device=device, generator=g)

    return loop


#: what each ``--modes`` entry times: ``maker(work, model, diffusion, batch, device, amp, compile_mode)``
STEP_MAKERS: Dict[str, Callable[..., Step]] = {"train": _train_step, "sample": _sample_step, "loop": _sample_loop}


def step_fn(mode: str, work: Workload, model: torch.nn.Module, diffusion: Any, batch: WorkloadBatch,
            device: torch.device, amp: str = "fp32", compile_mode: str = "none") -> Step:
    """The timed callable of one cell: ``mode`` one of :data:`MODES`."""
    return STEP_MAKERS[mode](work, model, diffusion, batch, device, amp, compile_mode)


def overhead_fns(work: Workload, model: torch.nn.Module, batch: WorkloadBatch, device: torch.device,
                 train: bool) -> Tuple[Step, Step]:
    """Keyframe selection and the interpolation back to all frames, alone, with the step's
    shapes: ``(select, interp)`` callables."""
    from ..adapters.diffusion import model_noise
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
    archs = list(work.archs if archs is None else archs)
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
    data = work.batch(s.batch, s.frames, dev, s.quick)
    rows: List[Dict[str, Any]] = []
    for arch in s.archs:
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
        "lengths": [int(v) for v in data.lengths], "model": work.size(s.quick), "quick": bool(s.quick),
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
            cells.append(Cell(red, cmode, model, step_fn(mode, s.work, model, diffusion, data, dev, s.amp, cmode)))
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
        "compile": c.compile_mode, "compile_applied": _applied(c.model), "launches": c.launches,
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
    from ..integrations.compile import check_compile_mode

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
