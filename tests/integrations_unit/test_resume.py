"""A sparse upstream run resumed from an optimizer state in 0.9's layout (FSQ key maps per layer)
(``integrations/resume.py``): the training loop's ``_load_optimizer_state`` hands its optimizer the
state in today's layout; for a dense model (the flag off) the very object upstream read. The loop
here is a stand-in with upstream's shape (``self.model``, ``self.opt``, a state read from a file);
``tests/integration`` resumes real MDM runs."""
import copy
import sys
import types
import warnings

import pytest
import torch
from torch import nn

from smdm_plugin.core.fsq import quantize_attention_keys
from smdm_plugin.integrations import resume

LEVELS = (8, 5, 5, 2)
pytestmark = pytest.mark.filterwarnings("ignore:The PyTorch API of nested tensors")


class StandInLoop:
    """Upstream's training loop as far as a resume goes: an ``AdamW`` over the model's parameters, a
    saved state read and loaded into it."""

    def __init__(self, model, path):
        self.model, self.path = model, path
        self.opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
        self.loaded = None
        self._load_optimizer_state()

    def _load_optimizer_state(self):
        state_dict = torch.load(self.path, weights_only=False)
        self.loaded = state_dict
        self.opt.load_state_dict(state_dict)


def _stack(bank: bool):
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = nn.TransformerEncoder(nn.TransformerEncoderLayer(32, 4, 64, dropout=0.0), 2)
    quantize_attention_keys(enc, LEVELS, bank=bank)
    return enc


def _saved_state(model, path):
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
    for _ in range(2):
        opt.zero_grad()
        model(torch.randn(5, 2, 32)).pow(2).mean().backward()
        opt.step()
    torch.save(opt.state_dict(), path)
    return opt.state_dict()


@pytest.fixture
def loop_module(monkeypatch):
    """The stand-in as ``train.training_loop``, hooked by ``resume.install_hooks`` (a sparse run's
    ``start.apply`` may have registered the hook already in this process: taken out first)."""
    from smdm_plugin.integrations import _hooks

    callbacks = _hooks._CALLBACKS.setdefault("train.training_loop", [])
    monkeypatch.setattr(_hooks, "_CALLBACKS", {**_hooks._CALLBACKS, "train.training_loop":
                                               [cb for cb in callbacks if cb is not resume._hook]})
    mod = types.ModuleType("train.training_loop")
    mod.TrainLoop = type("TrainLoop", (StandInLoop,), {})
    monkeypatch.setitem(sys.modules, "train.training_loop", mod)
    resume.install_hooks()
    return mod


def test_a_0_9_state_loads_into_the_banked_model(loop_module, tmp_path):
    legacy, banked = _stack(bank=False), _stack(bank=True)
    path = str(tmp_path / "opt.pt")
    saved = _saved_state(legacy, path)
    with pytest.raises(ValueError, match="doesn't match the size"):
        StandInLoop(copy.deepcopy(banked), path)                   # upstream's own loop, unhooked
    loop = loop_module.TrainLoop(banked, path)
    state = loop.opt.state_dict()
    assert len(state["param_groups"][0]["params"]) == len(saved["param_groups"][0]["params"]) - (4 * 2 - 4)
    bank = banked.fsq_key_maps
    index = [i for i, p in enumerate(banked.parameters()) if p is bank.down_weight][0]
    rows = [i for i, (n, p) in enumerate(legacy.named_parameters()) if n.endswith("key_down.weight")]
    torch.testing.assert_close(state["state"][index]["exp_avg"],
                               torch.stack([saved["state"][i]["exp_avg"] for i in rows]), rtol=0, atol=0)
    assert "load_state_dict" not in vars(loop.opt)                 # the optimizer as it was, after


def test_a_dense_model_gets_upstream_s_very_state(loop_module, tmp_path):
    dense = nn.Linear(4, 3)
    path = str(tmp_path / "opt.pt")
    opt = torch.optim.AdamW(dense.parameters(), lr=1e-2)
    dense(torch.randn(2, 4)).sum().backward()
    opt.step()
    torch.save(opt.state_dict(), path)
    seen = []
    original = torch.optim.AdamW.load_state_dict

    def spy(self, state_dict):
        seen.append(state_dict)
        return original(self, state_dict)

    torch.optim.AdamW.load_state_dict = spy
    try:
        loop = loop_module.TrainLoop(dense, path)
    finally:
        torch.optim.AdamW.load_state_dict = original
    assert seen == [loop.loaded] and seen[0] is loop.loaded      # handed on untouched
