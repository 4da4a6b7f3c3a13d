#!/usr/bin/env python
"""The one GPU check of the project (issue 36): on one CUDA GPU, in a bounded time, the matrix

    {trans_enc, trans_dec, DiP prefix, DoubleTake, MotionDiffuse} x {fp32, bf16 autocast}
    x {training step, sampling call, whole sampling loop} x {eager, default, reduce-overhead}

* **check**: every cell runs (``ok`` / the exception in one line) and matches the CPU within float
  tolerance: the sparse model (the paper's recipe, ``SparseConfig()`` at 80%, dynamic update on at
  sampling except in bf16 loops, ``dynamic_update``; dropout off: its draws differ between
  devices) at a small size, the same weights and inputs (drawn on the CPU), against the CPU's eager fp32 run on the static-shape path (what a GPU
  runs): three training steps' losses (AdamW steps between them), three guided sampling calls, one
  whole sampling loop after a first one (its noise drawn on the CPU); the largest error relative to
  the reference's largest value;
* **speed**: dense against sparse (MDM's size: latent 512, 8 layers, 4 heads, 196 frames, B=64,
  the paper's recipe at 80%), CUDA-event medians after warm-up, each cell as ``smdm bench`` times it
  (compiled cells capture the whole step: docs/compile.md);

and writes ONE markdown table between ``<!-- gpu-check:begin -->`` and ``<!-- gpu-check:end -->``
in docs/gpu.md (GPU, torch, CUDA and triton versions named), and prints it. Cells run in order of
need (eager, then reduce-overhead, then default; in each mode every check, then every speed cell)
until ``--budget-s`` (default 300 s of wall time on the GPU machine; ``inf``: no limit) is spent;
cells left out say ``not run``. Compilation (inductor, cold caches) takes most of the time: a
first run on a fresh machine may leave compiled cells out; ``--models`` / ``--precisions`` /
``--calls`` / ``--modes`` pick a part of the matrix.

    python scripts/gpu_check.py                       # on the GPU machine: writes docs/gpu.md
    python scripts/gpu_check.py --dry-run --doc /tmp/gpu.md   # on a CPU: tiny sizes, aot_eager (CI)

``--dry-run`` runs the same code on the CPU at tiny sizes with the ``aot_eager`` backend (CUDA
graphs do not apply there: ``reduce-overhead`` runs as ``default``, and the table says so).
"""
from __future__ import annotations

import argparse
import datetime
import gc
import os
import re
import statistics
import sys
import time
import traceback
import warnings
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch

from smdm_plugin.core.checks import static_mode
from smdm_plugin.training import benchmark, workloads
from smdm_plugin.training.timing import device_name, event_times

BEGIN, END = "<!-- gpu-check:begin -->", "<!-- gpu-check:end -->"
#: (family, variant, name in the table)
MODELS: Tuple[Tuple[str, str, str], ...] = (("mdm", "trans_enc", "trans_enc"), ("mdm", "trans_dec", "trans_dec"),
                                            ("mdm", "dip", "DiP prefix"), ("mdm", "doubletake", "DoubleTake"),
                                            ("motiondiffuse", "motiondiffuse", "MotionDiffuse"))
PRECISIONS = ("fp32", "bf16")
CALLS = {"train": "training step", "sample": "sampling call", "loop": "sampling loop"}
MODES = ("eager", "default", "reduce-overhead")
#: largest |CUDA - CPU| / largest |CPU| allowed: (precision, call) -> tolerance (a loop compounds
#: its steps; bf16 against the fp32 reference)
TOLERANCE = {("fp32", "train"): 1e-3, ("fp32", "sample"): 1e-3, ("fp32", "loop"): 1e-2,
             ("bf16", "train"): 5e-2, ("bf16", "sample"): 5e-2, ("bf16", "loop"): 2e-1}
REDUCTION = 0.8
DOC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs", "gpu.md")


@dataclass
class Sizes:
    """One size of the models and batches: ``quick`` (the tiny in-package model) or MDM's; batch,
    frames, diffusion steps T."""

    quick: bool
    batch: int
    frames: int
    steps: int


