"""FSQ quantiser and the FSQ-key ``nn.MultiheadAttention`` drop-in."""
import copy
import importlib.util
import math
import os
import subprocess
import sys
import warnings

import pytest
import torch
from torch import nn

from smdm_plugin.core.fsq import FSQ, FSQMultiheadAttention, quantize_attention_keys

LEVELS = (8, 5, 5, 2)
pytestmark = pytest.mark.filterwarnings("ignore:The PyTorch API of nested tensors")


# ----------------------------------------------------------------------------- FSQ
def test_fsq_outputs_on_level_grid_and_cover_all_levels():
    fsq = FSQ(LEVELS)
    z = torch.randn(20000, len(LEVELS)) * 3
    out = fsq(z)
    for i, L in enumerate(LEVELS):
        hw = L // 2
        ints = out[:, i] * hw
        assert torch.equal(ints, ints.round())                      # exactly on the grid
        vals = set(ints.round().long().tolist())
        assert vals == set(range(-hw, L - hw))                      # all L levels, no more
    assert out.abs().max() <= 1.0
    assert torch.equal(fsq(torch.zeros(1, len(LEVELS))), torch.zeros(1, len(LEVELS)))


def test_fsq_straight_through_gradient():
    fsq = FSQ(LEVELS)
    z = (torch.randn(256, len(LEVELS)) * 0.5).requires_grad_()
    fsq(z).sum().backward()
    assert (z.grad.abs() > 0).all()
    # gradient of the rounding is the identity: d/dz (bound(z) / floor(L/2))
    zz = z.detach().clone().requires_grad_()
    (fsq.bound(zz) / fsq._half_width).sum().backward()
    torch.testing.assert_close(z.grad, zz.grad)


def test_fsq_codes_indices_round_trip_full_codebook():
    fsq = FSQ(LEVELS)
    assert fsq.codebook_size == math.prod(LEVELS)
    idx = torch.arange(fsq.codebook_size)
    codes = fsq.indices_to_codes(idx)
    assert codes.shape == (fsq.codebook_size, len(LEVELS))
    assert torch.unique(codes, dim=0).shape[0] == fsq.codebook_size
    assert torch.equal(fsq.codes_to_indices(codes), idx)
    out = fsq(torch.randn(500, len(LEVELS)) * 3)                     # forward output -> index
    assert torch.equal(fsq.indices_to_codes(fsq.codes_to_indices(out)), out)


def test_fsq_rejects_bad_levels_and_shapes():
    with pytest.raises(ValueError):
        FSQ([])
    with pytest.raises(ValueError):
        FSQ([1, 4])
    with pytest.raises(ValueError):
        FSQ(LEVELS)(torch.randn(3, 5))


# ----------------------------------------------------------------------------- attention
def _pair(batch_first: bool, bias: bool = True, E: int = 32, H: int = 4):
    torch.manual_seed(0)
    mha = nn.MultiheadAttention(E, H, bias=bias, batch_first=batch_first)
    if bias:
        with torch.no_grad():
            mha.in_proj_bias.normal_()
            mha.out_proj.bias.normal_()
    fsq = FSQMultiheadAttention.from_mha(mha, LEVELS)
    return mha.eval(), fsq.eval()


def _inputs(batch_first: bool, B=3, L=5, S=7, E=32):
    g = torch.Generator().manual_seed(1)
    q = torch.randn(B, L, E, generator=g)
    kv = torch.randn(B, S, E, generator=g)
    v = torch.randn(B, S, E, generator=g)
    kpm = torch.zeros(B, S, dtype=torch.bool)
    kpm[0, 5:] = True
    kpm[2, 1] = True
    kpm[2, 6] = True
    if not batch_first:
        q, kv, v = (t.transpose(0, 1) for t in (q, kv, v))
    return q, kv, v, kpm


