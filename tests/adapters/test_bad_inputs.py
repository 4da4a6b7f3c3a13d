"""Reliability III, the library surface: an empty batch through a sparse model is the empty output
(every attention backend), inputs without values (the meta device) and arguments that are not what
they must be (a diffusion without training_losses, NaN statistics) are one clear error that leaves
the model as it was, and the motion metrics warn when finite positions overflow."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from smdm_plugin import TinyMDM, is_sparse, sparsify
from smdm_plugin.core.attention_backends import available_backends
from smdm_plugin.core.selection import select_keyframes

BACKENDS = available_backends(torch.device("cpu"))


def tiny(arch: str = "trans_enc") -> TinyMDM:
    torch.manual_seed(0)
    return TinyMDM(latent_dim=32, ff_size=64, num_layers=1, dropout=0.0, cond_mask_prob=0.0, arch=arch)


# ------------------------------------------------------------------------------ batch 0
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("arch", ["trans_enc", "trans_dec"])
@pytest.mark.parametrize("training", [True, False])
def test_an_empty_batch_gives_the_empty_output(backend, arch, training):
    """0.4.0: "cannot reshape tensor of 0 elements" on every backend; 0.2 returned the empty output."""
    m = sparsify(tiny(arch), {"reduction": 0.8, "attention_backend": backend})
    m.train(training)
    x = torch.zeros(0, m.njoints, m.nfeats, 40, requires_grad=training)
    out = m(x, torch.zeros(0, dtype=torch.long))
    assert out.shape == (0, m.njoints, m.nfeats, 40)
    if training:
        out.sum().backward()  # the empty batch also trains (a zero gradient), as the dense model does
        assert x.grad is not None and x.grad.shape == x.shape
    # a non-empty batch after it still runs sparse
    y = m(torch.randn(2, m.njoints, m.nfeats, 40), torch.zeros(2, dtype=torch.long))
    assert y.shape == (2, m.njoints, m.nfeats, 40) and torch.isfinite(y).all()


# ------------------------------------------------------------------------------ meta device
def test_meta_lengths_are_a_clear_error():
    """0.4.0: NotImplementedError ("Cannot copy out of meta tensor") from deep inside."""
    f = torch.randn(2, 40, 6)
    with pytest.raises(ValueError, match="select_keyframes: lengths is a 'meta' tensor"):
        select_keyframes(f, torch.tensor([40, 30], device="meta"))
    with pytest.raises(ValueError, match="select_keyframes: features is a 'meta' tensor"):
        select_keyframes(f.to("meta"))


# ------------------------------------------------------------------------------ sparsify's arguments
class NotADiffusion:
    num_timesteps = 100  # a step count, but no training_losses


def test_sparsify_names_a_diffusion_argument_that_is_not_one():
    """0.4.0: a raw AttributeError ('training_losses') after the model was half converted."""
    m = tiny()
    before = {k: v.clone() for k, v in m.state_dict().items()}
    with pytest.raises(TypeError, match="sparsify: diffusion must be a Gaussian diffusion with a callable "
                                        "training_losses.*got NotADiffusion"):
        sparsify(m, {"reduction": 0.8}, diffusion=NotADiffusion())
    assert not is_sparse(m) and m.state_dict().keys() == before.keys()
    assert all(torch.equal(before[k], v) for k, v in m.state_dict().items())


@pytest.mark.parametrize("where", ["std", "mean"])
@pytest.mark.parametrize("kind", ["numpy", "tensor"])
def test_nan_statistics_are_refused(where, kind):
    """0.4.0 accepted NaN in std and silently changed how many keyframes were selected."""
    D = tiny().njoints
    stats = {"mean": np.zeros(D, np.float32), "std": np.ones(D, np.float32)}
    stats[where][7] = np.nan
    if kind == "tensor":
        stats = {k: torch.from_numpy(v) for k, v in stats.items()}
    m = tiny()
    with pytest.raises(ValueError, match=f"sparsify: {where} holds a non-finite value \\(nan at index 7\\)"):
        sparsify(m, {"reduction": 0.8, "feature": "humanml3d"} if D == 263 else {"reduction": 0.8}, **stats)
    assert not is_sparse(m)


def test_complex_statistics_are_refused():
    m = tiny()
    with pytest.raises(ValueError, match="sparsify: std must be \\[D\\] real numbers"):
        sparsify(m, {"reduction": 0.8}, mean=np.zeros(m.njoints), std=np.ones(m.njoints, np.complex64))
    assert not is_sparse(m)


def test_set_mean_std_refuses_nan_statistics_and_keeps_the_old_ones():
    from smdm_plugin import set_mean_std
    from smdm_plugin.adapters.state import get_state

    m = sparsify(tiny(), {"reduction": 0.8})
    before = get_state(m).schedule
    std = np.ones(m.njoints, np.float32)
    std[3] = np.inf
    with pytest.raises(ValueError, match="set_mean_std: std holds a non-finite value \\(inf at index 3\\)"):
        set_mean_std(m, np.zeros(m.njoints, np.float32), std)
    assert get_state(m).schedule is before
