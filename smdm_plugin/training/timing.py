"""Measuring one callable the way ``smdm bench`` does: wall-clock medians with device syncs
(:func:`time_it`), the peak memory rise of a block (:class:`PeakMemory`: CUDA max allocated, else the
process RSS sampled every 2 ms), kernel launches (:func:`launches`) and what the machine was
(:func:`device_name`, :func:`load_averages`)."""
from __future__ import annotations

import ctypes
import os
import threading
import time
from typing import Any, Callable, List, Optional

import torch

__all__ = ["sync", "pin_malloc", "rss_bytes", "PeakMemory", "time_it", "event_times", "launches", "load_averages",
           "device_name"]


def sync(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA); nothing elsewhere."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def pin_malloc() -> bool:
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


def rss_bytes() -> int:
    """The process's resident set size (bytes; the peak where ``/proc`` is missing)."""
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
        self.base = rss_bytes()
        self._max = self.base
        self._stop = threading.Event()

        def poll() -> None:
            while not self._stop.is_set():
                self._max = max(self._max, rss_bytes())
                time.sleep(self.interval)

        self._thread = threading.Thread(target=poll, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak = torch.cuda.max_memory_allocated(self.device) - self.base
            return
        self._max = max(self._max, rss_bytes())
        self._stop.set()
        self._thread.join()
        self.peak = self._max - self.base


def time_it(fn: Callable[[], Any], device: torch.device, repeats: int, warmup: int) -> List[float]:
    """Wall-clock seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    sync(device)
    out = []
    for _ in range(repeats):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        out.append(time.perf_counter() - t0)
    return out


def event_times(fn: Callable[[], Any], device: torch.device, repeats: int, warmup: int) -> List[float]:
    """Seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones: on CUDA each measured
    by CUDA events recorded around the call on an idle stream (so the host's launch gaps count, as
    they do in a run), elsewhere :func:`time_it`'s wall clock."""
    if device.type != "cuda":
        return time_it(fn, device, repeats, warmup)
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        torch.cuda.synchronize(device)
        start.record()
        fn()
        end.record()
        end.synchronize()
        out.append(start.elapsed_time(end) / 1000.0)
    return out


#: host-side launch calls the CUDA profiler records (a CUDA graph replay is one cudaGraphLaunch)
CUDA_LAUNCH_CALLS = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx",
                     "cudaGraphLaunch", "cudaLaunchCooperativeKernel")


def launches(fn: Callable[[], None], device: torch.device, compiled: bool) -> Optional[int]:
    """Kernel launches of one call of ``fn`` (already warmed up). Eager: counted as CUDA runs them
    (:mod:`smdm_plugin.runtime.launches`, on any device). Compiled: on CUDA the launch calls the
    profiler records (a CUDA graph replay counts once); elsewhere None (a compiler's fused kernels
    bypass the dispatcher: nothing CUDA-equivalent to count)."""
    if not compiled:
        from ..runtime.launches import count_launches

        return count_launches(fn, warmup=0).count
    if device.type != "cuda":
        return None
    try:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            fn()
            torch.cuda.synchronize(device)
        return int(sum(e.count for e in prof.key_averages() if e.key in CUDA_LAUNCH_CALLS))
    except Exception:  # a profiler that cannot run here: say so in the table, never fail the bench
        return None


def load_averages() -> Optional[List[float]]:
    """The 1-, 5- and 15-minute load averages (2 decimals), or None where the OS has none."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def device_name(dev: torch.device) -> str:
    """The GPU's name, or the CPU's with its core count."""
    if dev.type == "cuda":
        return torch.cuda.get_device_name(dev)
    import platform

    return f"{platform.processor() or platform.machine()} ({os.cpu_count()} cores)"
