"""The FSQ key maps of a stack held as stacked parameters (``core/fsq_bank.py``): the same model as
per-layer ``nn.Linear`` key maps (outputs, gradients, an optimizer step, state dicts both ways), fewer
tensors for autograd and the optimizer, and the folded path reading the bank without stacking."""
import copy
import functools
import warnings

import pytest
import torch
from torch import nn

from smdm_plugin.core.fsq import FSQMultiheadAttention, folded_projections, quantize_attention_keys, \
    unquantize_attention_keys
from smdm_plugin.core.fsq_bank import KeyMapBank, KeyMapView, shared_bank
from smdm_plugin.runtime.launches import count_launches

LEVELS = (8, 5, 5, 2)
pytestmark = pytest.mark.filterwarnings("ignore:The PyTorch API of nested tensors")
KEY_MAPS = ("key_down.weight", "key_down.bias", "key_up.weight", "key_up.bias")


def _pair(n: int = 3, decoder: bool = False):
    """Two copies of one stack with FSQ keys: key maps banked, and each layer's own ``nn.Linear`` s."""
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if decoder:
            stack = nn.TransformerDecoder(nn.TransformerDecoderLayer(32, 4, 64, dropout=0.0), n)
        else:
            stack = nn.TransformerEncoder(nn.TransformerEncoderLayer(32, 4, 64, dropout=0.0), n)
    torch.manual_seed(1)
    own = copy.deepcopy(stack)
    assert quantize_attention_keys(own, LEVELS, bank=False) == n
    torch.manual_seed(1)                                            # the same key maps drawn
    banked = copy.deepcopy(stack)
    assert quantize_attention_keys(banked, LEVELS) == n
    return banked, own


def _run(stack: nn.Module, x: torch.Tensor) -> torch.Tensor:
    if isinstance(stack, nn.TransformerDecoder):
        return stack(x, x[:1])
    return stack(x)


def test_a_bank_holds_every_layers_key_maps_with_their_values_and_keys():
    banked, own = _pair()
    banks = [m for m in banked.modules() if isinstance(m, KeyMapBank)]
    assert len(banks) == 1 and banked.fsq_key_maps is banks[0] and banks[0].size == 3
    bank = banks[0]
    assert bank.down_weight.shape == (3, len(LEVELS), 8) and bank.up_weight.shape == (3, 8, len(LEVELS))
    assert bank.down_weight.requires_grad and not bank.up_bias.requires_grad    # key_up.bias stays frozen
    for i, layer in enumerate(banked.layers):
        a = layer.self_attn
        assert isinstance(a.key_down, KeyMapView) and a.key_down.index == i
        assert (a.key_down.in_features, a.key_down.out_features) == (8, len(LEVELS))
    assert shared_bank([layer.self_attn for layer in banked.layers]) is bank
    assert shared_bank([layer.self_attn for layer in banked.layers][::-1]) is None     # rows out of order
    assert shared_bank([layer.self_attn for layer in own.layers]) is None
    # the state dict: the bank's tensors under their parameter names (upstream training loops pair
    # named_parameters() with state_dict()), the rest as the per-layer model's
    sb, so = banked.state_dict(), own.state_dict()
    assert {n for n, _ in banked.named_parameters()} <= set(sb)
    per_layer = [k for k in so if k.split(".")[-2] in ("key_down", "key_up")]
    assert len(per_layer) == 4 * 3
    assert set(sb) == (set(so) - set(per_layer)) | {f"fsq_key_maps.{n}" for n in
                                                      ("down_weight", "down_bias", "up_weight", "up_bias")}
    for k in set(so) - set(per_layer):
        assert torch.equal(sb[k], so[k]), k
    for module, tensor, name in (("key_down", "weight", "down_weight"), ("key_up", "bias", "up_bias")):
        assert torch.equal(sb[f"fsq_key_maps.{name}"],
                           torch.stack([so[f"layers.{i}.self_attn.{module}.{tensor}"] for i in range(3)]))
    # fewer tensors for the optimizer: 4 per layer became 4
    n_own, n_banked = len(list(own.parameters())), len(list(banked.parameters()))
    assert n_own - n_banked == 4 * 3 - 4


