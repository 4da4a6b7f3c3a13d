"""Upstream MDM's training log read when it is read (``families/mdm/upstream_loop.py``): against a
copy of upstream's ``Logger`` semantics and its ``log_loss_dict`` (the reference, written out
here), the same values, keys, order and types at every dump, with no read from the device before
the dump; the timestep sampler's draws unchanged."""
from __future__ import annotations

import sys
import types
from collections import defaultdict

import numpy as np
import pytest
import torch
from helpers.upstream_norms import Trainer
from torch.overrides import TorchFunctionMode

from smdm_plugin.families.mdm import upstream_loop as L
from smdm_plugin.families.mdm import upstream_optim as U


def make_logger_module(name: str) -> types.ModuleType:
    """A module with upstream's logger API (``diffusion/logger.py``: ``Logger.logkv`` /
    ``logkv_mean`` / ``dumpkvs``, the free functions on ``Logger.CURRENT``), its own class."""
    mod = types.ModuleType(name)

    class Logger:
        CURRENT = None

        def __init__(self):
            self.name2val = defaultdict(float)
            self.name2cnt = defaultdict(int)
            self.dumps = []

        def logkv(self, key, val):
            self.name2val[key] = val

        def logkv_mean(self, key, val):
            oldval, cnt = self.name2val[key], self.name2cnt[key]
            self.name2val[key] = oldval * cnt / (cnt + 1) + val / (cnt + 1)
            self.name2cnt[key] = cnt + 1

        def dumpkvs(self):
            d = self.name2val
            out = d.copy()
            self.dumps.append([(k, type(v), v) for k, v in d.items()])
            self.name2val.clear()
            self.name2cnt.clear()
            return out

    mod.Logger = Logger
    mod.get_current = lambda: Logger.CURRENT
    mod.logkv = lambda key, val: Logger.CURRENT.logkv(key, val)
    mod.logkv_mean = lambda key, val: Logger.CURRENT.logkv_mean(key, val)
    mod.dumpkvs = lambda: Logger.CURRENT.dumpkvs()
    Logger.CURRENT = Logger()
    return mod


def make_loop_module(name: str, logger: types.ModuleType) -> types.ModuleType:
    """A module holding upstream's ``log_loss_dict`` (``train/training_loop.py``) as upstream writes it."""
    mod = types.ModuleType(name)
    mod.logger = logger

    def log_loss_dict(diffusion, ts, losses):
        for key, values in losses.items():
            mod.logger.logkv_mean(key, values.mean().item())
            for sub_t, sub_loss in zip(ts.cpu().numpy(), values.detach().cpu().numpy()):
                quartile = int(4 * sub_t / diffusion.num_timesteps)
                mod.logger.logkv_mean(f"{key}_q{quartile}", sub_loss)

    log_loss_dict.__module__ = name
    mod.log_loss_dict = log_loss_dict
    return mod


class Reads(TorchFunctionMode):
    """Counts reads of tensor values by the host (``item``, ``tolist``, ``numpy``, ``cpu``: a host
    sync each on a GPU)."""

    NAMES = {"item", "tolist", "numpy", "cpu"}

    def __init__(self):
        super().__init__()
        self.reads = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        self.reads += getattr(func, "__name__", "") in self.NAMES
        return func(*args, **(kwargs or {}))


@pytest.fixture
def pair(monkeypatch):
    """(upstream's logger and loop, the same with the log kept): two module pairs of their own."""
    ref_log, log = make_logger_module("ref_logger"), make_logger_module("kept_logger")
    ref_loop, loop = make_loop_module("ref_loop", ref_log), make_loop_module("kept_loop", log)
    for m in (ref_log, log, ref_loop, loop):
        monkeypatch.setitem(sys.modules, m.__name__, m)
    assert L.deferred_logger(log.Logger) and not L.deferred_logger(log.Logger)      # once
    log.Logger.CURRENT = log.Logger()
    loop.log_loss_dict = L.log_loss_dict_later(loop.log_loss_dict)
    return (ref_log, ref_loop), (log, loop)


