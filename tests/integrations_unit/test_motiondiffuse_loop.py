"""MotionDiffuse's training step without its mask loop or a host sync per step
(``families/motiondiffuse/upstream_loop.py``), against slow references written here from what
upstream's code computes (CI has no MotionDiffuse checkout; ``tests/integration`` runs the real one)."""
import sys
import types
from collections import OrderedDict

import numpy as np
import pytest
import torch

from smdm_plugin.families.motiondiffuse import upstream_loop as L
from smdm_plugin.integrations._hooks import WRAPPED
from smdm_plugin.families.motiondiffuse.standin import StandInMotionTransformer
from helpers import upstream_mask


def generate_src_mask(T, length):
    return upstream_mask.generate_src_mask(None, T, length)


@pytest.mark.parametrize("length", [torch.tensor([40, 31, 17, 1]), [40, 31, 17], [torch.tensor(5), torch.tensor(40)],
                                    torch.tensor([60, 0, 40]), torch.tensor([7])])
def test_src_mask_equals_upstream_s_loop(length):
    want = generate_src_mask(40, length)
    got = L.src_mask(40, length)
    assert got.dtype == want.dtype and got.shape == want.shape and torch.equal(got, want)


def test_src_mask_stays_on_the_lengths_device_and_traces():
    length = torch.tensor([12, 3])
    meta = L.src_mask(16, length.to("meta"))
    assert meta.device.type == "meta" and meta.shape == (2, 16)
    compiled = torch.compile(L.src_mask, backend="eager", fullgraph=True)
    assert torch.equal(compiled(16, length), generate_src_mask(16, length))


def test_mask_without_loop_is_the_model_s_own_and_leaves_the_class_alone():
    torch.manual_seed(0)
    model = StandInMotionTransformer()
    assert L.mask_without_loop(model) and model.generate_src_mask is L.src_mask
    assert StandInMotionTransformer.generate_src_mask is not L.src_mask
    assert not L.mask_without_loop(torch.nn.Linear(2, 2))
    x, length = torch.randn(2, 40, 12), torch.tensor([40, 9])
    fresh = StandInMotionTransformer()
    fresh.load_state_dict(model.state_dict())
    assert torch.equal(model(x, torch.tensor([3, 4]), length=length, text=["a", "b"]),
                       fresh(x, torch.tensor([3, 4]), length=length, text=["a", "b"]))


def _upstream_log(values, log_every):
    """MotionDiffuse's loop: ``logs[k] = v`` / ``logs[k] += v`` per step, printed as ``'%.4f' % (sum / n)``
    every ``log_every`` steps; returns the means printed to full precision (one read each)."""
    out, logs = [], OrderedDict()
    for it, v in enumerate(values, 1):
        for k, val in OrderedDict(loss=v).items():
            logs[k] = val if k not in logs else logs[k] + val
        if it % log_every == 0:
            mean = logs["loss"] / log_every
            out.append("%.17g" % mean)
            logs = OrderedDict()
    return out


LIMIT = L.LIMIT


@pytest.mark.parametrize("limit", [LIMIT, 3])
def test_loss_value_prints_upstream_s_sums(monkeypatch, limit):
    monkeypatch.setattr(L, "LIMIT", limit)
    losses = torch.rand(23, generator=torch.Generator().manual_seed(1)) * 3
    want = _upstream_log([v.item() for v in losses], 5)
    reads = []
    tolist = torch.Tensor.tolist
    monkeypatch.setattr(torch.Tensor, "tolist", lambda t: reads.append(t.numel()) or tolist(t))
    got = _upstream_log([L.LossValue.of(v) for v in losses], 5)
    assert got == want                                  # the same floats, to the last bit
    # every value read once (not the last 3 steps', unprinted, unless `limit` of them wait)
    assert sum(reads) == (20 if limit == LIMIT else 23)
    assert len(reads) == (4 if limit == LIMIT else 9)  # one copy per print (and per `limit` values waiting)
    lv = L.LossValue.of(torch.tensor(2.0))
    assert 1 + lv == 3.0 and lv + 1 == 3.0 and float(lv / 4) == 0.5 and f"{lv:.1f}" == "2.0"
    assert (L.LossValue.of(torch.tensor(1.0)) + (L.LossValue.of(torch.tensor(2.0)) + lv)) == 5.0


def test_upstream_loss_is_backward_g_s():
    g = torch.Generator().manual_seed(2)
    tr = types.SimpleNamespace(mse_criterion=torch.nn.MSELoss(reduction="none"),
                               fake_noise=torch.randn(3, 10, 6, generator=g), real_noise=torch.randn(3, 10, 6, generator=g),
                               src_mask=generate_src_mask(10, torch.tensor([10, 4, 7])))
    # backward_G's loss by its definition: each frame's mean squared error over features, averaged
    # over the frames the mask keeps (slowly, in float64)
    num = den = 0.0
    for i in range(3):
        for j in range(10):
            w = float(tr.src_mask[i, j])
            err = sum((float(a) - float(b)) ** 2 for a, b in zip(tr.fake_noise[i, j], tr.real_noise[i, j])) / 6
            num, den = num + w * err, den + w
    got = L.upstream_loss(tr)
    assert got.dtype == torch.float32 and got.shape == () and abs(float(got) - num / den) < 1e-6 * (num / den)


