import copy

import pytest
import torch
import torch.nn as nn

from smdm_plugin.core.keyframe_transformer import KeyframeTransformer
from smdm_plugin.core.interpolation import interpolate_keyframes
from smdm_plugin.core.attention_backends import get_backend

BACKENDS = ["masked", "compact", "varlen"]


def encoder(d=32, layers=2, dropout=0.0, norm_first=False, batch_first=False):
    layer = nn.TransformerEncoderLayer(d, 4, 64, dropout, "gelu", norm_first=norm_first, batch_first=batch_first)
    return nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)


def decoder(d=32, layers=2, dropout=0.0, norm_first=False):
    return nn.TransformerDecoder(nn.TransformerDecoderLayer(d, 4, 64, dropout, "gelu", norm_first=norm_first), layers)


def make_mask(B, N, lengths, k, gen):
    mask = torch.zeros(B, N, dtype=torch.bool)
    for b, L in enumerate(lengths):
        idx = torch.randperm(L - 2, generator=gen)[: k - 2] + 1
        mask[b, idx] = True
        mask[b, 0] = mask[b, L - 1] = True
    return mask


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("norm_first", [False, True])
def test_encoder_keyframe_outputs_equal_dense_masked_reference(backend, norm_first):
    gen = torch.Generator().manual_seed(0)
    S, B, d, lead = 41, 5, 32, 1
    enc = encoder(norm_first=norm_first).eval()
    x = torch.randn(S, B, d, generator=gen)
    lengths = [40, 33, 17, 40, 2]
    mask = torch.zeros(B, S - lead, dtype=torch.bool)
    for b, L in enumerate(lengths):
        k = min(L, 6)
        mask[b] = make_mask(1, S - lead, [L], k, gen)[0]
    wrap = KeyframeTransformer(copy.deepcopy(enc), backend=backend).eval()
    wrap.set_keyframes(mask)
    with torch.no_grad():
        out = wrap(x)
        keep = torch.cat([torch.ones(B, lead, dtype=torch.bool), mask], 1)
        ref = enc(x, src_key_padding_mask=~keep)  # dense layers, key padding over non-keyframes
    kt = keep.t()
    assert torch.allclose(out[kt], ref[kt], atol=1e-5)
    # non-keyframe frames are the linear interpolation of the keyframe outputs
    frames = ref[lead:].transpose(0, 1)
    assert torch.allclose(out[lead:].transpose(0, 1), interpolate_keyframes(frames, mask), atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_decoder_with_memory_padding_equals_reference(backend):
    gen = torch.Generator().manual_seed(1)
    S, B, d, M = 30, 4, 32, 5
    dec = decoder().eval()
    x, mem = torch.randn(S, B, d, generator=gen), torch.randn(M, B, d, generator=gen)
    mpad = torch.zeros(B, M, dtype=torch.bool)
    mpad[1, 3:] = True
    mask = make_mask(B, S, [30, 30, 11, 25], 5, gen)
    wrap = KeyframeTransformer(dec, backend=backend).eval()
    wrap.set_keyframes(mask)
    with torch.no_grad():
        out = wrap(x, mem, memory_key_padding_mask=mpad)
        ref = dec(x, mem, tgt_key_padding_mask=~mask, memory_key_padding_mask=mpad)
    assert torch.allclose(out[mask.t()], ref[mask.t()], atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_all_keyframes_equals_dense_module(backend):
    S, B, d = 25, 3, 32
    enc = encoder().eval()
    x = torch.randn(S, B, d)
    lengths = torch.tensor([24, 24, 13])
    pad = torch.arange(S - 1) >= lengths[:, None]
    pad = torch.cat([torch.zeros(B, 1, dtype=torch.bool), pad], 1)
    wrap = KeyframeTransformer(enc, backend=backend).eval()
    wrap.set_keyframes(~pad[:, 1:])
    with torch.no_grad():
        out, ref = wrap(x, src_key_padding_mask=pad), enc(x, src_key_padding_mask=pad)
    valid = ~pad.t()
    assert torch.allclose(out[valid], ref[valid], atol=1e-5)
    wrap.set_keyframes(torch.ones(B, S - 1, dtype=torch.bool))  # full-length: the whole output
    with torch.no_grad():
        assert torch.allclose(wrap(x), enc(x), atol=1e-5)


def test_training_mode_gradients_match_reference():
    gen = torch.Generator().manual_seed(3)
    S, B, d = 21, 4, 32
    enc = encoder(dropout=0.0).train()
    x = torch.randn(S, B, d, generator=gen, requires_grad=True)
    mask = make_mask(B, S, [21, 21, 15, 9], 4, gen)
    w = torch.randn(S, B, d, generator=gen)
    grads = {}
    for backend in BACKENDS:
        wrap = KeyframeTransformer(enc, backend=backend).train()
        wrap.set_keyframes(mask)
        x.grad = None
        enc.zero_grad()
        (wrap(x) * w).sum().backward()
        grads[backend] = (x.grad.clone(), enc.layers[0].linear1.weight.grad.clone())
    for backend in ("compact", "varlen"):
        assert torch.allclose(grads[backend][0], grads["masked"][0], atol=1e-4)
        assert torch.allclose(grads[backend][1], grads["masked"][1], atol=1e-4)
    assert torch.all(grads["compact"][0][~mask.t()] == 0)  # non-keyframe inputs are never read


def test_compaction_runs_on_capacity_tokens_and_keeps_state_dict_keys():
    S, B, d = 50, 3, 32
    enc = encoder().eval()
    keys = set(enc.state_dict())
    wrap = KeyframeTransformer(enc, backend="compact").eval()
    assert set(wrap.state_dict()) == keys
    seen = []
    enc.layers[0].register_forward_pre_hook(lambda m, a: seen.append(a[0].shape[0]))
    mask = torch.zeros(B, S, dtype=torch.bool)
    mask[:, [0, 10, 49]] = True
    mask[0, 20] = True
    x = torch.randn(S, B, d)
    for capacity in (4, 7):  # the plan's fixed capacity, not S (and not data-dependent)
        wrap.set_keyframes(mask, capacity=capacity)
        with torch.no_grad():
            out = wrap(x)
        assert seen[-1] == capacity
        if capacity == 4:
            first = out
    assert torch.allclose(out, first, atol=1e-6)  # extra (padded) slots change nothing


def test_batch_first_and_no_mask_runs_dense():
    enc = encoder(batch_first=True).eval()
    wrap = KeyframeTransformer(enc).eval()
    x = torch.randn(2, 12, 32)
    with torch.no_grad():
        assert torch.equal(wrap(x), enc(x))  # no keyframes set: the wrapped module, untouched
        mask = torch.ones(2, 12, dtype=torch.bool)
        wrap.set_keyframes(mask)
        assert torch.allclose(wrap(x), enc(x), atol=1e-5)


def test_bad_inputs():
    with pytest.raises(TypeError, match="TransformerEncoder"):
        KeyframeTransformer(nn.Linear(3, 3))
    wrap = KeyframeTransformer(encoder())
    wrap.set_keyframes(torch.ones(3, 99, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"keyframe plan is for \[B, N\]=\[3, 99\]"):
        wrap(torch.randn(10, 3, 32))
    with pytest.raises(ValueError, match="unknown"):
        get_backend("nope", torch.device("cpu"))
