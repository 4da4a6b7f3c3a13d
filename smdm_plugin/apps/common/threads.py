"""How many CPU threads a ``smdm`` command uses, so that the default is fast on the machine at hand."""
from __future__ import annotations

import os
import sys
from typing import Optional, Tuple

WAIT_POLICY = "PASSIVE"


def prepare_process() -> bool:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` (idle OpenMP threads sleep instead of spinning) unless the
    variable is set already. Returns whether it was set now; it only takes effect when torch has
    not been imported yet (the OpenMP runtime reads it when it loads)."""
    if "OMP_WAIT_POLICY" in os.environ or "torch" in sys.modules:
        return False
    os.environ["OMP_WAIT_POLICY"] = WAIT_POLICY
    return True


def usable_cores() -> int:
    """CPUs this process may run on (its affinity mask; ``os.cpu_count()`` where there is none)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def load_average() -> Optional[float]:
    """The 1-minute load average (runnable processes), or None where the OS does not report it."""
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):
        return None


def default_threads(cores: Optional[int] = None, load: Optional[float] = None,
                    local_processes: Optional[int] = None) -> int:
    """``max(1, round(cores / local_processes - load / local_processes))``: the cores left idle by
    other processes, shared among the ``local_processes`` of this job on the machine (torchrun's
    ``LOCAL_WORLD_SIZE``, default 1). ``cores``/``load`` default to :func:`usable_cores` /
    :func:`load_average` (no load figure: all cores)."""
    cores = usable_cores() if cores is None else int(cores)
    if load is None:
        load = load_average() or 0.0
    if local_processes is None:
        try:
            local_processes = max(1, int(os.environ.get("LOCAL_WORLD_SIZE", "1")))
        except ValueError:
            local_processes = 1
    free = (cores - max(0.0, float(load))) / local_processes
    return max(1, min(cores, int(free + 0.5)))


def choose_threads(requested: Optional[int] = None) -> Tuple[int, str]:
    """``(threads, why)``: ``requested`` (``--threads``), else ``OMP_NUM_THREADS``, else
    :func:`default_threads`; ``why`` says which, for the command's first line."""
    if requested:
        return int(requested), "--threads"
    env = os.environ.get("OMP_NUM_THREADS", "")
    if env.isdigit() and int(env) > 0:
        return int(env), "OMP_NUM_THREADS"
    cores, load = usable_cores(), load_average()
    n = default_threads(cores, load)
    how = f"{cores} cores, load {load:.1f}" if load is not None else f"{cores} cores"
    return n, f"auto: {how}; --threads to change"


def apply_threads(requested: Optional[int] = None) -> str:
    """Set torch's intra-op thread count (:func:`choose_threads`); returns a short note such as
    ``"1 CPU thread (auto: 2 cores, load 2.1; --threads to change)"``."""
    import torch

    n, why = choose_threads(requested)
    cores = usable_cores()
    if n > cores:   # oversubscribed: the threads wait for each other (docs/threads.md), said, never silent
        print(f"smdm: warning: {n} CPU threads ({why.split(':')[0]}) on the {cores} core{'s' if cores != 1 else ''} "
              f"this process can use: they wait for each other, slower than --threads {cores}", file=sys.stderr)
    torch.set_num_threads(n)
    return f"{n} CPU thread{'s' if n != 1 else ''} ({why})"


THREADS_HELP = ("CPU threads for torch (default: the cores other processes leave idle, from the load average "
                "at start; OMP_NUM_THREADS when set; see docs/threads.md)")