@pytest.mark.parametrize("decoder", [False, True])
def test_banked_key_maps_train_exactly_as_the_layers_own(decoder):
    """Outputs, every gradient and an AdamW step equal the per-layer key maps' (bit for bit: the same
    ops on the same values), on the folded path (the stack's functions run under the sparse model;
    here the modules) and through the modules' unfolded path."""
    banked, own = _pair(decoder=decoder)
    x = torch.randn(7, 2, 32)
    opts = [torch.optim.AdamW(m.parameters(), lr=1e-2) for m in (banked, own)]
    for step in range(2):
        outs = []
        for m, opt in zip((banked, own), opts):
            opt.zero_grad(set_to_none=True)
            out = _run(m, x)
            out.pow(2).mean().backward()
            opt.step()
            outs.append(out.detach())
        assert torch.equal(outs[0], outs[1]), step
        for lb, lo in zip(banked.layers, own.layers):
            ab, ao = lb.self_attn, lo.self_attn
            for name in ("weight", "bias"):
                assert torch.equal(ab.key_down.grad_of(name), getattr(ao.key_down, name).grad)
                assert torch.equal(getattr(ab.key_down, name), getattr(ao.key_down, name))
                assert torch.equal(getattr(ab.key_up, name), getattr(ao.key_up, name))
            assert ab.key_up.grad_of("bias") is None and ao.key_up.bias.grad is None
            assert torch.equal(ab.in_proj_weight.grad, ao.in_proj_weight.grad)


def test_the_fold_reads_the_bank_without_stacking_and_its_gradients_agree():
    banked, own = _pair(n=4)
    attns_b = [layer.self_attn for layer in banked.layers]
    attns_o = [layer.self_attn for layer in own.layers]
    counts = {}
    for name, attns in (("banked", attns_b), ("own", attns_o)):
        def fold(attns=attns):
            sum(w.sum() + b.sum() for w, b in folded_projections(attns)).backward()
        counts[name] = count_launches(fold, warmup=0).ops
    # per-layer maps: three stacks more (down weight, down bias, up weight); the banked fold stacks the
    # in-projections' weights and biases, and its backward the per-layer results' two gradients
    assert counts["own"]["aten.stack.default"] - counts["banked"]["aten.stack.default"] == 3
    assert counts["banked"]["aten.stack.default"] == 4
    bank = banked.fsq_key_maps
    for i, a in enumerate(attns_o):
        assert torch.equal(bank.down_weight.grad[i], a.key_down.weight.grad)
        assert torch.equal(bank.down_bias.grad[i], a.key_down.bias.grad)
        assert torch.equal(bank.up_weight.grad[i], a.key_up.weight.grad)
    # a subset of the layers, or one layer alone: the views stacked (the same values)
    for sub_b, sub_o in ((attns_b[1:3], attns_o[1:3]), (attns_b[:1], attns_o[:1])):
        assert shared_bank(sub_b) is None
        for (wb, bb), (wo, bo) in zip(folded_projections(sub_b), folded_projections(sub_o)):
            assert torch.equal(wb, wo) and torch.equal(bb, bo)


def test_a_state_dict_of_per_layer_key_maps_loads_and_a_bad_one_is_refused():
    """0.9's checkpoints (each layer's key maps) load into the bank, today's into a bank; a key
    missing, of the wrong shape or unknown is refused as torch refuses it."""
    banked, own = _pair()
    torch.manual_seed(7)
    with torch.no_grad():
        for p in own.parameters():
            p.add_(torch.randn_like(p))
    banked.load_state_dict(own.state_dict())                       # a per-layer checkpoint into a bank
    x = torch.randn(5, 2, 32)
    with torch.no_grad():
        assert torch.equal(banked(x), own(x))
    twin = _pair()[0]
    twin.load_state_dict(banked.state_dict())                      # and today's
    for k, v in banked.state_dict().items():
        assert torch.equal(twin.state_dict()[k], v), k
    sd, legacy = banked.state_dict(), own.state_dict()
    for d, key, bank_key in ((sd, "fsq_key_maps.down_weight", "fsq_key_maps.down_weight"),
                             (legacy, "layers.1.self_attn.key_down.weight", "fsq_key_maps.down_weight")):
        missing = {k: v for k, v in d.items() if k != key}
        with pytest.raises(RuntimeError, match="Missing key.*" + bank_key.replace(".", r"\.")):
            twin.load_state_dict(missing)
        assert twin.load_state_dict(missing, strict=False).missing_keys == [bank_key]
        with pytest.raises(RuntimeError, match="size mismatch for " + key.replace(".", r"\.")):
            twin.load_state_dict(dict(d, **{key: torch.zeros(3, 3)}))
    extra = dict(sd, **{"layers.1.self_attn.key_down.scale": torch.zeros(1)})
    with pytest.raises(RuntimeError, match=r"Unexpected key.*key_down\.scale"):
        twin.load_state_dict(extra)


