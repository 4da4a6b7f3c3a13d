"""Keyframe selection: batched Visvalingam–Whyatt (VW), heap VW reference, uniform, random, MDO;
training-time mask noise.

Shapes: ``features [B, N, F]`` (float), ``lengths [B]`` (long; None = all N valid), masks
``[B, N]`` bool (True = keyframe). A sample of valid length ``L`` keeps
``keyframe_count(L, reduction) = min(L, max(2, round((1 - reduction) * L)))`` frames, always
including frames ``0`` and ``L - 1`` and nothing at or beyond ``L``.

VW area of interior point ``p`` with live neighbours ``p_prev``, ``p_next`` (any dimension F):
``a = p_prev - p``, ``b = p_next - p``, ``area = 0.5 * sqrt(max(0, |a|²|b|² - (a·b)²))``. Points are
ranked by the key ``(2·area)² = max(0, |a|²|b|² - (a·b)²)`` (the same order; no square root, which
on CPU would use a threaded math-library call per step), computed in float64 (float32 on MPS). The
point with the smallest key is removed (ties: smallest frame index) and its two neighbours' keys
are recomputed, until ``K`` points remain.
"""
from __future__ import annotations

import heapq
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

METHODS = ("vw", "uniform", "random", "mdo")

LengthsLike = Union[torch.Tensor, Sequence[int], np.ndarray, None]


def keyframe_count(length: int, reduction: float) -> int:
    """Number of keyframes kept for a sample of valid length ``length`` (Python ``round``)."""
    return min(int(length), max(2, round((1.0 - float(reduction)) * int(length))))


# ----------------------------------------------------------------------------- validation
def _check_lengths(lengths: LengthsLike, B: int, N: int, device: torch.device, fn: str
                   ) -> Tuple[torch.Tensor, List[int]]:
    """``lengths`` as a long tensor [B] on ``device`` (None = all N) and as a list."""
    if lengths is None:
        if N < 2:
            raise ValueError(f"{fn}: N must be >= 2 frames, got N={N}")
        return torch.full((B,), N, dtype=torch.long, device=device), [N] * B
    lengths_t = torch.as_tensor(lengths if isinstance(lengths, torch.Tensor)
                                else np.asarray(lengths)).to(device=device)
    if lengths_t.dtype.is_floating_point or lengths_t.dtype == torch.bool:
        raise ValueError(f"{fn}: lengths must be an integer tensor [B={B}], "
                         f"got dtype {lengths_t.dtype}")
    lengths_t = lengths_t.long()
    if tuple(lengths_t.shape) != (B,):
        raise ValueError(f"{fn}: lengths must have shape [B={B}], got {tuple(lengths_t.shape)}")
    lens = lengths_t.tolist()
    if B and min(lens) < 2:
        raise ValueError(f"{fn}: lengths must be >= 2, got min {min(lens)}")
    if B and max(lens) > N:
        raise ValueError(f"{fn}: lengths must be <= N={N}, got max {max(lens)}")
    return lengths_t, lens


def _check(features: torch.Tensor, lengths: LengthsLike, reduction: float, fn: str,
           check_finite: bool = True) -> Tuple[torch.Tensor, torch.Tensor, List[int]]:
    """Validate inputs; returns (features, lengths [B] long on features' device, lengths list).
    ``check_finite=False`` leaves the NaN/inf check to the caller (VW does it on its own
    intermediate values)."""
    if not isinstance(features, torch.Tensor):
        features = torch.as_tensor(np.asarray(features))
    if features.dim() != 3:
        raise ValueError(f"{fn}: features must be 3-D [B, N, F], got shape {tuple(features.shape)}")
    B, N, _ = features.shape
    if not isinstance(reduction, (int, float)) or not 0.0 <= float(reduction) < 1.0:
        raise ValueError(f"{fn}: reduction must be a float in [0, 1) (fraction of frames "
                         f"dropped), got {reduction!r}")
    lengths_t, lens = _check_lengths(lengths, B, N, features.device, fn)
    if not features.dtype.is_floating_point:
        features = features.float()
    if not check_finite:
        return features, lengths_t, lens
    # one float64 reduction pass: NaN/inf anywhere in a frame makes its sum non-finite
    valid = torch.arange(N, device=features.device)[None, :] < lengths_t[:, None]
    sums = features.sum(-1, dtype=_work_dtype(features.device))
    if bool((~torch.isfinite(sums) & valid).any()):
        raise ValueError(f"{fn}: features contain NaN or inf (or values too large to sum) "
                         f"within the valid frames")
    return features, lengths_t, lens


def _work_dtype(device: torch.device) -> torch.dtype:
    return torch.float32 if device.type == "mps" else torch.float64


