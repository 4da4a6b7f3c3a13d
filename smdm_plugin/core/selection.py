"""Keyframe selection: Visvalingam–Whyatt (VW), uniform, random, MDO; the heap VW reference;
training-time mask noise."""
from __future__ import annotations

import heapq
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import numpy as np
import torch

from . import consts
from .checks import LengthsLike, as_lengths, host_checkable, require
from .kernels.perturb import perturb_mask_op, rank_select
from .kernels.vw import vw_keyframes
from .kernels.vw_perturb import MaskAndPlan, vw_perturb_mask, vw_perturb_plan
from .noise import CounterNoise
from .scalars import as_float
from .registry import Registry


@dataclass(frozen=True)
class Selector:
    """A registered keyframe selector.

    ``fn(features [B, N, F], lengths [B] long, counts [B] long, generator, forced [B, N] bool | None,
    active [B] bool | None) -> [B, N] bool``: inputs already checked; ``counts`` keyframes per sample
    (both ends included, ``forced`` frames count inside the budget). ``handles_forced``: ``fn`` keeps
    the forced frames itself; otherwise it is called without them, with ``counts`` reduced by the
    forced interior frames, and they are added to its mask. ``supports_active``: ``fn`` honours
    ``active`` (rows not selected at all); otherwise ``active`` is an error. ``host_sync``: it reads
    device values on the host (an ablation selector, e.g. MDO), not for the GPU hot path.
    ``with_noise``: ``fn`` and the training mask noise in one op, or None (``with_noise(features,
    lengths, counts, forced, u [B, N + 1], amount)``: :func:`perturb_checked`'s values on ``fn``'s
    mask with those uniforms; :func:`select_perturbed_checked` uses it). ``with_noise_plan``: that op
    with the keyframe plan made from its mask (``with_noise_plan(..., amount, slots, prefix) -> (mask,
    plan mask, plan tensors)``: :func:`select_perturbed_plan_checked`), or None."""

    fn: Callable[..., torch.Tensor]
    handles_forced: bool = False
    supports_active: bool = False
    host_sync: bool = False
    with_noise: Optional[Callable[..., torch.Tensor]] = None
    with_noise_plan: Optional[Callable[..., MaskAndPlan]] = None


#: the selectors by name (``SparseConfig.selector`` is validated against it)
SELECTORS: Registry[Selector] = Registry(
    "keyframe selector", holds=Selector,
    fields=dict(fn="callable", with_noise="callable or None", with_noise_plan="callable or None",
                handles_forced="a bool", supports_active="a bool", host_sync="a bool"))


def register_selector(name: str, fn: Callable[..., torch.Tensor], *, handles_forced: bool = False,
                      supports_active: bool = False, host_sync: bool = False,
                      with_noise: Optional[Callable[..., torch.Tensor]] = None,
                      with_noise_plan: Optional[Callable[..., MaskAndPlan]] = None, replace: bool = False) -> Selector:
    """Register a keyframe selector ``fn`` (signature: :class:`Selector`) under ``name``: then
    ``select_keyframes(..., method=name)`` and ``SparseConfig(selector=name)`` use it."""
    return SELECTORS.register(name, Selector(fn, handles_forced, supports_active, host_sync, with_noise,
                                             with_noise_plan), replace=replace)


def selector_names() -> Tuple[str, ...]:
    return SELECTORS.names()


def keyframe_count(length: int, reduction: float) -> int:
    """Number of keyframes kept for a sample of valid length ``length`` (Python ``round``)."""
    return min(int(length), max(2, round((1.0 - float(reduction)) * int(length))))


def keyframe_count_table(n_frames: int, reduction: float) -> torch.Tensor:
    """``[n_frames + 1]`` long: :func:`keyframe_count` of every length ``0..n_frames`` (exact Python
    arithmetic; index it with a lengths tensor on any device)."""
    return torch.tensor([keyframe_count(L, reduction) if L else 0 for L in range(n_frames + 1)], dtype=torch.long)


def uniform_table(n_frames: int, reduction: float) -> torch.Tensor:
    """``[n_frames + 1, n_frames]`` bool: row ``L`` is the uniform mask of a sample of length ``L``
    (rows 0 and 1 are empty: lengths start at 2)."""
    L = torch.arange(2, n_frames + 1)
    table = torch.zeros(n_frames + 1, n_frames, dtype=torch.bool)
    table[2:] = _uniform(L, keyframe_count_table(n_frames, reduction)[2:], n_frames)
    return table


