"""MDM/DiP training under ``torchrun``: DistributedDataParallel, a sampler per rank, rank-0 writes."""
from __future__ import annotations

import atexit
import functools
import inspect
import os
import random
import shutil
import tempfile
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Optional

if TYPE_CHECKING:  # (imported when training under torchrun: patches/mdm.patch imports this module in every run)
    from ...runtime.distributed import DistContext


@dataclass
class _Run:
    """This process under ``torchrun``."""

    rank: int
    world_size: int
    local_rank: int
    seed: int = 0
    save_dir: Optional[str] = None        # the real --save_dir (ranks > 0 write elsewhere)
    private_dir: Optional[str] = None     # where ranks > 0 send train_mdm's start-up writes
    ctx: Optional[DistContext] = None     # set by setup_dist


_RUN: Optional[_Run] = None


def active() -> bool:
    """Whether this process trains under ``torchrun`` with the hooks on (outside ``torchrun``,
    decided without importing anything)."""
    if os.environ.get("SMDM_DDP", "1") == "0" or not os.environ.get("LOCAL_RANK"):
        return False
    from ...runtime.distributed import launched_by_torchrun

    return launched_by_torchrun()


def _run() -> _Run:
    global _RUN
    if _RUN is None:
        _RUN = _Run(rank=int(os.environ["RANK"]), world_size=int(os.environ["WORLD_SIZE"]),
                    local_rank=int(os.environ["LOCAL_RANK"]))
    return _RUN


def _wrap(owner: Any, name: str, make: Callable[[Callable], Callable]) -> bool:
    """``owner.name`` -> ``make(original)``, once (:func:`~._hooks.wrap_once` with its own marker)."""
    from ...integrations._hooks import wrap_once

    return wrap_once(owner, name, make, marker="_smdm_ddp")


# --------------------------------------------------------------------------- utils.parser_util
def _patch_parser_util(mod: Any) -> None:
    def make(original):
        @functools.wraps(original)
        def train_args(*a, **kw):
            args = original(*a, **kw)
            run = _run()
            run.seed = int(getattr(args, "seed", 0) or 0)
            run.save_dir = getattr(args, "save_dir", None)
            if run.rank > 0:
                run.private_dir = tempfile.mkdtemp(prefix=f"smdm_rank{run.rank}_")
                atexit.register(shutil.rmtree, run.private_dir, True)
                args.save_dir = os.path.join(run.private_dir, "save")
                args.train_platform_type = "NoPlatform"
                for flag in ("eval_during_training", "gen_during_training"):
                    if hasattr(args, flag):
                        setattr(args, flag, False)
            return args
        return train_args

    _wrap(mod, "train_args", make)


# --------------------------------------------------------------------------- utils.dist_util
def _patch_dist_util(mod: Any) -> None:
    def make(original):
        @functools.wraps(original)
        def setup_dist(device=0):
            import torch

            from ...runtime.distributed import init_distributed

            original(device)
            run = _run()
            cuda = torch.cuda.is_available() and int(device) >= 0
            if cuda:
                mod.used_device = run.local_rank  # dist_util.dev() -> cuda:LOCAL_RANK
            run.ctx = init_distributed("cuda" if cuda else "cpu")
            if run.ctx.owns_group:
                atexit.register(_shutdown)
        return setup_dist

    _wrap(mod, "setup_dist", make)


def _shutdown() -> None:
    from ...runtime.distributed import shutdown_distributed

    if _RUN is not None and _RUN.ctx is not None:
        shutdown_distributed(_RUN.ctx)


# --------------------------------------------------------------------------- data_loaders.get_data
def _epoch_sampler(dataset: Any, run: _Run) -> Any:
    from torch.utils.data import DistributedSampler

    class EpochSampler(DistributedSampler):
        """A ``DistributedSampler`` that moves to the next epoch each time it is iterated (MDM's
        loop never calls ``set_epoch``)."""

        def __init__(self, *a: Any, **kw: Any) -> None:
            super().__init__(*a, **kw)
            self._next_epoch = 0

        def __iter__(self):
            self.set_epoch(self._next_epoch)
            self._next_epoch += 1
            return super().__iter__()

    return EpochSampler(dataset, num_replicas=run.world_size, rank=run.rank, shuffle=True, seed=run.seed,
                        drop_last=True)


def _patch_get_data(mod: Any) -> None:
    def make(original):
        signature = inspect.signature(original)

        @functools.wraps(original)
        def get_dataset_loader(*a, **kw):
            loader = original(*a, **kw)
            bound = signature.bind(*a, **kw)
            bound.apply_defaults()
            run = _run()
            if run.world_size < 2 or bound.arguments.get("split") != "train" \
                    or bound.arguments.get("hml_mode") != "train":
                return loader  # evaluation loaders (rank 0) and single-process runs: as upstream
            return type(loader)(loader.dataset, batch_size=loader.batch_size,
                                sampler=_epoch_sampler(loader.dataset, run), num_workers=loader.num_workers,
                                drop_last=loader.drop_last, collate_fn=loader.collate_fn)
        return get_dataset_loader

    _wrap(mod, "get_dataset_loader", make)