@pytest.mark.parametrize("batch_first", [False, True])
@pytest.mark.parametrize("bias", [True, False])
def test_bypassed_equals_nn_multihead_attention(batch_first, bias):
    mha, fsq = _pair(batch_first, bias)
    fsq.quantize = False
    q, k, v, kpm = _inputs(batch_first)
    L, S = 5, 7
    attn_mask = torch.zeros(L, S, dtype=torch.bool)
    attn_mask[1, 2] = True
    for kw in ({}, {"key_padding_mask": kpm}, {"key_padding_mask": kpm, "attn_mask": attn_mask},
               {"key_padding_mask": kpm.float().masked_fill(kpm, float("-inf"))}):
        for need in (True, False):
            for avg in (True, False):
                o1, w1 = mha(q, k, v, need_weights=need, average_attn_weights=avg, **kw)
                o2, w2 = fsq(q, k, v, need_weights=need, average_attn_weights=avg, **kw)
                torch.testing.assert_close(o2, o1, rtol=1e-5, atol=1e-5)
                if need:
                    torch.testing.assert_close(w2, w1, rtol=1e-5, atol=1e-5)
                else:
                    assert w2 is None
    # self-attention, 3-D per-head mask, unbatched
    x = q
    m3 = torch.zeros(3 * 4, L, L)
    m3[:, 0, 1] = float("-inf")
    torch.testing.assert_close(fsq(x, x, x, attn_mask=m3)[0], mha(x, x, x, attn_mask=m3)[0],
                               rtol=1e-5, atol=1e-5)
    xu = x[:, 0] if not batch_first else x[0]
    torch.testing.assert_close(fsq(xu, xu, xu)[0], mha(xu, xu, xu)[0], rtol=1e-5, atol=1e-5)


def test_quantised_matches_reference_computation():
    mha, fsq = _pair(True)
    q, k, v, kpm = _inputs(True)
    E, H, hd = 32, 4, 8
    wq, wk, wv = fsq.in_proj_weight.split(E)
    bq, bk, bv = fsq.in_proj_bias.split(E)

    def heads(t):
        return t.view(t.shape[0], t.shape[1], H, hd).transpose(1, 2)

    Q, K, V = heads(q @ wq.T + bq), heads(k @ wk.T + bk), heads(v @ wv.T + bv)
    K = fsq.key_up(fsq.fsq(fsq.key_down(K)))
    s = Q @ K.transpose(-1, -2) / math.sqrt(hd) + kpm[:, None, None, :].float() * -1e30
    ref = fsq.out_proj((s.softmax(-1) @ V).transpose(1, 2).reshape(3, 5, E))
    for need in (True, False):
        out, _ = fsq(q, k, v, key_padding_mask=kpm, need_weights=need)
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    dense, _ = mha(q, k, v, key_padding_mask=kpm)
    assert not torch.allclose(out, dense, atol=1e-3)                # quantiser is active


def test_sampling_cache_of_the_folded_projections_follows_weight_updates():
    """Without autograd the FSQ steps folded into key_down / key_up are cached; an in-place update
    of those weights (an optimizer step, load_state_dict) is seen by the next call."""
    _, fsq = _pair(True)
    q, k, v, kpm = _inputs(True)
    for _ in range(2):
        ref, _ = fsq(q, k, v, key_padding_mask=kpm, need_weights=False)        # autograd: not cached
        with torch.no_grad():
            cached, _ = fsq(q, k, v, key_padding_mask=kpm, need_weights=False)
            cached2, _ = fsq(q, k, v, key_padding_mask=kpm, need_weights=False)
        torch.testing.assert_close(cached, ref.detach(), rtol=1e-5, atol=1e-5)
        assert torch.equal(cached, cached2)
        with torch.no_grad():
            fsq.key_up.weight.mul_(-2.0)
            fsq.key_down.bias.add_(0.7)
        with torch.no_grad():
            changed, _ = fsq(q, k, v, key_padding_mask=kpm, need_weights=False)
        assert not torch.allclose(changed, cached, atol=1e-3)


