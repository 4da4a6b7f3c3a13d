import numpy as np
import pytest
import torch

from smdm_plugin.core.interpolation import interpolate_keyframes


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


# ----------------------------------------------------------------------------- C¹ Catmull-Rom
def catmull_rom_reference(features, mask):
    """Per sample, per frame, per channel loops: the non-uniform Catmull-Rom (cubic Hermite,
    tangent (p[k+1] - p[k-1]) / (t[k+1] - t[k-1]), one-sided at the ends), constant outside."""
    B, N, D = features.shape
    out = np.zeros((B, N, D))
    for b in range(B):
        t = [n for n in range(N) if mask[b, n]]
        p = [features[b, n].astype(np.float64) for n in t]
        K = len(t)

        def tangent(k):
            lo, hi = max(k - 1, 0), min(k + 1, K - 1)
            return (p[hi] - p[lo]) / max(t[hi] - t[lo], 1)

        for n in range(N):
            if n <= t[0]:
                out[b, n] = p[0]
            elif n >= t[-1]:
                out[b, n] = p[-1]
            else:
                k = max(i for i in range(K) if t[i] <= n)
                if t[k] == n:
                    out[b, n] = p[k]
                    continue
                h = t[k + 1] - t[k]
                s = (n - t[k]) / h
                out[b, n] = ((2 * s**3 - 3 * s**2 + 1) * p[k] + (s**3 - 2 * s**2 + s) * h * tangent(k)
                             + (-2 * s**3 + 3 * s**2) * p[k + 1] + (s**3 - s**2) * h * tangent(k + 1))
    return out


@pytest.mark.parametrize("seed", range(6))
def test_cubic_matches_a_slow_catmull_rom_reference_and_is_exact_at_keyframes(seed):
    gen = torch.Generator().manual_seed(seed)
    B, N, D = 4, int(torch.randint(3, 50, (), generator=gen)), 3
    mask = torch.rand(B, N, generator=gen) < 0.3
    mask[torch.arange(B), torch.randint(0, N, (B,), generator=gen)] = True
    f = torch.randn(B, N, D, generator=gen, dtype=torch.float64)
    out = interpolate_keyframes(f, mask, method="cubic")
    assert np.allclose(out.numpy(), catmull_rom_reference(f.numpy(), mask.numpy()), atol=1e-5)
    assert torch.equal(out[mask], f[mask])                       # exact at keyframes
    assert torch.equal(interpolate_keyframes(f, torch.ones(B, N, dtype=torch.bool), method="cubic"), f)


def test_cubic_is_c1_where_linear_has_kinks_and_keeps_straight_lines():
    N = 40
    mask = torch.zeros(1, N, dtype=torch.bool)
    mask[0, [0, 6, 13, 21, 30, 39]] = True
    t = torch.arange(N, dtype=torch.float64)
    smooth = torch.sin(t / 5).view(1, N, 1)
    lin = interpolate_keyframes(smooth, mask)[0, :, 0]
    cub = interpolate_keyframes(smooth, mask, method="cubic")[0, :, 0]
    jump = lambda y: (y[2:] - 2 * y[1:-1] + y[:-2]).abs()[5:34].max()   # largest change of slope
    assert jump(cub) < 0.3 * jump(lin)
    assert (cub - smooth[0, :, 0]).abs().max() < (lin - smooth[0, :, 0]).abs().max()
    line = (3 * t - 1).view(1, N, 1)                              # straight lines stay straight
    assert torch.allclose(interpolate_keyframes(line, mask, method="cubic"), line, atol=1e-9)


def test_cubic_per_sample_selection_and_gradients_reach_keyframes_only():
    from smdm_plugin.core.interpolation import interpolate_keyframes_cubic

    B, N, D = 3, 30, 4
    mask = torch.zeros(B, N, dtype=torch.bool)
    mask[:, [0, 7, 19, 29]] = True
    f = torch.randn(B, N, D, dtype=torch.float64, requires_grad=True)
    which = torch.tensor([True, False, True])
    out = interpolate_keyframes_cubic(f, mask, which)
    assert torch.allclose(out[which], interpolate_keyframes(f, mask, "cubic")[which])
    assert torch.allclose(out[~which], interpolate_keyframes(f, mask)[~which])
    (out * torch.randn(B, N, D, dtype=torch.float64)).sum().backward()
    assert torch.all(f.grad[~mask] == 0)
    with pytest.raises(ValueError, match="method must be one of"):
        interpolate_keyframes(f, mask, method="spline")