def keyframe_counts(lengths: torch.Tensor, reduction: float) -> torch.Tensor:
    """:func:`keyframe_count` of every element of ``lengths [B]`` (long), on its device, no sync.
    Computed in float64 (the same IEEE operations as Python's ``round((1 - r) * L)``); on MPS, which
    has no float64, on the CPU."""
    if lengths.device.type == "mps":
        return keyframe_counts(lengths.cpu(), reduction).to(lengths.device)
    L = lengths.long()
    k = torch.round(L.to(torch.float64) * (1.0 - float(reduction))).long()
    return torch.minimum(L, k.clamp_min(2))


def keyframe_capacity(n_frames: int, reduction: float, mask_noise: float = 0.0, forced: int = 0) -> int:
    """The most keyframes a sample of up to ``n_frames`` frames can get: ``K`` of the longest
    sample, or its ``forced`` protected frames when more, plus what mask noise can add
    (``round(mask_noise * K)``); at most ``n_frames``. A Python int: fixed per call, so every
    tensor shape downstream is static."""
    k = max(keyframe_count(n_frames, reduction), min(int(forced), n_frames))
    return min(int(n_frames), k + int(round(float(mask_noise) * k)))


def _check_reduction(reduction: float, fn: str) -> float:
    x = as_float(reduction)
    if x is None or not 0.0 <= x < 1.0:
        raise ValueError(f"{fn}: reduction must be a float in [0, 1) (fraction of frames dropped), got {reduction!r}")
    return x