def steps(log, loop, trainer, n_steps, seed=0, interval=3):
    """Upstream's calls per step (loss log, norms, step/samples), a dump every ``interval`` steps;
    returns the reads from the device outside the dumps."""
    g = torch.Generator().manual_seed(seed)
    diffusion = types.SimpleNamespace(num_timesteps=50)
    reads = 0
    for step in range(n_steps):
        ts = torch.randint(0, 50, (6,), generator=g)
        w = torch.rand(6, generator=g) + 0.5
        losses = {"loss": torch.rand(6, generator=g).requires_grad_(), "rot_mse": torch.rand(6, generator=g)}
        for p in trainer.master_params:
            p.grad = torch.randn(p.shape, generator=g)
        with Reads() as r:
            loop.log_loss_dict(diffusion, ts, {k: v * w for k, v in losses.items()})
            grad_norm, param_norm = trainer._compute_norms()
            log.logkv_mean("grad_norm", grad_norm)
            log.logkv_mean("param_norm", param_norm)
            log.logkv("step", step)
        reads += r.reads
        if (step + 1) % interval == 0:
            log.dumpkvs()
    log.dumpkvs()
    return reads


def params():
    g = torch.Generator().manual_seed(3)
    return [torch.randn(4, 3, generator=g), torch.randn(3, generator=g)]


def test_kept_log_dumps_upstreams_values_keys_order_and_types(pair, monkeypatch):
    (ref_log, ref_loop), (log, loop) = pair
    ref = Trainer(params())
    kept = Trainer(params())
    kept._compute_norms = types.MethodType(U.norms_in_one_sync(Trainer._compute_norms), kept)
    monkeypatch.setitem(sys.modules, U._LOGGER_MODULE, log)
    upstream_reads = steps(ref_log, ref_loop, ref, 7)
    reads = steps(log, loop, kept, 7)
    a, b = ref_log.Logger.CURRENT.dumps, log.Logger.CURRENT.dumps
    assert len(a) == len(b) == 3 and all(a) and a == b          # values, keys, order and types
    assert any(k.startswith("loss_q") for k, _, _ in a[0]) and any(t is np.float32 for _, t, _ in a[0])
    assert reads == 0 and upstream_reads >= 7 * (2 * 3 + 4)     # upstream: 3 per loss, one per norm


def test_reading_name2val_replays_what_waits(pair):
    """priorMDM reads ``get_current().name2val`` without a dump: it sees every call made."""
    (ref_log, ref_loop), (log, loop) = pair
    for m in (ref_log, log):
        m.logkv_mean("a", 1.0)
        m.logkv_mean("a", L.Later((torch.tensor(2.0),), L._item) if m is log else 2.0)
        m.logkv("b", 5)
    assert dict(log.Logger.CURRENT.name2val) == dict(ref_log.Logger.CURRENT.name2val) == {"a": 1.5, "b": 5}
    assert list(log.Logger.CURRENT.name2cnt.items()) == [("a", 2)]


def test_a_tensor_averaged_is_its_value_when_logged(pair):
    """``logkv_mean`` of a tensor averages its value at the call (upstream's arithmetic runs then); a
    tensor changed in place later does not change what the log says."""
    (ref_log, _), (log, _) = pair
    for m in (ref_log, log):
        x = torch.tensor(3.0)
        m.logkv_mean("x", x)
        x.add_(10.0)
        m.logkv_mean("x", x)
    assert float(log.Logger.CURRENT.name2val["x"]) == float(ref_log.Logger.CURRENT.name2val["x"]) == 8.0