def test_a_copy_has_its_own_bank_and_conversions_reach_the_views():
    banked, _ = _pair()
    twin = copy.deepcopy(banked)
    assert twin.fsq_key_maps is not banked.fsq_key_maps
    assert all(layer.self_attn.key_down.bank is twin.fsq_key_maps for layer in twin.layers)
    with torch.no_grad():
        twin.layers[2].self_attn.key_down.weight.fill_(3.0)         # writes the copy's bank row
    assert torch.equal(twin.fsq_key_maps.down_weight[2], torch.full_like(twin.fsq_key_maps.down_weight[2], 3.0))
    assert not torch.equal(banked.fsq_key_maps.down_weight[2], twin.fsq_key_maps.down_weight[2])
    twin.double()
    assert twin.layers[0].self_attn.key_up.weight.dtype == torch.float64
    out = twin(torch.randn(5, 2, 32, dtype=torch.float64))
    assert out.dtype == torch.float64


def test_unquantize_removes_the_bank_and_keeps_the_attention():
    banked, _ = _pair()
    x = torch.randn(5, 2, 32)
    for layer in banked.layers:
        layer.self_attn.quantize = False                            # dense attention with the same weights
    with torch.no_grad():
        before = banked(x)
    assert unquantize_attention_keys(banked) == 3
    assert not any(isinstance(m, (KeyMapBank, KeyMapView, FSQMultiheadAttention)) for m in banked.modules())
    assert "fsq_key_maps" not in banked._modules
    with torch.no_grad():
        torch.testing.assert_close(banked(x), before)


@pytest.mark.parametrize("groups", [1, 2])
def test_an_optimizer_state_saved_before_the_banks_resumes_the_same_training(groups):
    """A run resumed from an optimizer state written with per-layer key maps (0.9's layout) goes on
    exactly as the per-layer model does; a state that fits, or one that cannot be mapped, is handed
    on as it is."""
    from smdm_plugin.core.fsq_bank import upgrade_optimizer_state

    banked, own = _pair()
    x = torch.randn(6, 2, 32)

    def make(model):
        if groups == 1:
            return torch.optim.AdamW(model.parameters(), lr=1e-2)
        named = list(model.named_parameters())                      # biases without weight decay
        return torch.optim.AdamW([{"params": [p for n, p in named if n.endswith("bias")], "weight_decay": 0.0},
                                  {"params": [p for n, p in named if not n.endswith("bias")]}], lr=1e-2)

    def step(model, opt):
        opt.zero_grad(set_to_none=True)
        model(x).pow(2).mean().backward()
        opt.step()

    opt_own = make(own)
    for _ in range(3):
        step(own, opt_own)
    saved = copy.deepcopy(opt_own.state_dict())
    banked.load_state_dict(own.state_dict())                       # (0.9's checkpoint too)
    opt_b = make(banked)
    upgraded = upgrade_optimizer_state(saved, banked, opt_b)
    opt_b.load_state_dict(upgraded)
    fits = opt_b.state_dict()
    assert upgrade_optimizer_state(fits, banked, opt_b) is fits                 # already this layout
    for _ in range(2):
        step(own, opt_own)
        step(banked, opt_b)
    for k, v in own.state_dict().items():                          # (key maps: the views, by attribute)
        assert torch.equal(functools.reduce(getattr, k.split("."), banked), v), k
    # sizes that add up to neither layout: handed on, and torch refuses it
    bad = copy.deepcopy(saved)
    bad["param_groups"][0]["params"] = bad["param_groups"][0]["params"][:-1]
    assert upgrade_optimizer_state(bad, banked, opt_b) is bad
    with pytest.raises(ValueError):
        opt_b.load_state_dict(bad)
    # rows whose steps differ (one layer trained alone): not stacked
    odd = copy.deepcopy(saved)
    key = [k for k, st in odd["state"].items() if st["exp_avg"].shape == (len(LEVELS), 8)][0]
    odd["state"][key]["step"] = odd["state"][key]["step"] + 1
    assert upgrade_optimizer_state(odd, banked, opt_b) is odd


def test_the_stacks_sampling_cache_follows_the_bank_through_updates_and_casts():
    """Without autograd the stack folds once and keeps it (``StockStack._projections``); an update
    of the bank in place, a cast or a move of the model folds again (a stale fold would give the old
    values or the old dtype)."""
    from smdm_plugin.core.layers import stock_stack

    banked, own = _pair()
    banked.eval(), own.eval()
    x = torch.randn(5, 2, 32)
    stack = stock_stack(banked)
    assert stack is not None and stack._bank is banked.fsq_key_maps
    with torch.no_grad():
        first = stack.run(x, None)
        assert torch.equal(stack.run(x, None), first)
        for m in (banked, own):                                     # in place: the bank's version moves
            m.layers[1].self_attn.key_down.weight.mul_(1.5)
        torch.testing.assert_close(stack.run(x, None), own(x), rtol=0, atol=1e-6)
        assert not torch.equal(stack.run(x, None), first)
        banked.double(), own.double()
        out = stack.run(x.double(), None)
        assert out.dtype == torch.float64
        torch.testing.assert_close(out, own(x.double()), rtol=0, atol=1e-12)
