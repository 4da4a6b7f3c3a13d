"""The per-call protocol between the diffusion wrapper (or a user) and a sparse model."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional

import torch

#: the one key of ``y`` (MDM) / of the model's keyword arguments (MotionDiffuse) that carries a
#: :class:`KeyframeRequest`
KEYFRAMES_KEY = "smdm_keyframes"

#: the string keys of 0.3, refused with a message naming the new API
OLD_KEYS = ("keyframe_mask", "keyframe_capacity", "keyframe_forced")


@dataclass(frozen=True)
class KeyframeRequest:
    """The keyframes a caller asks for in one model call (every field optional).

    Attributes:
        mask: bool ``[B, N]`` keyframes chosen by the caller (training: the diffusion wrapper, from
            x0), or None: the model's sampling schedule on ``(x_t, t)`` decides.
        capacity: the static slot count ``K`` that goes with ``mask`` (a Python int >= 1), or None
            (then the largest row of ``mask`` when it can be read without a device sync, else
            ``N``).
        forced: bool ``[B, N]`` frames that must be keyframes (inside the keyframe budget), or None.
        forced_bound: the most frames ``forced`` marks in any sample (a Python int >= 0), known on
            the host, or None. Given, a sampling call sizes its plan from it instead of reading
            ``forced`` (a device sync on an accelerator) and checks it on the device.

    ``mask`` / ``forced`` are checked here to be bool ``[B, N]`` (a dtype and a shape: no sync);
    their counts (a keyframe per sample, none beyond ``capacity``) at the call, which reads them.
    """

    mask: Optional[torch.Tensor] = None
    capacity: Optional[int] = None
    forced: Optional[torch.Tensor] = None
    forced_bound: Optional[int] = None

    def __post_init__(self) -> None:
        for name in ("mask", "forced"):    # (inline: built at every sparse call, a frame costs host time)
            value = getattr(self, name)
            if value is not None and not (isinstance(value, torch.Tensor) and value.dtype == torch.bool
                                          and value.dim() == 2):
                _bad_frames(value, name)
        c = self.capacity
        if c is not None and (isinstance(c, bool) or not isinstance(c, int) or c < 1):
            raise TypeError(f"KeyframeRequest.capacity must be a Python int >= 1 or None, got {c!r}")
        if c is not None and self.mask is None:
            raise TypeError("KeyframeRequest.capacity is the slot count of a given mask: pass mask too")
        fb = self.forced_bound
        if fb is not None and (isinstance(fb, bool) or not isinstance(fb, int) or fb < 0):
            raise TypeError(f"KeyframeRequest.forced_bound must be a Python int >= 0 or None, got {fb!r}")


def _bad_frames(value: Any, name: str) -> None:
    """The error of ``KeyframeRequest.<name>`` that is not a bool tensor ``[B, N]`` (never cast)."""
    if not isinstance(value, torch.Tensor) or value.dtype != torch.bool:
        got = f"a {value.dtype} tensor" if isinstance(value, torch.Tensor) else type(value).__name__
        raise TypeError(f"KeyframeRequest.{name} must be a bool tensor [B, N] or None, got {got}")
    raise ValueError(f"KeyframeRequest.{name} must be a bool tensor [B, N], got shape {tuple(value.shape)}")


_EMPTY = KeyframeRequest()


def request_of(container: Optional[Mapping[str, Any]], where: str = "y") -> KeyframeRequest:
    """The :class:`KeyframeRequest` of one call (an empty one when ``container`` has none).

    ``container``: MDM's ``y`` or MotionDiffuse's keyword arguments; ``where`` names it in errors.
    A value of another type, or one of the 0.3 string keys, is a ``TypeError``."""
    if container is not None and type(container) is not dict and not isinstance(container, Mapping):
        raise TypeError(f"{where} must be a dict (MDM's y / MotionDiffuse's model keyword arguments) or None, "
                        f"got {type(container).__name__}")
    if not container:
        return _EMPTY
    for key in OLD_KEYS:
        if key in container:
            raise TypeError(f"{where}[{key!r}] is not read since smdm-plugin 0.4: pass "
                            f"{where}[{KEYFRAMES_KEY!r}] = smdm_plugin.KeyframeRequest(mask=, capacity=, "
                            f"forced=), e.g. smdm_plugin.with_forced({where}, forced)")
    request = container.get(KEYFRAMES_KEY)
    if request is None:
        return _EMPTY
    if not isinstance(request, KeyframeRequest):
        raise TypeError(f"{where}[{KEYFRAMES_KEY!r}] must be a smdm_plugin.KeyframeRequest, "
                        f"got {type(request).__name__}")
    return request


def with_request(container: Optional[Mapping[str, Any]], where: str = "y", **changes: Any) -> Dict[str, Any]:
    """A copy of ``container`` whose :class:`KeyframeRequest` has the fields in ``changes``
    (``mask=``, ``capacity=``, ``forced=``, ``forced_bound=``) replaced; the caller's dict is not changed."""
    request = dataclasses.replace(request_of(container, where), **changes)
    return {**(container or {}), KEYFRAMES_KEY: request}


def with_forced(y: Optional[Mapping[str, Any]], forced: Optional[torch.Tensor],
                bound: Optional[int] = None) -> Dict[str, Any]:
    """A copy of ``y`` (MDM's conditions, or MotionDiffuse's model keyword arguments) in which the
    frames of bool ``forced [B, N]`` must be keyframes in every call of a sparse model (a dense
    model ignores them); ``bound``: the most frames ``forced`` marks in a sample, when the caller
    knows it (``KeyframeRequest.forced_bound``: no device sync). Replaces forced frames already
    requested; ``y`` is not changed."""
    return with_request(y, forced=forced, forced_bound=bound)
