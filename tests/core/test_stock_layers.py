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


@pytest.mark.parametrize("fsq", [True, False], ids=["fsq", "mha"])
def test_a_decoder_stack_with_a_memory_mask_traces_whole_with_autograd(fsq):
    """Under ``torch.compile`` with autograd the stack runs as functions (every FSQ fold at once);
    DiP's text tokens come with a padding mask, made into an aligned bias inside the graph: one
    ``fullgraph`` trace, output and gradients equal to the modules'."""
    stack = _stack("decoder", False, fsq, "gelu")
    S, B, M = 7, 3, 16                           # rows already 16-aligned: the offset would be read
    g = torch.Generator().manual_seed(3)
    x = torch.randn(S, B, 32, generator=g, dtype=torch.float64, requires_grad=True)
    mem = torch.randn(M, B, 32, generator=g, dtype=torch.float64)
    mpad = torch.zeros(B, M, dtype=torch.bool)
    mpad[0, M - 2:] = True
    ran = []

    def call(x, mem, mpad):
        run = stock_stack(stack)
        ran.append(run is not None)
        return run.run(x, None, mem, aligned_key_bias(float_mask(mpad, torch.float64)))

    torch._dynamo.reset()
    out = torch.compile(call, fullgraph=True, backend="aot_eager")(x, mem, mpad)
    ref = stack(x, mem, memory_key_padding_mask=mpad)
    torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-11)
    params = [p for p in stack.parameters() if p.requires_grad]
    grads = torch.autograd.grad(out.square().sum(), [x] + params, allow_unused=True)
    grads_ref = torch.autograd.grad(ref.square().sum(), [x] + params, allow_unused=True)
    for a, b in zip(grads, grads_ref):
        if b is not None:
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * float(b.abs().max()))
    assert ran == [True]
    torch._dynamo.reset()


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


def _autocast_stack(fsq):
    stack = _stack("encoder", False, fsq, "gelu", layers=3).float()
    g = torch.Generator().manual_seed(2)
    x = torch.randn(9, 3, 32, generator=g)
    pad = torch.zeros(3, 9, dtype=torch.bool)
    pad[1, 6:] = True
    return stack, x, aligned_key_bias(float_mask(pad, torch.bfloat16))


def _param_casts(fn, params):
    """How many ``_to_copy`` ops inside ``fn()`` read the storage of one of ``params``."""
    from torch.utils._python_dispatch import TorchDispatchMode

    ptrs = {p.data_ptr() for p in params}

    class Casts(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func is torch.ops.aten._to_copy.default and args[0].data_ptr() in ptrs:
                Casts.n += 1
            return func(*args, **(kwargs or {}))

    with Casts():
        out = fn()
    return out, Casts.n


@pytest.mark.parametrize("fsq", [True, False], ids=["fsq", "mha"])
def test_a_sampling_call_under_autocast_casts_each_weight_once_per_version(fsq, monkeypatch):
    """Without autograd under autocast the matmul weights are cast once and kept while the
    parameters are unchanged: the second call casts no parameter, the outputs equal autocast's own
    casts exactly, and an in-place update of a weight is seen by the next call."""
    from smdm_plugin.core.layers import StockStack

    stack, x, bias = _autocast_stack(fsq)
    stack.eval()
    run = stock_stack(stack)
    params = [p for p in stack.parameters()]

    def call():
        with torch.no_grad(), torch.autocast("cpu", torch.bfloat16):
            return run.run(x, bias)

    def uncached():
        with monkeypatch.context() as m:
            m.setattr(StockStack, "_casts", lambda self, x: None)
            return call()

    first, n_first = _param_casts(call, params)
    second, n_second = _param_casts(call, params)
    ref, n_ref = _param_casts(uncached, params)
    assert n_second == 0 < n_ref and n_first >= n_ref
    assert first.dtype == torch.float32 and torch.equal(first, ref) and torch.equal(second, ref)
    with torch.no_grad():
        stack.layers[1].linear2.weight.mul_(1.5)
    after, n_after = _param_casts(call, params)
    assert n_after > 0 and torch.equal(after, uncached()) and not torch.equal(after, ref)


@pytest.mark.parametrize("fsq", [True, False], ids=["fsq", "mha"])
def test_a_training_call_under_autocast_casts_each_role_once_for_all_layers(fsq, monkeypatch):
    """With autograd under autocast each matmul parameter's cast is one stack-cast-unbind per role
    over the layers: outputs and every gradient equal autocast's own per-layer casts exactly."""
    from smdm_plugin.core.layers import StockStack

    stack, x, bias = _autocast_stack(fsq)
    stack.train()
    run = stock_stack(stack)
    params = [p for p in stack.parameters() if p.requires_grad]
    g = torch.randn(9, 3, 32, generator=torch.Generator().manual_seed(3))

    def step(cached):
        with monkeypatch.context() as m:
            if not cached:
                m.setattr(StockStack, "_stacked_casts", lambda self, dtype: None)
            with torch.autocast("cpu", torch.bfloat16):
                out = run.run(x, bias)
            return out, torch.autograd.grad(out, params, g, allow_unused=True)

    (out, grads), (ref, grads_ref) = step(True), step(False)
    assert torch.equal(out, ref)
    for a, b in zip(grads, grads_ref):
        assert (a is None and b is None) or torch.equal(a, b)
    _, n_cached = _param_casts(lambda: step(True), params)
    _, n_ref = _param_casts(lambda: step(False), params)
    assert n_cached < n_ref


@pytest.mark.parametrize("fsq", [True, False], ids=["fsq", "mha"])
@pytest.mark.parametrize("kind,M", [("encoder", 0), ("decoder", 5)])
def test_dropout_draws_as_the_modules_in_training_and_is_not_called_in_eval(kind, M, fsq, monkeypatch):
    """With dropout 0.1: in training the functional path draws the modules' masks (the same
    outputs from the same seed); in eval it calls no dropout at all (a sampling call's host time:
    ``F.dropout(x, p, False)`` returns ``x`` after a Python call) and equals the modules."""
    import torch.nn.functional as F

    stack = _stack(kind, False, fsq, "gelu")
    for m in stack.modules():
        if isinstance(m, nn.Dropout):
            m.p = 0.1
        elif hasattr(m, "in_proj_weight"):                 # (attention dropout)
            m.dropout = 0.1
    calls = []
    dropout = F.dropout
    monkeypatch.setattr(F, "dropout", lambda *a, **k: calls.append(1) or dropout(*a, **k))
    g = torch.Generator().manual_seed(2)
    x = torch.randn(9, 3, 32, generator=g, dtype=torch.float64)
    mem = torch.randn(M, 3, 32, generator=g, dtype=torch.float64) if M else None
    run = stock_stack(stack)
    for training in (True, False):
        stack.train(training)
        torch.manual_seed(5)
        ref = stack(x, mem) if mem is not None else stack(x)
        torch.manual_seed(5)
        calls.clear()
        out = run.run(x, None, mem, None)
        torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-11)
        assert bool(calls) == training and (not training or not torch.equal(out, run.run(x, None, mem, None)))
