"""One model call as a family reads it (:class:`CallInputs`) and the keyframe plan built from it
(:func:`keyframe_plan`), for every family."""
from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from typing import Any, Callable, List, Optional, Protocol, Tuple, Union

import torch

from ..core import consts
from ..core.attention import compute_dtype
from ..core.checks import as_mask, compiling, host_checkable, require
from ..core.plan import KeyframePlan
from ..core.schedule import MaskSchedule
from .request import KEYFRAMES_KEY, KeyframeRequest


class PlanState(Protocol):
    """What :func:`keyframe_plan` reads of a model's :class:`~smdm_plugin.adapters.family.SparseState`
    (named by its fields, so this module needs not import the state, which holds the family, whose
    ``read_call`` returns :class:`CallInputs`)."""

    schedule: MaskSchedule
    variant: Any                          # its prefix_len: DiP's dense prefix frames
    schedule_mask: Optional[torch.Tensor]
    schedule_plan: Optional[KeyframePlan]


@dataclass
class CallInputs:
    """One model call as the family reads it (batch-major).

    Attributes:
        frames: ``[B, N, D]`` the motion of the call (x_t while sampling, x_t in training).
        timesteps: ``[B]`` diffusion steps (or None).
        lengths: ``[B]`` long, valid frames (validated, ``2 <= L <= N``).
        forced: bool ``[B, N]`` frames that must be keyframes (``KeyframeRequest.forced`` on the
            call's device, shape checked), or None.
        mask: bool ``[B, N]`` keyframes chosen by the caller (training: ``KeyframeRequest.mask``),
            or None (sampling).
        capacity: the slot count chosen with ``mask`` (a Python int), or None.
        mask_name: how the family's calls pass ``mask`` (for error messages).
        forced_bound: ``KeyframeRequest.forced_bound`` (a host-known bound on ``forced``), or None.
    """

    frames: torch.Tensor
    timesteps: Any
    lengths: torch.Tensor
    forced: Optional[torch.Tensor] = None
    mask: Optional[torch.Tensor] = None
    capacity: Optional[int] = None
    mask_name: str = "KeyframeRequest.mask"
    forced_bound: Optional[int] = None

    @classmethod
    def of(cls, frames: torch.Tensor, timesteps: Any, lengths: torch.Tensor, request: KeyframeRequest,
           where: str) -> "CallInputs":
        """The inputs of a call whose :class:`~smdm_plugin.adapters.request.KeyframeRequest` came in
        ``where`` (``y``, ``model_kwargs``: error messages); its forced frames checked ``[B, N]``
        and moved to ``frames``' device."""
        B, N = frames.shape[:2]
        name = f"{where}[{KEYFRAMES_KEY!r}]"
        return cls(frames, timesteps, lengths, as_mask(request.forced, B, N, frames.device, f"{name}.forced"),
                   request.mask, request.capacity, f"{name}.mask", request.forced_bound)

    def plan(self, state: PlanState) -> KeyframePlan:
        """The call's :class:`~smdm_plugin.core.plan.KeyframePlan` (see :func:`keyframe_plan`)."""
        return keyframe_plan(state, self.frames, self.timesteps, self.lengths, self.forced, self.mask,
                             self.capacity, self.mask_name, self.forced_bound)


#: (source tensors, their versions, key, result), most recently used first: the last few
_REUSED: List[tuple] = []
_REUSED_LOCK = threading.Lock()
#: how many results :func:`reuse_for` keeps (a guided step: per pass the lengths, the forced
#: frames and the plan; an upstream guidance wrapper's copied ``y`` makes new ones every step)
REUSE_KEEP = 8

Sources = Union[Optional[torch.Tensor], Tuple[Optional[torch.Tensor], ...]]


def _versions(sources: Tuple[Optional[torch.Tensor], ...]) -> Optional[tuple]:
    """The version counters of ``sources`` (-1 for an absent one), or None when one is an inference
    tensor (``torch.inference_mode``: no counter, an in-place change could not be seen)."""
    out = []
    for s in sources:
        if s is None:
            out.append(-1)
        elif s.is_inference():
            return None
        else:
            out.append(s._version)
    return tuple(out)


