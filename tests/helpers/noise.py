"""The mask-noise cases of the ``smdm::perturb_mask`` tests (tests/core/test_mask_noise.py), importable in a
fresh interpreter too (the Triton interpreter run: ``sys.path`` gets tests/, then ``from helpers.noise import
noise_cases``)."""
from __future__ import annotations

import torch


def noise_cases(seed, B=24, N=50):
    g = torch.Generator().manual_seed(seed)
    lengths = torch.randint(4, N + 1, (B,), generator=g)
    valid = torch.arange(N)[None] < lengths[:, None]
    mask = (torch.rand(B, N, generator=g) < 0.3) & valid
    mask[torch.arange(B), 0] = True
    mask[torch.arange(B), lengths - 1] = True
    protected = (torch.rand(B, N, generator=g) < 0.1) & mask
    u = torch.rand(B, N + 1, generator=g)
    u[:, 1:9] = u[:, 1:2]                                   # tied uniforms: the lower frame first
    return mask, lengths, u, protected
