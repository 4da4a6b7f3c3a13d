"""sparsify / unsparsify of MotionDiffuse (its family) on a small stand-in with MotionTransformer's
attribute names and forward contract (smdm_plugin/families/motiondiffuse/standin.py; CI has no MotionDiffuse
checkout)."""
import argparse

import pytest
import torch

from smdm_plugin.families.motiondiffuse.standin import StandInDiffusion, StandInMotionTransformer
from smdm_plugin import SparseConfig
from smdm_plugin.core.lipschitz import LipschitzMLP, lipschitz_loss
from smdm_plugin import KeyframeRequest, with_forced
from smdm_plugin import sparsify as sparsify_motiondiffuse, unsparsify as unsparsify_motiondiffuse
from smdm_plugin.families.motiondiffuse.model import trainer_loss, training_mean_std
from smdm_plugin.families.motiondiffuse.upstream import (add_sparse_options, attach_trainer,
                                                    config_from_opt)


def _inputs(B=3, T=40, D=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, T, D, generator=g)
    t = torch.randint(0, 50, (B,), generator=g)
    length = torch.tensor([40, 31, 17])[:B]
    return x, t, length, ["a person walks", "jumps", "waves"][:B]


def _dense_cfg(**kw):
    base = dict(reduction=0.0, lipschitz=False, mask_noise=0.0, feature="raw")
    base.update(kw)
    return SparseConfig(**base)


# --------------------------------------------------------------------------- tests
def test_all_keyframes_equals_dense():
    torch.manual_seed(0)
    model = StandInMotionTransformer().eval()
    x, t, length, text = _inputs()
    with torch.no_grad():
        dense = model(x, t, length=length, text=text)
        sparsify_motiondiffuse(model, _dense_cfg())
        full = torch.ones(x.shape[:2], dtype=torch.bool)
        sparse_explicit = model(x, t, length=length, text=text, smdm_keyframes=KeyframeRequest(mask=full))
        sparse_sched = model(x, t, length=length, text=text)  # reduction 0 -> every frame
    valid = torch.arange(40)[None] < length[:, None]
    assert (sparse_explicit - dense)[valid].abs().max() < 1e-5
    assert (sparse_sched - dense)[valid].abs().max() < 1e-5


def test_sparse_tokens_and_interpolation():
    torch.manual_seed(1)
    model = StandInMotionTransformer().eval()
    sparsify_motiondiffuse(model, _dense_cfg(reduction=0.8))
    x, t, length, text = _inputs()
    seen = []
    model.temporal_decoder_blocks[0].register_forward_hook(lambda m, a, o: seen.append(a[0].shape[1]))
    mask = torch.zeros(3, 40, dtype=torch.bool)
    mask[:, [0, 10, 16]] = True
    with torch.no_grad():
        out = model(x, t, length=length, text=text, smdm_keyframes=KeyframeRequest(mask=mask))
    assert seen == [3]  # only keyframe tokens went through the decoder blocks
    # hidden features are linear between keyframes, and `out` is linear (no Lipschitz MLP here)
    mid = out[:, 5]
    assert torch.allclose(mid, 0.5 * (out[:, 0] + out[:, 10]), atol=1e-5)
    # forced frames are honoured
    forced = torch.zeros(3, 40, dtype=torch.bool)
    forced[:, 7] = True
    with torch.no_grad():
        model(x, t, length=length, text=text, **with_forced({}, forced))
    last = model._smdm_state.family_state.last_mask
    assert bool(last[:, 7].all())
    assert not bool(last[2, 17:].any())  # nothing beyond the valid length (17)
    with torch.no_grad(), pytest.raises(TypeError, match=r"model_kwargs\['keyframe_forced'\] is not read since "
                                                         r"smdm-plugin 0.4"):
        model(x, t, length=length, text=text, keyframe_forced=forced)   # 0.3's keyword: refused, not ignored
    with torch.no_grad(), pytest.raises(TypeError, match=r"unexpected keyword argument\(s\) \['forced'\]"):
        model(x, t, length=length, text=text, forced=forced)


