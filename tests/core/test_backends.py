"""Keyframe attention backends: every registered backend against the dense masked reference,
auto-selection, forcing by name, clean fallbacks (CPU); CUDA checks skip without CUDA."""
import copy

import pytest
import torch
import torch.nn as nn

from smdm_plugin import register_backend
from smdm_plugin.core.keyframe_transformer import KeyframeTransformer
from smdm_plugin.core import attention_backends as ab
from smdm_plugin.core import packed_attention
from smdm_plugin.core.attention_backends import available_backends, compact_backend, get_backend, varlen_backend
from smdm_plugin.core.fill import fill_frames
from smdm_plugin.core.packing import Packing
from smdm_plugin.core.rows import lerp_rows
from smdm_plugin.core.plan import KeyframePlan

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def encoder(d=32, layers=2, dropout=0.0, norm_first=False):
    layer = nn.TransformerEncoderLayer(d, 4, 64, dropout, "gelu", norm_first=norm_first)
    return nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)


def decoder(d=32, layers=2, dropout=0.0, norm_first=False):
    return nn.TransformerDecoder(nn.TransformerDecoderLayer(d, 4, 64, dropout, "gelu", norm_first=norm_first),
                                 layers)


def keyframes(B, N, lengths, k, seed=0):
    g = torch.Generator().manual_seed(seed)
    mask = torch.zeros(B, N, dtype=torch.bool)
    for b, L in enumerate(lengths):
        idx = torch.randperm(max(L - 2, 0), generator=g)[: max(k - 2, 0)] + 1
        mask[b, idx] = True
        mask[b, 0] = mask[b, L - 1] = True
    return mask


def run(fn, inner, x, keep, memory=None, memory_key_padding_mask=None, capacity=None):
    """A backend's kept-token outputs scattered back to ``[S, B, d]`` (zeros elsewhere)."""
    plan = KeyframePlan.build(keep, capacity)
    h, rows = fn(inner, x, plan, 0, memory, memory_key_padding_mask)
    return fill_frames(h, rows, plan, 0, interpolate=False)


def registered():
    return sorted(ab.BACKENDS.names())


def reference(inner, x, keep, memory=None):
    """The dense module, key padding over everything that is not kept."""
    if memory is None:
        return inner(x, src_key_padding_mask=~keep)
    return inner(x, memory, tgt_key_padding_mask=~keep)


@pytest.mark.parametrize("backend", registered())
@pytest.mark.parametrize("kind", ["encoder", "decoder"])
@pytest.mark.parametrize("norm_first", [False, True])
def test_backend_equals_masked_reference_eval(backend, kind, norm_first):
    torch.manual_seed(0)
    S, B, d = 33, 5, 32
    inner = (encoder if kind == "encoder" else decoder)(norm_first=norm_first).eval()
    x = torch.randn(S, B, d)
    memory = torch.randn(2, B, d) if kind == "decoder" else None
    keep = keyframes(B, S, [33, 30, 12, 33, 3], 7)
    fn = ab.BACKENDS.get(backend).fn
    with torch.no_grad():
        out = run(fn, inner, x, keep, memory=memory)
        ref = reference(inner, x, keep, memory)
    kt = keep.t()
    assert torch.allclose(out[kt], ref[kt], atol=1e-5)


@pytest.mark.parametrize("backend", registered())
def test_backend_equals_reference_in_training_without_dropout(backend):
    torch.manual_seed(1)
    S, B, d = 25, 4, 32
    inner = encoder(dropout=0.0).train()
    keep = keyframes(B, S, [25, 20, 9, 25], 5)
    x = torch.randn(S, B, d, requires_grad=True)
    w = torch.randn(S, B, d)
    kt = keep.t().unsqueeze(-1).float()
    grads = {}
    for name, fn in (("ref", None), (backend, ab.BACKENDS.get(backend).fn)):
        x.grad = None
        inner.zero_grad()
        out = reference(inner, x, keep) if fn is None else run(fn, inner, x, keep)
        (out * w * kt).sum().backward()
        grads[name] = (out.detach() * kt, x.grad.clone(), inner.layers[0].self_attn.in_proj_weight.grad.clone())
    for a, b in zip(grads[backend], grads["ref"]):
        assert torch.allclose(a, b, atol=1e-4)


