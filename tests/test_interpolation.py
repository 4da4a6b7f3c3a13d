import numpy as np
import pytest
import torch

from smdm_plugin import interpolate_keyframes


def random_mask(B, N, k, gen):
    mask = torch.zeros(B, N, dtype=torch.bool)
    for b in range(B):
        idx = torch.randperm(N - 2, generator=gen)[: k - 2] + 1
        mask[b, idx] = True
        mask[b, 0] = mask[b, N - 1] = True
    return mask


def numpy_reference(features, mask):
    """np.interp per sample and channel: the obviously correct version."""
    B, N, D = features.shape
    out = np.zeros((B, N, D))
    for b in range(B):
        kf = np.nonzero(mask[b])[0]
        for d in range(D):
            out[b, :, d] = np.interp(np.arange(N), kf, features[b, kf, d])
    return out


def test_reproduces_piecewise_linear_signals_exactly():
    gen = torch.Generator().manual_seed(1)
    B, N, D = 5, 60, 7
    mask = random_mask(B, N, 12, gen)
    knots = torch.randn(B, N, D, generator=gen, dtype=torch.float64)
    truth = torch.from_numpy(numpy_reference(knots.numpy(), mask.numpy()))
    garbage = torch.where(mask.unsqueeze(-1), truth, torch.randn(B, N, D, dtype=torch.float64) * 100)
    out = interpolate_keyframes(garbage, mask)
    assert torch.allclose(out, truth, atol=1e-12)
    assert torch.equal(out[mask], truth[mask])  # exact at keyframes


def test_matches_reference_with_constant_ends_and_any_mask():
    gen = torch.Generator().manual_seed(2)
    B, N, D = 8, 40, 3
    mask = torch.rand(B, N, generator=gen) < 0.2
    mask[:, 5] = True  # at least one per row, keyframes not at the ends
    f = torch.randn(B, N, D, generator=gen)
    out = interpolate_keyframes(f, mask).numpy()
    assert np.allclose(out, numpy_reference(f.numpy(), mask.numpy()), atol=1e-5)


def test_gradients_reach_keyframes_only():
    B, N, D = 3, 30, 4
    mask = torch.zeros(B, N, dtype=torch.bool)
    mask[:, [0, 7, 19, 29]] = True
    f = torch.randn(B, N, D, requires_grad=True)
    (interpolate_keyframes(f, mask) * torch.randn(B, N, D)).sum().backward()
    assert torch.all(f.grad[~mask] == 0)
    assert torch.all(f.grad[mask].abs().sum(-1) > 0)


def test_errors_name_the_argument():
    with pytest.raises(ValueError, match="features must be"):
        interpolate_keyframes(torch.zeros(4, 5), torch.ones(4, 5, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask must be"):
        interpolate_keyframes(torch.zeros(2, 5, 3), torch.ones(2, 4, dtype=torch.bool))
    m = torch.ones(2, 5, dtype=torch.bool)
    m[1] = False
    with pytest.raises(ValueError, match="at least one keyframe"):
        interpolate_keyframes(torch.zeros(2, 5, 3), m)