def _check(features, lengths: LengthsLike, reduction: float, fn: str
           ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Validate inputs; returns (features as float, lengths [B] long on features' device)."""
    if not isinstance(features, torch.Tensor):
        arr = np.asarray(features)
        features = torch.as_tensor(arr) if arr.dtype.kind in "biuf" else features
    if not isinstance(features, torch.Tensor) or features.dtype.is_complex:
        got = features.dtype if isinstance(features, torch.Tensor) else type(features).__name__
        raise TypeError(f"{fn}: features must be a real floating tensor [B, N, F] (integers are converted), got {got}")
    if features.dim() != 3:
        raise ValueError(f"{fn}: features must be 3-D [B, N, F], got shape {tuple(features.shape)}")
    if features.device.type == "meta":
        raise ValueError(f"{fn}: features is a 'meta' tensor (no values); pass the motion [B, N, F] on a real device")
    B, N, _ = features.shape
    _check_reduction(reduction, fn)
    lengths_t = as_lengths(lengths, B, N, features.device, fn)
    if not features.dtype.is_floating_point:
        features = features.float()
    if B and N:
        # one reduction pass: NaN/inf anywhere in a valid frame makes its sum non-finite
        valid = torch.arange(N, device=features.device)[None, :] < lengths_t[:, None]
        sums = features.detach().sum(-1, dtype=_work_dtype(features.device))
        require(torch.isfinite(sums) | ~valid,
                f"{fn}: features contain NaN or inf (or values too large to sum) within the valid frames")
    return features, lengths_t


def _check_generator(generator: object, fn: str) -> None:
    """A ``TypeError`` naming ``fn`` unless ``generator`` is what :func:`_rand` draws from."""
    if generator is not None and not isinstance(generator, (torch.Generator, CounterNoise)):
        raise TypeError(f"{fn}: generator must be a torch.Generator, a CounterNoise or None, "
                        f"got {type(generator).__name__}")


def _bool_tensor(t: object, shape: Tuple[int, ...], dims: str, what: str) -> torch.Tensor:
    """``t`` itself when it is a bool tensor of ``shape`` (axes ``dims``, e.g. ``"B, N"``); else a
    ``TypeError`` (not a bool tensor: never coerced) or ``ValueError`` (shape) naming ``what``.
    Metadata only: free on any device."""
    expected = f"{what} must be a bool tensor [{dims}]=[{', '.join(map(str, shape))}]"
    if not isinstance(t, torch.Tensor) or t.dtype != torch.bool:
        raise TypeError(f"{expected}, got {t.dtype if isinstance(t, torch.Tensor) else type(t).__name__}")
    if tuple(t.shape) != shape:
        raise ValueError(f"{expected}, got shape {tuple(t.shape)}")
    return t


def _as_bool(value: object, shape: Tuple[int, ...], dims: str, device: torch.device, what: str
             ) -> Optional[torch.Tensor]:
    """None, or ``value`` (a bool tensor, array or list) checked by :func:`_bool_tensor`, on ``device``."""
    if value is None:
        return None
    if not isinstance(value, torch.Tensor):
        arr = np.asarray(value)
        value = torch.as_tensor(arr) if arr.dtype == np.bool_ else value
    return _bool_tensor(value, shape, dims, what).to(device)


def _work_dtype(device: torch.device) -> torch.dtype:
    return torch.float32 if device.type == "mps" else torch.float64


def _rand(shape: Tuple[int, ...], generator: Optional[torch.Generator], device: torch.device
          ) -> torch.Tensor:
    """Uniform [0, 1) float32 numbers from ``generator`` (a ``torch.Generator`` on its device, or a
    :class:`~smdm_plugin.core.noise.CounterNoise`: counter-based, no RNG state), moved to
    ``device``; None: torch's global stream."""
    if generator is None:
        return torch.rand(shape, device=device)
    if isinstance(generator, CounterNoise):
        return generator.uniform(shape).to(device)
    return torch.rand(shape, generator=generator, device=generator.device).to(device)


# ----------------------------------------------------------------------------- public API
def select_keyframes(features: torch.Tensor, lengths: LengthsLike = None, reduction: float = 0.8,
                     method: str = "vw", generator: Optional[torch.Generator] = None,
                     forced: Optional[torch.Tensor] = None, active: Optional[torch.Tensor] = None
                     ) -> torch.Tensor:
    """Keyframe mask ``[B, N]`` bool for ``features [B, N, F]``.

    ``method``: "vw" (Visvalingam–Whyatt), "uniform" (evenly spaced), "random" (endpoints plus
    random frames drawn from ``generator``), "mdo" (maximum distance optimal: the K frames incl.
    both endpoints maximising the summed Euclidean distance between consecutive keyframes).
    ``forced [B, N]`` bool: frames always kept, inside the budget (VW never removes them; the other
    methods pick ``K - |forced interior frames|`` frames of their own). ``active [B]`` bool (VW
    only): rows to select at all; inactive rows come back all False and cost nothing.
    """
    if not isinstance(method, str):
        raise TypeError(f"select_keyframes: method must be a str (a selector's name), got {type(method).__name__}")
    if method not in SELECTORS:
        raise ValueError(f"select_keyframes: unknown method {method!r}; known: {SELECTORS.names()}")
    _check_generator(generator, "select_keyframes")
    features, lengths_t = _check(features, lengths, reduction, "select_keyframes")
    B, N, _ = features.shape
    forced = _as_bool(forced, (B, N), "B, N", features.device, "select_keyframes: forced")
    if active is not None and not SELECTORS.get(method).supports_active:
        raise ValueError(f"select_keyframes: active rows are not supported by method={method!r}")
    active = _as_bool(active, (B,), "B", features.device, "select_keyframes: active")
    if B == 0:
        return torch.zeros(B, N, dtype=torch.bool, device=features.device)
    counts = keyframe_counts(lengths_t, reduction)
    mask = select_checked(features, lengths_t, counts, method, generator, forced, active)
    _check_selected(mask, lengths_t, counts, active, method)
    return mask


def _check_selected(mask: torch.Tensor, lengths: torch.Tensor, counts: torch.Tensor, active: Optional[torch.Tensor],
                    method: str) -> None:
    """On the CPU only (a read of values: never a device sync): every selected row keeps frames 0
    and ``L - 1`` and at least its ``counts`` keyframes, none past ``L``; an inactive row none."""
    if not host_checkable(mask):
        return
    idx = torch.arange(mask.shape[1])[None]
    ends = (idx == 0) | (idx == (lengths - 1)[:, None])
    ok = (mask | ~ends).all(1) & ~(mask & (idx >= lengths[:, None])).any(1) & (mask.sum(1) >= counts)
    ok = ok if active is None else torch.where(active, ok, ~mask.any(1))
    if not bool(ok.all()):
        b = int((~ok).nonzero()[0])
        raise ValueError(f"select_keyframes: keyframe selector {method!r} must keep frames 0 and L - 1 and at least K "
                         f"keyframes, none past L (an inactive row: none); sample {b} (L={int(lengths[b])}, "
                         f"K={int(counts[b])}) got frames {mask[b].nonzero().flatten().tolist()}")


def select_checked(features: torch.Tensor, lengths: torch.Tensor, counts: torch.Tensor, method: str = "vw",
                   generator: Optional[torch.Generator] = None, forced: Optional[torch.Tensor] = None,
                   active: Optional[torch.Tensor] = None) -> torch.Tensor:
    """:func:`select_keyframes` on inputs already checked, with the keyframe ``counts [B]`` given
    (the hot path: validation and counts happen once per call, upstream of this)."""
    sel = SELECTORS.get(method)
    with torch.no_grad():
        if sel.handles_forced:
            return _selected(sel, method, features, lengths, counts, generator, forced, active)
        idx = torch.arange(features.shape[1], device=features.device)[None]
        k = counts
        if forced is not None:
            interior = forced & (idx > 0) & (idx < (lengths - 1)[:, None])
            k = torch.clamp_min(k - interior.sum(1), 2)               # the forced frames' share of K
        mask = _selected(sel, method, features, lengths, k, generator, None, active)
        return mask if forced is None else mask | (forced & (idx < lengths[:, None]))


def _selected(sel: Selector, method: str, features: torch.Tensor, *args: object) -> torch.Tensor:
    """``sel.fn(features, *args)``, checked to be a bool ``[B, N]`` mask (metadata: free on any device;
    the message made only for an error)."""
    mask = sel.fn(features, *args)
    if isinstance(mask, torch.Tensor) and mask.dtype == torch.bool and mask.shape == features.shape[:2]:
        return mask
    return _bool_tensor(mask, tuple(features.shape[:2]), "B, N", f"keyframe selector {method!r}: its mask")


def _uniform(lengths: torch.Tensor, k: torch.Tensor, N: int) -> torch.Tensor:
    """Evenly spaced: frame ``round_half_up(i * (L-1) / (K-1))`` for ``i < K`` (distinct)."""
    i = torch.arange(N, device=lengths.device)[None]
    L1, K1 = (lengths - 1)[:, None], (k - 1)[:, None]
    pos = (2 * i * L1 + K1) // (2 * K1)                                # integer round half up
    pos = torch.where(i < k[:, None], pos, pos[:, :1])                 # unused slots -> frame 0
    mask = torch.zeros(lengths.shape[0], N, dtype=torch.bool, device=lengths.device)
    return mask.scatter_(1, pos, True)


def _rank_select(cand: torch.Tensor, count: torch.Tensor, generator: Optional[torch.Generator],
                 u: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``[B, N]`` bool: ``count[b]`` random entries among ``cand[b]`` (fewer if not enough);
    ``u``: the ``[B, N]`` uniforms to rank by (default: drawn from ``generator``)."""
    return rank_select(cand, count, _rand(cand.shape, generator, cand.device) if u is None else u)


def _random(lengths: torch.Tensor, k: torch.Tensor, N: int, generator: Optional[torch.Generator]
            ) -> torch.Tensor:
    i = torch.arange(N, device=lengths.device)[None]
    interior = (i > 0) & (i < (lengths - 1)[:, None])
    ends = (i == 0) | (i == (lengths - 1)[:, None])
    return ends | _rank_select(interior, k - 2, generator)


def _mdo(features: torch.Tensor, lengths: torch.Tensor, k_t: torch.Tensor) -> torch.Tensor:
    """Exact DP: f_k[j] = max_{i<j} f_{k-1}[i] + D[i, j], f_1 = [0, -inf, ...]; O(K N²). Reads
    ``max K`` on the host (the number of DP rounds)."""
    device = features.device
    B, N, _ = features.shape
    X = features.to(_work_dtype(device))
    D = torch.cdist(X, X, compute_mode="donot_use_mm_for_euclid_dist")  # [B, N, N] symmetric
    i = torch.arange(N, device=device)
    valid = i[None] < lengths[:, None]
    # Dt[b, j, i] = D[b, i, j] for i < j < L (edge i -> j), else -inf; reduce over the last dim
    ok = (i[None, :] < i[:, None])[None] & valid[:, :, None] & valid[:, None, :]
    Dt = D.masked_fill_(~ok, float("-inf"))
    kmax = int(k_t.max())
    f = torch.full((B, N), float("-inf"), dtype=D.dtype, device=device)
    f[:, 0] = 0.0
    args = []
    buf = torch.empty_like(Dt)
    for _ in range(2, kmax + 1):
        f, a = torch.add(f[:, None, :], Dt, out=buf).max(-1)           # over i (first max)
        args.append(a)
    cur = (lengths - 1)[:, None]
    mask = torch.zeros(B, N, dtype=torch.bool, device=device).scatter_(1, cur, True)
    for k in range(kmax, 1, -1):
        prev = args[k - 2].gather(1, cur)
        cur = torch.where((k <= k_t)[:, None], prev, cur)
        mask.scatter_(1, cur, True)
    return mask


register_selector("vw", lambda f, lengths, k, g, forced, active: vw_keyframes(f, lengths, k, forced, active),
                  handles_forced=True, supports_active=True, with_noise=vw_perturb_mask,
                  with_noise_plan=vw_perturb_plan)
register_selector("uniform", lambda f, lengths, k, g, forced, active: _uniform(lengths, k, f.shape[1]))
register_selector("random", lambda f, lengths, k, g, forced, active: _random(lengths, k, f.shape[1], g))
register_selector("mdo", lambda f, lengths, k, g, forced, active: _mdo(f.detach(), lengths, k), host_sync=True)
#: the built-in selectors' names (the registry may hold more: :func:`selector_names`)
METHODS = ("vw", "uniform", "random", "mdo")


# ----------------------------------------------------------------------------- reference
def _ref_key(P: np.ndarray, i: int, j: int, k: int) -> float:
    """VW key (2·area)² of point ``j`` with neighbours ``i``, ``k``."""
    a = P[i] - P[j]
    b = P[k] - P[j]
    aa = (a * a).sum()
    bb = (b * b).sum()
    ab = (a * b).sum()
    return float(max(0.0, aa * bb - ab * ab))


def vw_reference(points: np.ndarray, k: int, forced: Optional[np.ndarray] = None) -> np.ndarray:
    """Plain heap VW (heapq, lazy deletion by version) on ``points [L, F]``: the sorted kept
    indices, ``max(k, protected)`` of them, where protected = ``0``, ``L - 1`` and the ``forced``
    frames (bool ``[L]``, never removed). The slow, obviously correct definition the fast kernels
    are tested against: same key, float64, ties broken by the lowest frame."""
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2:
        raise ValueError(f"vw_reference: points must be 2-D [L, F], got shape {P.shape}")
    L = P.shape[0]
    if not 2 <= k <= L:
        raise ValueError(f"vw_reference: k must be in [2, L={L}], got {k}")
    protected = np.zeros(L, dtype=bool)
    protected[[0, L - 1]] = True
    if forced is not None:
        forced = np.asarray(forced, dtype=bool)
        if forced.shape != (L,):
            raise ValueError(f"vw_reference: forced must be bool [L={L}], got shape {forced.shape}")
        protected |= forced
    prev = list(range(-1, L - 1))
    nxt = list(range(1, L + 1))
    alive = [True] * L
    version = [0] * L
    heap = [(_ref_key(P, j - 1, j, j + 1), j, 0) for j in range(1, L - 1) if not protected[j]]
    heapq.heapify(heap)                                  # (key, frame, version): ties -> frame
    remaining = L
    target = max(k, int(protected.sum()))
    while remaining > target:
        _, j, ver = heapq.heappop(heap)
        if not alive[j] or ver != version[j]:
            continue                                     # stale entry
        alive[j] = False
        remaining -= 1
        p, n = prev[j], nxt[j]
        nxt[p], prev[n] = n, p
        for q in (p, n):
            if not protected[q]:
                version[q] += 1
                heapq.heappush(heap, (_ref_key(P, prev[q], q, nxt[q]), q, version[q]))
    return np.flatnonzero(alive)


# ----------------------------------------------------------------------------- mask noise
def perturb_mask(mask: torch.Tensor, lengths: LengthsLike = None, amount: float = 0.1,
                 generator: Optional[torch.Generator] = None, protected: Optional[torch.Tensor] = None
                 ) -> torch.Tensor:
    """Training-time mask noise on ``mask [B, N]`` bool. Per sample with ``K`` keyframes, draws
    ``c`` uniformly in ``[-m, m]`` with ``m = round(amount * K)`` and adds ``c`` random frames
    (c > 0) or drops ``-c`` random interior keyframes (c < 0). Never drops frame 0, L-1 or a
    ``protected [B, N]`` frame, never adds at/after L, never goes below 2 keyframes. Returns a new
    mask; at most ``K + round(amount * K)`` keyframes (see :func:`keyframe_capacity`)."""
    if not isinstance(mask, torch.Tensor) or mask.dim() != 2:
        shape = tuple(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"perturb_mask: mask must be a 2-D bool tensor [B, N], got {shape}")
    _bool_tensor(mask, tuple(mask.shape), "B, N", "perturb_mask: mask")             # its dtype
    if as_float(amount) is None or not 0.0 <= as_float(amount) <= 1.0:
        raise ValueError(f"perturb_mask: amount must be a float in [0, 1] (fraction of "
                         f"keyframes), got {amount!r}")
    _check_generator(generator, "perturb_mask")
    B, N = mask.shape
    device = mask.device
    lengths_t = as_lengths(lengths, B, N, device, "perturb_mask")
    protected = _as_bool(protected, (B, N), "B, N", device, "perturb_mask: protected")
    return perturb_checked(mask, lengths_t, float(amount), generator, protected)


def perturb_checked(mask: torch.Tensor, lengths_t: torch.Tensor, amount: float,
                    generator: Optional[torch.Generator] = None, protected: Optional[torch.Tensor] = None
                    ) -> torch.Tensor:
    """:func:`perturb_mask` on inputs already checked (lengths ``[B]`` long on the mask's device):
    one draw of ``[B, N + 1]`` uniforms (the count, then the frames), then ``smdm::perturb_mask``
    (:mod:`~smdm_plugin.core.kernels.perturb`: one op)."""
    B, N = mask.shape
    with torch.no_grad():
        u = _rand((B, N + 1), generator, mask.device)
        return perturb_mask_op(mask, lengths_t, u, float(amount), protected)


def select_perturbed_checked(features: torch.Tensor, lengths: torch.Tensor, counts: torch.Tensor, method: str,
                             amount: float, generator: Optional[torch.Generator] = None,
                             forced: Optional[torch.Tensor] = None) -> torch.Tensor:
    """A training mask on inputs already checked: :func:`select_checked`, then (``amount > 0``)
    :func:`perturb_checked` with ``forced`` protected; one op where the selector has a ``with_noise``
    form (VW: one launch on CUDA, :mod:`~smdm_plugin.core.kernels.vw_perturb`). The same values and
    the same draws either way (the selector's draws, if any, before the noise's ``[B, N + 1]``)."""
    with_noise = SELECTORS.get(method).with_noise
    if amount <= 0 or with_noise is None:
        mask = select_checked(features, lengths, counts, method, generator, forced)
        return perturb_checked(mask, lengths, amount, generator, forced) if amount > 0 else mask
    B, N = features.shape[:2]
    with torch.no_grad():
        return with_noise(features, lengths, counts, forced, _rand((B, N + 1), generator, features.device),
                          float(amount))


def select_perturbed_plan_checked(features: torch.Tensor, lengths: torch.Tensor, counts: torch.Tensor, method: str,
                                  amount: float, generator: Optional[torch.Generator], slots: int, prefix: int = 0
                                  ) -> MaskAndPlan:
    """:func:`select_perturbed_checked` (no forced frames, ``amount > 0``) with the keyframe plan of
    ``prefix`` always-kept frames then its mask, ``slots`` slots, in one op: the selector's
    ``with_noise_plan`` (it must have one; VW: one launch on CUDA). ``(mask [B, N], plan mask [B,
    prefix + N], plan tensors)``; the same draws as :func:`select_perturbed_checked`."""
    B, N = features.shape[:2]
    with torch.no_grad():
        return SELECTORS.get(method).with_noise_plan(features, lengths, counts, None,
                                                     _rand((B, N + 1), generator, features.device), float(amount),
                                                     int(slots), int(prefix))