def _rand(shape: Tuple[int, ...], generator: Optional[torch.Generator], device: torch.device
          ) -> torch.Tensor:
    """Uniform [0, 1) float32 numbers from ``generator`` (on its device), moved to ``device``."""
    if generator is None:
        return torch.rand(shape, device=device)
    return torch.rand(shape, generator=generator, device=generator.device).to(device)


# ----------------------------------------------------------------------------- public API
def select_keyframes(features: torch.Tensor, lengths: LengthsLike = None, reduction: float = 0.8,
                     method: str = "vw", generator: Optional[torch.Generator] = None
                     ) -> torch.Tensor:
    """Keyframe mask ``[B, N]`` bool for ``features [B, N, F]``.

    ``method``: "vw" (Visvalingam–Whyatt), "uniform" (evenly spaced), "random" (endpoints plus
    random frames drawn from ``generator``), "mdo" (maximum distance optimal: the K frames incl.
    both endpoints maximising the summed Euclidean distance between consecutive keyframes).
    """
    if method not in METHODS:
        raise ValueError(f"select_keyframes: unknown method {method!r}; known: {METHODS}")
    features, lengths_t, lens = _check(features, lengths, reduction, "select_keyframes",
                                       check_finite=method != "vw")
    ks = [keyframe_count(L, reduction) for L in lens]
    with torch.no_grad():
        if features.shape[0] == 0:
            return torch.zeros(features.shape[:2], dtype=torch.bool, device=features.device)
        if method == "vw":
            return _vw_batched(features.detach(), lens, ks)
        k_t = torch.tensor(ks, dtype=torch.long, device=features.device)
        if method == "uniform":
            return _uniform(lengths_t, k_t, features.shape[1])
        if method == "random":
            return _random(lengths_t, k_t, features.shape[1], generator)
        return _mdo(features.detach(), lengths_t, lens, ks)


