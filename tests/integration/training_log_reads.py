"""Upstream MDM's training log: upstream's, or kept until it is read (``families/mdm/upstream_loop.py``
and the norms of ``upstream_optim.norms_in_one_sync``; ``SMDM_TEST_KEEP_LOG=1``), on upstream's own
``TrainLoop`` and ``diffusion.logger``. Run inside ``train.train_mdm`` through ``mdm_harness.py -c``;
at exit prints one line ``TRAINING_LOG {json}``: the host's reads of tensor values (``item``,
``tolist``, ``numpy``, ``cpu``: a host sync each on a GPU) inside each ``run_step``: inside the
optimizer's ``step`` (a foreach AdamW's counters; the fused one reads none), apart (:class:`Reads`)
and the others; every dump (``dumpkvs``: key, type and value, in order); the class of the loop's
data. Under ``smdm run`` with ``--sparse_compile`` the package's hooks apply instead (where the
fused optimizer does)."""
import atexit
import json
import os
import runpy
import sys

import torch

import train.training_loop as loop_mod
from diffusion import logger
from diffusion.fp16_util import MixedPrecisionTrainer

if os.environ.get("SMDM_TEST_KEEP_LOG") == "1":
    from smdm_plugin.families.mdm.upstream_loop import deferred_logger, log_loss_dict_later
    from smdm_plugin.families.mdm.upstream_optim import norms_in_one_sync

    deferred_logger(logger.Logger)
    loop_mod.log_loss_dict = log_loss_dict_later(loop_mod.log_loss_dict)
    MixedPrecisionTrainer._compute_norms = norms_in_one_sync(MixedPrecisionTrainer._compute_norms)


class Reads:
    """Counts calls of the tensor methods that read values back (patched on ``torch.Tensor`` while
    counting: a ``TorchFunctionMode`` would be traced into the compiled step): inside the
    optimizer's ``step``; made by torch itself (tracing a compiled step) or by a device's own
    kernel of the package (``smdm_plugin/core/kernels``: the CPU's numpy keyframe selection; CUDA
    runs another), counted apart; and every other read (upstream's code, the package's hooks)."""

    NAMES = ("item", "tolist", "numpy", "cpu")
    APART = (os.path.dirname(torch.__file__) + os.sep, os.path.join("smdm_plugin", "core", "kernels") + os.sep)

    def __init__(self):
        self.reads = self.optimizer_reads = self.apart = 0
        self.in_optimizer = False
        self.saved = {}

    def __enter__(self):
        for name in self.NAMES:
            method = self.saved[name] = getattr(torch.Tensor, name)
            setattr(torch.Tensor, name, self.counted(method))
        return self

    def __exit__(self, *exc):
        for name, method in self.saved.items():
            setattr(torch.Tensor, name, method)

    def counted(self, method):
        def call(*args, **kwargs):
            caller = sys._getframe(1).f_code.co_filename
            if self.in_optimizer:
                self.optimizer_reads += 1
            elif any(part in caller for part in self.APART):
                self.apart += 1
            else:
                self.reads += 1
            return method(*args, **kwargs)
        return call


row = {"reads": [], "optimizer_reads": [], "apart": [], "dumps": [], "data": None}
_run_step, _dumpkvs = loop_mod.TrainLoop.run_step, logger.Logger.dumpkvs


def run_step(self, batch, cond):
    row["data"] = type(self.data).__name__
    opt_step = self.opt.step
    r = Reads()

    def step(*args, **kwargs):
        r.in_optimizer = True
        try:
            return opt_step(*args, **kwargs)
        finally:
            r.in_optimizer = False

    self.opt.step = step
    try:
        with r:
            _run_step(self, batch, cond)
    finally:
        del self.opt.step
    row["reads"].append(r.reads)
    row["optimizer_reads"].append(r.optimizer_reads)
    row["apart"].append(r.apart)


def dumpkvs(self):
    out = _dumpkvs(self)
    row["dumps"].append([[k, type(v).__name__, repr(v)] for k, v in out.items()])
    return out


loop_mod.TrainLoop.run_step, logger.Logger.dumpkvs = run_step, dumpkvs
atexit.register(lambda: print("TRAINING_LOG " + json.dumps(row), flush=True))
runpy.run_module("train.train_mdm", run_name="__main__")
