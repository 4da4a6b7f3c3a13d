"""Sparse mode's lifecycle and inputs: sparsify / unsparsify / re-sparsify with diffusions, in any
order and with several models; sampling masks that depend on everything they should (no cache to
go stale); bad ``y['lengths']`` / ``y['mask']`` are errors, never clamped; masks chosen while
loading data."""
import copy

import pytest
import torch

from smdm_plugin import SimpleDiffusion, SparseConfig, TinyMDM, is_sparse, sparsify, unsparsify
from smdm_plugin.adapters.request import KEYFRAMES_KEY
from smdm_plugin.families.mdm.model import keyframe_collate
from smdm_plugin.core.checks import static_mode


def tiny(**kw):
    torch.manual_seed(0)
    return TinyMDM(latent_dim=32, ff_size=64, num_layers=2, dropout=0.0, cond_mask_prob=0.0, **kw)


def batch(B=3, N=60, lengths=None, seed=0):
    g = torch.Generator().manual_seed(seed)
    lengths = torch.tensor(lengths or [N, N - 10, N // 2])
    x = torch.randn(B, 263, 1, N, generator=g)
    y = {"mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N), "lengths": lengths,
         "text_embed": torch.randn(1, B, 512, generator=g)}
    return x, y


T = torch.tensor([3, 20, 40])


def seen_masks(model):
    """Every keyframe mask the model's transformer gets (per call)."""
    seen = []
    tr = model._smdm_state.family_state.transformer
    orig = tr.set_plan
    tr.set_plan = lambda p: (p is not None and seen.append(p.mask.clone()), orig(p))
    return seen


def losses(diffusion, model, x, y):
    return diffusion.training_losses(model, x, T, {"y": dict(y)}, noise=torch.ones_like(x))


# ----------------------------------------------------------------------------- lifecycle
def test_unsparsify_restores_the_diffusion_and_trains_as_upstream():
    dense = tiny()
    reference = SimpleDiffusion(50)
    model, diffusion = tiny(), SimpleDiffusion(50)
    original = diffusion.training_losses
    sparsify(model, SparseConfig(), diffusion=diffusion)
    assert diffusion.training_losses is not original
    unsparsify(model)
    assert "training_losses" not in vars(diffusion) and not hasattr(diffusion, "_smdm_diffusion")
    assert diffusion.training_losses == original                  # the bound method again
    x, y = batch()
    assert torch.equal(losses(diffusion, model, x, y)["loss"], losses(reference, dense, x, y)["loss"])


def test_resparsify_uses_the_new_config():
    model, diffusion = tiny(), SimpleDiffusion(50)
    x, y = batch()
    sparsify(model, SparseConfig(reduction=0.8, mask_noise=0.0, lipschitz_lambda=0.5), diffusion=diffusion)
    seen = seen_masks(model)
    first = losses(diffusion, model, x, y)
    unsparsify(model)
    sparsify(model, SparseConfig(reduction=0.5, mask_noise=0.0, lipschitz_lambda=0.0), diffusion=diffusion)
    seen2 = seen_masks(model)
    second = losses(diffusion, model, x, y)
    assert seen[0].sum(1).tolist() == [12, 10, 6] and seen2[0].sum(1).tolist() == [30, 25, 15]
    assert "lip" in first and "lip" not in second


def test_one_diffusion_shared_by_two_models_trains_each_with_its_own_config():
    diffusion = SimpleDiffusion(50)
    a = sparsify(tiny(), SparseConfig(reduction=0.8, mask_noise=0.0), diffusion=diffusion)
    b = sparsify(tiny(), SparseConfig(reduction=0.5, mask_noise=0.0), diffusion=diffusion)
    sa, sb = seen_masks(a), seen_masks(b)
    x, y = batch()
    losses(diffusion, a, x, y)
    losses(diffusion, b, x, y)
    assert sa[0].sum(1).tolist() == [12, 10, 6] and sb[0].sum(1).tolist() == [30, 25, 15]
    unsparsify(a)                                                  # b still needs the wrapper
    assert "training_losses" in vars(diffusion)
    losses(diffusion, b, x, y)
    assert sb[1].sum(1).tolist() == [30, 25, 15]
    assert torch.equal(losses(diffusion, a, x, y)["loss"], losses(SimpleDiffusion(50), a, x, y)["loss"])
    unsparsify(b)
    assert "training_losses" not in vars(diffusion) and not hasattr(diffusion, "_smdm_diffusion")


def test_wrapped_models_and_ema_copies_find_their_own_state():
    diffusion = SimpleDiffusion(50)
    model = sparsify(tiny(), SparseConfig(mask_noise=0.0), diffusion=diffusion)
    ema = copy.deepcopy(model)
    assert ema._smdm_state is not model._smdm_state and ema._smdm_state.family_state.transformer is ema.seqTransEncoder
    wrapper = torch.nn.Sequential()
    wrapper.add_module("module", model)                           # a DDP-like wrapper
    x, y = batch()
    assert torch.allclose(losses(diffusion, ema, x, y)["loss"], losses(diffusion, model, x, y)["loss"])
    assert is_sparse(model) and is_sparse(ema)


# ----------------------------------------------------------------------------- sampling masks
def test_sampling_masks_follow_lengths_and_x_t_without_a_cache():
    model = sparsify(tiny(), SparseConfig(reduction=0.8, dynamic_update=True)).eval()
    seen = seen_masks(model)
    x, y = batch()
    late = torch.tensor([2, 2, 2])
    with torch.no_grad():
        model(x, late, dict(y))
        model(x, late, dict(y))                                    # classifier-free guidance: same x_t twice
        y2 = {**y, "lengths": torch.tensor([60, 30, 20]),
              "mask": (torch.arange(60) < torch.tensor([60, 30, 20])[:, None]).view(3, 1, 1, 60)}
        model(x, late, y2)                                         # same x_t (same storage), new lengths
        x.copy_(torch.randn(x.shape, generator=torch.Generator().manual_seed(9)))
        model(x, late, dict(y))                                    # same storage and shape, new values
    assert torch.equal(seen[0], seen[1])
    assert seen[2][1, 30:].sum() == 0 and seen[2][1, 29] and not torch.equal(seen[2], seen[0])
    assert not torch.equal(seen[3], seen[0])


# ----------------------------------------------------------------------------- bad lengths
@pytest.mark.parametrize("lengths,match", [
    (torch.tensor([60, 61, 30]), r"y\['lengths'\]: lengths must be <= N=60, got max 61"),
    (torch.tensor([60, 1, 30]), r"y\['lengths'\]: lengths must be >= 2, got min 1"),
    (torch.tensor([60.0, 50.0, 30.0]), r"y\['lengths'\]: lengths must be an integer tensor"),
    (torch.tensor([60, 50]), r"y\['lengths'\]: lengths must have shape \[B=3\]"),
])
def test_bad_lengths_are_errors_not_clamped(lengths, match):
    model = sparsify(tiny(), SparseConfig()).eval()
    x, y = batch()
    y = {k: v for k, v in y.items() if k != "mask"}
    with torch.no_grad(), pytest.raises(ValueError, match=match):
        model(x, T, {**y, "lengths": lengths})


def test_a_mask_with_fewer_than_two_valid_frames_is_an_error():
    model = sparsify(tiny(), SparseConfig()).eval()
    x, y = batch()
    y["mask"] = y["mask"].clone()
    y["mask"][2, ..., 1:] = False
    with torch.no_grad(), pytest.raises(ValueError, match=r"y\['mask'\] must mark at least 2 valid frames"):
        model(x, T, dict(y))


def test_on_the_static_path_bad_lengths_still_say_what_is_wrong():
    """No host read on accelerators: the check is torch._assert_async, with the same message."""
    model = sparsify(tiny(), SparseConfig()).eval()
    x, y = batch()
    y = {k: v for k, v in y.items() if k != "mask"}
    with torch.no_grad(), static_mode(), pytest.raises(RuntimeError, match=r"y\['lengths'\]: lengths must be in \[2, N=60\]"):
        model(x, T, {**y, "lengths": torch.tensor([60, 61, 30])})


# ----------------------------------------------------------------------------- masks from the loader
def test_keyframe_collate_chooses_the_masks_the_diffusion_would():
    diffusion = SimpleDiffusion(50)
    model = sparsify(tiny(), SparseConfig(mask_noise=0.0), diffusion=diffusion)
    x, y = batch()
    collate = keyframe_collate(lambda b: (x, {"y": dict(y)}), model._smdm_state.schedule)
    motion, cond = collate(None)
    seen = seen_masks(model)
    losses(diffusion, model, motion, cond["y"])                    # the loader's mask is used ...
    losses(diffusion, model, x, y)                                 # ... and equals the in-step one
    assert torch.equal(seen[0], cond["y"][KEYFRAMES_KEY].mask) and torch.equal(seen[0], seen[1])


@pytest.mark.parametrize("M", [1, 120])
def test_conditions_for_another_length_are_cut_to_the_window_with_a_warning(M):
    """MDM's sample.generate with dataset prompts and --motion_length 2: x has N=60 frames while
    y['mask'] is a one-frame placeholder (or made for 120 frames) and y['lengths'] say 120. Every
    frame of the window is valid, as in the dense model; lengths < 2 are still errors."""
    model = sparsify(tiny(), SparseConfig()).eval()
    x, y = batch()
    N = x.shape[-1]
    other = {**y, "lengths": torch.full((3,), 120), "mask": torch.ones(3, 1, 1, M, dtype=torch.bool)}
    seen = seen_masks(model)
    with torch.no_grad(), pytest.warns(UserWarning, match=rf"covers {M} frames but the motion has N={N}"):
        model(x, T, other)
    with torch.no_grad():
        model(x, T, {**y, "lengths": torch.full((3,), N), "mask": torch.ones(3, 1, 1, N, dtype=torch.bool)})
    assert torch.equal(seen[0], seen[1])
    with torch.no_grad(), pytest.warns(UserWarning), pytest.raises(ValueError, match=r"lengths must be >= 2, got min 1"):
        model(x, T, {**other, "lengths": torch.tensor([1, 120, 120])})
