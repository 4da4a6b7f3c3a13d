"""``smdm bench``: what sparse keyframe mode saves in wall-clock time, measured in one run.

For the MDM-size in-package backbone (:class:`~smdm_plugin.backbone.TinyMDM`, latent 512, 8
layers, 4 heads, ff 1024; ``trans_enc`` and ``trans_dec``) on a HumanML3D-like batch (batch 64,
196 frames, valid lengths drawn in 40..196 with a fixed seed, cached text embeddings — no CLIP) it
times, dense and at every reduction rate:

* a **training step**: ``SimpleDiffusion.training_losses`` (with the sparse diffusion attached, so
  keyframe selection on x0 is included) + backward + ``AdamW.step``;
* a **sampling step** with classifier-free guidance (two forward passes, ``eval``, ``no_grad``) at
  a late diffusion step (``t <= gamma*T``, where the mask is re-selected by VW on x_t: the
  costliest step of the schedule);
* the **overhead** of keyframe selection (features + VW + mask noise) and of the interpolation
  back to all frames (forward + backward in training), as a share of the sparse step;
* **peak memory** of the step: CUDA max allocated, or on CPU the peak rise of the process RSS
  during the step (sampled from ``/proc/self/statm``; glibc's mmap threshold is pinned so freed
  activations go back to the OS and the number is per step, not cumulative).

Medians over ``--repeats`` after ``--warmup`` runs. Dense and sparse run the same module types
with the same fast-path setting (``torch.backends.mha`` fast path off for both, see
``--fastpath``), so the ratio compares like with like.

``python -m smdm_plugin.bench keyframes`` times batched VW alone on ``[64, 196, 64]``.
"""
from __future__ import annotations

import argparse
import ctypes
import json
import os
import statistics
import sys
import threading
import time
from typing import Any, Callable, Dict, List, Optional

import torch

TARGETS = {"train": 4.0, "sample": 3.5, "overhead": 0.10}  # at reduction 0.8, MDM size, CPU


