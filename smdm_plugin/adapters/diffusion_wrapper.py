"""Wrap a Gaussian diffusion's ``training_losses`` (MDM / guided-diffusion style, or the
in-package :class:`~smdm_plugin.reference.simple_diffusion.SimpleDiffusion`) for sparse training: keyframes
selected from the clean motion, the loss on every (interpolated) frame, ``+ lipschitz_lambda * L_lip``."""
from __future__ import annotations

import functools
import weakref
from dataclasses import dataclass, field
from typing import Any, List, Optional, Tuple

import torch.nn as nn

from ..core.noise import NOISE_STEP, NOISE_TABLE, CounterNoise
from .call import protected_count, training_plan
from .state import find_sparse_model, get_state


def diffusion_steps(diffusion: Any) -> int:
    """T of the training schedule (``original_num_steps`` of a respaced diffusion)."""
    for attr in ("original_num_steps", "num_timesteps", "num_steps", "T"):
        if getattr(diffusion, attr, None):
            return int(getattr(diffusion, attr))
    raise ValueError(f"attach_diffusion: cannot read the step count of {type(diffusion).__name__} "
                     "(expected num_timesteps or original_num_steps)")


def model_noise(sparse: nn.Module) -> Optional[CounterNoise]:
    """The random numbers of ``sparse``'s next training mask: its step counter and noise table
    buffers (:mod:`~smdm_plugin.core.noise`); None when its config draws nothing."""
    table = getattr(sparse, NOISE_TABLE, None)
    return None if table is None else CounterNoise(getattr(sparse, NOISE_STEP), table,
                                                   get_state(sparse).schedule.noise_salt)


#: the one attribute a wrapped diffusion carries
HOOK_ATTR = "_smdm_diffusion"


@dataclass
class DiffusionHook:
    """What :func:`attach_diffusion` keeps on a diffusion: its own ``training_losses`` (restored
    by :func:`detach_diffusion`) and weak references to the sparse models attached to it."""

    original: Any
    models: List["weakref.ref"] = field(default_factory=list)

    def live(self, but: Optional[nn.Module] = None) -> list:
        """The attached models that are alive and still sparse (``but`` left out)."""
        return [m for m in (r() for r in self.models) if m is not None and m is not but and get_state(m) is not None]


def _hook(diffusion: Any) -> Optional[DiffusionHook]:
    return diffusion.__dict__.get(HOOK_ATTR)


def attach_diffusion(diffusion: Any, model: Optional[nn.Module] = None) -> Any:
    """Wrap ``diffusion.training_losses`` in place (once) and return ``diffusion``; each call uses
    the config of the sparse model it trains.

    Args:
        model: the sparse model trained with this diffusion; needed only when the callable handed
            to ``training_losses`` is not an ``nn.Module`` containing it, and remembered so that
            ``unsparsify`` can restore the diffusion.
    """
    hook = _hook(diffusion)
    if hook is None:
        hook = DiffusionHook(diffusion.training_losses)
    if model is not None:
        hook.models = [r for r in hook.models if r() is not None and r() is not model] + [weakref.ref(model)]
        state = get_state(model)
        if state is not None and not any(r() is diffusion for r in state.diffusions):
            state.diffusions.append(weakref.ref(diffusion))
    if _hook(diffusion) is not None:
        return diffusion
    original = hook.original

    @functools.wraps(original)
    def training_losses(model, x_start, t, model_kwargs=None, *args, **kwargs):
        # (parameter names as upstream's: MotionDiffuse's trainer passes model=..., x_start=...)
        if isinstance(model, nn.Module):
            sparse = find_sparse_model(model)
        else:  # a plain callable: the one attached sparse model, if there is exactly one
            live = hook.live()
            sparse = live[0] if len(live) == 1 else None
        if sparse is None:  # a dense model: exactly the upstream behaviour
            return original(model, x_start, t, model_kwargs, *args, **kwargs)
        state = get_state(sparse)
        family = state.family
        call = family.training_inputs(state, x_start, model_kwargs or {})
        mask, capacity = call.mask, call.capacity
        if mask is None and call.forced is None:  # valid by construction: the plan checks it no more
            mask, capacity, state.schedule_plan = training_plan(state, call.frames, call.lengths, model_noise(sparse))
            state.schedule_mask = mask
        elif mask is None:                       # else: chosen in data loading (mdm.keyframe_collate)
            mask, capacity = training_keyframes(state.schedule, call.frames, call.lengths, call.forced,
                                                model_noise(sparse))
        model_kwargs = family.with_keyframes(state, model_kwargs or {}, mask, capacity)
        try:
            terms = original(model, x_start, t, model_kwargs, *args, **kwargs)
        finally:
            state.schedule_mask = state.schedule_plan = None
        return family.finish_losses(state, sparse, terms, mask)

    diffusion.training_losses = training_losses
    setattr(diffusion, HOOK_ATTR, hook)
    return diffusion


def detach_diffusion(diffusion: Any) -> Any:
    """Undo :func:`attach_diffusion`: the original ``training_losses`` again."""
    if _hook(diffusion) is not None:
        del diffusion.training_losses
        delattr(diffusion, HOOK_ATTR)
    return diffusion


def release_diffusions(model: nn.Module) -> None:
    """Forget ``model`` in the diffusions it was attached to; restore each diffusion that has no
    other live sparse model (called by ``unsparsify``)."""
    state = get_state(model)
    if state is None:
        return
    for ref in state.diffusions:
        diffusion = ref()
        hook = None if diffusion is None else _hook(diffusion)
        if hook is None:
            continue
        hook.models = [r for r in hook.models if r() is not None and r() is not model]
        if not hook.live(but=model):
            detach_diffusion(diffusion)
    state.diffusions.clear()


def training_keyframes(schedule: Any, frames: Any, lengths: Any, forced: Any,
                       noise: Optional[CounterNoise] = None) -> Tuple[Any, int]:
    """``(mask bool [B, N], capacity K)``: the training keyframes of x0 ``frames [B, N, D]``
    (valid ``lengths [B]``, ``forced [B, N]`` or None) by ``schedule`` (a ``MaskSchedule``), its
    random draws from ``noise`` (:mod:`~smdm_plugin.core.noise`; advanced by one)."""
    mask = schedule.training_mask(frames, lengths, forced, noise, checked=True)
    return mask, schedule.capacity(frames.shape[1], training=True, forced=protected_count(forced, lengths))