def reuse_for(source: Sources, key: tuple, compute: Callable[[], Any]) -> Any:
    """``compute()``, or its result for the same ``source`` tensors (a tensor, or a tuple of tensors
    and Nones: the same objects, each unchanged since: same version) and ``key`` (ints, devices,
    dtypes, objects compared by ``==``) from one of the last :data:`REUSE_KEEP` calls: the lengths
    of a sampling loop's ``y['mask']`` are read and validated once, not at every step and guidance
    pass (and once per training step: the diffusion wrapper's x0 call and the model call share
    them); a sampling loop's forced keyframes and their plan are made once. Not while tracing
    (the traced graph computes them), not for inference tensors (no version counter)."""
    if compiling():
        return compute()
    sources = source if isinstance(source, tuple) else (source,)
    versions = _versions(sources)
    if versions is None:
        return compute()
    with _REUSED_LOCK:                                  # (threads sampling at once share the list)
        for i, (srcs, vers, k, out) in enumerate(_REUSED):
            if len(srcs) == len(sources) and all(a is b for a, b in zip(srcs, sources)) and vers == versions \
                    and k == key:
                if i:
                    _REUSED.insert(0, _REUSED.pop(i))
                return out
    out = compute()
    with _REUSED_LOCK:
        _REUSED.insert(0, (sources, versions, key, out))
        del _REUSED[REUSE_KEEP:]
    return out


def keyframe_plan(state: PlanState, frames: torch.Tensor, timesteps: Any, lengths: torch.Tensor,
                  forced: Optional[torch.Tensor], mask: Any = None, capacity: Any = None,
                  mask_name: str = "KeyframeRequest.mask", forced_bound: Optional[int] = None) -> KeyframePlan:
    """The keyframe plan of one model call, for every family.

    Args:
        frames: the call's motion ``[B, N, D]`` (x_t while sampling).
        timesteps: ``[B]`` (or a scalar) diffusion step; None = 0.
        lengths: ``[B]`` long, validated (``2 <= L <= N``).
        forced: bool ``[B, N]`` frames that must be keyframes, or None.
        mask: bool ``[B, N]`` keyframes chosen by the caller (training: the diffusion wrapper from
            x0), else None: the sampling schedule on ``(frames, timesteps)``.
        capacity: the slot count that goes with a given ``mask`` (a Python int); None: the largest
            row of ``mask`` when it can be read without a sync, else ``N``.
        mask_name: how the caller passed ``mask`` (error messages).
        forced_bound: the most frames ``forced`` marks in a sample, known on the host (sampling:
            the plan is sized from it, no read of ``forced``; checked on the device), or None.
    """
    B, N = frames.shape[:2]
    device = frames.device
    if mask is not None and mask is state.schedule_mask and forced is None and not compiling():
        # training: the schedule's own mask (valid, in capacity), its plan made with it (training_plan)
        plan = state.schedule_plan
        if plan is not None and plan.capacity == _slots(state, capacity, N):
            return plan
        check, cubic = False, None
    elif mask is not None:                                 # training (or a caller's own mask)
        valid = consts.arange(N, device)[None] < lengths[:, None]
        # a mask chosen while loading (keyframe_collate) is still on the CPU: upstream loops move
        # y's tensors, not the KeyframeRequest; copy it without waiting for the device
        mask = torch.as_tensor(mask).to(device, non_blocking=True)
        if tuple(mask.shape) != (B, N):
            raise ValueError(f"{mask_name} must be bool [B, N]=[{B}, {N}], got {tuple(mask.shape)}")
        mask = mask.to(torch.bool) & valid
        if forced is not None:
            mask = mask | (forced & valid)
        if capacity is None:                               # a mask from elsewhere: size it safely
            capacity = int(mask.sum(1).max()) if host_checkable(mask) and B else N
        check, cubic = True, None
    else:                                                  # sampling: the schedule on x_t
        t = timesteps if timesteps is not None else torch.zeros(B, dtype=torch.long, device=device)
        cubic = state.schedule.cubic_samples(t, B, device, frames.shape[-1])   # C¹ fill: [B] bool
        if state.schedule.late_steps == 0:
            # the uniform mask (with any forced frames) depends on neither x_t nor t: a sampling loop
            # makes its plan once (per lengths and forced tensor; not a per-sample C¹ fill's), its
            # steps look it up
            dtype = compute_dtype(frames)
            if forced is None:                             # a table lookup
                key, sources = ("uniform plan", state.schedule, N, state.variant.prefix_len, dtype, cubic), lengths
                make = lambda: _uniform_plan(state, lengths, N, cubic, dtype)   # noqa: E731
            else:
                key = ("forced plan", state.schedule, N, state.variant.prefix_len, forced_bound, dtype, cubic)
                sources = (forced, lengths)
                make = lambda: _forced_plan(state, frames, t, lengths, forced, forced_bound, dtype, cubic)  # noqa: E731
            return make() if isinstance(cubic, torch.Tensor) else reuse_for(sources, key, make)
        mask = state.schedule.sampling_mask(frames, t, lengths, forced, checked=True)
        capacity = state.schedule.capacity(N, training=False, forced=protected_count(forced, lengths, forced_bound))
        check = False                                      # 2..capacity keyframes by construction
    return _build(state, mask, capacity, check, cubic)


