"""Process groups under ``torchrun``, shared by ``smdm train`` and the MDM training hooks.

``torchrun`` (torch.distributed.elastic) starts one process per device and sets ``RANK``,
``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT``; :func:`init_distributed`
reads them, picks the device (``cuda:LOCAL_RANK`` on CUDA, else the CPU) and the backend (``nccl``
on CUDA, ``gloo`` on the CPU) and joins the group. Without those variables it returns a
single-process :class:`DistContext` and touches nothing, so the same code runs with or without
``torchrun``.
"""
from __future__ import annotations

import datetime
import os
from dataclasses import dataclass, field
from typing import Mapping, Optional

import torch

TORCHRUN_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
#: minutes a collective may wait (rank 0 evaluating or sampling while the others wait at the next
#: all-reduce); override with SMDM_DIST_TIMEOUT_MIN
DEFAULT_TIMEOUT_MIN = 180.0


def launched_by_torchrun(env: Optional[Mapping[str, str]] = None) -> bool:
    """Whether this process was started by ``torchrun`` (all of :data:`TORCHRUN_VARS` are set)."""
    env = os.environ if env is None else env
    return all(env.get(k) for k in TORCHRUN_VARS)


def backend_for(device: torch.device) -> str:
    """``nccl`` for CUDA devices, ``gloo`` otherwise (CPU)."""
    return "nccl" if device.type == "cuda" else "gloo"


def resolve_device(name: str = "auto", local_rank: int = 0) -> torch.device:
    """``auto``: ``cuda:local_rank`` when CUDA is available, else MPS (single process), else CPU.
    ``cuda`` without an index becomes ``cuda:local_rank``."""
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda", local_rank)
        mps = getattr(torch.backends, "mps", None)
        if mps is not None and mps.is_available() and local_rank == 0:
            return torch.device("mps")
        return torch.device("cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and dev.index is None:
        return torch.device("cuda", local_rank)
    return dev


@dataclass(frozen=True)
class DistContext:
    """Where this process stands: ``rank`` of ``world_size`` processes, ``local_rank`` on its node,
    its ``device``; ``owns_group`` when :func:`init_distributed` created the process group."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    owns_group: bool = False

    @property
    def distributed(self) -> bool:
        """Whether a process group is up (collectives are needed; ``torchrun`` with
        ``--nproc_per_node 1`` too)."""
        return torch.distributed.is_available() and torch.distributed.is_initialized()

    @property
    def is_main(self) -> bool:
        """Rank 0: the only process that writes checkpoints, logs and plots."""
        return self.rank == 0

    def barrier(self) -> None:
        if self.distributed:
            torch.distributed.barrier()

    def broadcast_flag(self, value: bool) -> bool:
        """Rank 0's ``value`` on every rank (e.g. "the output folder may be written")."""
        if not self.distributed:
            return value
        t = torch.tensor([int(bool(value))], device=self.device if self.device.type == "cuda" else "cpu")
        torch.distributed.broadcast(t, 0)
        return bool(t.item())

    def mean(self, value: torch.Tensor) -> torch.Tensor:
        """The mean of ``value`` over the ranks (a new tensor; ``value`` itself when single)."""
        if not self.distributed:
            return value
        out = value.detach().clone()
        torch.distributed.all_reduce(out)
        return out / self.world_size

    def max_divergence(self, module: torch.nn.Module) -> float:
        """The largest absolute difference of any parameter or buffer of ``module`` between ranks
        (0.0 when they hold identical values; always 0.0 in a single process)."""
        tensors = [t.detach().float().reshape(-1) for t in list(module.parameters()) + list(module.buffers())]
        if not self.distributed or not tensors:
            return 0.0
        flat = torch.cat(tensors)
        hi, lo = flat.clone(), flat.clone()
        torch.distributed.all_reduce(hi, op=torch.distributed.ReduceOp.MAX)
        torch.distributed.all_reduce(lo, op=torch.distributed.ReduceOp.MIN)
        return float((hi - lo).max())


def constant_buffers_kwargs() -> dict:
    """``DistributedDataParallel`` keywords for a model whose buffers never change in training
    (positional tables, markers; no batch-norm statistics): no buffer broadcast before every
    forward. ``forward_sync_buffers=False`` (newer torch) still syncs them once at construction;
    older torch only has ``broadcast_buffers=False``."""
    import inspect

    from torch.nn.parallel import DistributedDataParallel

    params = inspect.signature(DistributedDataParallel.__init__).parameters
    return {"forward_sync_buffers": False} if "forward_sync_buffers" in params else {"broadcast_buffers": False}


def timeout_minutes(env: Optional[Mapping[str, str]] = None) -> float:
    env = os.environ if env is None else env
    text = env.get("SMDM_DIST_TIMEOUT_MIN", "")
    try:
        value = float(text) if text else DEFAULT_TIMEOUT_MIN
    except ValueError:
        raise ValueError(f"SMDM_DIST_TIMEOUT_MIN must be a number of minutes, got {text!r}") from None
    if not value > 0:
        raise ValueError(f"SMDM_DIST_TIMEOUT_MIN must be > 0, got {text!r}")
    return value


def init_distributed(device: str = "auto") -> DistContext:
    """Join the ``torchrun`` process group (once; later calls reuse it) and pick this process's
    device; a single-process context when not started by ``torchrun``."""
    if not launched_by_torchrun():
        return DistContext(device=resolve_device(device))
    rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    local_rank = int(os.environ["LOCAL_RANK"])
    dev = resolve_device(device, local_rank)
    if dev.type == "mps":
        raise ValueError("device: torch.distributed has no MPS backend; use cpu or cuda under torchrun")
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    owns = False
    if not torch.distributed.is_initialized():
        torch.distributed.init_process_group(
            backend=backend_for(dev), rank=rank, world_size=world,
            timeout=datetime.timedelta(minutes=timeout_minutes()))
        owns = True
    return DistContext(rank=rank, world_size=world, local_rank=local_rank, device=dev, owns_group=owns)


def shutdown_distributed(ctx: DistContext) -> None:
    """Leave the process group if :func:`init_distributed` created it."""
    if ctx.owns_group and torch.distributed.is_initialized():
        # all ranks leave together: a rank tearing gloo down while a peer is still in its last
        # collective aborts the process ("terminate called without an active exception")
        # and objects still bound to the group (DDP reducers of finished trainers, kept alive by
        # reference cycles) are freed first, not by the collector after the group is gone
        import gc

        gc.collect()
        try:
            torch.distributed.barrier()
        finally:
            torch.distributed.destroy_process_group()
