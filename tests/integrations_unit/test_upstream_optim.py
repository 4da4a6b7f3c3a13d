"""A captured upstream training run's optimizer step (``runtime/fused_optim.py``,
``families/mdm/upstream_optim.py``): upstream's Adam / AdamW swapped for a fused one that stays
fused across a resume, and MDM's logged norms read back in one host sync with upstream's values.
torch's fused Adam(W) runs on the CPU (torch >= 2.4), so the optimizers are checked here against
torch's foreach ones; the hooks apply only where ``fused_optimizer_kwargs`` says so (CUDA), which
the tests stand in for."""
from __future__ import annotations

import copy
import sys
import types

import numpy as np
import pytest
import torch
from helpers.upstream_norms import Trainer

from smdm_plugin.families.mdm import upstream_optim as U
from smdm_plugin.runtime import compile as compile_mod
from smdm_plugin.runtime.fused_optim import FUSED_OF, FusedAdamW

PAIRS = pytest.mark.parametrize("torch_cls", list(FUSED_OF), ids=lambda c: c.__name__)


def fused_on_cpu() -> bool:
    try:
        torch.optim.AdamW([torch.zeros(1, requires_grad=True)], fused=True)
    except (RuntimeError, ValueError):
        return False
    return True


needs_cpu_fused = pytest.mark.skipif(not fused_on_cpu(), reason="this torch has no fused AdamW on the CPU")

KW = {"lr": 1e-2, "weight_decay": 0.01, "betas": (0.9, 0.99)}


def params(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(7, 5, generator=g).requires_grad_(), torch.randn(5, generator=g).requires_grad_()]


def run(opt, ps, steps: int, seed: int = 1) -> None:
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        for p in ps:
            p.grad = torch.randn(p.shape, generator=g)
        opt.step()


@needs_cpu_fused
@PAIRS
def test_fused_optimizer_steps_as_torchs(torch_cls):
    a, b = params(), params()
    fused, plain = FUSED_OF[torch_cls](a, **KW), torch_cls(b, **KW)
    assert isinstance(fused, torch_cls)
    assert fused.param_groups[0]["fused"] and not plain.param_groups[0]["fused"]
    run(fused, a, 5)
    run(plain, b, 5)
    for x, y in zip(a, b):
        assert torch.allclose(x, y, atol=1e-6, rtol=1e-5)
        assert not torch.equal(x, params()[0] if x.dim() == 2 else params()[1])   # it moved


@needs_cpu_fused
@PAIRS
def test_resuming_a_foreach_state_stays_fused_and_continues_as_torchs(torch_cls):
    """Upstream's resume: ``load_state_dict`` of a state a foreach optimizer saved, then
    ``param_groups[0]['capturable'] = True`` (MDM's ``_load_optimizer_state``); the steps after
    match a foreach optimizer resumed from the same state."""
    a = params()
    first = torch_cls(a, **KW)
    run(first, a, 3)
    saved = first.state_dict()
    assert saved["param_groups"][0]["fused"] in (None, False) and saved["state"][0]["step"].device.type == "cpu"
    b, c = [p.detach().clone().requires_grad_() for p in a], [p.detach().clone().requires_grad_() for p in a]
    resumed, plain = FUSED_OF[torch_cls](b, **KW), torch_cls(c, **KW)
    resumed.load_state_dict(copy.deepcopy(saved))     # as read from a checkpoint: tensors of its own
    plain.load_state_dict(copy.deepcopy(saved))
    resumed.param_groups[0]["capturable"] = True
    assert resumed.param_groups[0]["fused"] is True and resumed.param_groups[0]["foreach"] is None
    for p in b:
        step = resumed.state[p]["step"]
        assert step.dtype == torch.float32 and step.device == p.device and float(step) == 3.0
    run(resumed, b, 4, seed=2)
    run(plain, c, 4, seed=2)
    for x, y in zip(b, c):
        assert torch.allclose(x, y, atol=1e-6, rtol=1e-5)
    assert float(resumed.state[b[0]]["step"]) == 7.0