# --------------------------------------------------------------------------- train.training_loop
def _ddp_class():
    from torch.nn.parallel import DistributedDataParallel

    class MDMDistributedDataParallel(DistributedDataParallel):
        """DDP that also answers the wrapped model's own attributes (MDM's diffusion reads e.g.
        ``model.all_goal_joint_names`` from what it is given)."""

        def __getattr__(self, name: str) -> Any:
            try:
                return super().__getattr__(name)
            except AttributeError:
                module = self._modules.get("module")
                if module is None:
                    raise
                return getattr(module, name)

    return MDMDistributedDataParallel


def _all_gather_cat(values: Any) -> Any:
    """``[b, K]`` per rank -> ``[world * b, K]`` (equal ``b`` on every rank: MDM drops the last
    incomplete batch)."""
    import torch
    import torch.distributed as dist

    parts = [torch.empty_like(values) for _ in range(dist.get_world_size())]
    dist.all_gather(parts, values.contiguous())
    return torch.cat(parts)


def _patch_training_loop(mod: Any) -> None:
    import torch

    cls = mod.TrainLoop

    def make_init(original):
        @functools.wraps(original)
        def __init__(self, args, *a, **kw):
            run = _run()
            if run.rank > 0 and run.save_dir is not None:
                # resume reads the real folder (rank 0 created it before joining the group)
                args.save_dir = run.save_dir if os.path.isdir(run.save_dir) else args.save_dir
            original(self, args, *a, **kw)
            if run.ctx is None or not run.ctx.distributed:
                return
            dev = run.ctx.device
            # MDM's buffers are constants (positional table, sparse marker), and DDP's per-forward
            # buffer broadcast fails on MDM's `pe` (a transposed view whose size-1 dimension has a
            # large stride: DDP copies it onto an overlapping view of itself)
            from ...runtime.distributed import constant_buffers_kwargs

            self.ddp_model = _ddp_class()(self.model, device_ids=[dev.index] if dev.type == "cuda" else None,
                                          **constant_buffers_kwargs())
            self.use_ddp = True
            self.global_batch = self.batch_size * run.world_size
            steps = torch.tensor([int(self.resume_step)], device=dev if dev.type == "cuda" else "cpu")
            lo, hi = steps.clone(), steps.clone()
            torch.distributed.all_reduce(lo, op=torch.distributed.ReduceOp.MIN)
            torch.distributed.all_reduce(hi, op=torch.distributed.ReduceOp.MAX)
            if int(lo) != int(hi):
                raise RuntimeError(f"smdm (torchrun): the ranks resume from different steps ({int(lo)} vs "
                                   f"{int(hi)}); every rank must see --save_dir {run.save_dir} (a shared file "
                                   "system) to resume")
        return __init__

    def make_run_loop(original):
        @functools.wraps(original)
        def run_loop(self, *a, **kw):
            run = _run()
            if run.rank > 0:  # rank 0 keeps upstream's random stream
                import numpy as np

                seed = run.seed + run.rank
                random.seed(seed)
                np.random.seed(seed)
                torch.manual_seed(seed)
            return original(self, *a, **kw)
        return run_loop

    def rank0_only(original):
        @functools.wraps(original)
        def method(self, *a, **kw):
            if _run().rank == 0:
                return original(self, *a, **kw)
            return None
        return method

    _wrap(cls, "__init__", make_init)
    _wrap(cls, "run_loop", make_run_loop)
    _wrap(cls, "save", rank0_only)
    for name in ("evaluate", "generate_during_training"):
        _wrap(cls, name, rank0_only)

    def make_log(original):
        @functools.wraps(original)
        def log_loss_dict(diffusion, ts, losses):
            run = _run()
            if run.ctx is None or not run.ctx.distributed:
                return original(diffusion, ts, losses)
            keys = list(losses)
            table = torch.stack([ts.float()] + [losses[k].detach().float().reshape(-1) for k in keys], 1)
            table = _all_gather_cat(table)
            return original(diffusion, table[:, 0].long(), {k: table[:, i + 1] for i, k in enumerate(keys)})
        return log_loss_dict

    _wrap(mod, "log_loss_dict", make_log)
    if _run().rank > 0:
        _wrap(mod, "tqdm", lambda original: functools.partial(original, disable=True))


# --------------------------------------------------------------------------- entry point
def install_hooks() -> None:
    """Register this extension's import hooks (called by :func:`smdm_plugin.families.mdm.upstream.install_hooks`,
    and by the line ``patches/mdm.patch`` adds to ``train/train_mdm.py``). A no-op unless the
    process was started by ``torchrun`` (and ``SMDM_DDP`` is not ``0``); idempotent."""
    if not active():
        return
    from ...integrations._hooks import on_import

    if _run().rank > 0:
        # MDM's diffusion.logger: no stdout/log/csv output on ranks > 0 (its own MPI rule, which
        # does not know torchrun's RANK)
        os.environ.setdefault("OPENAI_LOG_FORMAT", "")
    on_import("utils.parser_util", _patch_parser_util)
    on_import("utils.dist_util", _patch_dist_util)
    on_import("data_loaders.get_data", _patch_get_data)
    on_import("train.training_loop", _patch_training_loop)
