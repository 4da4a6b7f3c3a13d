"""With ``--sparse``, upstream's random draws outside the model are those of the dense run: the
integrations' sparsify (sparse layers' initial weights) must not consume the global
``torch``/``numpy``/``random`` streams, so a sampling run (MDM's ``sample.generate``, priorMDM's
DoubleTake: prompts drawn, then noise) sees the same prompts and the same noise for a seed.

The reference is the dense run itself: same seed, same upstream-like script, flag off."""
import argparse
import random
import warnings

import numpy as np
import torch

from smdm_plugin import TinyMDM
from smdm_plugin.adapters.surgery import is_sparse
from smdm_plugin.families.mdm.upstream import sparsify_mdm
from smdm_plugin.families.doubletake.upstream import sparsify_priormdm
from smdm_plugin.reference.simple_diffusion import SimpleDiffusion

STEPS, N = 10, 40


class DoubleTake_MDM(TinyMDM):  # priorMDM's class name is what selects the DoubleTake family
    pass


def _args(sparse: bool) -> argparse.Namespace:
    settings = dict(sparse_reduction=0.8, sparse_feature="raw", sparse_gamma=0.5) if sparse else {}  # (dense: none,
    return argparse.Namespace(sparse=sparse, sparse_diffusion_steps=STEPS, blend_len=5,       # or it is refused)
                              model_path="save/model.pt", **settings)


def _upstream_like_run(cls, sparsify_fn, sparse: bool, seed: int = 7):
    """What upstream's sampling scripts do, in order: fix the seed, build the model (the hook
    sparsifies it), draw prompts (numpy / random), sample from torch noise; returns every
    upstream draw and the RNG states at the end."""
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    model = cls(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=2, cond_mode="no_cond",
                dropout=0.0).eval()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sparsify_fn(model, _args(sparse), None, None)
    assert is_sparse(model) == sparse
    prompts = (np.random.choice(1000, size=3), random.sample(range(1000), 3))
    lens = torch.tensor([N, 30])
    y = {"lengths": lens, "mask": (torch.arange(N)[None] < lens[:, None]).view(2, 1, 1, N)}
    if cls is DoubleTake_MDM:  # first take: the handshake frames are forced keyframes
        y["is_transition"] = torch.zeros(2, N)
        y["is_transition"][0, 24:30] = 1
        y["is_transition"][1, :6] = 1
    with torch.no_grad():
        sample = SimpleDiffusion(STEPS).p_sample_loop(model, (2, 8, 1, N), {"y": y})
    after = (torch.randn(4), np.random.rand(4), random.random())
    return prompts, sample, after, torch.get_rng_state(), np.random.get_state()[1], random.getstate()


def _check_same_stream(cls, sparsify_fn):
    dense = _upstream_like_run(cls, sparsify_fn, sparse=False)
    sparse = _upstream_like_run(cls, sparsify_fn, sparse=True)
    for a, b in zip(dense[0], sparse[0]):
        assert np.array_equal(a, b)                      # same prompts
    assert torch.equal(dense[2][0], sparse[2][0])        # same torch draws after the run
    assert np.array_equal(dense[2][1], sparse[2][1]) and dense[2][2] == sparse[2][2]
    assert torch.equal(dense[3], sparse[3])
    assert np.array_equal(dense[4], sparse[4]) and dense[5] == sparse[5]
    assert torch.isfinite(sparse[1]).all() and not torch.equal(dense[1], sparse[1])  # a sparse model ran


def test_mdm_sample_generate_rng_stream_unchanged():
    _check_same_stream(TinyMDM, sparsify_mdm)


def test_doubletake_rng_stream_unchanged():
    _check_same_stream(DoubleTake_MDM, sparsify_priormdm)


def test_sparsify_init_still_follows_the_seed():
    """The sparse layers are still drawn from the user's seed: two runs give the same weights."""
    def weights():
        torch.manual_seed(3)
        m = TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=2, cond_mode="no_cond")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sparsify_mdm(m, _args(True))
        return [p.detach().clone() for p in m.parameters()]
    a, b = weights(), weights()
    assert all(torch.equal(x, y) for x, y in zip(a, b))