@needs_cpu_fused
@PAIRS
def test_a_fused_state_resumes_in_torchs(torch_cls):
    """A checkpoint of a fused run resumed without the flag: torch's optimizer takes the saved groups
    (fused) and steps on."""
    a = params()
    fused = FUSED_OF[torch_cls](a, **KW)
    run(fused, a, 2)
    b = [p.detach().clone().requires_grad_() for p in a]
    plain = torch_cls(b, **KW)
    plain.load_state_dict(copy.deepcopy(fused.state_dict()))
    run(plain, b, 2, seed=3)
    run(fused, a, 2, seed=3)
    for x, y in zip(a, b):
        assert torch.allclose(x, y, atol=1e-6)


@PAIRS
def test_foreach_true_is_refused(torch_cls):
    with pytest.raises(ValueError, match="foreach=True"):
        FUSED_OF[torch_cls](params(), foreach=True)


class ScalarReads(torch.utils._python_dispatch.TorchDispatchMode):
    """Counts ``.item()`` reads (``aten._local_scalar_dense``: a host sync on a GPU), stacks, and
    norms (one per tensor, or per list)."""

    def __init__(self):
        super().__init__()
        self.items = self.stacks = self.norms = self.foreach_norms = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.items += func is torch.ops.aten._local_scalar_dense.default
        self.norms += func.overloadpacket is torch.ops.aten.linalg_vector_norm
        self.foreach_norms += func.overloadpacket is torch.ops.aten._foreach_norm
        self.stacks += func.overloadpacket is torch.ops.aten.stack or func.overloadpacket is torch.ops.aten.cat
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("with_grads", [True, False])
def test_norms_in_one_sync_equal_upstreams_bit_for_bit(with_grads):
    ps = [torch.randn(64, 33) * 3, torch.randn(33), torch.randn(4, 4, 4),
          torch.randn(5, 9).half(), torch.randn(7).bfloat16()]            # MDM's frozen CLIP: float16
    if with_grads:
        for i, p in enumerate(ps[:2]):      # the last has no gradient (a frozen layer)
            p.grad = torch.randn_like(p) * (i + 1)
    t = Trainer(ps)
    fast = U.norms_in_one_sync(Trainer._compute_norms)
    with ScalarReads() as upstream_reads:
        want = Trainer._compute_norms(t, 2.0)
    with ScalarReads() as reads:
        got = fast(t, 2.0)
    assert got == want and all(type(g) is type(w) for g, w in zip(got, want))
    assert upstream_reads.items == len(ps) + 2 * with_grads       # a read per norm upstream
    assert reads.items == 0 and reads.stacks == 1                 # one stack, read back once by tolist
    assert reads.norms == 0 and reads.foreach_norms == 3 + with_grads   # per dtype (and the gradients')


class Loop:
    """The part of upstream's ``TrainLoop`` the EMA reads, and its EMA the way upstream updates it
    (two ops per parameter)."""

    def __init__(self, model, model_avg, use_ema=True, beta=0.9999):
        self.model, self.model_avg, self.use_fp16 = model, model_avg, False
        self.mp_trainer = Trainer(list(model.parameters()))
        self.args = types.SimpleNamespace(use_ema=use_ema, avg_model_beta=beta)

    def update_average_model(self):
        if self.args.use_ema:
            for param, avg_param in zip(self.mp_trainer.master_params, self.model_avg.parameters()):
                avg_param.data.mul_(self.args.avg_model_beta).add_(param.data, alpha=1 - self.args.avg_model_beta)


class OpCount(torch.utils._python_dispatch.TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.ops = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops += 1
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("use_ema", [True, False])
def test_ema_in_two_ops_equals_upstreams_bit_for_bit(use_ema):
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(9, 7), torch.nn.LayerNorm(7), torch.nn.Linear(7, 3))
    avg = copy.deepcopy(model)
    for p in avg.parameters():
        p.data.add_(torch.randn_like(p))
    avgs = [avg, copy.deepcopy(avg)]
    ref, fast = Loop(model, avgs[0], use_ema, beta=0.9), Loop(model, avgs[1], use_ema, beta=0.9)
    ema = U.average_in_two_ops(Loop.update_average_model)
    before = [p.detach().clone() for p in avgs[0].parameters()]
    for _ in range(3):
        with OpCount() as upstream_ops:
            Loop.update_average_model(ref)
        with OpCount() as ops:
            ema(fast)
    for a, b, c in zip(avgs[0].parameters(), avgs[1].parameters(), before):
        assert torch.equal(a, b) and torch.equal(a, c) != use_ema
    n = len(list(model.parameters()))
    assert ops.ops == (2 if use_ema else 0)                       # two multi-tensor ops
    assert upstream_ops.ops >= (2 * n if use_ema else 0)          # upstream: two (and .data's) per tensor