def test_the_log_reads_back_by_itself_after_limit_calls(pair, monkeypatch):
    (_, _), (log, _) = pair
    monkeypatch.setattr(L, "LIMIT", 5)
    current = log.Logger.CURRENT
    for i in range(4):
        log.logkv_mean("x", L.Later((torch.tensor(float(i)),), L._item))
    assert len(vars(current)[L._PENDING]) == 4 and not vars(current)["name2val"]
    log.logkv_mean("x", 4.0)
    assert not vars(current)[L._PENDING] and vars(current)["name2val"]["x"] == 2.0


def test_one_copy_per_dtype():
    ts, a, b = torch.arange(5), torch.rand(5), torch.rand(())
    with Reads() as r:
        host = L._to_host([ts, a, b, a])
    assert r.reads == 2                                  # int64 and float32
    assert torch.equal(host[id(ts)], ts) and torch.equal(host[id(a)], a) and host[id(b)].shape == ()


def test_norms_are_upstreams_with_the_log_and_floats_for_fp16(monkeypatch):
    log = make_logger_module("norm_logger")
    monkeypatch.setitem(sys.modules, U._LOGGER_MODULE, log)
    ps = params()
    for p in ps:
        p.grad = torch.randn_like(p)
    hooked = U.norms_in_one_sync(Trainer._compute_norms)
    expected = Trainer(ps)._compute_norms(2.0)
    assert hooked(Trainer(ps), 2.0) == expected                              # logger not kept: floats
    L.deferred_logger(log.Logger)
    later = hooked(Trainer(ps), 2.0)
    assert all(isinstance(v, L.Later) for v in later)
    host = L._to_host([t for v in later for t in v.tensors])
    assert tuple(v.make(*(host[id(t)] for t in v.tensors)) for v in later) == expected
    assert hooked(Trainer(ps, use_fp16=True), 2.0) == expected               # fp16 checks the norm: floats


class Sampler:
    """Upstream's ``ScheduleSampler.sample`` (``diffusion/resample.py``), uniform weights."""

    def weights(self):
        return np.ones(10)

    def sample(self, batch_size, device):
        w = self.weights()
        p = w / np.sum(w)
        indices_np = np.random.choice(len(p), size=(batch_size,), p=p)
        indices = torch.from_numpy(indices_np).long().to(device)
        weights_np = 1 / (len(p) * p[indices_np])
        weights = torch.from_numpy(weights_np).float().to(device)
        return indices, weights


def test_sampler_draws_as_upstream_and_copies_to_cuda_from_pinned_memory(monkeypatch):
    hooked = L.sample_without_sync(Sampler.sample)
    np.random.seed(0)
    a = Sampler().sample(8, "cpu")
    np.random.seed(0)
    b = hooked(Sampler(), 8, "cpu")
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    calls = []
    monkeypatch.setattr(torch.Tensor, "pin_memory", lambda self: calls.append("pin") or self)
    monkeypatch.setattr(torch.Tensor, "to", lambda self, *a, **k: calls.append((str(a[0]), k)) or self)
    np.random.seed(0)
    c = hooked(Sampler(), 8, "cuda")
    assert calls == [("cpu", {})] * 2 + ["pin", ("cuda", {"non_blocking": True})] * 2   # drawn, then pinned
    assert all(torch.equal(x, y) for x, y in zip(a, c))                        # the same draws


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_sampler_on_cuda_equals_upstream():
    hooked = L.sample_without_sync(Sampler.sample)
    np.random.seed(1)
    a = Sampler().sample(8, "cuda")
    np.random.seed(1)
    b = hooked(Sampler(), 8, "cuda")
    assert all(x.device.type == "cuda" and torch.equal(x, y) for x, y in zip(a, b))