@dataclass
class Settings:
    """What the check runs: device, compile backend, the check's and the speed's sizes, timing
    repeats (loops: ``loop_repeats``), the time budget, the selected rows and modes, and whether
    compiled speed cells are profiled after timing."""

    device: torch.device
    backend: str
    check: Sizes
    speed: Sizes
    repeats: int
    warmup: int
    loop_repeats: int
    budget_s: float
    models: List[Tuple[str, str, str]]
    precisions: List[str]
    calls: List[str]
    modes: List[str]
    profile: bool = False      # compiled speed cells: where a call's time goes (:func:`profile_calls`)


@dataclass
class Row:
    """One (model, precision, call) row: per mode the check (``ok 3e-06`` / ``FAIL`` / the error)
    and the speed (dense and sparse medians in ms)."""

    name: str
    precision: str
    call: str
    check: Dict[str, str] = field(default_factory=dict)
    speed: Dict[str, Tuple[float, float]] = field(default_factory=dict)
    speed_error: Dict[str, str] = field(default_factory=dict)


class Clock:
    """The time budget: :meth:`left` seconds (wall clock) since the start."""

    def __init__(self, budget_s: float) -> None:
        self.start, self.budget = time.perf_counter(), budget_s

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def left(self) -> float:
        return self.budget - self.elapsed()


# ----------------------------------------------------------------------------------------- running
def one_line(e: BaseException) -> str:
    """An exception as one table-safe line: ``Type: first line`` (cut at 120 characters)."""
    text = f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''}"
    text = text.replace("|", "/")
    return text if len(text) <= 120 else text[:117] + "..."


def compile_mode(mode: str) -> str:
    """The compile helper's mode of a table mode (``eager`` is ``none``)."""
    return "none" if mode == "eager" else mode


def free(device: torch.device) -> None:
    """Forget compiled graphs and free cached memory between cells."""
    torch._dynamo.reset()
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()


def dynamic_update(call: str, precision: str) -> bool:
    """Whether a check cell samples with the dynamic update (VW on ``x_t`` in the last steps): not
    in a bf16 loop, where bf16 rounding of ``x_t`` moves VW's choice of keyframes and with it the
    whole sample (measured on the CPU, bf16 autocast against fp32, T = 10: largest error 0.31-1.16
    of the largest value with it, 0.005-0.018 without, the dense model's 0.016): a different
    sample, not a wrong one. The sampling call (one step inside the late steps) keeps it."""
    return call != "train" and not (call == "loop" and precision == "bf16")


def run_values(s: Settings, family: str, arch: str, call: str, device: torch.device, amp: str, mode: str,
               reduction: Optional[float] = REDUCTION, size: Optional[Sizes] = None,
               dynamic: Optional[bool] = None, **config: Any) -> List[torch.Tensor]:
    """What a check compares: three training losses, three sampling call outputs, or the sample of
    a second whole loop (the first warms it up), as CPU float32 tensors. ``dynamic``: sample with
    the dynamic update (default: :func:`dynamic_update` of ``call`` and ``amp``); ``config``: more
    ``workloads.build`` settings of the sparse model (``fsq="off"``, ``lipschitz=False``, ...)."""
    z = size or s.check
    work = workloads.WORKLOADS.get(family)
    dynamic = dynamic_update(call, amp) if dynamic is None else dynamic
    sparse = dict(config, **({"dynamic_update": True} if dynamic else {})) if reduction is not None else {}
    model, diffusion = workloads.build(arch, reduction, device, z.quick, z.steps, family=family, frames=z.frames,
                                       **sparse)
    workloads.without_dropout(model)                 # random draws differ between devices
    data = work.batch(z.batch, z.frames, device, z.quick, arch)
    if call == "loop":
        model.eval()
        step = benchmark.sampling_step(work, model, diffusion, device, compile_mode(mode), s.backend)
        out = None
        for _ in range(2):
            with torch.no_grad(), benchmark.autocast(device, amp):
                out = benchmark.sample_loop(step, tuple(data.x.shape), z.steps, work.sample_kwargs(data), device,
                                            torch.Generator().manual_seed(1))
        values = [out]
    else:
        fn = benchmark.step_fn(call, work, model, diffusion, data, device, amp, compile_mode(mode), s.backend)
        values = [fn() for _ in range(3)]
    return [v.detach().float().cpu() for v in values]