def test_hooks_apply_only_where_the_fused_optimizer_does(monkeypatch):
    from smdm_plugin.integrations import _hooks

    monkeypatch.setattr(_hooks, "_CALLBACKS", {})          # this test's modules, hooked afresh
    loop = types.ModuleType(U._LOOP_MODULE)
    loop.AdamW = torch.optim.AdamW

    class TrainLoop(Loop):
        pass

    loop.TrainLoop = TrainLoop
    fp16 = types.ModuleType(U._FP16_MODULE)

    class MixedPrecisionTrainer(Trainer):
        pass

    fp16.MixedPrecisionTrainer = MixedPrecisionTrainer
    monkeypatch.setitem(sys.modules, U._LOOP_MODULE, loop)
    monkeypatch.setitem(sys.modules, U._FP16_MODULE, fp16)
    assert U.fast_optimizer_step("cpu", "default") is None                 # CPU: upstream's optimizer
    assert U.fast_optimizer_step("cuda", "none") is None                   # no compile: upstream's
    assert loop.AdamW is torch.optim.AdamW and MixedPrecisionTrainer._compute_norms is Trainer._compute_norms
    assert TrainLoop.update_average_model is Loop.update_average_model
    assert U.fast_optimizer_step("cuda", "reduce-overhead") == U.OPTIMIZER_NOTE
    assert loop.AdamW is FusedAdamW
    assert TrainLoop.update_average_model is not Loop.update_average_model
    hooked = MixedPrecisionTrainer._compute_norms
    assert hooked is not Trainer._compute_norms and getattr(hooked, U._MARK)
    U.fast_optimizer_step("cuda", "default")                               # twice: hooked once
    assert MixedPrecisionTrainer._compute_norms is hooked


def test_train_device_is_upstreams(monkeypatch):
    dist_util = types.ModuleType("utils.dist_util")
    dist_util.dev = lambda: torch.device("meta")
    monkeypatch.setitem(sys.modules, "utils.dist_util", dist_util)
    assert U.train_device() == torch.device("meta")
    monkeypatch.delitem(sys.modules, "utils.dist_util")
    assert U.train_device().type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_the_policy_is_the_one_smdm_train_uses():
    assert compile_mod.fused_optimizer_kwargs("cuda", "default") == {"fused": True}
    assert compile_mod.fused_optimizer_kwargs("cpu", "default") == {}


def test_motiondiffuse_trainer_adam_is_fused_only_where_the_policy_says(monkeypatch):
    """MotionDiffuse's ``DDPMTrainer.train`` builds ``optim.Adam`` from its module's ``optim``:
    hooked only where the fused optimizer applies, every other name still torch's."""
    from smdm_plugin.families.motiondiffuse.upstream import LOSS_READ_NOTE, OPTIMIZER_NOTE, fuse_trainer_optimizer
    from smdm_plugin.integrations._hooks import WRAPPED
    from smdm_plugin.runtime.fused_optim import FusedAdam

    mod = types.ModuleType("fake_ddpm_trainer")
    mod.optim = torch.optim
    trainer_cls = type("DDPMTrainer", (), {"__module__": mod.__name__})
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    trainer = trainer_cls()
    assert fuse_trainer_optimizer(trainer, "cpu", "default") is None and mod.optim is torch.optim
    assert fuse_trainer_optimizer(trainer, "cuda", "none") is None and mod.optim is torch.optim
    # upstream's backward_G (the patch route) reads the loss: the note says so
    assert fuse_trainer_optimizer(trainer, "cuda", "default") == LOSS_READ_NOTE
    hooked = type("DDPMTrainer", (), {"__module__": mod.__name__, "backward_G": lambda self: None})
    setattr(hooked.backward_G, WRAPPED, True)                 # the hooks' backward_G
    assert fuse_trainer_optimizer(hooked(), "cuda", "default") == OPTIMIZER_NOTE
    assert mod.optim.Adam is FusedAdam and mod.optim.SGD is torch.optim.SGD
    assert mod.optim.lr_scheduler is torch.optim.lr_scheduler