def test_is_causal_and_weights_shape():
    _, fsq = _pair(True)
    x = torch.randn(2, 6, 32)
    causal = nn.Transformer.generate_square_subsequent_mask(6)
    o1, w = fsq(x, x, x, attn_mask=causal, is_causal=True, average_attn_weights=False)
    o2, _ = fsq(x, x, x, is_causal=True, need_weights=False)
    torch.testing.assert_close(o1, o2, rtol=1e-5, atol=1e-6)
    assert w.shape == (2, 4, 6, 6) and torch.all(w[..., 0, 1:] == 0)


def test_key_padding_mask_honoured():
    for batch_first in (False, True):
        _, fsq = _pair(batch_first)
        q, k, v, kpm = _inputs(batch_first)
        out, _ = fsq(q, k, v, key_padding_mask=kpm, need_weights=False)
        k2, v2 = k.clone(), v.clone()
        bmask = kpm if batch_first else kpm.T
        k2[bmask] = 100 * torch.randn(int(kpm.sum()), 32)
        v2[bmask] = 100 * torch.randn(int(kpm.sum()), 32)
        out2, _ = fsq(q, k2, v2, key_padding_mask=kpm, need_weights=False)
        torch.testing.assert_close(out2, out, rtol=0, atol=1e-5)


def test_dense_checkpoint_loads_with_same_names():
    mha = nn.MultiheadAttention(32, 4)
    fsq = FSQMultiheadAttention(32, 4)
    missing, unexpected = fsq.load_state_dict(mha.state_dict(), strict=False)
    assert not unexpected
    assert sorted(missing) == ["key_down.bias", "key_down.weight", "key_up.bias", "key_up.weight"]
    for name in ("in_proj_weight", "in_proj_bias", "out_proj.weight", "out_proj.bias"):
        assert torch.equal(fsq.state_dict()[name], mha.state_dict()[name])
    with pytest.raises(ValueError):
        FSQMultiheadAttention(32, 4, kdim=16)
    with pytest.raises(ValueError):
        FSQMultiheadAttention.from_mha(nn.MultiheadAttention(32, 4, add_bias_kv=True), LEVELS)


# ----------------------------------------------------------------------------- in transformers
def _encoder(batch_first: bool, E=32, H=4, n=2):
    torch.manual_seed(0)
    layer = nn.TransformerEncoderLayer(E, H, 64, dropout=0.1, batch_first=batch_first)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = nn.TransformerEncoder(layer, n)
    return enc


@pytest.mark.parametrize("batch_first", [False, True])
def test_inside_transformer_encoder_train_and_eval(batch_first):
    enc = _encoder(batch_first)
    dense = _encoder(batch_first)
    assert quantize_attention_keys(enc, LEVELS) == 2
    assert all(isinstance(l.self_attn, FSQMultiheadAttention) for l in enc.layers)
    B, N, E = 3, 9, 32
    x = torch.randn(B, N, E) if batch_first else torch.randn(N, B, E)
    kpm = torch.zeros(B, N, dtype=torch.bool)
    kpm[1, 6:] = True                                               # left-aligned padding
    # train: runs, gradients reach the quantiser and the projections
    enc.train()
    enc(x, src_key_padding_mask=kpm).pow(2).mean().backward()
    for l in enc.layers:                                           # (the key maps: rows of one bank)
        a = l.self_attn
        for g in (a.key_down.grad_of("weight"), a.key_up.grad_of("weight"), a.in_proj_weight.grad):
            assert g is not None and g.abs().sum() > 0
    # eval: no_grad (where the fused fast path would be taken) == grad-enabled normal path
    enc.eval()
    dense.eval()
    for mask in (kpm, None):
        with torch.no_grad():
            y_ng = enc(x, src_key_padding_mask=mask)
            y_dense = dense(x, src_key_padding_mask=mask)
        y_g = enc(x, src_key_padding_mask=mask).detach()
        valid = ~kpm if batch_first else ~kpm.T
        torch.testing.assert_close(y_ng[valid], y_g[valid], rtol=1e-5, atol=1e-5)
        assert not torch.allclose(y_ng[valid], y_dense[valid], atol=1e-3)  # FSQ was used