def test_lipschitz_swap_and_unsparsify():
    torch.manual_seed(2)
    model = StandInMotionTransformer()
    old_in, old_out = model.joint_embed, model.out
    sparsify_motiondiffuse(model, SparseConfig(feature="raw", lipschitz_layers=2))
    assert isinstance(model.joint_embed, LipschitzMLP) and isinstance(model.out, LipschitzMLP)
    assert "smdm_sparse_version" in model.state_dict()
    assert SparseConfig().fsq and model._smdm_state.config.fsq is False      # linear attention: no FSQ keys
    x, t, length, text = _inputs()
    out = model(x, t, length=length, text=text)
    assert out.shape == x.shape
    # the state dict round-trips into a fresh sparse model (strict, as DDPMTrainer.load does)
    other = sparsify_motiondiffuse(StandInMotionTransformer(), SparseConfig(feature="raw"))
    other.load_state_dict(model.state_dict(), strict=True)
    unsparsify_motiondiffuse(model)
    assert model.joint_embed is old_in and model.out is old_out
    assert "forward" not in model.__dict__ and "smdm_sparse_version" not in model.state_dict()


def upstream_backward_g(fake_noise, real_noise, src_mask):
    """MotionDiffuse's DDPMTrainer.backward_G loss: per-frame MSE weighted by src_mask [B, T]."""
    err = ((fake_noise - real_noise) ** 2).mean(dim=-1)
    return (err * src_mask).sum() / src_mask.sum()


class Trainer:
    """What trainer_loss reads of a DDPMTrainer after forward()."""

    def __init__(self, encoder, diffusion, opt=None):
        self.encoder, self.diffusion, self.opt = encoder, diffusion, opt

    def forward(self, x, t, length, text, noise=None):
        out = self.diffusion.training_losses(model=self.encoder, x_start=x, t=t,
                                             model_kwargs={"text": text, "length": length}, noise=noise)
        self.real_noise, self.fake_noise = out["target"], out["pred"]
        self.src_mask = self.encoder.generate_src_mask(x.shape[1], length)
        return out


def test_dense_loss_is_upstream_s_own():
    """Upstream's trainer already excludes padded frames (src_mask): nothing to fix in dense mode."""
    torch.manual_seed(4)
    tr = Trainer(StandInMotionTransformer(), StandInDiffusion())
    x, t, length, text = _inputs()
    noise = torch.randn_like(x)
    tr.forward(x, t, length, text, noise)
    up = upstream_backward_g(tr.fake_noise, tr.real_noise, tr.src_mask)
    assert trainer_loss(tr, up) is up
    noise2 = noise.clone()
    noise2[~(torch.arange(40)[None] < length[:, None])] += 100.0  # padded frames' targets
    tr.forward(x, t, length, text, noise2)
    assert torch.allclose(upstream_backward_g(tr.fake_noise, tr.real_noise, tr.src_mask), up, atol=1e-6)


def test_sparse_loss_counts_interpolated_frames_not_padded_ones():
    torch.manual_seed(3)
    model = StandInMotionTransformer()
    diff = StandInDiffusion()
    sparsify_motiondiffuse(model, _dense_cfg(reduction=0.8, lipschitz=True, lipschitz_lambda=0.0),
                           diffusion=diff)
    tr = Trainer(model, diff)
    x, t, length, text = _inputs()
    noise = torch.randn_like(x)
    valid = torch.arange(40)[None] < length[:, None]

    def loss_with(target_noise):
        torch.manual_seed(0)  # same keyframes (mask noise) every time
        out = tr.forward(x, t, length, text, target_noise)
        return trainer_loss(tr, upstream_backward_g(tr.fake_noise, tr.real_noise, tr.src_mask)), out

    base, out = loss_with(noise)
    keys = out["keyframe_mask"]
    assert not (keys & ~valid).any()  # keyframes are valid frames only
    padded = noise.clone()
    padded[~valid] += 100.0
    assert torch.allclose(loss_with(padded)[0], base, atol=1e-5)  # padded frames: out of the loss
    between = (valid & ~keys).nonzero()[0]  # a valid, interpolated frame
    moved = noise.clone()
    moved[between[0], between[1]] += 1.0
    assert not torch.allclose(loss_with(moved)[0], base)  # interpolated frames: in the loss


