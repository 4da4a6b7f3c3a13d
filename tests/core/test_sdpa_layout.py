"""Every attention of a sparse call reaches ``F.scaled_dot_product_attention`` in the layout every
SDPA kernel accepts (issue 36: cuDNN's kernel crashed with ``misaligned address`` on bf16 sampling of
trans_dec, whose FSQ attention handed it 8-channel query/key heads cut from one projection and a key
mask of 39-element rows). Checked on the CPU under ``static_mode`` (the code path of accelerators):
q, k, v with strides and offsets of multiples of 8 elements (views of one projection: the H200 ran
every SDPA kernel on them, ``scripts/gpu_diagnose.py --sections layout``), head sizes multiples of
8, mask rows 16-element aligned (:func:`smdm_plugin.core.attention.sdpa_layout_problems`; the
head strides in half precision, where cuDNN's kernel runs)."""
import sys

import pytest
import torch
import torch.nn.functional as F

from smdm_plugin import SimpleDiffusion, SparseConfig, TinyMDM, sparsify
from smdm_plugin.core.attention import aligned_key_bias, sdpa_layout_problems
from smdm_plugin.core.checks import static_mode
from smdm_plugin.reference.simple_diffusion import ClassifierFreeGuidance

VARIANTS = {
    "trans_enc": dict(arch="trans_enc"),
    "trans_dec": dict(arch="trans_dec"),
    "dip": dict(arch="trans_dec", emb_trans_dec=True, context_len=20, pred_len=40),
}


class SdpaSpy:
    """Patches ``F.scaled_dot_product_attention`` (looked up at call time by this package and
    ``nn.MultiheadAttention``) and records the layout problems of every call the package makes
    (``nn.MultiheadAttention``'s own calls — upstream's dense cross-attention — are PyTorch's)."""

    def __init__(self, monkeypatch):
        self.calls, self.problems = 0, []
        original = F.scaled_dot_product_attention

        def spy(q, k, v, attn_mask=None, *args, **kwargs):
            if "smdm_plugin" in sys._getframe(1).f_code.co_filename:
                self.calls += 1
                self.problems += sdpa_layout_problems(q, k, v, attn_mask)
            return original(q, k, v, attn_mask, *args, **kwargs)
        monkeypatch.setattr(F, "scaled_dot_product_attention", spy)


def _model(name, N, hooked=False):
    torch.manual_seed(0)
    model = TinyMDM(latent_dim=64, ff_size=128, num_layers=2, num_heads=4, dropout=0.1, **VARIANTS[name])
    diffusion = SimpleDiffusion(10)
    sparsify(model, SparseConfig(dynamic_update=True), diffusion=diffusion)
    if hooked:   # a hook on a layer: the modules run (the functional path would skip the hook)
        layer = (model.seqTransEncoder if name == "trans_enc" else model.seqTransDecoder).layers[0]
        layer.register_forward_hook(lambda m, a, out: None)
    B = 3
    g = torch.Generator().manual_seed(1)
    lengths = torch.tensor([N, N - 7, N - 20]) if name != "dip" else torch.full((B,), N)
    x = torch.randn(B, 263, 1, N, generator=g)
    y = {"mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N), "lengths": lengths,
         "text_embed": torch.randn(1, B, 512, generator=g)}
    if name == "dip":
        y["prefix"] = torch.randn(B, 263, 1, 20, generator=g)
    return model, diffusion, x, y


@pytest.mark.parametrize("hooked", [False, True], ids=["functional", "modules"])
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("name", list(VARIANTS))
def test_every_attention_of_a_sparse_call_has_the_layout_every_sdpa_kernel_accepts(name, precision, hooked, monkeypatch):
    """Training step and sampling calls (early and late steps, the VW update on) of trans_enc,
    trans_dec and DiP, fp32 and bf16 autocast, through the stock layers as functions and through the
    modules (a hooked layer): no SDPA call with strided heads, odd head sizes or unaligned mask
    rows. (The sequence lengths are chosen so that the keyframe slots are not a multiple of 16.)"""
    spy = SdpaSpy(monkeypatch)
    model, diffusion, x, y = _model(name, 40 if name == "dip" else 61, hooked)
    bf16 = precision == "bf16"
    with static_mode():
        model.train()
        with torch.autocast("cpu", torch.bfloat16, enabled=bf16):
            loss = diffusion.training_losses(model, x, torch.tensor([1, 4, 8]), {"y": dict(y)})["loss"].mean()
        loss.backward()
        model.eval()
        guided = ClassifierFreeGuidance(model)
        with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=bf16):
            for t in (8, 0):
                guided(x, torch.full((3,), t), dict(y))
    assert spy.calls > 0
    assert not spy.problems, spy.problems[:4]