@pytest.mark.parametrize("backend", ["auto", "compact", "varlen", "masked"])
def test_keyframe_transformer_matches_reference_with_interpolation(backend):
    torch.manual_seed(2)
    S, B, d = 41, 3, 32
    enc = encoder().eval()
    mask = keyframes(B, S - 1, [40, 31, 8], 6)
    keep = torch.cat([torch.ones(B, 1, dtype=torch.bool), mask], 1)
    x = torch.randn(S, B, d)
    wrap = KeyframeTransformer(copy.deepcopy(enc), backend=backend).eval()
    wrap.set_keyframes(mask)
    with torch.no_grad():
        out = wrap(x)
        ref = reference(enc, x, keep)
    from smdm_plugin.core.interpolation import interpolate_keyframes

    expect = torch.cat([ref[:1], interpolate_keyframes(ref[1:].transpose(0, 1), mask).transpose(0, 1)])
    assert torch.allclose(out, expect, atol=1e-5)


def test_auto_selection_and_forcing_by_name():
    cpu = torch.device("cpu")
    assert set(available_backends(cpu)) >= {"masked", "compact", "varlen"}
    assert get_backend("auto", cpu) is varlen_backend  # packed rows are the fast path on CPU too
    assert get_backend("compact", cpu) is compact_backend
    assert get_backend("masked", cpu) is ab.masked_backend
    assert get_backend("varlen", cpu) is varlen_backend
    with pytest.raises(ValueError, match="unknown"):
        get_backend("xformers", cpu)


def test_backend_unavailable_on_device_falls_back_to_compact():
    register_backend("_never", lambda *a, **k: 1 / 0, available=lambda d: False)
    try:
        with pytest.warns(RuntimeWarning, match="'_never' falls back to 'compact'"):
            assert get_backend("_never", torch.device("cpu")) is compact_backend
    finally:
        ab.BACKENDS.unregister("_never")
        ab._WARNED.clear()


def test_a_fallback_says_so_once_naming_both_backends_and_why():
    """A backend asked for by name that does not run a call warns once per process and reason;
    ``auto`` choosing ``compact`` is not a fallback, and a call that runs as asked is silent."""
    import warnings

    ab._WARNED.clear()
    tr = KeyframeTransformer(encoder(), backend="varlen").eval()
    tr.set_keyframes(torch.tensor([[True, False, True, True]] * 2))
    x = torch.randn(5, 2, 32)                                       # 1 lead token + 4 frames
    pad = torch.tensor([[True, False, False, False, False], [False] * 5])
    try:
        with torch.no_grad(), warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            tr(x)                                                   # varlen runs it: silent
            assert caught == []
            for _ in range(3):                                      # padded lead tokens: compact
                tr(x, src_key_padding_mask=pad)
            tr.backend = "auto"
            tr(x, src_key_padding_mask=pad)                         # auto: not a fallback
        assert len(caught) == 1, [str(w.message) for w in caught]
        msg = str(caught[0].message)
        assert "'varlen' falls back to 'compact'" in msg and "padded lead tokens" in msg
        assert caught[0].category is RuntimeWarning
    finally:
        ab._WARNED.clear()


def test_varlen_decoder_with_padded_memory_is_correct():
    torch.manual_seed(3)
    S, B, d = 20, 3, 32
    dec = decoder().eval()
    x, mem = torch.randn(S, B, d), torch.randn(3, B, d)
    mpad = torch.tensor([[False, False, True], [False, False, False], [False, True, True]])
    keep = keyframes(B, S, [20, 15, 4], 5)
    with torch.no_grad():
        out = run(varlen_backend, dec, x, keep, memory=mem, memory_key_padding_mask=mpad)
        ref = dec(x, mem, tgt_key_padding_mask=~keep, memory_key_padding_mask=mpad)
    assert torch.allclose(out[keep.t()], ref[keep.t()], atol=1e-5)


def test_varlen_falls_back_to_compact_for_hooks_and_custom_attention():
    torch.manual_seed(4)
    S, B, d = 18, 2, 32
    enc = encoder().eval()
    keep = keyframes(B, S, [18, 10], 4)
    x = torch.randn(S, B, d)
    calls = []
    h = enc.layers[0].register_forward_pre_hook(lambda m, a: calls.append(a[0].shape[0]))
    with torch.no_grad():
        out = run(varlen_backend, enc, x, keep, capacity=4)
    h.remove()
    with torch.no_grad():
        ref = reference(enc, x, keep)
    assert calls == [4]  # hooks fire: ran through the modules (compact, capacity tokens)
    assert torch.allclose(out[keep.t()], ref[keep.t()], atol=1e-5)
    assert packed_attention.supports_packed(enc)  # the hook is gone: packed again
    h = enc.layers[1].self_attn.register_forward_hook(lambda m, a, o: None)
    assert not packed_attention.supports_packed(enc)  # varlen uses the attention's weights: its hooks would not fire
    h.remove()