def test_training_losses_passes_keyframes_and_keeps_upstream_terms():
    torch.manual_seed(5)
    model = StandInMotionTransformer()
    diff = StandInDiffusion()
    x, t, length, text = _inputs()
    noise = torch.randn_like(x)
    plain = diff.training_losses(model, x, t, {"text": text, "length": length}, noise=noise)
    sparsify_motiondiffuse(model, _dense_cfg(reduction=0.8, mask_noise=0.0), diffusion=diff)
    terms = diff.training_losses(model, x, t, {"text": text, "length": length}, noise=noise)
    assert set(terms) == set(plain) | {"keyframe_mask"}
    keys = terms["keyframe_mask"]
    assert torch.equal(keys, model._smdm_state.family_state.last_mask)  # the mask the model ran on
    counts = keys.sum(1)
    want = torch.tensor([max(2, round(0.2 * int(L))) for L in length])
    assert torch.equal(counts, want)
    torch.testing.assert_close(terms["mse"], ((noise - terms["pred"]) ** 2).mean(dim=(1, 2)))  # upstream's


def test_trainer_loss_adds_lipschitz_and_keyframe_only_ablation(tmp_path):
    import argparse

    parser = argparse.ArgumentParser()
    add_sparse_options(parser)
    add_sparse_options(parser)  # idempotent
    assert "--masked_loss" not in parser._option_string_actions  # the no-op option is gone
    opt = parser.parse_args(["--sparse", "--sparse_feature", "raw", "--sparse_reduction", "0.5",
                             "--sparse_lipschitz_lambda", "0.01"])
    opt.is_train, opt.model_dir = True, str(tmp_path / "model")
    tr = Trainer(StandInMotionTransformer(), StandInDiffusion(), opt)
    attach_trainer(tr)
    assert (tmp_path / "model" / "sparse_config.json").exists()
    x, t, length, text = _inputs()
    tr.forward(x, t, length, text)
    up = upstream_backward_g(tr.fake_noise, tr.real_noise, tr.src_mask)
    loss = trainer_loss(tr, up)
    assert torch.allclose(loss, up + 0.01 * lipschitz_loss(tr.encoder))
    loss.backward()
    assert tr.encoder.joint_embed.net[0].parametrizations.weight.original.grad is not None
    # interpolate=False: the loss over valid keyframes only (reference: a loop over frames)
    state = tr.encoder._smdm_state
    state.config = state.config.replace(interpolate=False, lipschitz_lambda=0.0)
    with torch.no_grad():
        tr.forward(x, t, length, text)
        got = trainer_loss(tr, upstream_backward_g(tr.fake_noise, tr.real_noise, tr.src_mask))
    keys = tr.encoder._smdm_state.family_state.last_mask
    errs = [((tr.fake_noise[b, i] - tr.real_noise[b, i]) ** 2).mean() for b in range(3) for i in range(40)
            if keys[b, i] and i < int(length[b])]
    assert torch.allclose(got, torch.stack(errs).mean(), atol=1e-6)


def test_config_from_get_opt_strings(tmp_path):
    opt = argparse.Namespace()
    # what MotionDiffuse's get_opt makes of opt.txt lines
    opt.sparse, opt.sparse_reduction, opt.sparse_lipschitz_lambda = True, 0.8, "1e-06"
    opt.sparse_fsq_levels, opt.sparse_lipschitz_hidden = "[8, 8, 8, 5, 5, 5]", "None"
    opt.sparse_diffusion_steps, opt.is_train, opt.model_dir = 1000, False, str(tmp_path)
    cfg = config_from_opt(opt)
    assert cfg.enabled and cfg.lipschitz_lambda == 1e-6 and cfg.fsq_levels == (8, 8, 8, 5, 5, 5)
    SparseConfig(reduction=0.5).save(str(tmp_path))
    # opt.txt and sparse_config.json describe the same model: a disagreement is an error, not ignored
    with pytest.raises(ValueError, match=r"opt.txt and .*sparse_config.json disagree: reduction: opt.txt 0.8, "
                                         r"sparse_config.json 0.5; lipschitz_lambda"):
        config_from_opt(opt)
    opt.sparse_reduction, opt.sparse_lipschitz_lambda = "0.5", "0.0"
    assert config_from_opt(opt).reduction == 0.5  # the saved config (it agrees)


def test_training_mean_std():
    mean, std = training_mean_std([0.0] * 263, [1.0] * 263, feat_bias=25)
    assert std[0] == pytest.approx(0.04) and std[4] == 1.0 and std[-1] == pytest.approx(0.04)