def test_the_layout_check_sees_what_crashed_cudnn():
    """The checker itself: the 0.7 folded path's key mask of 39-element rows is reported, and so are
    heads of 6 channels (FSQ's six levels unpadded) or cut at an odd offset; the views of one
    projection the package hands SDPA (8-channel query/key heads, 16-channel values) and an aligned
    mask are not; in fp32 (no cuDNN) only the head size counts."""
    B, S, H, P, hd = 2, 39, 4, 8, 16
    proj = torch.randn(S, B, 2 * H * P + H * hd, dtype=torch.bfloat16)

    def cut(t, start, size):          # H heads of ``size`` channels from ``start``: [B, H, S, size] views
        return t[..., start:start + H * size].unflatten(-1, (H, size)).permute(1, 2, 0, 3)

    q, k, v = cut(proj, 0, P), cut(proj, H * P, P), cut(proj, 2 * H * P, hd)
    bias = torch.zeros(B, S, dtype=torch.bfloat16)
    problems = sdpa_layout_problems(q, k, v, bias.view(B, 1, 1, S))
    assert len(problems) == 1 and "mask" in problems[0]
    aligned = aligned_key_bias(bias)
    assert not sdpa_layout_problems(q, k, v, aligned)
    assert aligned.shape == (B, 1, 1, S) and aligned.stride(0) % 16 == 0 and torch.equal(aligned[:, 0, 0], bias)
    odd = torch.randn(S, B, 6 * H * 3, dtype=torch.bfloat16)     # 6-channel heads: strides of 6 elements
    six = [cut(odd, i * 6 * H, 6) for i in range(3)]
    found = sdpa_layout_problems(*six, aligned)
    assert sum("head size 6" in m for m in found) == 3 and sum("aligned to 8" in m for m in found) == 3
    shifted = cut(proj, 4, P)                                  # a head cut 4 elements (8 bytes) in
    assert any("offset 4" in m for m in sdpa_layout_problems(shifted, k, v, aligned))
    f = [t.float() for t in six]                                  # fp32: strides do not count
    assert all("head size" in m for m in sdpa_layout_problems(*f, aligned_key_bias(bias.float())))


def test_layout_copies_switch_changes_the_layout_not_the_values():
    """``use_layout_copies(True)`` hands SDPA contiguous ``[B, S, H·e]`` heads (the switch for a GPU
    whose kernels would refuse views), the default hands it views of the projections; a trans_dec
    bf16 sampling call gives the same values either way; anything but a bool or None is refused."""
    from smdm_plugin.core.attention import use_layout_copies

    model, _, x, y = _model("trans_dec", 61)
    model.eval()
    seen = {}
    original = F.scaled_dot_product_attention

    def spy(q, *args, **kwargs):
        seen.setdefault(mode, []).append(q.transpose(1, 2).is_contiguous())
        return original(q, *args, **kwargs)

    out = {}
    try:
        F.scaled_dot_product_attention = spy
        for mode in (None, True):
            use_layout_copies(mode)
            with static_mode(), torch.no_grad(), torch.autocast("cpu", torch.bfloat16):
                out[mode] = model(x, torch.full((3,), 5), y=dict(y)).float()
    finally:
        F.scaled_dot_product_attention = original
        use_layout_copies(None)
    assert seen[True] and all(seen[True]) and not any(seen[None])
    torch.testing.assert_close(out[None], out[True], rtol=1e-2, atol=1e-2)
    with pytest.raises(TypeError, match="use_layout_copies"):
        use_layout_copies("yes")