@pytest.mark.parametrize("kind", ["encoder", "decoder"])
def test_varlen_packs_fsq_attention_and_matches_the_reference(kind):
    """FSQ keys (the paper's recipe) are re-applied to the packed keys: same outputs and
    gradients as the masked reference and the compact backend."""
    from smdm_plugin.core.fsq import quantize_attention_keys

    torch.manual_seed(5)
    S, B, d = 16, 3, 32
    inner = (encoder if kind == "encoder" else decoder)().train()
    quantize_attention_keys(inner, (8, 5, 5, 5))
    assert packed_attention.supports_packed(inner)
    keep = keyframes(B, S, [16, 9, 5], 4)
    x = torch.randn(S, B, d, requires_grad=True)
    mem = torch.randn(1, B, d) if kind == "decoder" else None
    w = torch.randn(S, B, d) * keep.t()[..., None]
    results = {}
    for name, fn in (("varlen", varlen_backend), ("compact", compact_backend), ("masked", ab.masked_backend)):
        x.grad = None
        inner.zero_grad()
        out = run(fn, inner, x, keep, memory=mem)
        (out * w).sum().backward()
        key_down = inner.layers[0].self_attn.key_down.grad_of("weight").clone()
        results[name] = (out.detach() * keep.t()[..., None], x.grad.clone(), key_down)
    for name in ("varlen", "compact"):
        for a, b in zip(results[name], results["masked"]):
            assert torch.allclose(a, b, atol=1e-5), name