class _Sampler:
    """A timestep sampler with ``ScheduleSampler.sample``'s contract: draws with numpy's global
    generator, returns ``(timesteps int64, weights float32)`` copied to ``device``."""

    def sample(self, batch_size, device):
        drawn = np.random.randint(0, 50, size=batch_size)
        return torch.as_tensor(drawn, dtype=torch.int64).to(device), torch.full((batch_size,), 1.0).to(device)


def _hooked_backward(self):
    """The hooks' ``backward_G`` (marked as ``wrap_once`` marks it)."""


setattr(_hooked_backward, WRAPPED, True)


def _trainer_module(monkeypatch):
    """A module standing in for ``trainers/ddpm_trainer.py``: ``torch``, ``build_dataloader`` and a
    trainer whose ``forward`` makes its lengths with ``torch.LongTensor`` (as upstream's)."""
    mod = types.ModuleType("fake_ddpm_trainer")
    mod.torch = torch
    batches = [["a"], torch.randn(1, 8, 3), torch.tensor([5])]
    mod.build_dataloader = lambda dataset, **kw: torch.utils.data.DataLoader(dataset, batch_size=2)

    class Trainer:
        device = torch.device("cpu")
        backward_G = _hooked_backward

        def __init__(self):
            self.sampler = _Sampler()

        def forward(self, batch_data):
            caption, motions, m_lens = batch_data
            T = motions.shape[1]
            self.cur_len = mod.torch.LongTensor([min(T, m) for m in m_lens]).to(self.device)
            return self.cur_len

    Trainer.__module__ = mod.__name__
    mod.Trainer = Trainer
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    return mod, Trainer, batches


def test_loop_without_sync_hooks_the_trainer_and_keeps_its_values(monkeypatch):
    mod, Trainer, batch = _trainer_module(monkeypatch)
    tr = Trainer()
    np.random.seed(5)
    want_t = tr.sampler.sample(4, "cpu")
    done = L.loop_without_sync(tr)
    assert done == ["lengths", "batches", "timesteps", "loss"] and L.deferring(tr)
    assert isinstance(mod.torch, L.TrainerTorch) and mod.torch.nn is torch.nn
    assert torch.equal(tr.forward([["a", "b"], torch.zeros(2, 6, 3), torch.tensor([9, 4])]), torch.tensor([6, 4]))
    assert mod.torch.LongTensor([1, 2]).dtype == torch.long            # outside forward: torch's own
    np.random.seed(5)
    got_t = tr.sampler.sample(4, "cpu")
    assert all(torch.equal(a, b) and a.dtype == b.dtype for a, b in zip(got_t, want_t))
    data = [(["x"][0], torch.full((8, 3), float(i)), i + 3) for i in range(4)]
    loader = mod.build_dataloader(data)
    assert isinstance(loader, L.MotionBatches) and len(loader) == 2
    got = list(loader)
    assert list(got[0][0]) == ["x", "x"] and torch.equal(got[1][1][0], torch.full((8, 3), 2.0))
    assert torch.equal(got[1][2], torch.tensor([5, 6]))
    hooked = (vars(tr)["forward"], vars(tr.sampler)["sample"], mod.build_dataloader, mod.torch)
    assert L.loop_without_sync(tr) == ["lengths", "batches", "timesteps", "loss"]   # once: nothing wrapped twice
    assert hooked == (vars(tr)["forward"], vars(tr.sampler)["sample"], mod.build_dataloader, mod.torch)
    assert isinstance(L.log_of(tr, torch.tensor(1.5))["loss_mot_rec"], L.LossValue)
    assert L.log_of(Trainer(), torch.tensor(1.5)) == OrderedDict(loss_mot_rec=1.5)
    Trainer.backward_G = lambda self: None                    # upstream's own (the patch route)
    other = Trainer()
    assert L.loop_without_sync(other) == ["lengths", "batches", "timesteps"] and not L.deferring(other)


@pytest.mark.parametrize("is_train", [False, True])
def test_compile_trainer_gives_the_mask_and_a_sampling_run_s_timesteps(monkeypatch, is_train):
    """``--sparse_compile`` (dense too): the denoiser's padding mask without a loop; a sampling
    run's diffusion module sees :class:`~smdm_plugin.integrations.timesteps.TorchView` (its
    ``th.tensor([i] * B, device)`` per step filled on the device), a training run's stays torch."""
    from smdm_plugin.families.motiondiffuse.upstream import compile_trainer
    from smdm_plugin.integrations.timesteps import TorchView

    mod = types.ModuleType("fake_motiondiffuse_gaussian_diffusion")
    mod.th = torch
    mod.GaussianDiffusion = type("GaussianDiffusion", (), {"__module__": mod.__name__})
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    model = StandInMotionTransformer()
    opt = types.SimpleNamespace(sparse_compile="default", is_train=is_train, device=torch.device("cpu"))
    trainer = types.SimpleNamespace(opt=opt, encoder=model, diffusion=mod.GaussianDiffusion(), device=opt.device)
    assert compile_trainer(trainer) is not None
    assert vars(model)["generate_src_mask"] is L.src_mask
    assert isinstance(mod.th, TorchView) != is_train


def test_compile_trainer_without_the_flag_leaves_upstream_alone():
    from smdm_plugin.families.motiondiffuse.upstream import compile_trainer

    model = StandInMotionTransformer()
    opt = types.SimpleNamespace(sparse_compile="none", is_train=True, device=torch.device("cpu"))
    trainer = types.SimpleNamespace(opt=opt, encoder=model, diffusion=None, device=opt.device)
    assert compile_trainer(trainer) is None and "generate_src_mask" not in vars(model)
