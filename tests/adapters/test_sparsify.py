"""The MDM adapter on the in-package MDM-compatible backbone (CI has no upstream checkout)."""
import copy

import pytest
import torch
import torch.nn as nn

from smdm_plugin import KeyframeRequest, with_forced
from smdm_plugin.adapters.request import KEYFRAMES_KEY
from smdm_plugin import SimpleDiffusion, SparseConfig, TinyMDM, is_sparse, sparsify, unsparsify
from smdm_plugin.families.mdm.model import detect_variant
from smdm_plugin.core.lipschitz import lipschitz_loss
from smdm_plugin.core.fsq import FSQMultiheadAttention, quantize_attention_keys
from smdm_plugin.core.lipschitz import LipschitzMLP

VARIANTS = {
    "mdm-trans_enc": dict(arch="trans_enc"),
    "mdm-trans_dec": dict(arch="trans_dec"),
    "mdm-trans_dec-emb": dict(arch="trans_dec", emb_trans_dec=True),
    "dip": dict(arch="trans_dec", emb_trans_dec=True, context_len=20, pred_len=40),
}


def tiny(**kw):
    torch.manual_seed(0)
    return TinyMDM(latent_dim=64, ff_size=128, num_layers=2, **kw)


def batch(model, B=3, N=None, lengths=None, seed=0):
    g = torch.Generator().manual_seed(seed)
    N = N or (model.pred_len if model.is_prefix_comp else 60)
    lengths = torch.tensor(lengths or [N] * B)
    x = torch.randn(B, 263, 1, N, generator=g)
    y = {"mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N), "lengths": lengths,
         "text_embed": torch.randn(1, B, 512, generator=g)}
    if model.is_prefix_comp:
        y["prefix"] = torch.randn(B, 263, 1, model.context_len, generator=g)
    return x, torch.tensor([1, 30, 45][:B]), y


def record_keyframes(model):
    """The keyframe mask handed to the transformer at every call (None after each call)."""
    seen = []
    tr = model._smdm_state.family_state.transformer
    orig = tr.set_plan
    tr.set_plan = lambda p: (seen.append(None if p is None else p.mask.clone()), orig(p))
    return seen


@pytest.mark.parametrize("name", VARIANTS)
def test_detects_variant(name):
    assert detect_variant(tiny(**VARIANTS[name])).name == name


def test_unknown_model_is_a_clear_error():
    with pytest.raises(TypeError, match=r"missing attribute\(s\) \['input_process', 'output_process', 'arch'\]"):
        sparsify(nn.Linear(3, 3), SparseConfig())
    m = tiny()
    m.arch = "gru"
    with pytest.raises(TypeError, match="gru"):
        sparsify(m, SparseConfig())


def test_disabled_flag_leaves_model_bit_for_bit():
    model = tiny()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    ref = copy.deepcopy(model).eval()
    out = sparsify(model, SparseConfig(enabled=False))
    assert out is model and not is_sparse(model)
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items()) and len(before) == len(model.state_dict())
    x, t, y = batch(model)
    with torch.no_grad():
        assert torch.equal(model.eval()(x, t, y), ref(x, t, y))