def relative_error(got: Sequence[torch.Tensor], want: Sequence[torch.Tensor]) -> float:
    """Largest |got - want| over the largest |want| (inf when a value is not finite)."""
    err = 0.0
    for a, b in zip(got, want):
        if not torch.isfinite(a).all():
            return float("inf")
        err = max(err, float((a - b).abs().max()) / max(float(b.abs().max()), 1e-6))
    return err


def check_cell(s: Settings, family: str, arch: str, precision: str, call: str, mode: str,
               reference: Callable[[], List[torch.Tensor]]) -> str:
    """``ok 3.1e-06``, ``FAIL 2.0e-01 > 5e-02`` or the exception of one cell, in one line."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            got = run_values(s, family, arch, call, s.device, precision, mode)
        err = relative_error(got, reference())
    except Exception as e:  # noqa: BLE001 - a crash is the cell's result
        traceback.print_exc(file=sys.stderr)
        return "error: " + one_line(e)
    finally:
        free(s.device)
    tol = TOLERANCE[(precision, call)]
    return f"ok {err:.1e}" if err <= tol else f"FAIL {err:.1e} > {tol:.0e}"


def compile_counts() -> Tuple[int, int]:
    """``(graphs, CUDA-graph skips)`` so far in this process: Dynamo's unique graphs, and the times
    inductor ran a graph without the CUDA graphs ``reduce-overhead`` asked for (at compile time or,
    for an input mutated in place, at a call: every kernel then launches from the host; the reason
    is logged under ``TORCH_LOGS=cudagraphs``)."""
    from torch._dynamo.utils import counters

    return int(counters["stats"]["unique_graphs"]), int(counters["inductor"]["cudagraph_skips"])


#: the profiler's host-side events that each stand for a launch, a copy or a wait
PROFILE_EVENTS = ("LaunchKernel", "cuLaunch", "GraphLaunch", "Memcpy", "Synchronize", "EventSynchronize", "Memset")


def profile_calls(fn: Callable[[], Any], device: torch.device, calls: int = 3
                  ) -> Tuple[Any, float, float, Dict[str, int]]:
    """``calls`` calls of ``fn`` under the torch profiler: ``(key averages, host self ms per call,
    GPU busy ms per call, per call the count of each event of`` :data:`PROFILE_EVENTS` ``)``."""
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=acts) as prof:
        for _ in range(calls):
            fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
    avg = prof.key_averages()
    counts: Dict[str, int] = {}
    for e in avg:
        if any(k in e.key for k in PROFILE_EVENTS):
            counts[e.key] = counts.get(e.key, 0) + e.count // calls
    host = sum(e.self_cpu_time_total for e in avg) / calls / 1e3
    gpu = sum(getattr(e, "self_device_time_total", 0) for e in avg) / calls / 1e3
    return avg, host, gpu, counts


def profile_lines(fn: Callable[[], Any], device: torch.device, calls: int = 3, top: int = 12) -> List[str]:
    """A compiled call's profile in a few lines: host self time, GPU busy time, launches, copies and
    waits per call, then the ``top`` host events by self time (what runs outside the CUDA graphs)."""
    avg, host, gpu, counts = profile_calls(fn, device, calls)
    lines = [f"host self {host:.2f} ms/call (profiled), GPU busy {gpu:.2f} ms/call; "
             + (", ".join(f"{k} {v}" for k, v in sorted(counts.items())) or "no launches seen")]
    for e in sorted(avg, key=lambda e: -e.self_cpu_time_total)[:top]:
        lines.append(f"  {e.self_cpu_time_total / calls / 1e3:7.3f} ms  x{e.count // calls:<4d} {e.key[:90]}")
    return lines


def speed_cell(s: Settings, family: str, arch: str, precision: str, call: str, mode: str,
               log: Optional[Callable[[str], None]] = None) -> Tuple[float, float]:
    """``(dense ms, sparse ms)``: medians of CUDA-event times (wall clock off CUDA) after warm-up,
    dense and sparse interleaved, each cell as ``smdm bench`` times it. A compiled cell tells
    ``log`` the graphs each model compiled and how many of them run without CUDA graphs, the graphs
    compiled and CUDA-graph skips while timing, and with ``s.profile`` each model's profile
    (:func:`profile_lines`) after the timing."""
    z, work = s.speed, workloads.WORKLOADS.get(family)
    data = work.batch(z.batch, z.frames, s.device, z.quick, arch)
    fns = []
    for reduction in (None, REDUCTION):
        model, diffusion = workloads.build(arch, reduction, s.device, z.quick, z.steps, family=family,
                                           frames=z.frames, **({"dynamic_update": True}
                                                               if call == "sample" and reduction else {}))
        fns.append(benchmark.step_fn(call, work, model, diffusion, data, s.device, precision, compile_mode(mode),
                                     s.backend))
    loop = call == "loop"
    repeats, warmup = (s.loop_repeats, 1) if loop else (s.repeats, s.warmup)
    times: List[List[float]] = [[], []]
    counts = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for fn in fns:                               # compiled: the eager first call, then the capture
            before = compile_counts()
            for _ in range(max(warmup, 1 if loop else 2)):
                fn()
            counts.append([b - a for a, b in zip(before, compile_counts())])
        before = compile_counts()
        for _ in range(repeats):                     # interleaved: machine load hits both alike
            for i, fn in enumerate(fns):
                times[i] += event_times(fn, s.device, 1, 0)
        timed = [b - a for a, b in zip(before, compile_counts())]
    if log is not None and mode != "eager":
        log(f"compiled {arch} {precision} {call} {mode}: dense {counts[0][0]} graph(s), {counts[0][1]} without CUDA "
            f"graphs; sparse {counts[1][0]} graph(s), {counts[1][1]} without CUDA graphs; while timed {timed[0]} "
            f"compiled, {timed[1]} CUDA-graph skips")
        if s.profile:
            for kind, fn in zip(("dense", "sparse"), fns):
                try:
                    for line in profile_lines(fn, s.device):
                        log(f"profile {arch} {precision} {call} {mode} {kind}: {line}")
                except Exception as e:  # noqa: BLE001 - a diagnostic: the cell's times stand
                    log(f"profile {arch} {precision} {call} {mode} {kind}: error: {one_line(e)}")
    return statistics.median(times[0]) * 1e3, statistics.median(times[1]) * 1e3


def applied_mode(s: Settings, mode: str) -> str:
    """What ``mode`` runs as here (``reduce-overhead`` needs CUDA and inductor)."""
    if mode == "reduce-overhead" and (s.device.type != "cuda" or s.backend != "inductor"):
        return "default"
    return mode


def run(s: Settings, log: Callable[[str], None] = print,
        after_cell: Optional[Callable[[List[Row], Clock, int], None]] = None) -> Tuple[List[Row], Clock, int]:
    """Every selected cell in order of need until the budget is spent: ``(rows, clock, cells left
    out)``; ``after_cell(rows, clock, cells left out so far)`` after each cell run (the table of a
    run killed by a time limit is then on disk)."""
    clock = Clock(s.budget_s)
    rows = {(n, p, c): Row(n, p, c) for _, _, n in s.models for p in s.precisions for c in s.calls}
    refs: Dict[Tuple[str, str, bool], List[torch.Tensor]] = {}
    skipped = 0

    def reference(family: str, arch: str, call: str, precision: str) -> Callable[[], List[torch.Tensor]]:
        dynamic = dynamic_update(call, precision)

        def get() -> List[torch.Tensor]:
            if (arch, call, dynamic) not in refs:
                with static_mode():
                    refs[(arch, call, dynamic)] = run_values(s, family, arch, call, torch.device("cpu"), "fp32",
                                                             "eager", dynamic=dynamic)
            return refs[(arch, call, dynamic)]
        return get

    order = [m for m in ("eager", "reduce-overhead", "default") if m in s.modes]
    for mode in order:
        for kind in ("check", "speed"):
            for family, arch, name in s.models:
                for precision in s.precisions:
                    for call in s.calls:
                        row = rows[(name, precision, call)]
                        if clock.left() <= 0:
                            skipped += 1
                            continue
                        if kind == "check":
                            row.check[mode] = check_cell(s, family, arch, precision, call, mode,
                                                         reference(family, arch, call, precision))
                            log(f"check {name} {precision} {call} {mode}: {row.check[mode]} ({clock.elapsed():.0f} s)")
                            if after_cell is not None:
                                after_cell(list(rows.values()), clock, skipped)
                            continue
                        try:
                            row.speed[mode] = speed_cell(s, family, arch, precision, call, mode, log)
                            log(f"speed {name} {precision} {call} {mode}: dense {row.speed[mode][0]:.2f} ms, "
                                f"sparse {row.speed[mode][1]:.2f} ms ({clock.elapsed():.0f} s)")
                        except Exception as e:  # noqa: BLE001 - a crash is the cell's result
                            traceback.print_exc(file=sys.stderr)
                            row.speed_error[mode] = "error: " + one_line(e)
                        finally:
                            free(s.device)
                        if after_cell is not None:
                            after_cell(list(rows.values()), clock, skipped)
    return list(rows.values()), clock, skipped


# ----------------------------------------------------------------------------------------- the table
def versions() -> str:
    """torch, CUDA and triton versions, in words."""
    try:
        import triton

        tri = triton.__version__
    except ImportError:
        tri = "not installed"
    return f"torch {torch.__version__}, CUDA {torch.version.cuda or 'n/a'}, triton {tri}"


def table(s: Settings, rows: List[Row], clock: Clock, skipped: int) -> str:
    """The markdown block written between the markers: a setting line and one table."""
    def size(z: Sizes) -> str:
        model = "tiny in-package model" if z.quick else "MDM size (latent 512, 8 layers, 4 heads)"
        return f"{model}, B={z.batch}, {z.frames} frames, T={z.steps}"

    modes = [m for m in MODES if m in s.modes]
    head = ["model", "precision", "call"]
    for m in modes:
        label = m if applied_mode(s, m) == m else f"{m} (ran {applied_mode(s, m)})"
        head += [f"{label}: check", f"{m}: dense ms", f"{m}: sparse ms", f"{m}: speed-up"]
    lines = [f"GPU check (`scripts/gpu_check.py`, {datetime.date.today().isoformat()}): "
             f"{device_name(s.device)} ({s.device}); {versions()}; compile backend {s.backend}.",
             "",
             f"Check: sparse model, paper recipe at {int(REDUCTION * 100)}% (dynamic update on at sampling except in bf16 loops: `dynamic_update`; no dropout), "
             f"{size(s.check)}, against the CPU's eager fp32 run (static-shape path); largest error relative to "
             f"the reference's largest value (tolerance fp32 {TOLERANCE[('fp32', 'sample')]:.0e} "
             f"(loop {TOLERANCE[('fp32', 'loop')]:.0e}), bf16 {TOLERANCE[('bf16', 'sample')]:.0e} "
             f"(loop {TOLERANCE[('bf16', 'loop')]:.0e})). Speed: dense against sparse, {size(s.speed)}, medians of "
             f"{s.repeats} (loops {s.loop_repeats}) after warm-up, CUDA events; compiled cells capture the whole step "
             f"(docs/compile.md). {clock.elapsed():.0f} s of a {s.budget_s:.0f} s budget"
             + (f"; {skipped} check / speed cells not run (budget: `--budget-s`)" if skipped else "") + ".",
             "",
             "| " + " | ".join(head) + " |",
             "| " + " | ".join(["---"] * 3 + ["---", "---:", "---:", "---:"] * len(modes)) + " |"]
    for r in rows:
        cells = [r.name, r.precision, CALLS[r.call]]
        for m in modes:
            cells.append(r.check.get(m, "not run"))
            if m in r.speed:
                d, sp = r.speed[m]
                cells += [f"{d:.2f}", f"{sp:.2f}", f"{d / sp:.2f}×"]
            else:
                cells += [r.speed_error.get(m, "not run"), "—", "—"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_doc(path: str, block: str) -> None:
    """Replace what lies between the markers of ``path`` by ``block`` (the rest untouched);
    ``ValueError`` naming the file when the markers are missing."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    pattern = re.compile(re.escape(BEGIN) + r".*?" + re.escape(END), re.S)
    if len(pattern.findall(text)) != 1:
        raise ValueError(f"{path}: needs one {BEGIN} ... {END} section")
    text = pattern.sub(lambda _: f"{BEGIN}\n{block}\n{END}", text)
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)


