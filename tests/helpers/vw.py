"""The VW test cases (:func:`cases`) and the heap reference on a batch (:func:`reference_mask`): the
``smdm::vw_keyframes`` tests (tests/core/test_vw_op.py) and the training mask's (tests/core/test_vw_perturb.py,
also in a fresh interpreter: :func:`torch_case`)."""
from __future__ import annotations

import numpy as np
import torch

from smdm_plugin.core.selection import keyframe_count, vw_reference


def reference_mask(X, lengths, counts, forced=None, active=None):
    B, N, _ = X.shape
    out = np.zeros((B, N), dtype=bool)
    for b in range(B):
        if active is not None and not active[b]:
            continue
        L = int(lengths[b])
        f = None if forced is None else forced[b, :L]
        out[b, vw_reference(X[b, :L], int(counts[b]), f)] = True
    return out


def cases(seed):
    """(X [B, N, F] float32, lengths, counts, forced or None, active or None): random walks,
    ties (integer-valued), constant motion, every length 2..N, forced frames, inactive rows."""
    rng = np.random.default_rng(seed)
    B, N, F = 6, int(rng.integers(2, 48)), int(rng.integers(1, 7))
    X = rng.standard_normal((B, N, F)).cumsum(1).astype(np.float32)
    kind = seed % 4
    if kind == 1:
        X = np.round(X)                                    # many exact ties
    elif kind == 2:
        X[:] = 0.0                                         # constant motion: every key is 0
        X[..., -1] = np.arange(N) * 0.1                    # (the frame-index column)
    lengths = rng.integers(2, N + 1, B)
    lengths[0] = N
    red = float(rng.uniform(0.0, 0.95))
    counts = np.array([keyframe_count(int(L), red) for L in lengths])
    forced = None
    if kind == 3:
        forced = rng.random((B, N)) < 0.15
    active = rng.random(B) < 0.8 if seed % 5 == 0 else None
    return X, lengths, counts, forced, active


#: the mask-noise amounts the training-mask tests run
AMOUNTS = (0.1, 0.5, 1.0)


def torch_case(seed):
    """A VW case as tensors (active rows dropped: training has none) with ``[B, N + 1]`` uniforms,
    some tied."""
    X, L, K, f, _ = cases(seed)
    u = torch.rand(X.shape[0], X.shape[1] + 1, generator=torch.Generator().manual_seed(seed))
    u[:, 1:5] = u[:, 1:2]
    return (torch.from_numpy(X), torch.from_numpy(L).long(), torch.from_numpy(K).long(),
            None if f is None else torch.from_numpy(f)), u