def test_fast_optimizer_step_keeps_the_log_and_hooks_the_sampler_only_on_cuda(monkeypatch):
    from smdm_plugin.integrations import _hooks

    monkeypatch.setattr(_hooks, "_CALLBACKS", {})          # this test's modules, hooked afresh
    log = make_logger_module(U._LOGGER_MODULE)
    loop = make_loop_module(U._LOOP_MODULE, log)
    resample = types.ModuleType(U._SAMPLER_MODULE)
    resample.ScheduleSampler = type("ScheduleSampler", (Sampler,), {})
    for m in (log, loop, resample):
        monkeypatch.setitem(sys.modules, m.__name__, m)
    original_loss_log = loop.log_loss_dict
    assert U.fast_optimizer_step("cpu", "default") is None
    assert not L.deferring(log) and loop.log_loss_dict is original_loss_log
    assert resample.ScheduleSampler.sample is Sampler.sample
    assert U.fast_optimizer_step("cuda", "default") == U.OPTIMIZER_NOTE
    assert L.deferring(log) and loop.log_loss_dict is not original_loss_log
    target = types.SimpleNamespace(multi_target_cond=True)            # the note says the batches are upstream's
    assert U.fast_optimizer_step("cuda", "default", target) == U.OPTIMIZER_NOTE + U.UPSTREAM_BATCHES
    assert resample.ScheduleSampler.sample is not Sampler.sample


def batches(n=3):
    g = torch.Generator().manual_seed(5)
    return [(torch.randn(2, 4, 1, 6, generator=g),
             {"y": {"mask": torch.ones(2, 1, 1, 6, dtype=torch.bool), "lengths": torch.tensor([6, 4]),
                    "text": ["a", "b"]}}) for _ in range(n)]


class Loop:
    """Upstream's ``TrainLoop.__init__`` as far as the data goes: ``device``, ``data``, ``args``."""

    def __init__(self, data, device, multi_target_cond=False):
        self.data, self.device = data, torch.device(device)
        self.args = types.SimpleNamespace(multi_target_cond=multi_target_cond)


def test_batches_reach_the_device_as_upstreams_loop_moves_them():
    loader = torch.utils.data.DataLoader(batches(), batch_size=None)
    loop = Loop(loader, "cpu")
    L.batches_on_device(Loop.__init__)(loop, loader, "cpu")
    assert isinstance(loop.data, L.DeviceBatches) and len(loop.data) == 3 and loop.data.dataset is loader.dataset
    for (motion, cond), (m0, c0) in zip(loop.data, batches()):
        moved = motion.to(loop.device)                           # upstream's loop: nothing left to copy
        assert moved is motion and torch.equal(motion, m0) and cond["y"]["text"] == c0["y"]["text"]
        assert all(torch.equal(cond["y"][k], c0["y"][k]) for k in ("mask", "lengths"))
    other = L.DeviceBatches([("not", "a batch")], torch.device("cpu"))
    assert list(other) == [("not", "a batch")]                   # any other batch as the loader gives it


@pytest.mark.filterwarnings("ignore:'pin_memory' argument is set as true but no accelerator")
def test_batches_go_to_cuda_from_pinned_memory(monkeypatch):
    calls = []
    monkeypatch.setattr(torch.Tensor, "pin_memory", lambda self: calls.append("pin") or self)
    monkeypatch.setattr(torch.Tensor, "to", lambda self, *a, **k: calls.append((str(a[0]), k)) or self)
    loader = torch.utils.data.DataLoader(batches(1), batch_size=None)
    loop = Loop(loader, "cuda")
    L.batches_on_device(Loop.__init__)(loop, loader, "cuda")
    assert loader.pin_memory is True                              # the loader pins (its thread, with workers)
    list(loop.data)
    assert calls == ["pin", ("cuda", {"non_blocking": True})] * 3   # motion, mask, lengths


def test_multi_target_cond_keeps_upstreams_data():
    """MDM's ``--multi_target_cond`` samples goals on the batch's device before the loop moves it."""
    loader = batches()
    loop = Loop(loader, "cpu", multi_target_cond=True)
    L.batches_on_device(Loop.__init__)(loop, loader, "cpu", multi_target_cond=True)
    assert loop.data is loader