def test_direct_construction_with_nested_tensor_path():
    """A layer built with an FSQ ``self_attn`` before ``nn.TransformerEncoder`` (nested tensors
    stay enabled): eval + no_grad + padding mask goes through nested tensors and still works."""
    torch.manual_seed(0)
    layer = nn.TransformerEncoderLayer(32, 4, 64, batch_first=True)
    layer.self_attn = FSQMultiheadAttention.from_mha(layer.self_attn, LEVELS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = nn.TransformerEncoder(layer, 2).eval()
        assert enc.use_nested_tensor
        x = torch.randn(3, 7, 32)
        kpm = torch.zeros(3, 7, dtype=torch.bool)
        kpm[0, 4:] = True
        with torch.no_grad():
            y = enc(x, src_key_padding_mask=kpm)
    y_ref = enc(x, src_key_padding_mask=kpm).detach()
    torch.testing.assert_close(y[~kpm], y_ref[~kpm], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("batch_first", [False, True])
def test_inside_transformer_decoder_self_attention_only(batch_first):
    torch.manual_seed(0)
    dec = nn.TransformerDecoder(nn.TransformerDecoderLayer(32, 4, 64, batch_first=batch_first), 2)
    assert quantize_attention_keys(dec, LEVELS) == 2
    for l in dec.layers:
        assert isinstance(l.self_attn, FSQMultiheadAttention)
        assert type(l.multihead_attn) is nn.MultiheadAttention
    shape_t, shape_m = ((2, 6, 32), (2, 4, 32)) if batch_first else ((6, 2, 32), (4, 2, 32))
    tgt, mem = torch.randn(shape_t), torch.randn(shape_m)
    tkpm = torch.tensor([[False] * 6, [False] * 4 + [True] * 2])
    dec.train()
    dec(tgt, mem, tgt_key_padding_mask=tkpm).sum().backward()
    assert dec.layers[0].self_attn.key_down.grad_of("weight").abs().sum() > 0
    dec.eval()
    with torch.no_grad():
        y = dec(tgt, mem, tgt_key_padding_mask=tkpm,
                tgt_mask=nn.Transformer.generate_square_subsequent_mask(6), tgt_is_causal=True)
    assert y.shape == tgt.shape and torch.isfinite(y).all()


# ----------------------------------------------------------------------------- the folded path (issue 27)
def _self_attention_pair(bias, batch_first, seed=0):
    """An FSQ attention layer in training mode (no dropout) with random key projections."""
    torch.manual_seed(seed)
    attn = FSQMultiheadAttention(32, 4, bias=bias, batch_first=batch_first, levels=(8, 8, 8, 5, 5, 5))
    with torch.no_grad():
        for p in (attn.key_down.weight, attn.key_down.bias, attn.key_up.weight, attn.key_up.bias):
            p.normal_()
        if bias:
            attn.in_proj_bias.normal_()
    return attn.train()


@pytest.mark.parametrize("batch_first", [False, True])
@pytest.mark.parametrize("bias", [True, False])
def test_folded_self_attention_equals_the_unfolded_computation(bias, batch_first):
    """Self-attention (query is key is value) runs the folded path: key_down / key_up folded into
    the in-projection, P-channel query codes and key codes. Its output and the gradient of every
    trainable parameter equal the unfolded path's (the same module given a copy of the keys:
    key_down(k), FSQ, key_up(.), full-width attention), with a key padding mask."""
    attn = _self_attention_pair(bias, batch_first)
    assert attn.code_dim % 8 == 0 and attn.code_dim >= attn.fsq.dim
    g = torch.Generator().manual_seed(3)
    x = torch.randn(2, 9, 32, generator=g) if batch_first else torch.randn(9, 2, 32, generator=g)
    kpm = torch.zeros(2, 9, dtype=torch.bool)
    kpm[1, 6:] = True
    grads = []
    for folded in (True, False):
        attn.zero_grad(set_to_none=True)
        xi = x.clone().requires_grad_()
        key = xi if folded else xi.clone()                  # a copy: not `query is key`, the unfolded path
        out, w = attn(xi, key, key if not folded else xi, key_padding_mask=kpm, need_weights=True)
        (out * torch.linspace(-1, 1, out.numel()).view_as(out)).sum().backward()
        grads.append((out.detach(), w.detach(), xi.grad,
                      {n: p.grad for n, p in attn.named_parameters() if p.requires_grad}))
    (o1, w1, x1, p1), (o2, w2, x2, p2) = grads
    torch.testing.assert_close(o1, o2, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(w1, w2, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(x1, x2, rtol=1e-4, atol=1e-5)
    assert p1.keys() == p2.keys() and "key_up.bias" not in p1
    for n in p1:
        assert p1[n] is not None, f"{n}: no gradient on the folded path"
        torch.testing.assert_close(p1[n], p2[n], rtol=1e-3, atol=1e-5, msg=n)


def test_key_up_bias_is_inert_and_frozen():
    """``q·key_up.bias`` is the same for every key of a query: changing key_up.bias changes no
    output (softmax drops it), so it is frozen (no trainable parameter without a gradient: DDP
    with find_unused_parameters=False and optimizers see none)."""
    attn = _self_attention_pair(True, False).eval()
    x = torch.randn(7, 2, 32)
    ref, _ = attn(x, x.clone(), x.clone(), need_weights=False)      # the unfolded path reads key_up.bias
    with torch.no_grad():
        attn.key_up.bias.add_(5.0)
    moved, _ = attn(x, x.clone(), x.clone(), need_weights=False)
    torch.testing.assert_close(moved, ref, rtol=1e-4, atol=1e-5)
    assert not attn.key_up.bias.requires_grad
    attn.train()
    attn(x, x, x)[0].sum().backward()
    assert all(p.grad is not None for p in attn.parameters() if p.requires_grad)


def test_all_layers_folded_at_once_equal_each_layer_folded_alone():
    """``fold_keys`` (training: every layer's folded in-projection from one stacked computation)
    gives the same outputs and gradients as each layer folding its own."""
    from smdm_plugin.core.fsq import fold_keys

    layers = [_self_attention_pair(True, False, seed=s) for s in range(3)]
    x = torch.randn(6, 2, 32)
    res = []
    for together in (True, False):
        for a in layers:
            a.zero_grad(set_to_none=True)
        with fold_keys(layers if together else [], x):
            h = x
            for a in layers:
                h = a(h, h, h, need_weights=False)[0]
        h.pow(2).sum().backward()
        res.append((h.detach(), [p.grad.clone() for a in layers for p in a.parameters() if p.requires_grad]))
    torch.testing.assert_close(res[0][0], res[1][0], rtol=1e-5, atol=1e-6)
    for a, b in zip(res[0][1], res[1][1]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


# ----------------------------------------------------------------------------- smdm::fsq_code
def test_fsq_code_op_equals_its_formula_with_a_straight_through_gradient():
    """``fsq_code``: ``round(tanh(z)·half_l + neg_offset)`` in float32, in z's dtype, for strided z
    (a column block) and bfloat16; gradient ``g·half_l·(1 - tanh(z)²)``, the same with the bf16
    composite's saved float32 tanh. By default CUDA runs the composite's few ops (the Triton
    kernels are off: their launches cost the host more, docs/gpu.md); switched on, one CUDA launch
    each way; no ``torch.library`` dispatch in eager mode either way (host time)."""
    from smdm_plugin.core.kernels.fsq_code import fsq_code
    from smdm_plugin.runtime.launches import count_launches

    attn = _self_attention_pair(True, False)
    neg, half = attn.code_constants(torch.float32)
    C = neg.shape[0]
    base = torch.randn(5, 3, 2 * C, dtype=torch.float64) * 2
    z = base[..., C:].float().requires_grad_()                      # strided rows, like the in-projection's block
    r = fsq_code(z, neg, half)
    ref = torch.round(torch.tanh(z.detach().double()) * half.double() + neg.double()).float()
    assert torch.equal(r, ref) and r.dtype == torch.float32
    g = torch.randn_like(r)
    r.backward(g)
    torch.testing.assert_close(z.grad, g * half * (1 - torch.tanh(z.detach()) ** 2))
    zb = z.detach().bfloat16()
    rb = fsq_code(zb, neg, half)
    assert rb.dtype == torch.bfloat16
    assert torch.equal(rb.float(), torch.round(torch.addcmul(neg, torch.tanh(zb.float()), half)))
    zb.requires_grad_()
    fsq_code(zb, neg, half).backward(g.bfloat16())
    ref_b = (g.bfloat16().float() * half * (1 - torch.tanh(zb.detach().float()) ** 2)).bfloat16()
    assert zb.grad.dtype == torch.bfloat16 and torch.equal(zb.grad, ref_b)
    from smdm_plugin.core.kernels.dispatch import use_triton_kernels

    names = ["FSQ code", "FSQ code gradient"]
    zz = z.detach().clone().requires_grad_()
    ops = count_launches(lambda: fsq_code(zz, neg, half).sum().backward()).ops
    assert "smdm.fsq_code" not in ops and "smdm.fsq_code_backward" not in ops
    assert ops["aten.tanh.default"] == 1 and ops["aten.tanh_backward.default"] == 1, ops   # tanh once
    before = use_triton_kernels(True, names)
    try:
        zz.grad = None
        ops = count_launches(lambda: fsq_code(zz, neg, half).sum().backward(), warmup=0).ops
        grad = zz.grad
    finally:
        for name, on in before.items():
            use_triton_kernels(on, [name])
    assert ops["smdm.fsq_code"] == 1 and ops["smdm.fsq_code_backward"] == 1
    assert "aten.tanh.default" not in ops
    torch.testing.assert_close(grad, half * (1 - torch.tanh(z.detach()) ** 2))
    assert not any(k.startswith("smdm.") and k.endswith(".default") for k in ops), ops   # no custom op


def test_fsq_code_compiles_fullgraph_and_equals_eager():
    from smdm_plugin.core.kernels.fsq_code import fsq_code

    attn = _self_attention_pair(True, False)
    neg, half = attn.code_constants(torch.float32)
    z = torch.randn(4, 7, neg.shape[0], requires_grad=True)
    fn = torch.compile(lambda t: fsq_code(t, neg, half), fullgraph=True, backend="aot_eager")
    out = fn(z)
    assert torch.equal(out, fsq_code(z.detach(), neg, half))
    out.sum().backward()
    torch.testing.assert_close(z.grad, half * (1 - torch.tanh(z.detach()) ** 2))


def test_fsq_code_triton_kernels_equal_the_composite_in_interpreter_mode(triton_interpreter):
    """The CUDA kernels' code, run by Triton's interpreter on the CPU: codes and gradients equal the
    composite on strided float32 and bfloat16 input."""
    code = (
        "import torch\n"
        "from smdm_plugin.core.kernels.fsq_code import fsq_code_composite, fsq_code_grad_composite\n"
        "from smdm_plugin.core.kernels.fsq_triton import fsq_code_triton, fsq_code_backward_triton\n"
        "torch.manual_seed(0)\n"
        "C = 32\n"
        "neg = torch.randn(C).round() / 2\n"
        "half = torch.rand(C) * 3\n"
        "bad = 0\n"
        "for dt in (torch.float32, torch.bfloat16):\n"
        "    z = (torch.randn(6, 5, 3 * C) * 2).to(dt)[..., C:2 * C]\n"
        "    g = torch.randn(6, 5, C).to(dt)\n"
        "    bad += int(not torch.equal(fsq_code_triton(z, neg, half), fsq_code_composite(z, neg, half)))\n"
        "    bad += int(not torch.allclose(fsq_code_backward_triton(g, z, half).float(),\n"
        "                                  fsq_code_grad_composite(g, z, half).float(), rtol=1e-2, atol=1e-3))\n"
        "print('mismatches', bad)\n")
    out = triton_interpreter(code)
    assert "mismatches 0" in out, out

def test_unquantize_attention_keys_is_the_inverse_of_quantize():
    """``unquantize_attention_keys`` (public, the PEFT-style way back): every FSQ self-attention of a
    transformer becomes ``nn.MultiheadAttention`` with its current q/k/v/out weights (trained ones
    included), so the model equals the dense one it came from; cross-attention is untouched."""
    from smdm_plugin.core.fsq import quantize_attention_keys, unquantize_attention_keys

    torch.manual_seed(0)
    layer = nn.TransformerDecoderLayer(32, 4, 64, dropout=0.0)
    dense = nn.TransformerDecoder(layer, 2).eval()
    model = copy.deepcopy(dense)
    assert quantize_attention_keys(model, LEVELS) == 2
    with torch.no_grad():                                    # a "trained" change of a kept weight
        model.layers[0].self_attn.in_proj_weight.mul_(1.5)
        dense.layers[0].self_attn.in_proj_weight.mul_(1.5)
    cross = model.layers[1].multihead_attn
    assert unquantize_attention_keys(model) == 2
    assert all(type(m.self_attn) is nn.MultiheadAttention for m in model.layers)
    assert model.layers[1].multihead_attn is cross
    assert set(model.state_dict()) == set(dense.state_dict())
    x, mem = torch.randn(5, 2, 32), torch.randn(7, 2, 32)
    torch.testing.assert_close(model(x, mem), dense(x, mem))
    assert unquantize_attention_keys(model) == 0             # nothing left to convert


# ----------------------------------------------------------------------------- one seed, one model on every device
def test_fsq_attention_draws_its_weights_on_the_cpu_whatever_the_device():
    """A GPU's sparse model must equal the CPU's for one seed: the new key maps are drawn from the
    CPU generator and moved (0.9 drew them on the device: the H200 check compared different weights,
    and the device's generator, upstream's noise on CUDA, moved). ``meta`` stands for the GPU."""
    torch.manual_seed(0)
    cpu = FSQMultiheadAttention(32, 4, levels=LEVELS)
    after_cpu = torch.rand(4)
    torch.manual_seed(0)
    meta = FSQMultiheadAttention(32, 4, levels=LEVELS, device="meta")
    after_meta = torch.rand(4)
    assert meta.key_down.weight.device.type == "meta" and meta._code_half_l.device.type == "meta"
    assert torch.equal(after_cpu, after_meta)                 # the same CPU draws were made for both
    torch.manual_seed(0)
    again = FSQMultiheadAttention(32, 4, levels=LEVELS, device="cpu")
    for (name, a), (_, b) in zip(cpu.state_dict().items(), again.state_dict().items()):
        assert torch.equal(a, b), name


def test_workload_build_refuses_a_fsq_setting_it_does_not_know():
    from smdm_plugin.training import workloads

    with pytest.raises(ValueError, match="fsq must be one of"):
        workloads.build("trans_enc", 0.8, torch.device("cpu"), True, 10, frames=40, fsq=False)
