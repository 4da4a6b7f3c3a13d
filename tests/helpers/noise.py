"""The mask-noise cases of the ``smdm::perturb_mask`` tests (tests/core/test_mask_noise.py) and the rule
written out (:func:`slow_perturb`), importable in a fresh interpreter too (the Triton interpreter run:
``sys.path`` gets tests/, then ``from helpers.noise import noise_cases``)."""
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


def slow_perturb(mask, lengths, u, amount, protected):
    """The noise rule written out per sample with Python lists (the reference)."""
    out = mask.clone()
    for b in range(mask.shape[0]):
        L, m = int(lengths[b]), mask[b].tolist()
        k = sum(m)
        mm = float(torch.round(torch.tensor(k, dtype=torch.float32) * torch.tensor(amount, dtype=torch.float32)))
        c = min(float(torch.floor(u[b, 0] * torch.tensor(2 * mm + 1, dtype=torch.float32))) - mm, mm)
        prot = protected[b].tolist() if protected is not None else [False] * len(m)
        if c > 0:
            cand, n = [i for i in range(L) if not m[i]], int(c)
        else:
            cand, n = [i for i in range(1, L - 1) if m[i] and not prot[i]], int(min(-c, k - 2))
        for i in sorted(cand, key=lambda i: (float(u[b, 1 + i]), i))[:n]:
            out[b, i] = not out[b, i]
    return out