def _uniform_plan(state: PlanState, lengths: torch.Tensor, N: int, cubic: Any, dtype: torch.dtype) -> KeyframePlan:
    """The sampling plan of the uniform mask, looked up (:meth:`MaskSchedule.uniform_plan`; the key
    bias in ``dtype``, the attention's), with the C¹ fill's taps for ``cubic`` samples."""
    taps = None
    if cubic is not None and not state.variant.prefix_len:
        f_tab, w_tab = state.schedule.cubic_taps(N, lengths.device)
        taps = (f_tab[lengths], w_tab[lengths])
    return state.schedule.uniform_plan(lengths, N, state.variant.prefix_len, cubic, taps, dtype)


def _forced_plan(state: PlanState, frames: torch.Tensor, t: Any, lengths: torch.Tensor, forced: torch.Tensor,
                 forced_bound: Optional[int], dtype: torch.dtype, cubic: Any) -> KeyframePlan:
    """The sampling plan of the uniform mask with ``forced`` frames (no dynamic update: it depends
    on neither ``x_t`` nor ``t``, so a sampling loop makes it once: :func:`keyframe_plan`); its key
    bias in ``dtype`` (the attention's: cast once, not per call)."""
    mask = state.schedule.sampling_mask(frames, t, lengths, forced, checked=True)
    capacity = state.schedule.capacity(frames.shape[1], training=False,
                                       forced=protected_count(forced, lengths, forced_bound))
    plan = _build(state, mask, capacity, False, cubic)     # 2..capacity keyframes by construction
    if compiling() or plan.key_bias.dtype == dtype:      # (traced: the attention casts it)
        return plan
    return replace(plan, key_bias=plan.key_bias.to(dtype))


def _slots(state: PlanState, capacity: Any, N: int) -> int:
    """The slots of a plan of ``N`` frames with ``capacity`` keyframes (clamped to ``1..N``) after the
    variant's always-kept prefix frames (DiP), if any."""
    return max(1, min(int(capacity), N)) + state.variant.prefix_len


def _build(state: PlanState, mask: torch.Tensor, capacity: Any, check: bool, cubic: Any = None) -> KeyframePlan:
    """The plan of keyframe ``mask [B, N]`` with ``capacity`` slots (clamped to ``1..N``), after the
    variant's always-kept prefix frames (DiP), if any."""
    B, N = mask.shape
    prefix = state.variant.prefix_len
    if prefix:
        mask = torch.cat([mask.new_ones(B, prefix), mask], dim=1)
    return KeyframePlan.build(mask, _slots(state, capacity, N), check=check, cubic=cubic)


def training_plan(state: PlanState, frames: torch.Tensor, lengths: torch.Tensor, noise: Any
                  ) -> Tuple[torch.Tensor, int, Optional[KeyframePlan]]:
    """``(mask [B, N], capacity, plan or None)``: the training keyframes of x0 ``frames [B, N, D]``
    without forced frames (valid ``lengths [B]``, checked), drawn from ``noise`` (advanced by one),
    with the plan :func:`keyframe_plan` would build of them where the schedule makes both in one op
    (:meth:`MaskSchedule.training_plan`; else None: the call builds it)."""
    schedule, N = state.schedule, frames.shape[1]
    capacity = schedule.capacity(N, training=True)
    made = schedule.training_plan(frames, lengths, _slots(state, capacity, N), state.variant.prefix_len, noise,
                                  checked=True)
    if made is None:
        return schedule.training_mask(frames, lengths, None, noise, checked=True), capacity, None
    return made[0], capacity, made[1]


def protected_count(forced: Optional[torch.Tensor], lengths: torch.Tensor, bound: Optional[int] = None) -> int:
    """The most protected frames (both ends + forced) of any sample: with ``bound`` (the most
    frames ``forced`` marks in a sample, known on the host) ``bound + 2``, at most ``N``, and the
    bound checked on the device (no sync); else a host read of ``forced`` (free on the CPU; one
    device sync on an accelerator)."""
    if forced is None:
        return 0
    idx = torch.arange(forced.shape[1], device=forced.device)
    valid = idx[None] < lengths[:, None]
    if bound is not None:
        require(((forced & valid).sum(1) <= bound),
                f"KeyframeRequest.forced marks more frames in a sample than its forced_bound={bound}")
        return min(int(bound) + 2, forced.shape[1])
    ends = (idx[None] == 0) | (idx[None] == (lengths - 1)[:, None])
    return int(((forced | ends) & valid).sum(1).max()) if forced.shape[0] else 0
