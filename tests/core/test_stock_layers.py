"""The stock transformer layers run as functions (``core/layers.py``) equal their modules: encoder
and decoder stacks, post- and pre-norm, FSQ-keyed and plain attention, relu and gelu, key masks and
a memory mask, one-key memory (MDM trans_dec's condition token); outputs and every gradient; and
the modules run instead whenever a hook or a custom layer is present."""
import pytest
import torch
import torch.nn as nn

from smdm_plugin.core.attention import aligned_key_bias, float_mask
from smdm_plugin.core.fsq import quantize_attention_keys
from smdm_plugin.core.layers import stock_stack


def _stack(kind, norm_first, fsq, activation, layers=2, d=32, heads=4):
    torch.manual_seed(0)
    if kind == "encoder":
        layer = nn.TransformerEncoderLayer(d, heads, 2 * d, dropout=0.0, activation=activation, norm_first=norm_first)
        stack = nn.TransformerEncoder(layer, layers, norm=nn.LayerNorm(d), enable_nested_tensor=False)
    else:
        layer = nn.TransformerDecoderLayer(d, heads, 2 * d, dropout=0.0, activation=activation, norm_first=norm_first)
        stack = nn.TransformerDecoder(layer, layers)
    if fsq:
        quantize_attention_keys(stack, (8, 8, 8, 5, 5, 5))
    with torch.no_grad():                       # a trained-looking key_up.bias (inert either way)
        for p in stack.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return stack.double()


def _run_both(stack, S, B, M, training):
    d = stack.layers[0].linear1.in_features
    g = torch.Generator().manual_seed(1)
    x = torch.randn(S, B, d, generator=g, dtype=torch.float64, requires_grad=True)
    pad = torch.zeros(B, S, dtype=torch.bool)
    pad[1, S - 3:] = True
    bias = float_mask(pad, torch.float64)
    decoder = isinstance(stack, nn.TransformerDecoder)
    mem = torch.randn(M, B, d, generator=g, dtype=torch.float64, requires_grad=True) if decoder else None
    mpad = None
    if decoder and M > 1:
        mpad = torch.zeros(B, M, dtype=torch.bool)
        mpad[0, M - 1] = True
    stack.train(training)
    if decoder:
        ref = stack(x, mem, tgt_key_padding_mask=bias, memory_key_padding_mask=mpad)
    else:
        ref = stack(x, src_key_padding_mask=bias)
    run = stock_stack(stack)
    assert run is not None
    mbias = None if mpad is None else aligned_key_bias(float_mask(mpad, torch.float64))
    out = run.run(x, aligned_key_bias(bias), mem, mbias)
    return x, mem, ref, out


@pytest.mark.parametrize("activation", ["relu", "gelu"])
@pytest.mark.parametrize("fsq", [True, False], ids=["fsq", "mha"])
@pytest.mark.parametrize("norm_first", [False, True], ids=["post", "pre"])
@pytest.mark.parametrize("kind,M", [("encoder", 0), ("decoder", 1), ("decoder", 5)])
def test_functional_layers_equal_the_modules(kind, M, norm_first, fsq, activation):
    stack = _stack(kind, norm_first, fsq, activation)
    for training in (False, True):               # (dropout 0: the same maths in both modes)
        x, mem, ref, out = _run_both(stack, 9, 3, M, training)
        torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-11)
        if training:
            g = torch.randn_like(ref)
            wrt = [x] + [p for p in stack.parameters() if p.requires_grad] + ([mem] if mem is not None else [])
            grads_ref = torch.autograd.grad(ref, wrt, g, allow_unused=True)
            grads = torch.autograd.grad(out, wrt, g, allow_unused=True)
            for a, b in zip(grads, grads_ref):
                if a is None or b is None:              # (one key: the query's projection gets 0 in exact maths)
                    assert all(t is None or float(t.abs().max()) < 1e-12 for t in (a, b))
                else:
                    # (the FSQ codes' gradient is float32 maths in both: float32 round-off)
                    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * float(b.abs().max()))


def test_hooks_and_custom_layers_run_the_modules():
    """A hook on any module of the stack, a global module hook, or a layer of another class: no
    functional path (the hook must run); removing the hook brings it back; a replaced submodule is
    seen (the stack is rebuilt)."""
    stack = _stack("encoder", False, True, "gelu")
    assert stock_stack(stack) is not None
    handle = stack.layers[1].linear2.register_forward_hook(lambda m, a, o: None)
    assert stock_stack(stack) is None
    handle.remove()
    assert stock_stack(stack) is not None
    glob = torch.nn.modules.module.register_module_forward_hook(lambda m, a, o: None)
    assert stock_stack(stack) is None
    glob.remove()
    old = stock_stack(stack)
    stack.layers[0].linear1 = nn.Linear(32, 64).double()          # a new submodule: rebuilt, still stock
    new = stock_stack(stack)
    assert new is not None and new is not old and new.layers[0].l1 is stack.layers[0].linear1

    stack.layers[1].self_attn.quantize = False                     # a plain attribute: seen too
    x = torch.randn(5, 2, 32, dtype=torch.float64)
    torch.testing.assert_close(stock_stack(stack).run(x, None), stack(x), rtol=1e-10, atol=1e-11)

    class Custom(nn.TransformerEncoderLayer):
        pass

    stack.layers[0] = Custom(32, 4, 64).double()
    assert stock_stack(stack) is None
