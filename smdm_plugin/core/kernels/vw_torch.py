"""Batched Visvalingam–Whyatt in plain torch ops, for any device (the portable kernel of
``smdm::vw_keyframes``: used where no dedicated kernel exists, e.g. CUDA without Triton).

One removal per step for every sample, ``max(removals)`` steps, each a fixed handful of small ops
on ``[B, <=10]`` index tensors. Bookkeeping uses flat indices ``b * N + i`` into one long table
(sections: prev, next, key write slot, identity) read with ``take`` and written with ``put_``; keys
live in a flat ``[B*N + 1]`` tensor whose last element is a trash slot for writes that must not land
(protected frames: endpoints, padding, forced). A sample that has removed enough points gets key
``-inf`` at its frame 0, so its later steps pick frame 0 and only rewrite unchanged values. Reads the
removal counts on the host once per call (a device sync on accelerators).
"""
from __future__ import annotations

from typing import Dict, List, Optional

import torch


def work_dtype(device: torch.device) -> torch.dtype:
    """Keys are float64, except on MPS (no float64 there)."""
    return torch.float32 if device.type == "mps" else torch.float64


def vw_torch(features: torch.Tensor, lengths: torch.Tensor, counts: torch.Tensor,
             forced: Optional[torch.Tensor] = None, active: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Keyframe mask ``[B, N]`` bool; arguments as :func:`smdm_plugin.core.kernels.vw.vw_keyframes`."""
    device = features.device
    B, N, Fd = features.shape
    if B == 0 or N == 0:
        return torch.zeros(B, N, dtype=torch.bool, device=device)
    wd = work_dtype(device)
    BN = B * N
    idx = torch.arange(N, device=device)
    L_t = lengths.to(device=device, dtype=torch.long)
    last = (L_t - 1)[:, None]
    protected = (idx[None] == 0) | (idx[None] >= last)                 # endpoints + padding
    if forced is not None:
        protected = protected | forced.to(device=device, dtype=torch.bool)
    nprot = (protected & (idx[None] < L_t[:, None])).sum(1)
    nrem_t = (L_t - torch.maximum(counts.to(device=device, dtype=torch.long), nprot)).clamp_min(0)
    if active is not None:
        nrem_t = torch.where(active.to(device=device, dtype=torch.bool), nrem_t, 0)
    nrem: List[int] = nrem_t.tolist()
    steps = max(nrem)

    base = (torch.arange(B, device=device) * N)[:, None]               # [B, 1]
    flat = base + idx[None]                                            # [B, N]
    prev = base + (idx[None] - 1).clamp_min(0)
    nxt = base + torch.minimum(idx[None] + 1, last)
    write = torch.where(protected, torch.full_like(flat, BN), flat)    # BN = trash slot
    T = torch.empty(4 * BN, dtype=torch.long, device=device)
    for k, sec in enumerate((prev, nxt, write, flat)):
        T[k * BN:(k + 1) * BN].view(B, N).copy_(sec)

    area = torch.full((BN + 1,), float("inf"), dtype=wd, device=device)
    area2 = area[:BN].view(B, N)
    X64 = features.to(wd)
    if N > 2:
        d = X64[:, 1:] - X64[:, :-1]                                   # [B, N-1, F]
        dd = (d * d).sum(-1)
        dots = (d[:, 1:] * d[:, :-1]).sum(-1)
        x = (dd[:, 1:] * dd[:, :-1] - dots * dots).clamp_min_(0)
        area2[:, 1:-1] = x.masked_fill_(protected[:, 1:-1], float("inf"))

    # per step: v = (p, n, p | p, n, p, p, n, n | write slot of r); u = (Wp, Wn, pp, p, n, nn)
    s0, s1, s2, s3 = 0, BN, 2 * BN, 3 * BN
    boff1 = base.T + torch.tensor([s0, s1, s0, s0, s1, s0, s0, s1, s1, s2], device=device)[:, None]
    off2 = torch.tensor([s1, s0, 0, s2, s2, s0, s3, s3, s1], device=device)[:, None]
    Xf = X64.reshape(BN, Fd)
    infs = torch.full((B,), float("inf"), dtype=wd, device=device)
    done_at: Dict[int, List[int]] = {}
    for b, n in enumerate(nrem):
        if n < steps:
            done_at.setdefault(n, []).append(b)
    done_idx = {s: torch.tensor(r, dtype=torch.long, device=device) * N for s, r in done_at.items()}
    for s in range(steps):
        if s in done_idx:
            area.index_fill_(0, done_idx[s], float("-inf"))            # frame 0 of done rows
        r = area2.argmin(1)                                            # first minimum = lowest i
        v = T.take(r + boff1)                                          # [10, B]
        w = v[:9] + off2
        T.put_(w[0:2], v[1:3])                                         # unlink r
        u = T.take(w[3:9])
        pts = Xf.index_select(0, u[2:6].reshape(-1)).view(4, B, Fd)    # pp, p, n, nn
        d = pts[1:] - pts[:-1]
        dd = (d * d).sum(-1)
        dots = (d[1:] * d[:-1]).sum(-1)
        x = dd[1:] * dd[:-1] - dots * dots
        area.put_(u[0:2], x.clamp_min_(0))
        area.put_(v[9], infs)
    keep = (area2 < float("inf")) | protected
    keep &= idx[None] < L_t[:, None]
    if active is not None:
        keep &= active.to(device=device, dtype=torch.bool)[:, None]
    return keep
