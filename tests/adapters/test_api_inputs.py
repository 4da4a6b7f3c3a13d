"""Bad arguments to the public adapters API (keyframe requests, in-betweening, text cache, text-encoder
swap): one TypeError / ValueError naming the argument, or a warning for a setting that cannot apply."""
from __future__ import annotations

import warnings

import pytest
import torch
import torch.nn as nn

from smdm_plugin import SimpleDiffusion, TinyMDM
from smdm_plugin.adapters import inbetween_sampling as ib
from smdm_plugin.adapters.request import KeyframeRequest, with_forced
from smdm_plugin.adapters.text_cache import TextEmbeddingCache, install_text_cache, remove_text_cache
from smdm_plugin.adapters.text_encoder import swap_text_encoder

D, N = 12, 10


def tiny(**kw) -> TinyMDM:
    torch.manual_seed(0)
    args = dict(njoints=D, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, num_heads=4, cond_mode="no_cond",
                clip_dim=16, dropout=0.0)
    return TinyMDM(**{**args, **kw}).eval()


def constraint(lengths=None, D_: int = D) -> ib.KeyframeConstraint:
    return ib.keyframe_constraint(torch.randn(2, N, D_, generator=torch.Generator().manual_seed(0)), [0, 4], lengths)


class MDMLikeDiffusion:
    """MDM's GaussianDiffusion.p_sample_loop signature: no imputation=, no generator=."""

    def p_sample_loop(self, model, shape, noise=None, clip_denoised=True, model_kwargs=None, progress=False):
        return model_kwargs["y"]["inpainted_motion"].clone()


class FlatEncoder(nn.Module):
    """A frozen text encoder: captions -> zeros [B, width]."""

    def __init__(self, width=8):
        super().__init__()
        self.width = width
        self.lin = nn.Linear(2, 8).requires_grad_(False)

    def forward(self, texts):
        return torch.zeros(len(texts), 8)


# --------------------------------------------------------------------------- KeyframeRequest, with_forced
@pytest.mark.parametrize("field", ["mask", "forced"])
def test_request_refuses_a_float_mask(field):
    with pytest.raises(TypeError, match=rf"KeyframeRequest.{field} must be a bool tensor \[B, N\].*float32"):
        KeyframeRequest(**{field: torch.full((2, N), 0.3)})


def test_a_request_without_keyframes_or_beyond_its_capacity_is_named_at_the_call():
    """Counts need the values: read where the call reads them (never a sync at construction), the error
    naming the request's fields."""
    from smdm_plugin import sparsify

    model = sparsify(tiny(), dict(reduction=0.5)).eval()
    x, t = torch.randn(2, D, 1, N), torch.tensor([1, 1])
    mask = torch.zeros(2, N, dtype=torch.bool)
    mask[0, [0, 5]] = True
    with pytest.raises(ValueError, match=r"KeyframePlan: every sample needs .*KeyframeRequest.mask"):
        model(x, t, {"smdm_keyframes": KeyframeRequest(mask=mask)})
    mask[1, [0, 2, 9]] = True
    with pytest.raises(ValueError, match=r"more than the capacity \(KeyframeRequest.capacity\)"):
        model(x, t, {"smdm_keyframes": KeyframeRequest(mask=mask, capacity=2)})


@pytest.mark.parametrize("y", [5, [("text", "x")]])
def test_with_forced_names_y(y):
    with pytest.raises(TypeError, match=r"^y must be a dict .* got (int|list)"):
        with_forced(y, torch.ones(2, N, dtype=torch.bool))


# --------------------------------------------------------------------------- sample_inbetween
def test_sample_inbetween_names_a_constraint_that_is_not_one():
    with pytest.raises(TypeError, match="sample_inbetween: constraint must be a KeyframeConstraint"):
        ib.sample_inbetween(tiny(), SimpleDiffusion(2), torch.randn(2, N, D))


def test_sample_inbetween_names_a_diffusion_without_p_sample_loop():
    with pytest.raises(TypeError, match="sample_inbetween: diffusion must have a p_sample_loop.*NoneType"):
        ib.sample_inbetween(tiny(), None, constraint())


def test_sample_inbetween_names_both_feature_sizes():
    c = ib.keyframe_constraint(torch.randn(2, N, 10), [0, 9])
    with pytest.raises(ValueError, match=r"constraint has D=10 features .* njoints \* nfeats = 12 \* 1 = 12"):
        ib.sample_inbetween(tiny(), SimpleDiffusion(2), c)