# ----------------------------------------------------------------------------------------- utils
def pick_device(name: str = "auto") -> torch.device:
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        return torch.device("cpu")
    return torch.device(name)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _pin_malloc() -> bool:
    """Fix glibc's mmap threshold at 1 MiB so that big freed tensors are unmapped at once (RSS then
    follows the live tensors; without this the dynamic threshold keeps them in the heap)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
        ok = libc.mallopt(M_MMAP_THRESHOLD, 1 << 20) == 1
        libc.mallopt(M_TRIM_THRESHOLD, 1 << 20)
        return ok
    except Exception:
        return False


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except Exception:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


class PeakMemory:
    """Context manager: peak memory rise (bytes) during the block."""

    def __init__(self, device: torch.device, interval: float = 0.002) -> None:
        self.device, self.interval, self.peak = device, interval, 0

    def __enter__(self) -> "PeakMemory":
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.base = torch.cuda.memory_allocated(self.device)
            return self
        self.base = _rss_bytes()
        self._max = self.base
        self._stop = threading.Event()

        def poll() -> None:
            while not self._stop.is_set():
                self._max = max(self._max, _rss_bytes())
                time.sleep(self.interval)

        self._thread = threading.Thread(target=poll, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak = torch.cuda.max_memory_allocated(self.device) - self.base
            return
        self._max = max(self._max, _rss_bytes())
        self._stop.set()
        self._thread.join()
        self.peak = self._max - self.base


def time_it(fn: Callable[[], Any], device: torch.device, repeats: int, warmup: int) -> List[float]:
    for _ in range(warmup):
        fn()
    _sync(device)
    out = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        out.append(time.perf_counter() - t0)
    return out


# ----------------------------------------------------------------------------------------- setup
def mdm_size(quick: bool = False) -> Dict[str, int]:
    if quick:
        return dict(latent_dim=64, ff_size=128, num_layers=2, num_heads=4)
    return dict(latent_dim=512, ff_size=1024, num_layers=8, num_heads=4)


def make_batch(batch: int, frames: int, device: torch.device, seed: int = 0, min_len: int = 40
               ) -> Dict[str, Any]:
    """A HumanML3D-like batch: normal features ``[B, 263, 1, N]``, lengths in ``min_len..N``."""
    g = torch.Generator().manual_seed(seed)
    lo = min(min_len, frames)
    lengths = torch.randint(lo, frames + 1, (batch,), generator=g)
    lengths[0] = frames  # the longest sample sets the padded length
    x = torch.randn(batch, 263, 1, frames, generator=g)
    valid = torch.arange(frames) < lengths[:, None]
    x = x * valid.view(batch, 1, 1, frames)
    y = {"mask": valid.view(batch, 1, 1, frames).to(device), "lengths": lengths.to(device),
         "text_embed": torch.randn(1, batch, 512, generator=g).to(device)}
    return {"x": x.to(device), "y": y, "lengths": lengths}


def build(arch: str, reduction: Optional[float], device: torch.device, quick: bool, steps: int,
          backend: str = "auto", seed: int = 0):
    """(model, diffusion) — dense when ``reduction`` is None."""
    from ..adapters.mdm import sparsify
    from ..reference.backbone import TinyMDM
    from ..core.config import SparseConfig
    from ..reference.diffusion import SimpleDiffusion

    torch.manual_seed(seed)
    model = TinyMDM(arch=arch, **mdm_size(quick)).to(device)
    diffusion = SimpleDiffusion(steps)
    if reduction is not None:
        cfg = SparseConfig(reduction=reduction, attention_backend=backend)
        sparsify(model, cfg, diffusion=diffusion)
    return model, diffusion


def _train_step_fn(model, diffusion, batch, device, seed: int = 0) -> Callable[[], None]:
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    g = torch.Generator(device="cpu").manual_seed(seed)
    B = batch["x"].shape[0]

    def step() -> None:
        t = torch.randint(0, diffusion.num_timesteps, (B,), generator=g).to(device)
        loss = diffusion.training_losses(model, batch["x"], t, {"y": dict(batch["y"])})["loss"].mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


def _sample_step_fn(model, diffusion, batch, device, gamma: float = 0.1) -> Callable[[], None]:
    from ..reference.diffusion import ClassifierFreeGuidance

    model.eval()
    cfg = ClassifierFreeGuidance(model, scale=2.5)
    B = batch["x"].shape[0]
    t_late = max(0, int(gamma * diffusion.num_timesteps) - 1)  # VW re-selection on x_t
    t = torch.full((B,), t_late, dtype=torch.long, device=device)
    x_t = diffusion.q_sample(batch["x"], t)

    def step() -> None:
        with torch.no_grad():
            x_t.add_(0)  # bump the version: every step is a new x_t (no stale mask cache)
            cfg(x_t, t, dict(batch["y"]))

    return step


def _overhead_fns(model, batch, device, train: bool):
    """Keyframe selection and the interpolation back to all frames, alone, with the step's
    shapes: ``(select, interp)`` callables."""
    from ..adapters.state import frames_layout, get_state
    from ..core.attention_backends import Packing, get_backend, supports_packed, varlen_backend

    state = get_state(model)
    sched, tr = state.schedule, state.transformer
    frames = frames_layout(batch["x"])
    lengths = batch["lengths"].to(device)
    B, N = frames.shape[:2]
    d = model.latent_dim
    if train:
        def select():
            return sched.training_mask(frames, lengths)
    else:
        t = torch.zeros(B, dtype=torch.long, device=device)

        def select():
            return sched.sampling_mask(frames, t, lengths)
    mask = select()
    lead = 1 if model.arch == "trans_enc" or getattr(model, "emb_trans_dec", False) else 0
    tr.n_lead = lead
    keep = torch.cat([mask.new_ones(B, lead), mask], 1) if lead else mask
    packed = (get_backend(tr.backend, device, train) is varlen_backend and tr.interpolate
              and supports_packed(tr.inner))
    if packed:
        T = int(keep.sum())
        h = torch.randn(T, d, device=device, requires_grad=train)
        fill = lambda: tr._packed_fill(h, Packing(keep), keep)
    else:
        h = torch.randn(N + lead, B, d, device=device, requires_grad=train)
        fill = lambda: tr._fill(h, keep)

    def interp():
        if train:
            fill().sum().backward()
        else:
            with torch.no_grad():
                fill()

    return select, interp


# ----------------------------------------------------------------------------------------- run
def run_bench(archs=("trans_enc", "trans_dec"), reductions=(0.6, 0.7, 0.8, 0.9), batch: int = 64,
              frames: int = 196, repeats: int = 3, warmup: int = 1, device: str = "auto",
              quick: bool = False, backend: str = "auto", steps: int = 1000, fastpath: bool = False,
              modes=("train", "sample"), progress: Optional[Callable[[str], None]] = None
              ) -> Dict[str, Any]:
    """Interleaved: every repeat times dense and each reduction in turn, so that load from other
    processes (shared CI machines) hits all variants alike. Wall-clock and process CPU time."""
    mha = getattr(torch.backends, "mha", None)
    has_fp = mha is not None and hasattr(mha, "set_fastpath_enabled")
    before = mha.get_fastpath_enabled() if has_fp else None
    if has_fp:
        mha.set_fastpath_enabled(bool(fastpath))
    try:
        return _run_bench(archs, reductions, batch, frames, repeats, warmup, device, quick, backend, steps,
                          fastpath, modes, progress)
    finally:
        if has_fp:
            mha.set_fastpath_enabled(before)


def _run_bench(archs, reductions, batch, frames, repeats, warmup, device, quick, backend, steps, fastpath,
               modes, progress) -> Dict[str, Any]:
    dev = pick_device(device)
    if dev.type == "cpu":
        _pin_malloc()
    data = make_batch(batch, frames, dev)
    say = progress or (lambda s: None)
    rows: List[Dict[str, Any]] = []
    variants: List[Optional[float]] = [None] + list(reductions)
    for arch in archs:
        for mode in modes:
            cells = []
            for red in variants:
                model, diffusion = build(arch, red, dev, quick, steps, backend)
                fn = (_train_step_fn if mode == "train" else _sample_step_fn)(model, diffusion, data, dev)
                cells.append({"red": red, "model": model, "fn": fn, "wall": [], "cpu": [], "mem": 0})
            for _ in range(warmup):
                for c in cells:
                    c["fn"]()
            for _ in range(repeats):
                for c in cells:
                    with PeakMemory(dev) as mem:
                        _sync(dev)
                        w0, c0 = time.perf_counter(), time.process_time()
                        c["fn"]()
                        _sync(dev)
                        c["wall"].append(time.perf_counter() - w0)
                        c["cpu"].append(time.process_time() - c0)
                    c["mem"] = max(c["mem"], mem.peak)
            dense = cells[0]
            d_wall, d_cpu = statistics.median(dense["wall"]), statistics.median(dense["cpu"])
            for c in cells:
                red, wall, cpu = c["red"], statistics.median(c["wall"]), statistics.median(c["cpu"])
                row: Dict[str, Any] = {
                    "arch": arch, "mode": mode, "reduction": 0.0 if red is None else red,
                    "variant": "dense" if red is None else f"sparse {int(round(red * 100))}%",
                    "median_s": wall, "cpu_s": cpu, "times_s": c["wall"], "cpu_times_s": c["cpu"],
                    "speedup": d_wall / wall, "cpu_speedup": d_cpu / cpu, "peak_mem_mib": c["mem"] / 2 ** 20,
                }
                if red is not None:
                    sel, interp = _overhead_fns(c["model"], data, dev, mode == "train")
                    t_sel = statistics.median(time_it(sel, dev, repeats, 1))
                    t_int = statistics.median(time_it(interp, dev, repeats, 1))
                    # CFG: both forward passes interpolate; the mask is selected once (cached)
                    n_int = 1 if mode == "train" else 2
                    row.update(select_s=t_sel, interp_s=t_int * n_int,
                               overhead_share=(t_sel + t_int * n_int) / wall)
                rows.append(row)
                say(_row_line(row))
            del cells
    return {
        "device": str(dev), "device_name": _device_name(dev), "torch": torch.__version__,
        "threads": torch.get_num_threads(), "batch": batch, "frames": frames,
        "lengths": [int(v) for v in data["lengths"]], "model": mdm_size(quick), "repeats": repeats,
        "warmup": warmup, "backend": backend, "fastpath": bool(fastpath), "diffusion_steps": steps,
        "load_average": _loadavg(), "rows": rows, "targets": TARGETS,
    }


def _loadavg() -> Optional[List[float]]:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def _device_name(dev: torch.device) -> str:
    if dev.type == "cuda":
        return torch.cuda.get_device_name(dev)
    import platform

    return f"{platform.processor() or platform.machine()} ({os.cpu_count()} cores)"


def _row_line(r: Dict[str, Any]) -> str:
    sp = f" x{r['speedup']:.2f} (cpu x{r['cpu_speedup']:.2f})"
    ov = f" overhead {100 * r['overhead_share']:.1f}%" if "overhead_share" in r else ""
    return f"{r['arch']} {r['mode']:6s} {r['variant']:10s} {r['median_s'] * 1000:9.1f} ms{sp}{ov}"


def markdown(result: Dict[str, Any]) -> str:
    lines = [f"device: {result['device_name']} ({result['device']}), torch {result['torch']}, "
             f"{result['threads']} threads; batch {result['batch']}, {result['frames']} frames, model "
             f"{result['model']}; median of {result['repeats']} (interleaved) after {result['warmup']} "
             f"warm-up; load average {result.get('load_average')}",
             "",
             "| arch | step | variant | wall (ms) | speed-up (wall) | CPU time (ms) | speed-up (CPU) | "
             "selection (ms) | interpolation (ms) | overhead share | peak mem (MiB) |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in result["rows"]:
        sp = "—" if r.get("speedup") is None else f"{r['speedup']:.2f}×"
        sel = f"{r['select_s'] * 1000:.1f}" if "select_s" in r else "—"
        itp = f"{r['interp_s'] * 1000:.1f}" if "interp_s" in r else "—"
        ov = f"{100 * r['overhead_share']:.1f}%" if "overhead_share" in r else "—"
        lines.append(f"| {r['arch']} | {r['mode']} | {r['variant']} | {r['median_s'] * 1000:.1f} | {sp} | "
                     f"{r['cpu_s'] * 1000:.1f} | {r['cpu_speedup']:.2f}× | "
                     f"{sel} | {itp} | {ov} | {r['peak_mem_mib']:.0f} |")
    at = [r for r in result["rows"] if abs(r["reduction"] - 0.8) < 1e-9]
    if at:
        lines += ["", "targets at 80% reduction: training ≥ 4×, sampling ≥ 3.5×, selection + "
                  "interpolation < 10% of the sparse step"]
        for r in at:
            tgt = TARGETS[r["mode"]]
            ok = r["speedup"] is not None and r["speedup"] >= tgt
            lines.append(f"* {r['arch']} {r['mode']}: {r['speedup']:.2f}× wall, {r['cpu_speedup']:.2f}× CPU "
                         f"(target {tgt}×) "
                         f"{'met' if ok else 'MISSED'}; overhead {100 * r['overhead_share']:.1f}% "
                         f"{'met' if r['overhead_share'] < TARGETS['overhead'] else 'MISSED'}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------- keyframes
def bench_keyframes(batch: int = 64, frames: int = 196, dims: int = 64, reduction: float = 0.8,
                    repeats: int = 5, device: str = "auto") -> Dict[str, Any]:
    """Batched VW on ``[batch, frames, dims]`` (random walk features, full lengths)."""
    from ..core.selection import select_keyframes

    dev = pick_device(device)
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(batch, frames, dims, generator=g).cumsum(1).to(dev)
    times = time_it(lambda: select_keyframes(feats, None, reduction, "vw"), dev, repeats, 1)
    return {"shape": [batch, frames, dims], "reduction": reduction, "device": str(dev),
            "median_s": statistics.median(times), "times_s": times}


# ----------------------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--arch", nargs="+", default=["trans_enc", "trans_dec"], choices=["trans_enc", "trans_dec"])
    p.add_argument("--reductions", nargs="+", type=float, default=[0.6, 0.7, 0.8, 0.9])
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--frames", type=int, default=196)
    p.add_argument("--repeats", type=int, default=3, help="timed runs per cell (median reported)")
    p.add_argument("--warmup", type=int, default=1, help="untimed runs before timing")
    p.add_argument("--device", default="auto", help="auto (cuda if available) | cpu | cuda | cuda:1 ...")
    p.add_argument("--backend", default="auto", choices=["auto", "compact", "varlen", "masked"],
                   help="keyframe attention backend of the sparse model")
    p.add_argument("--modes", nargs="+", default=["train", "sample"], choices=["train", "sample"])
    p.add_argument("--steps", type=int, default=1000, help="diffusion steps T (MDM: 1000)")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (CPU)")
    p.add_argument("--fastpath", action="store_true",
                   help="leave torch's MHA/Transformer fast path enabled (default: off for dense and sparse)")
    p.add_argument("--quick", action="store_true",
                   help="tiny model, batch 4, 60 frames, 1 repeat, no warm-up: a smoke run")
    p.add_argument("--out", default=None, help="write the JSON result here (and the table beside it, .md)")


def busy_note(threads: int) -> Optional[str]:
    """A warning when other processes already keep the CPU busy (timings with several threads per
    process then suffer badly from oversubscription: threads wait on preempted partners)."""
    load = _loadavg()
    cores = os.cpu_count() or 1
    if load and threads > 1 and load[0] > cores:
        return (f"note: load average {load[0]:.1f} on {cores} cores — other jobs are running; "
                f"{threads} threads per process will be slowed by oversubscription, consider --threads 1")
    return None


def main_bench(args: argparse.Namespace) -> Dict[str, Any]:
    if args.threads:
        torch.set_num_threads(args.threads)
    note = busy_note(torch.get_num_threads()) if pick_device(args.device).type == "cpu" else None
    if note:
        print(note, file=sys.stderr)
    if args.quick:
        args.batch, args.frames = min(args.batch, 4), min(args.frames, 60)
        args.repeats, args.warmup = 1, 0
    result = run_bench(args.arch, args.reductions, args.batch, args.frames, args.repeats, args.warmup,
                       args.device, args.quick, args.backend, args.steps, args.fastpath, args.modes,
                       progress=lambda s: print(s, file=sys.stderr, flush=True))
    table = markdown(result)
    print(table)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(result, f, indent=2)
        with open(os.path.splitext(args.out)[0] + ".md", "w") as f:
            f.write(table + "\n")
        print(f"\nwrote {args.out}")
    return result


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "keyframes":
        p = argparse.ArgumentParser(prog="python -m smdm_plugin.bench keyframes",
                                    description="time batched VW keyframe selection")
        p.add_argument("--batch", type=int, default=64)
        p.add_argument("--frames", type=int, default=196)
        p.add_argument("--dims", type=int, default=64)
        p.add_argument("--reduction", type=float, default=0.8)
        p.add_argument("--repeats", type=int, default=5)
        p.add_argument("--device", default="auto")
        a = p.parse_args(argv[1:])
        r = bench_keyframes(a.batch, a.frames, a.dims, a.reduction, a.repeats, a.device)
        print(f"batched VW on {r['shape']} (reduction {r['reduction']}, {r['device']}): "
              f"{r['median_s'] * 1000:.1f} ms (median of {len(r['times_s'])})")
        return 0
    if argv and argv[0] == "steps":
        argv = argv[1:]
    p = argparse.ArgumentParser(prog="smdm bench", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    main_bench(p.parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