def test_packing_roundtrip_and_lerp_rows_gradient():
    keep = torch.tensor([[1, 0, 1, 1, 0], [0, 1, 0, 0, 0], [1, 1, 1, 1, 1]], dtype=torch.bool)
    p = Packing(keep)
    assert p.T == 9 and p.max == 5 and p.counts.tolist() == [3, 1, 5]
    t = torch.randn(p.T, 4, requires_grad=True)
    padded = p.pad(t)
    assert padded.shape == (3, 5, 4) and torch.equal(padded[1, 1:], torch.zeros(4, 4))
    assert torch.equal(p.unpad(padded), t)
    padded.sum().backward()
    assert torch.equal(t.grad, torch.ones_like(t))
    h = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    prev = torch.tensor([0, 0, 2, 5, 5])
    nxt = torch.tensor([0, 2, 4, 5, 1])
    w = torch.tensor([[0.0], [0.25], [0.5], [0.0], [0.9]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda h: lerp_rows(h, prev, nxt, w), (h,))
    assert torch.equal(lerp_rows(h, prev, nxt, w), torch.lerp(h[prev], h[nxt], w))


@CUDA
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_varlen_on_cuda_matches_masked(dtype):
    torch.manual_seed(6)
    S, B, d = 40, 4, 64
    enc = encoder(d=d).eval().to("cuda", dtype)
    keep = keyframes(B, S, [40, 22, 9, 40], 8).cuda()
    x = torch.randn(S, B, d, device="cuda", dtype=dtype)
    assert get_backend("auto", x.device) is compact_backend  # static shapes on accelerators
    with torch.no_grad():
        out = run(varlen_backend, enc, x, keep)
        ref = run(ab.masked_backend, enc, x, keep)
    tol = 1e-4 if dtype == torch.float32 else 2e-2
    assert torch.allclose(out[keep.t()].float(), ref[keep.t()].float(), atol=tol)


def test_single_memory_token_matches_reference_gradients():
    """MDM trans_dec: one condition token per sample; varlen keeps outputs and every gradient
    (the query projection's exact zeros included)."""
    torch.manual_seed(7)
    dec = decoder().train()
    x = torch.randn(20, 3, 32, requires_grad=True)
    mem = torch.randn(1, 3, 32, requires_grad=True)
    keep = keyframes(3, 20, [20, 14, 6], 4)
    w = torch.randn(20, 3, 32) * keep.t()[..., None]
    grads = {}
    for name, fn in (("varlen", varlen_backend), ("masked", ab.masked_backend)):
        dec.zero_grad()
        x.grad = mem.grad = None
        (run(fn, dec, x, keep, memory=mem) * w).sum().backward()
        grads[name] = [x.grad.clone(), mem.grad.clone()] + [p.grad.clone() for p in dec.parameters()]
    for a, b in zip(grads["varlen"], grads["masked"]):
        assert torch.allclose(a, b, atol=1e-5)


@pytest.mark.parametrize("kind", ["encoder", "decoder"])
@pytest.mark.parametrize("fsq", [False, True])
def test_varlen_runs_pytorch_s_own_layers_batch_first_and_leaves_them_unchanged(kind, fsq):
    """varlen calls the wrapped module's own forward on packed rows: batch-first layers and FSQ
    keys work as in the module itself, and the module is not changed (same attention objects, no
    attribute added)."""
    from smdm_plugin.core.fsq import quantize_attention_keys

    torch.manual_seed(8)
    d, B, S = 32, 3, 17
    if kind == "encoder":
        inner = nn.TransformerEncoder(nn.TransformerEncoderLayer(d, 4, 64, 0.0, batch_first=True), 2,
                                      enable_nested_tensor=False)
    else:
        inner = nn.TransformerDecoder(nn.TransformerDecoderLayer(d, 4, 64, 0.0, batch_first=True), 2)
    if fsq:
        quantize_attention_keys(inner, (8, 5, 5, 5))
    inner.train()
    assert packed_attention.supports_packed(inner)
    before = [(dict(vars(layer)), layer.self_attn) for layer in inner.layers]
    keep = keyframes(B, S, [17, 11, 4], 5)
    mem = torch.randn(2, B, d) if kind == "decoder" else None
    x = torch.randn(S, B, d, requires_grad=True)
    w = torch.randn(S, B, d) * keep.t()[..., None]
    results = {}
    for name, fn in (("varlen", varlen_backend), ("masked", ab.masked_backend)):
        x.grad = None
        inner.zero_grad()
        (run(fn, inner, x, keep, memory=mem) * w).sum().backward()
        results[name] = (x.grad.clone(), inner.layers[0].self_attn.in_proj_weight.grad.clone())
    for a, b in zip(results["varlen"], results["masked"]):
        assert torch.allclose(a, b, atol=1e-5)
    assert [(dict(vars(layer)), layer.self_attn) for layer in inner.layers] == before


def test_varlen_falls_back_for_a_custom_layer_class():
    class MyLayer(nn.TransformerEncoderLayer):
        def forward(self, src, *args, **kwargs):
            return super().forward(src, *args, **kwargs) * 2

    enc = nn.TransformerEncoder(MyLayer(32, 4, 64, 0.0), 2, enable_nested_tensor=False).eval()
    assert not packed_attention.supports_packed(enc) and packed_attention.supports_packed(encoder())
    keep = keyframes(2, 12, [12, 7], 4)
    x = torch.randn(12, 2, 32)
    with torch.no_grad():
        out = run(varlen_backend, enc, x, keep)
        ref = reference(enc, x, keep)
    assert torch.allclose(out[keep.t()], ref[keep.t()], atol=1e-5)


def test_row_ops_with_and_without_autograd_equal_plain_indexing():
    """The row operations (``core/rows.py``) give plain indexing's values with autograd (their own
    backward: gradcheck) and without it (a sampling call runs their forward as plain ops, no
    ``Function.apply``), and leave no graph behind when nothing needs a gradient."""
    from smdm_plugin.core.rows import gather_rows, lerp_row_pairs, scatter_rows

    h = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    prev, nxt = torch.tensor([0, 0, 2, 5, 5]), torch.tensor([0, 2, 4, 5, 1])
    idx = torch.tensor([4, 0, 2])
    w = torch.tensor([[0.0], [0.25], [0.5], [0.0], [0.9]], dtype=torch.float64)
    pairs = torch.cat([prev, nxt])
    want = {"lerp": torch.lerp(h[prev], h[nxt], w), "gather": h[idx],
            "scatter": torch.zeros(7, 3, dtype=torch.float64).index_put((torch.tensor([1, 6, 3]),), h[:3])}
    ops = {"lerp": lambda h: lerp_row_pairs(h, pairs, w), "gather": lambda h: gather_rows(h, idx),
           "scatter": lambda h: scatter_rows(h[:3], torch.tensor([1, 6, 3]), 7)}
    for name, op in ops.items():
        assert torch.autograd.gradcheck(op, (h,)), name
        assert torch.equal(op(h), want[name]) and op(h).grad_fn is not None, name
        with torch.no_grad():
            out = op(h)
        assert torch.equal(out, want[name]) and out.grad_fn is None, name
        assert torch.equal(op(h.detach()), want[name]), name