@pytest.mark.parametrize("kw, match", [({"generator": 5}, "generator must be a torch.Generator or None, got int"),
                                       ({"y": 5}, "y must be a dict of conditions .* got int")])
def test_sample_inbetween_names_a_bad_generator_or_y(kw, match):
    with pytest.raises(TypeError, match=f"sample_inbetween: {match}"):
        ib.sample_inbetween(tiny(), SimpleDiffusion(2), constraint(), **kw)


@pytest.mark.parametrize("key, value", [("lengths", torch.tensor([10, 10])),
                                        ("mask", torch.ones(2, 1, 1, N, dtype=torch.bool))])
def test_sample_inbetween_refuses_y_lengths_that_disagree_with_the_constraint(key, value):
    c = constraint(lengths=[5, 5])
    with pytest.raises(ValueError, match=rf"y\['{key}'\] gives lengths \[10, 10\] but the constraint's lengths "
                                         r"are \[5, 5\]"):
        ib.sample_inbetween(tiny(), SimpleDiffusion(2), c, y={key: value})
    agree = {"lengths": torch.tensor([5, 5]), "mask": (torch.arange(N) < 5).view(1, 1, 1, N).expand(2, 1, 1, N)}
    out = ib.sample_inbetween(tiny(), SimpleDiffusion(2), c, y={key: agree[key]})
    assert out.shape == (2, N, D)


def test_sample_inbetween_warns_that_a_generator_is_not_used_by_an_mdm_style_diffusion():
    with pytest.warns(UserWarning, match="sample_inbetween: generator is not used: MDMLikeDiffusion"):
        ib.sample_inbetween(tiny(), MDMLikeDiffusion(), constraint(), generator=torch.Generator())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ib.sample_inbetween(tiny(), MDMLikeDiffusion(), constraint())   # no generator: no warning


# --------------------------------------------------------------------------- install_text_cache
def test_install_text_cache_again_with_other_arguments_is_an_error():
    model = tiny(cond_mode="text", clip_dim=8, text_encoder=FlatEncoder())
    wrapped = install_text_cache(model, capacity=4)
    assert install_text_cache(model) is wrapped and install_text_cache(model, capacity=4) is wrapped
    assert install_text_cache(model, cache=wrapped.cache) is wrapped
    with pytest.raises(ValueError, match=r"a text cache of capacity 4 is already installed .* capacity=1000, "
                                         r"call remove_text_cache\(model\) first"):
        install_text_cache(model, capacity=1000)
    with pytest.raises(ValueError, match="already installed .* for another cache"):
        install_text_cache(model, cache=TextEmbeddingCache(4))
    remove_text_cache(model)
    assert install_text_cache(model, capacity=1000).cache.capacity == 1000


def test_install_text_cache_names_a_cache_that_is_not_one():
    model = tiny(cond_mode="text", clip_dim=8, text_encoder=FlatEncoder())
    with pytest.raises(TypeError, match="install_text_cache: cache must be a TextEmbeddingCache or None, got int"):
        install_text_cache(model, cache=5)
    with pytest.raises(ValueError, match=r"capacity=5 does not apply to the given cache \(its capacity is 4\)"):
        install_text_cache(model, capacity=5, cache=TextEmbeddingCache(4))


# --------------------------------------------------------------------------- swap_text_encoder
def test_swap_with_a_ready_module_warns_about_the_settings_it_ignores():
    model = tiny(cond_mode="text", clip_dim=8, text_encoder=FlatEncoder())
    with pytest.warns(UserWarning, match=r"pooling='cls', dtype=torch.float16 ignored"):
        swap_text_encoder(model, FlatEncoder(), pooling="cls", dtype=torch.float16)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        swap_text_encoder(model, FlatEncoder())                          # defaults: no warning
    assert model.clip_dim == 8


@pytest.mark.parametrize("width, error", [(True, TypeError), (8.0, TypeError), (0, ValueError), (-3, ValueError)])
def test_swap_names_a_width_that_is_not_a_positive_int(width, error):
    model = tiny(cond_mode="text", clip_dim=8, text_encoder=FlatEncoder())
    before = model.embed_text
    with pytest.raises(error, match="swap_text_encoder: encoder.width must be a positive int"):
        swap_text_encoder(model, FlatEncoder(width))
    assert model.embed_text is before                                    # nothing changed
