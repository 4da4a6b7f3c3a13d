"""Host work of upstream MDM's step after the loss (``mp_trainer.optimize(opt)``: the logged norms and
AdamW; ``update_average_model``: ``--use_ema``), upstream's against what ``--sparse_compile``
runs where the fused optimizer applies (``families/mdm/upstream_optim.py``), on upstream's own
``TrainLoop`` at the size ``sys.argv`` builds. Run inside ``train.train_mdm`` through
``mdm_harness.py -c``: the first ``run_step`` runs upstream's loss forward and backward, counts both
and prints one line ``OPTIMIZER_STEP_WORK {json}``, then the process exits.

Counted with ``smdm_plugin.training.hosttime.host_work`` (aten ops and Python frames per call, after
two warm-up calls) and a count of ``aten._local_scalar_dense`` (``.item()``: a host sync on a GPU)."""
import json
import runpy
import sys

import torch
from torch.utils._python_dispatch import TorchDispatchMode

import train.training_loop as loop_mod
from diffusion.fp16_util import MixedPrecisionTrainer
from smdm_plugin.families.mdm.upstream_optim import average_in_two_ops, norms_in_one_sync
from smdm_plugin.runtime.fused_optim import FusedAdamW
from smdm_plugin.training.hosttime import host_work


class Reads(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.reads = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.reads += func is torch.ops.aten._local_scalar_dense.default
        return func(*args, **(kwargs or {}))


def count(fn):
    work = host_work(fn)
    with Reads() as r:
        fn()
    return {"ops": work.ops, "calls": work.calls, "reads": r.reads}


def measure(self, batch, cond):
    self.forward_backward(batch, cond)
    trainer, params = self.mp_trainer, list(self.mp_trainer.master_params)
    group = self.opt.param_groups[0]
    fused = FusedAdamW(params, lr=group["lr"], weight_decay=group["weight_decay"], betas=group["betas"])
    upstream_ema, ema = loop_mod.TrainLoop.update_average_model, average_in_two_ops(loop_mod.TrainLoop.update_average_model)
    upstream_norms, norms = MixedPrecisionTrainer._compute_norms, norms_in_one_sync(MixedPrecisionTrainer._compute_norms)
    same_norms = upstream_norms(trainer) == norms(trainer)

    def upstream_step():
        trainer.optimize(self.opt)
        upstream_ema(self)

    def hooked_step():
        MixedPrecisionTrainer._compute_norms = norms
        try:
            trainer.optimize(fused)
        finally:
            MixedPrecisionTrainer._compute_norms = upstream_norms
        ema(self)

    row = {"params": len(params), "with_grad": sum(p.grad is not None for p in params),
           "use_ema": bool(self.args.use_ema), "same_norms": bool(same_norms),
           "upstream": count(upstream_step), "hooked": count(hooked_step)}
    print("OPTIMIZER_STEP_WORK " + json.dumps(row), flush=True)
    raise SystemExit(0)


loop_mod.TrainLoop.run_step = measure
runpy.run_module("train.train_mdm", run_name="__main__")