def _vw_batched(features: torch.Tensor, lens: List[int], ks: List[int]) -> torch.Tensor:
    """Batched VW: one removal per step for every sample, ``max(L - K)`` steps, each a fixed
    handful of small ops on ``[B, ≤10]`` index tensors (no host syncs). Bookkeeping uses flat
    indices ``b * N + i`` into one long table (sections: prev, next, area write slot,
    identity) read with ``take`` and written with ``put_``; keys live in a flat ``[B*N + 1]``
    tensor whose last element is a trash slot for writes that must not land (endpoints,
    padding). A sample that has removed enough points gets key ``-inf`` at its frame 0, so its
    later steps pick frame 0 and only rewrite unchanged values."""
    device = features.device
    B, N, Fd = features.shape
    wd = _work_dtype(device)
    BN = B * N
    L_t = torch.tensor(lens, dtype=torch.long, device=device)
    nrem = [L - k for L, k in zip(lens, ks)]
    steps = max(nrem)

    idx = torch.arange(N, device=device)
    base = (torch.arange(B, device=device) * N)[:, None]               # [B, 1]
    last = (L_t - 1)[:, None]
    protected = (idx[None] == 0) | (idx[None] >= last)                 # endpoints + padding
    flat = base + idx[None]                                            # [B, N]
    prev = base + (idx[None] - 1).clamp_min(0)
    nxt = base + torch.minimum(idx[None] + 1, last)
    write = torch.where(protected, torch.full_like(flat, BN), flat)    # BN = trash slot
    T = torch.empty(4 * BN, dtype=torch.long, device=device)          # filled section-wise:
    for k, sec in enumerate((prev, nxt, write, flat)):                 # small ops stay serial
        T[k * BN:(k + 1) * BN].view(B, N).copy_(sec)

    # initial keys (2·area)², in batch chunks of <= 32768 elements: small float64 temporaries
    # and no intra-op thread pool (costly on a loaded CPU); same arithmetic as the steps below
    area = torch.full((BN + 1,), float("inf"), dtype=wd, device=device)
    area2 = area[:BN].view(B, N)
    dd_all = torch.empty(B, N - 1, dtype=wd, device=device)
    X64 = features if features.dtype == wd else torch.empty(B, N, Fd, dtype=wd, device=device)
    chunk = max(1, (1 << 15) // max(1, N * Fd))
    for c0 in range(0, B, chunk):
        X = X64[c0:c0 + chunk]
        if X64 is not features:
            X.copy_(features[c0:c0 + chunk])
        d = X[:, 1:] - X[:, :-1]                                       # [b, N-1, F]
        dd = torch.sum(d * d, -1, out=dd_all[c0:c0 + chunk])
        dots = (d[:, 1:] * d[:, :-1]).sum(-1)                          # [b, N-2]
        x = (dd[:, 1:] * dd[:, :-1] - dots * dots).clamp_min_(0)
        area2[c0:c0 + chunk, 1:-1] = x.masked_fill_(protected[c0:c0 + chunk, 1:-1], float("inf"))
    # NaN/inf in a valid frame makes |d|² of a valid pair (i, i+1 <= L-1) non-finite
    # (and an overflowing key would read as removed): reject both
    bad = (~torch.isfinite(dd_all) & (idx[None, :-1] < last)).any()
    if bool(bad | (~(area2 < float("inf")) & ~protected).any()):
        raise ValueError("select_keyframes: features contain NaN or inf (or values too large) "
                         "within the valid frames")

    # per step: v = (p, n, p | p, n, p, p, n, n | write slot of r); u = (Wp, Wn, pp, p, n, nn)
    s0, s1, s2, s3 = 0, BN, 2 * BN, 3 * BN
    # index tensors are [k, B] so that every slice used below is contiguous
    boff1 = base.T + torch.tensor([s0, s1, s0, s0, s1, s0, s0, s1, s1, s2], device=device)[:, None]
    # w = v[:9] + off2: (next[p], prev[n] | W[p], W[n], prev[p], p, n, next[n]) positions
    off2 = torch.tensor([s1, s0, 0, s2, s2, s0, s3, s3, s1], device=device)[:, None]
    Xf = X64.reshape(BN, Fd)
    infs = torch.full((B,), float("inf"), dtype=wd, device=device)
    done_at: dict = {}
    for b, n in enumerate(nrem):
        if n < steps:
            done_at.setdefault(n, []).append(b)
    done_idx = {s: torch.tensor(rows, dtype=torch.long, device=device) * N
                for s, rows in done_at.items()}
    for s in range(steps):
        if s in done_idx:
            area.index_fill_(0, done_idx[s], float("-inf"))            # frame 0 of done rows
        r = area2.argmin(1)                                            # first minimum = lowest i
        v = T.take(r + boff1)                                          # [10, B]
        w = v[:9] + off2
        T.put_(w[0:2], v[1:3])                                         # unlink r
        u = T.take(w[3:9])                                             # (untouched by the put)
        pts = Xf.index_select(0, u[2:6].view(-1)).view(4, B, Fd)       # pp, p, n, nn
        d = pts[1:] - pts[:-1]                                         # [3, B, F]
        dd = (d * d).sum(-1)                                           # [3, B]
        dots = (d[1:] * d[:-1]).sum(-1)                                # [2, B]
        x = dd[1:] * dd[:-1] - dots * dots
        area.put_(u[0:2], x.clamp_min_(0))
        area.put_(v[9], infs)

    # removed points have key +inf; kept interior points a finite key (float32 input cannot
    # overflow it in float64)
    return (area2 < float("inf")) | (idx[None] == 0) | (idx[None] == last)


def _uniform(lengths: torch.Tensor, k: torch.Tensor, N: int) -> torch.Tensor:
    """Evenly spaced: frame ``round_half_up(i * (L-1) / (K-1))`` for ``i < K`` (distinct)."""
    i = torch.arange(N, device=lengths.device)[None]
    L1, K1 = (lengths - 1)[:, None], (k - 1)[:, None]
    pos = (2 * i * L1 + K1) // (2 * K1)                                # integer round half up
    pos = torch.where(i < k[:, None], pos, pos[:, :1])                 # unused slots -> frame 0
    mask = torch.zeros(lengths.shape[0], N, dtype=torch.bool, device=lengths.device)
    return mask.scatter_(1, pos, True)


def _rank_select(cand: torch.Tensor, count: torch.Tensor, generator: Optional[torch.Generator]
                 ) -> torch.Tensor:
    """``[B, N]`` bool: ``count[b]`` random entries among ``cand[b]`` (fewer if not enough)."""
    B, N = cand.shape
    keys = torch.where(cand, _rand((B, N), generator, cand.device), 2.0)
    order = keys.argsort(1)
    rank_ok = torch.arange(N, device=cand.device)[None] < count[:, None]
    take = rank_ok & cand.gather(1, order)
    return torch.zeros_like(cand).scatter_(1, order, take)


def _random(lengths: torch.Tensor, k: torch.Tensor, N: int, generator: Optional[torch.Generator]
            ) -> torch.Tensor:
    i = torch.arange(N, device=lengths.device)[None]
    interior = (i > 0) & (i < (lengths - 1)[:, None])
    ends = (i == 0) | (i == (lengths - 1)[:, None])
    return ends | _rank_select(interior, k - 2, generator)


def _mdo(features: torch.Tensor, lengths: torch.Tensor, lens: List[int], ks: List[int]
         ) -> torch.Tensor:
    """Exact DP: f_k[j] = max_{i<j} f_{k-1}[i] + D[i, j], f_1 = [0, -inf, ...]; O(K N²)."""
    device = features.device
    B, N, _ = features.shape
    X = features.to(_work_dtype(device))
    D = torch.cdist(X, X, compute_mode="donot_use_mm_for_euclid_dist")  # [B, N, N] symmetric
    i = torch.arange(N, device=device)
    valid = i[None] < lengths[:, None]
    # Dt[b, j, i] = D[b, i, j] for i < j < L (edge i -> j), else -inf; reduce over the last dim
    ok = (i[None, :] < i[:, None])[None] & valid[:, :, None] & valid[:, None, :]
    Dt = D.masked_fill_(~ok, float("-inf"))
    kmax = max(ks)
    f = torch.full((B, N), float("-inf"), dtype=D.dtype, device=device)
    f[:, 0] = 0.0
    args = []
    buf = torch.empty_like(Dt)
    for _ in range(2, kmax + 1):
        f, a = torch.add(f[:, None, :], Dt, out=buf).max(-1)           # over i (first max)
        args.append(a)
    k_t = torch.tensor(ks, device=device)
    cur = (lengths - 1)[:, None]
    mask = torch.zeros(B, N, dtype=torch.bool, device=device).scatter_(1, cur, True)
    for k in range(kmax, 1, -1):
        prev = args[k - 2].gather(1, cur)
        cur = torch.where((k <= k_t)[:, None], prev, cur)
        mask.scatter_(1, cur, True)
    return mask


# ----------------------------------------------------------------------------- reference
def _ref_key(P: np.ndarray, i: int, j: int, k: int) -> float:
    """VW key (2·area)² of point ``j`` with neighbours ``i``, ``k``."""
    a = P[i] - P[j]
    b = P[k] - P[j]
    aa = (a * a).sum()
    bb = (b * b).sum()
    ab = (a * b).sum()
    return float(max(0.0, aa * bb - ab * ab))


def vw_reference(points: np.ndarray, k: int) -> np.ndarray:
    """Plain heap VW (heapq, lazy deletion by version) on ``points [L, F]``; sorted kept indices
    (``k`` of them, incl. 0 and L-1). Same key, float64 and tie-breaking as the batched one."""
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2:
        raise ValueError(f"vw_reference: points must be 2-D [L, F], got shape {P.shape}")
    L = P.shape[0]
    if not 2 <= k <= L:
        raise ValueError(f"vw_reference: k must be in [2, L={L}], got {k}")
    prev = list(range(-1, L - 1))
    nxt = list(range(1, L + 1))
    alive = [True] * L
    version = [0] * L
    heap = [(_ref_key(P, j - 1, j, j + 1), j, 0) for j in range(1, L - 1)]
    heapq.heapify(heap)                                  # (key, frame, version): ties -> frame
    remaining = L
    while remaining > k:
        _, j, ver = heapq.heappop(heap)
        if not alive[j] or ver != version[j]:
            continue                                     # stale entry
        alive[j] = False
        remaining -= 1
        p, n = prev[j], nxt[j]
        nxt[p], prev[n] = n, p
        for q in (p, n):
            if 0 < q < L - 1:
                version[q] += 1
                heapq.heappush(heap, (_ref_key(P, prev[q], q, nxt[q]), q, version[q]))
    return np.flatnonzero(alive)


# ----------------------------------------------------------------------------- mask noise
def perturb_mask(mask: torch.Tensor, lengths: LengthsLike = None, amount: float = 0.1,
                 generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """Training-time mask noise on ``mask [B, N]`` bool. Per sample with ``K`` keyframes, draws
    ``c`` uniformly in ``[-m, m]`` with ``m = round(amount * K)`` and adds ``c`` random frames
    (c > 0) or drops ``-c`` random interior keyframes (c < 0). Never drops frame 0 or L-1, never
    adds at/after L, never goes below 2 keyframes. Returns a new mask."""
    if not isinstance(mask, torch.Tensor) or mask.dim() != 2:
        shape = tuple(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"perturb_mask: mask must be a 2-D bool tensor [B, N], got {shape}")
    if not isinstance(amount, (int, float)) or not 0.0 <= float(amount) <= 1.0:
        raise ValueError(f"perturb_mask: amount must be a float in [0, 1] (fraction of "
                         f"keyframes), got {amount!r}")
    B, N = mask.shape
    device = mask.device
    lengths_t, _ = _check_lengths(lengths, B, N, device, "perturb_mask")
    with torch.no_grad():
        i = torch.arange(N, device=device)[None]
        valid = i < lengths_t[:, None]
        m = mask.bool() & valid
        k = m.sum(1)
        mmax = torch.round(float(amount) * k.double()).long()
        c = (_rand((B,), generator, device).double() * (2 * mmax + 1).double()).floor().long() - mmax
        interior = (i > 0) & (i < (lengths_t - 1)[:, None])
        cand = torch.where((c > 0)[:, None], valid & ~m, m & interior)
        n_drop_max = (k - 2).clamp_min(0)
        count = torch.where(c > 0, c, (-c).minimum(n_drop_max))
        return m ^ _rank_select(cand, count, generator)
