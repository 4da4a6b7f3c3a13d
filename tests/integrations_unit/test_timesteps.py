"""Upstream's sampling loops' timesteps filled on the device (``integrations/timesteps.py``):
``th.tensor([i] * B, device=...)`` as ``torch.full`` (no host copy) with torch's values and dtype;
everything else torch's, traced by ``torch.compile`` as torch."""
from __future__ import annotations

import sys
import types

import pytest
import torch

from smdm_plugin.integrations import timesteps as T

CASES = [([7] * 5, {}), ([0] * 1, {}), ([999] * 64, {"dtype": torch.int32}), ([3] * 4, {"dtype": torch.float32})]


@pytest.mark.parametrize("data,kw", CASES)
def test_filled_timesteps_equal_torchs(data, kw, monkeypatch):
    expected = torch.tensor(data, device="cpu", **kw)
    calls = []
    real = torch.tensor
    monkeypatch.setattr(torch, "tensor", lambda *a, **k: calls.append(a) or real(*a, **k))
    for device in ("cpu", "meta"):                              # meta: a device that is not the host
        got = T.tensor(data, device=device, **kw)
        assert got.device.type == device and got.dtype == expected.dtype and got.shape == expected.shape
    assert torch.equal(T.tensor(data, device="cpu", **kw), expected)
    assert not calls                                             # no tensor made from host data


@pytest.mark.parametrize("data,kw", [([1, 2], {"device": "meta"}), ([], {"device": "meta"}),
                                     ([True] * 3, {"device": "meta"}), ([1.0] * 3, {"device": "meta"}),
                                     ([2] * 3, {}), ([2] * 3, {"device": "meta", "requires_grad": False}),
                                     (5, {"device": "meta"})])
def test_anything_else_is_torchs(data, kw, monkeypatch):
    calls = []
    real = torch.tensor
    monkeypatch.setattr(torch, "tensor", lambda *a, **k: calls.append(a) or real(*a, **k))
    got = T.tensor(data, **kw)
    expected = real(data, **kw)
    assert len(calls) == 1 and got.dtype == expected.dtype and got.shape == expected.shape


def test_a_view_is_torch_but_its_tensor():
    view = T.TorchView()
    for name in ("randn_like", "nn", "Tensor", "float32", "no_grad", "where", "full"):
        assert getattr(view, name) is getattr(torch, name), name
    assert view.tensor is T.tensor and torch.tensor is not T.tensor
    assert view._dynamo is torch._dynamo                          # read through: torch's lazy names


def test_a_view_sees_what_is_patched_on_torch_later(monkeypatch):
    view = T.TorchView()
    patched = lambda a: a                                          # noqa: E731
    monkeypatch.setattr(torch, "from_numpy", patched)
    assert view.from_numpy is patched


def test_upstream_code_seeing_a_view_compiles_whole():
    mod = types.ModuleType("fake_diffusion_module")
    mod.th = T.TorchView()
    exec("def step(x, i):\n    t = th.tensor([i] * x.shape[0], device=x.device)\n"
         "    return th.sin(x) * t[:, None] + th.ones_like(x)\n", vars(mod))
    x = torch.randn(3, 2)
    eager = mod.step(x, 4)
    compiled = torch.compile(mod.step, backend="aot_eager", fullgraph=True)(x, 4)
    assert torch.allclose(eager, compiled) and torch.allclose(eager, torch.sin(x) * 4 + 1)


def test_hooked_where_the_diffusion_classes_live(monkeypatch):
    base_mod, sub_mod, other = (types.ModuleType(n) for n in ("fake_gd", "fake_respace", "fake_other"))
    base_mod.th, sub_mod.th, other.th = torch, torch, torch
    Base = type("GaussianDiffusion", (), {"__module__": "fake_gd"})
    Sub = type("SpacedDiffusion", (Base,), {"__module__": "fake_respace"})
    for m in (base_mod, sub_mod, other):
        monkeypatch.setitem(sys.modules, m.__name__, m)
    assert T.timesteps_without_copy(Sub()) == 2
    view = base_mod.th
    assert isinstance(view, T.TorchView) and isinstance(sub_mod.th, T.TorchView) and other.th is torch
    assert T.timesteps_without_copy(Sub()) == 2 and base_mod.th is view           # once


def test_a_list_made_again_is_copied_on_the_device_until_it_changes(monkeypatch):
    """respace's ``th.tensor(self.timestep_map, device=..., dtype=...)`` at every call: made from
    the host once, then copied on the device; a changed list is made again; each result is the
    caller's own."""
    calls = []
    real = torch.tensor
    monkeypatch.setattr(torch, "tensor", lambda *a, **k: calls.append(a) or real(*a, **k))
    monkeypatch.setattr(T, "_LISTS", type(T._LISTS)())
    timestep_map = [0, 5, 10, 15]
    first = T.tensor(timestep_map, device="cpu", dtype=torch.int64)
    first.add_(100)                                               # the caller's own: not what is kept
    again = T.tensor(timestep_map, device="cpu", dtype=torch.int64)
    assert len(calls) == 1 and torch.equal(again, real([0, 5, 10, 15]))
    timestep_map[1] = 6
    changed = T.tensor(timestep_map, device="cpu", dtype=torch.int64)
    assert len(calls) == 2 and torch.equal(changed, real([0, 6, 10, 15]))
    assert T.tensor(list(timestep_map), device="cpu", dtype=torch.int32).dtype == torch.int32   # another list
    assert len(calls) == 3


def test_kept_lists_are_bounded(monkeypatch):
    monkeypatch.setattr(T, "_LISTS", type(T._LISTS)())
    lists = [[i, i + 1] for i in range(T.MAX_LISTS + 5)]
    for data in lists:
        T.tensor(data, device="cpu")
    assert len(T._LISTS) == T.MAX_LISTS
