"""Batched Visvalingam–Whyatt on the CPU, in numpy (the ``cpu`` kernel of ``smdm::vw_keyframes``).

One removal per step for every sample that still has points to remove; samples are sorted by
their removal count so that the active ones are always a leading slice (no masking, no idle rows).
Each step is a handful of numpy calls on ``[a, 4, F]`` gathers: the removed point's two neighbours
get their keys recomputed from the four live points around them, in float64.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

_CHUNK = 8  # samples per chunk for the initial keys (bounded float64 temporaries)


def vw_numpy(X: np.ndarray, lengths: np.ndarray, counts: np.ndarray,
             forced: Optional[np.ndarray] = None, active: Optional[np.ndarray] = None) -> np.ndarray:
    """Keyframe mask ``[B, N]`` bool.

    Args:
        X: features ``[B, N, F]`` (float32 or float64; keys are computed in float64).
        lengths: ``[B]`` valid frames (2 <= L <= N). counts: ``[B]`` frames to keep.
        forced: optional ``[B, N]`` bool, frames that are never removed (they count towards the
            kept frames; a sample keeps ``max(count, protected frames)``).
        active: optional ``[B]`` bool; inactive samples get an all-False row and no work.
    """
    B, N, F = X.shape
    out = np.zeros((B, N), dtype=bool)
    rows = np.arange(B) if active is None else np.flatnonzero(active)
    if rows.size == 0 or N == 0:
        return out
    idx = np.arange(N)
    L = np.asarray(lengths, dtype=np.int64)[rows]
    K = np.asarray(counts, dtype=np.int64)[rows]
    prot = (idx[None] == 0) | (idx[None] >= (L - 1)[:, None])
    if forced is not None:
        prot = prot | np.asarray(forced, dtype=bool)[rows]
    valid = idx[None] < L[:, None]
    nrem = np.maximum(0, L - np.maximum(K, (prot & valid).sum(1)))
    order = np.argsort(-nrem, kind="stable")
    rows, L, nrem, prot = rows[order], L[order], nrem[order], prot[order]
    A = rows.size

    key = np.full((A, N), np.inf)
    if N > 2:
        dbuf = np.empty((min(_CHUNK, A), N - 1, F))
        for c0 in range(0, A, _CHUNK):
            r = rows[c0:c0 + _CHUNK]
            d = dbuf[:len(r)]
            np.subtract(X[r, 1:], X[r, :-1], out=d, dtype=np.float64)
            e = np.einsum("bnf,bnf->bn", d, d)                          # |x_{i+1} - x_i|^2
            g = np.einsum("bnf,bnf->bn", d[:, 1:], d[:, :-1])           # (x_{i+1}-x_i).(x_i-x_{i-1})
            key[c0:c0 + len(r), 1:-1] = np.maximum(e[:, 1:] * e[:, :-1] - g * g, 0.0)
    key[prot] = np.inf
    steps = int(nrem.max())
    if steps:
        kf, pf = key.reshape(-1), prot.reshape(-1)
        Xf = X.reshape(B * N, F)
        prev = np.arange(A * N) - 1                                     # flat indices, this order
        nxt = np.arange(A * N) + 1
        base = np.arange(A) * N
        shift = (rows - np.arange(A)) * N                               # this order -> X's rows
        active_at = np.searchsorted(-nrem, -np.arange(1, steps + 1), side="right")
        last = B * N - 1
        for s in range(steps):
            a = active_at[s]
            r = key[:a].argmin(1)                                       # first minimum: lowest frame
            r += base[:a]
            p, n = prev[r], nxt[r]
            nxt[p] = n
            prev[n] = p
            kf[r] = np.inf
            q = np.stack((prev[p], p, n, nxt[n]), 1)
            q += shift[:a, None]
            np.clip(q, 0, last, out=q)                                  # ends' outer neighbours: unused
            P = Xf[q].astype(np.float64)                                # [a, 4, F]
            d = P[:, 1:] - P[:, :-1]
            e = np.einsum("bkf,bkf->bk", d, d)
            g = np.einsum("bkf,bkf->bk", d[:, 1:], d[:, :-1])
            new = e[:, 1:] * e[:, :-1]
            new -= g * g
            np.maximum(new, 0.0, out=new)
            pn = q[:, 1:3] - shift[:a, None]
            new[pf[pn]] = np.inf                                        # protected keys stay inf
            kf[pn] = new
    keep = ((key < np.inf) | prot) & (idx[None] < L[:, None])
    out[rows] = keep
    return out