@pytest.mark.parametrize("fsq", [False, True], ids=["mha", "fsq"])
@pytest.mark.parametrize("name", VARIANTS)
def test_all_keyframes_equals_dense(name, fsq):
    """With FSQ keys the dense reference has the same FSQ attention (quantised before the copy)."""
    dense = tiny(**VARIANTS[name]).eval()
    if fsq:
        assert quantize_attention_keys(dense, SparseConfig().fsq_levels) > 0
    model = sparsify(copy.deepcopy(dense), SparseConfig(reduction=0.0, lipschitz=False, mask_noise=0.0,
                                                        fsq=fsq)).eval()
    N = 40 if name == "dip" else 60
    x, t, y = batch(dense, N=N, lengths=[N, N - 7, N // 2])
    with torch.no_grad():
        out, ref = model(x, t, dict(y)), dense(x, t, dict(y))
    valid = y["mask"].expand_as(out)
    assert (out - ref)[valid].abs().max() < 1e-5


@pytest.mark.parametrize("name", VARIANTS)
def test_transformer_sees_only_keyframes(name):
    model = sparsify(tiny(**VARIANTS[name]), SparseConfig(reduction=0.8, lipschitz=False)).eval()
    tr = model._smdm_state.family_state.transformer
    tokens = []
    tr.layers[0].register_forward_pre_hook(lambda m, a, kw=None: tokens.append(a[0].shape[0]))
    seen = record_keyframes(model)
    x, t, y = batch(model)
    with torch.no_grad():
        model(x, t, y)
    prefix = model.context_len if model.is_prefix_comp else 0
    N = x.shape[-1]
    K = max(2, round(0.2 * N))
    lead = 1 if (model.arch == "trans_enc" or model.emb_trans_dec) else 0
    assert seen[0].sum(1).tolist() == [K + prefix] * 3
    if prefix:
        assert seen[0][:, :prefix].all()  # DiP context frames stay dense
    assert tokens == [lead + prefix + K]
    assert seen[-1] is None  # cleared after the call


def test_sampling_schedule_uniform_early_vw_late():
    cfg = SparseConfig(reduction=0.8, gamma=0.1, diffusion_steps=50, lipschitz=False, dynamic_update=True)
    model = sparsify(tiny(), cfg).eval()
    seen = record_keyframes(model)
    x, _, y = batch(model, B=2)
    with torch.no_grad():
        model(x, torch.tensor([40, 40]), y)
        model(x, torch.tensor([5, 5]), y)     # the paper's t = 6 > gamma*T = 5: still uniform
        model(x, torch.tensor([4, 4]), y)     # the paper's t = 5: VW on x_t
    from smdm_plugin import select_keyframes
    from smdm_plugin.core.schedule import MaskSchedule
    uniform = select_keyframes(torch.zeros(2, 60, 1), None, 0.8, "uniform")
    vw = select_keyframes(MaskSchedule(model._smdm_state.config).features(x.squeeze(2).transpose(1, 2)), None, 0.8, "vw")
    assert torch.equal(seen[0], uniform) and torch.equal(seen[2], uniform)
    assert torch.equal(seen[4], vw) and not torch.equal(vw, uniform)
    model._smdm_state.config.dynamic_update = False
    with torch.no_grad():
        model(x + 1, torch.tensor([4, 4]), y)
    assert torch.equal(seen[6], uniform)


def test_dynamic_update_auto_follows_table_2():
    auto = dict(dynamic_update=None)
    assert not SparseConfig(diffusion_steps=50, **auto).dynamic and not SparseConfig(diffusion_steps=10, **auto).dynamic
    assert SparseConfig(diffusion_steps=100, **auto).dynamic and SparseConfig(diffusion_steps=1000, **auto).dynamic
    assert not SparseConfig(diffusion_steps=1000, prefix_frames=20, **auto).dynamic   # DiP
    assert not SparseConfig(diffusion_steps=1000).dynamic       # the default: off (measured, docs/defaults.md)
    assert SparseConfig(diffusion_steps=50, dynamic_update=True).dynamic


def test_explicit_and_forced_keyframes_are_honoured():
    model = sparsify(tiny(), SparseConfig(reduction=0.9, lipschitz=False)).eval()
    seen = record_keyframes(model)
    x, t, y = batch(model, B=2)
    explicit = torch.zeros(2, 60, dtype=torch.bool)
    explicit[:, [0, 30, 59]] = True
    forced = torch.zeros(2, 60, dtype=torch.bool)
    forced[:, 10:14] = True
    with torch.no_grad():
        model(x, t, {**y, KEYFRAMES_KEY: KeyframeRequest(mask=explicit)})
        model(x, t, with_forced(y, forced))
        model(x, t, {**y, KEYFRAMES_KEY: KeyframeRequest(mask=explicit, forced=forced)})
    assert torch.equal(seen[0], explicit)
    assert seen[2][forced].all()
    assert torch.equal(seen[4], explicit | forced)
    with pytest.raises(ValueError, match=r"y\['smdm_keyframes'\].mask must be bool \[B, N\]"):
        model(x, t, {**y, KEYFRAMES_KEY: KeyframeRequest(mask=explicit[:, :10])})
    with pytest.raises(ValueError, match=r"y\['smdm_keyframes'\].forced must be a bool tensor \[B, N\]"):
        model(x, t, with_forced(y, forced[:1]))


@pytest.mark.parametrize("key", ["keyframe_mask", "keyframe_capacity", "keyframe_forced"])
def test_the_string_keys_of_0_3_are_an_error_naming_the_request(key):
    """0.4: keyframes travel as one KeyframeRequest; an old key is refused, never ignored."""
    model = sparsify(tiny(), SparseConfig(reduction=0.9, lipschitz=False)).eval()
    x, t, y = batch(model, B=2)
    with torch.no_grad(), pytest.raises(TypeError, match=rf"y\['{key}'\] is not read since smdm-plugin 0.4: "
                                                         r"pass y\['smdm_keyframes'\] = smdm_plugin.KeyframeRequest"):
        model(x, t, {**y, key: torch.ones(2, 60, dtype=torch.bool)})
    with pytest.raises(TypeError, match=r"y\['smdm_keyframes'\] must be a smdm_plugin.KeyframeRequest, got dict"):
        model(x, t, {**y, KEYFRAMES_KEY: {"mask": None}})
    with pytest.raises(TypeError, match="KeyframeRequest.capacity must be a Python int >= 1"):
        KeyframeRequest(mask=torch.ones(2, 60, dtype=torch.bool), capacity=torch.tensor(3))
    with pytest.raises(TypeError, match="capacity is the slot count of a given mask"):
        KeyframeRequest(capacity=3)
    for bad in (-1, 1.5, True, torch.tensor(3)):
        with pytest.raises(TypeError, match="KeyframeRequest.forced_bound must be a Python int >= 0"):
            KeyframeRequest(forced=torch.ones(2, 60, dtype=torch.bool), forced_bound=bad)


def test_lipschitz_layers_swapped_and_unsparsify_restores_dense():
    dense = tiny().eval()
    model = sparsify(copy.deepcopy(dense), SparseConfig()).eval()
    assert isinstance(model.input_process.poseEmbedding, LipschitzMLP)
    assert isinstance(model.output_process.poseFinal, LipschitzMLP)
    assert "smdm_sparse_version" in model.state_dict()
    assert lipschitz_loss(model) > 0
    unsparsify(model)
    x, t, y = batch(model)
    with torch.no_grad():
        assert torch.equal(model(x, t, y), dense(x, t, y))
    assert set(model.state_dict()) == set(dense.state_dict())


def test_deepcopy_for_ema_and_already_sparse_error():
    model = sparsify(tiny(), SparseConfig()).eval()
    ema = copy.deepcopy(model)
    x, t, y = batch(model)
    with torch.no_grad():
        assert torch.equal(ema(x, t, y), model(x, t, y))
    with pytest.raises(ValueError, match="already sparse"):
        sparsify(model, SparseConfig())


def test_training_losses_use_x0_mask_and_add_lipschitz_term():
    model = tiny()
    diffusion = SimpleDiffusion(50)
    sparsify(model, SparseConfig(lipschitz_lambda=0.5, mask_noise=0.0), diffusion=diffusion)
    assert model._smdm_state.config.diffusion_steps == 50
    seen = record_keyframes(model)
    x, _, y = batch(model)
    t = torch.tensor([49, 49, 49])
    torch.manual_seed(1)
    terms = diffusion.training_losses(model, x, t, {"y": y})
    from smdm_plugin.core.schedule import MaskSchedule
    expected = MaskSchedule(model._smdm_state.config).training_mask(x.squeeze(2).transpose(1, 2), y["lengths"])
    assert torch.equal(seen[0], expected)  # from x0, not from the (pure-noise) x_t
    assert torch.allclose(terms["loss"] - terms["mse"], 0.5 * terms["lip"])
    assert KEYFRAMES_KEY not in y  # the caller's dict is not mutated


def test_sparse_training_reduces_loss_on_real_motion(hml_batch):
    x, lengths, mean, std = hml_batch
    N = x.shape[-1]
    y = {"mask": (torch.arange(N) < lengths[:, None]).view(-1, 1, 1, N), "lengths": lengths,
         "text_embed": torch.zeros(1, len(lengths), 512)}
    torch.manual_seed(0)
    model = TinyMDM(latent_dim=64, ff_size=128, num_layers=2, cond_mode="no_cond", dropout=0.0)
    diffusion = SimpleDiffusion(50)
    sparsify(model, SparseConfig(), diffusion=diffusion, mean=mean, std=std)
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    g = torch.Generator().manual_seed(0)
    losses = []
    for step in range(60):
        t = torch.randint(0, 50, (len(lengths),), generator=g)
        loss = diffusion.training_losses(model, x, t, {"y": y})["loss"].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert sum(losses[-10:]) / 10 < 0.7 * sum(losses[:10]) / 10


def test_unsparsify_turns_fsq_attention_back_into_mha_with_its_trained_weights():
    model = sparsify(tiny(), SparseConfig(fsq=True))
    fsq = [m for m in model.modules() if isinstance(m, FSQMultiheadAttention)]
    assert len(fsq) == 2
    with torch.no_grad():
        fsq[0].in_proj_weight.add_(1.0)                              # as if trained in sparse mode
    trained = fsq[0].in_proj_weight.detach().clone()
    unsparsify(model)
    attns = [m.self_attn for m in model.modules() if hasattr(m, "self_attn")]
    assert [type(a) for a in attns] == [nn.MultiheadAttention] * 2
    assert torch.equal(attns[0].in_proj_weight, trained)
    assert not any("key_down" in k for k in model.state_dict())