# ----------------------------------------------------------------------------------------- CLI
def settings(a: argparse.Namespace) -> Settings:
    """The parsed options as :class:`Settings` (``--dry-run``: CPU, tiny sizes, ``aot_eager``)."""
    if a.dry_run:
        tiny = Sizes(True, 2, 24, 4)
        return Settings(torch.device("cpu"), "aot_eager", tiny, tiny, 1, 0, 1, float("inf"),
                        [m for m in MODELS if m[1] in a.models], a.precisions, a.calls, a.modes, a.profile)
    device = torch.device(a.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("gpu_check: no CUDA device here (use --dry-run on a CPU)")
    speed = Sizes(a.quick, a.batch, a.frames, a.steps)
    check = Sizes(True, 4, 40, 10)
    if a.quick:
        speed = replace(check)
    return Settings(device, a.backend, check, speed, a.repeats, a.warmup, a.loop_repeats, a.budget_s,
                    [m for m in MODELS if m[1] in a.models], a.precisions, a.calls, a.modes, a.profile)


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="gpu_check.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda", help="the GPU (default cuda)")
    p.add_argument("--dry-run", action="store_true",
                   help="on the CPU at tiny sizes with the aot_eager backend: checks that the script runs (CI)")
    p.add_argument("--quick", action="store_true", help="speed at the check's tiny size (a smoke run on a GPU)")
    p.add_argument("--models", nargs="+", default=[m[1] for m in MODELS], choices=[m[1] for m in MODELS])
    p.add_argument("--precisions", nargs="+", default=list(PRECISIONS), choices=PRECISIONS)
    p.add_argument("--calls", nargs="+", default=list(CALLS), choices=list(CALLS))
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    p.add_argument("--batch", type=int, default=64, help="speed batch (default 64)")
    p.add_argument("--frames", type=int, default=196, help="speed frames (default 196; DiP: 40 after 20)")
    p.add_argument("--steps", type=int, default=50, help="diffusion steps T (default 50)")
    p.add_argument("--repeats", type=int, default=20, help="timed calls per speed cell (default 20)")
    p.add_argument("--warmup", type=int, default=5, help="untimed calls first (default 5)")
    p.add_argument("--loop-repeats", type=int, default=3, help="timed loops per loop cell (default 3)")
    p.add_argument("--budget-s", type=float, default=300.0, help="wall-clock budget in seconds (default 300)")
    p.add_argument("--backend", default="inductor", help="torch.compile backend (default inductor)")
    p.add_argument("--doc", default=DOC, help="the markdown file whose gpu-check section is replaced "
                                              "(default docs/gpu.md)")
    p.add_argument("--no-doc", action="store_true", help="print the table only")
    p.add_argument("--profile", action="store_true",
                   help="after timing a compiled cell, log each model's profile (host and GPU time per call, launches, "
                        "the top host events)")
    a = p.parse_args(argv)
    s = settings(a)
    def save(rows: List[Row], clock: Clock, skipped: int) -> None:
        if not a.no_doc:
            write_doc(a.doc, table(s, rows, clock, skipped) + "\n\n(run in progress: the cells above so far)")

    rows, clock, skipped = run(s, log=lambda line: print(line, file=sys.stderr, flush=True), after_cell=save)
    block = table(s, rows, clock, skipped)
    print(block)
    if not a.no_doc:
        write_doc(a.doc, block)
        print(f"\nwrote the table into {a.doc}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
