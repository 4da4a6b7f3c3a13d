"""Forced keyframes for priorMDM's DoubleTake (long-sequence generation from a sparse prior)."""
from __future__ import annotations

from typing import Any, Dict, Optional, Sequence

import torch
from torch import nn
from torch.utils.hooks import RemovableHandle

from ..mdm.model import MDMFamily, is_doubletake_model
from ...adapters.call import reuse_for
from ...adapters.request import request_of, with_forced
from ...adapters.state import SparseState

#: the paper's DoubleTake transition blending length, in seconds
PAPER_BLEND_SECONDS = 0.25
#: priorMDM's own ``--blend_len`` default (frames)
PRIORMDM_BLEND_LEN = 20


def paper_blend_len(fps: float = 20.0) -> int:
    """The paper's blending length in frames at ``fps`` (0.25 s: 5 frames at HumanML3D's 20 fps)."""
    if not fps > 0:
        raise ValueError(f"paper_blend_len: fps must be > 0, got {fps}")
    return int(round(PAPER_BLEND_SECONDS * fps))


#: the paper's blending length at HumanML3D's 20 fps, in frames
PAPER_BLEND_LEN = paper_blend_len(20.0)


def _lengths_list(lengths) -> list:
    if isinstance(lengths, torch.Tensor):
        return [int(v) for v in lengths.reshape(-1).tolist()]
    return [int(v) for v in lengths]


def doubletake_forced_frames(lengths: Sequence[int], handshake_size: int,
                             n_frames: Optional[int] = None, *, take: str = "first",
                             blend_len: int = PAPER_BLEND_LEN, device=None) -> torch.Tensor:
    """Frames that must be keyframes in DoubleTake's first or second take, bool ``[B, N]``.

    Args:
        lengths: the first take's segment lengths ``[S]`` (``y['lengths']`` before DoubleTake
            changes them).
        handshake_size: ``--handshake_size``.
        n_frames: frames of the batch. First take: default ``max(lengths)``; second take:
            default ``(max(lengths) - 2 h) * 2 + h`` (priorMDM's ``new_sample_seq_len``).
        take: ``"first"`` (rows = segments, ``[S, N]``) or ``"second"`` (rows = pairs of
            neighbouring segments, ``[S - 1, N]``).
        blend_len: ``--blend_len`` (second take); default the paper's 0.25 s (5 frames at 20 fps).
            Below 2, priorMDM draws no blend ramp and nothing is forced in the second take.
    """
    lens = _lengths_list(lengths)
    S, h = len(lens), int(handshake_size)
    if S < 1:
        raise ValueError("doubletake_forced_frames: lengths must not be empty")
    if h < 0 or blend_len < 0:
        raise ValueError(f"doubletake_forced_frames: handshake_size and blend_len must be >= 0, "
                         f"got {handshake_size}, {blend_len}")
    if take == "first":
        N = max(lens) if n_frames is None else int(n_frames)
        if max(lens) > N:
            raise ValueError(f"doubletake_forced_frames: lengths must be <= n_frames={N}, got {lens}")
        forced = torch.zeros(S, N, dtype=torch.bool, device=device)
        for i, L in enumerate(lens):
            if i > 0:
                forced[i, :h] = True          # shared with the end of segment i - 1
            if i < S - 1:
                forced[i, max(0, L - h):L] = True  # shared with the start of segment i + 1
        return forced
    if take == "second":
        if S < 2:
            raise ValueError("doubletake_forced_frames: the second take needs >= 2 segments")
        N = (max(lens) - 2 * h) * 2 + h if n_frames is None else int(n_frames)
        forced = torch.zeros(S - 1, N, dtype=torch.bool, device=device)
        if blend_len < 2:  # priorMDM: `if blend_len >= 2` draws the ramps; else nothing is regenerated
            return forced
        for i in range(S - 1):
            b = lens[i] - 2 * h  # where the handshake starts in the second-take sequence
            forced[i, max(0, b - blend_len):min(N, b + h + blend_len)] = True
        return forced
    raise ValueError(f"doubletake_forced_frames: take must be 'first' or 'second', got {take!r}")


def doubletake_forced_from_y(y: Dict[str, Any], batch_size: int, n_frames: int,
                             device=None) -> Optional[torch.Tensor]:
    """The forced keyframes ``[B, N]`` of one DoubleTake model call, read from ``y``.

    Second take (``inpainting_mask`` present, frames with mask < 1 exist): the transition
    windows, i.e. the span from the first to the last frame with mask < 1 around each
    handshake, which covers both blend ramps and the handshake between them. First take:
    ``is_transition`` > 0. Returns None when ``y`` carries neither (plain MDM sampling).
    """
    forced = None
    mask = y.get("inpainting_mask")
    trans = y.get("is_transition")
    trans = trans if isinstance(trans, torch.Tensor) and trans.dim() == 2 and trans.shape == (batch_size, n_frames) \
        else None
    if isinstance(mask, torch.Tensor) and mask.shape[0] == batch_size and mask.shape[-1] == n_frames:
        m = mask.reshape(batch_size, -1, n_frames).float()
        free = (m < 1.0).any(dim=1)  # frames where the model's output is (partly) used
        # with is_transition there are forced frames either way (no free frame: none from here, the
        # same values): no read of ``free`` on the host
        if trans is not None or bool(free.any()):
            forced = _close_gaps(free, max_gap=_max_gap(y, free))
    if trans is not None:
        t = trans.to(torch.bool)
        forced = t if forced is None else (forced | t.to(forced.device))
    if forced is None:
        return None
    return forced.to(device) if device is not None else forced


def _max_gap(y: Dict[str, Any], free: torch.Tensor) -> int:
    """The handshake between two blend ramps keeps mask 1; close gaps up to its size."""
    h = y.get("handshake_size")
    if h is not None:
        return int(h)
    return int(free.shape[1])  # close any gap between the first and last free frame of a pair


def _close_gaps(free: torch.Tensor, max_gap: int) -> torch.Tensor:
    """Fill runs of False of length <= ``max_gap`` that lie between two True frames (per row), on
    the device: a frame is filled when the nearest True frames before and after it are at most
    ``max_gap + 1`` apart (no host read)."""
    N = free.shape[1]
    idx = torch.arange(N, device=free.device).expand_as(free)
    before = torch.where(free, idx, -1).cummax(dim=1).values                     # last True at or before
    after = torch.where(free, idx, N).flip(1).cummin(dim=1).values.flip(1)      # first True at or after
    return free | ((before >= 0) & (after < N) & (after - before <= max_gap + 1))


def doubletake_window_mask(y: Dict[str, Any], batch_size: int, n_frames: int) -> Optional[torch.Tensor]:
    """The valid-frame mask ``[B, 1, 1, N]`` bool of a DoubleTake call's own window, from
    ``y['lengths'] [B]``, when ``y`` is a DoubleTake call (``is_transition`` present) whose
    ``y['mask']`` covers another number of frames: priorMDM's ``sample/double_take.py`` passes a
    fixed 196-frame mask (HumanML3D's maximum) to both takes, whose windows are ``n_frames``
    (first take) and ``(max(lengths) - 2 h) * 2 + h`` (second take), while its ``y['lengths']``
    are those of the take being sampled. None when nothing needs replacing."""
    mask, lengths = y.get("mask"), y.get("lengths")
    if "is_transition" not in y or not isinstance(mask, torch.Tensor) or mask.shape[-1] == n_frames:
        return None
    if not isinstance(lengths, torch.Tensor) or lengths.numel() != batch_size:
        return None
    idx = torch.arange(n_frames, device=lengths.device)
    return (idx[None] < lengths.reshape(batch_size, 1)).view(batch_size, 1, 1, n_frames)


def doubletake_forced_bound(handshake_size: int, blend_len: int) -> int:
    """The most frames DoubleTake forces in one sample (priorMDM's geometry): a first-take segment's
    two handshakes ``2 h``, a second-take pair's blend ramps and handshake ``h + 2 blend_len``
    (:func:`doubletake_forced_frames`). Given to :func:`attach_doubletake_forcing`, a sampling call
    sizes its plan from it without reading the forced frames (no device sync)."""
    h, b = int(handshake_size), int(blend_len)
    if h < 0 or b < 0:
        raise ValueError(f"doubletake_forced_bound: handshake_size and blend_len must be >= 0, got {h}, {b}")
    return max(2 * h, h + 2 * b if b >= 2 else 0)


# --------------------------------------------------------------------------- model hook
def _find_y(args, kwargs):
    if "y" in kwargs:
        return kwargs["y"], "kw"
    if len(args) >= 3:
        return args[2], "pos"
    return None, None


def _forcing(y: Dict[str, Any], B: int, N: int, device: torch.device):
    """``(forced [B, N] or None, window mask [B, 1, 1, N] or None)`` of a DoubleTake call
    (:func:`doubletake_forced_from_y`, :func:`doubletake_window_mask`), made once for the same
    tensors of ``y`` (the same objects, unchanged: :func:`~smdm_plugin.adapters.call.reuse_for`): a
    sampling loop's steps and guidance passes share them, and with them their keyframe plan."""
    h = y.get("handshake_size")
    if h is not None and (isinstance(h, bool) or not isinstance(h, int)):
        return doubletake_forced_from_y(y, B, N, device=device), doubletake_window_mask(y, B, N)
    sources = tuple(v if isinstance(v, torch.Tensor) else None
                    for v in (y.get(k) for k in ("inpainting_mask", "is_transition", "mask", "lengths")))
    return reuse_for(sources, ("doubletake forcing", B, N, device, h, "is_transition" in y),
                     lambda: (doubletake_forced_from_y(y, B, N, device=device), doubletake_window_mask(y, B, N)))


class _ForcingHook:
    """The forward pre-hook of :func:`attach_doubletake_forcing` (``bound``: the run's
    :func:`doubletake_forced_bound`, or None: each call reads its forced frames to size its plan)."""

    def __init__(self) -> None:
        self.bound: Optional[int] = None

    @property
    def reads_on_host(self) -> bool:
        """Whether a call reads on the host (without a bound: the count of its forced frames, to
        size the plan): graph capture then allows a break (``ModelFamily.traces_whole``)."""
        return self.bound is None

    def __call__(self, module: nn.Module, args, kwargs):
        return _doubletake_pre_hook(module, args, kwargs, self.bound)


def _doubletake_pre_hook(module: nn.Module, args, kwargs, bound: Optional[int] = None):
    y, where = _find_y(args, kwargs)
    if not isinstance(y, dict):
        return None
    x = args[0] if args else kwargs.get("x")
    if not isinstance(x, torch.Tensor):
        return None
    B, N = x.shape[0], x.shape[-1]
    forced, window = _forcing(y, B, N, x.device)
    if forced is None and window is None:
        return None
    y = dict(y)  # never write into the caller's dict (DoubleTake reuses it across takes)
    if window is not None:
        y["mask"] = window
    if forced is not None:
        request = request_of(y)
        prev = None if request.forced is None else torch.as_tensor(request.forced)
        if prev is not None and prev.shape == forced.shape:
            forced = reuse_for((forced, prev), ("doubletake forced | request", forced.device),
                               lambda: forced | prev.to(forced.device, torch.bool))
            bound = None if bound is None or request.forced_bound is None else bound + request.forced_bound
        y = with_forced(y, forced, bound)
    if where == "kw":
        kwargs = dict(kwargs)
        kwargs["y"] = y
    else:
        args = tuple(args[:2]) + (y,) + tuple(args[3:])
    return args, kwargs


def has_doubletake_forcing(model: nn.Module) -> bool:
    """Whether :func:`attach_doubletake_forcing` hooked ``model`` (read from its hooks: the model
    carries no attribute of ours)."""
    return any(isinstance(h, _ForcingHook) for h in model._forward_pre_hooks.values())


def _attach(model: nn.Module) -> Optional[RemovableHandle]:
    """The handle of a new forcing hook on ``model``; None when it already has one."""
    if has_doubletake_forcing(model):
        return None
    # prepend: must run before sparsify's own pre-hook, which reads the forced frames
    return model.register_forward_pre_hook(_ForcingHook(), with_kwargs=True, prepend=True)


def attach_doubletake_forcing(model: nn.Module, forced_bound: Optional[int] = None) -> nn.Module:
    """Make every call of ``model(x, t, y)`` carry forced keyframes (:func:`with_forced`) derived
    from DoubleTake's ``is_transition`` / ``inpainting_mask``, and a ``y['mask']`` of the call's own
    window (:func:`doubletake_window_mask`), in a copy of ``y``. ``forced_bound``: the most frames
    forced in a sample (:func:`doubletake_forced_bound` of the run's ``--handshake_size`` and
    ``--blend_len``), so that no call reads them on the host (checked on the device); None: each
    call reads them (one device sync per call on an accelerator). Idempotent (a second call sets the
    bound); returns ``model``."""
    if forced_bound is not None and (isinstance(forced_bound, bool) or not isinstance(forced_bound, int)
                                     or forced_bound < 0):
        raise TypeError(f"attach_doubletake_forcing: forced_bound must be a Python int >= 0 or None, "
                        f"got {forced_bound!r}")
    _attach(model)
    for h in model._forward_pre_hooks.values():
        if isinstance(h, _ForcingHook):
            h.bound = forced_bound
    return model


def detach_doubletake_forcing(model: nn.Module) -> nn.Module:
    """Remove :func:`attach_doubletake_forcing`'s hook (if any); returns ``model``."""
    for key in [k for k, h in model._forward_pre_hooks.items() if isinstance(h, _ForcingHook)]:
        del model._forward_pre_hooks[key]
        model._forward_pre_hooks_with_kwargs.pop(key, None)
    return model


# --------------------------------------------------------------------------- the family
class DoubleTakeFamily(MDMFamily):
    """priorMDM's ``doubleTake_MDM``: an MDM whose calls also carry DoubleTake's forced keyframes
    (``is_transition`` / ``inpainting_mask`` in ``y``), added by :func:`attach_doubletake_forcing`
    when the model is sparsified (and removed again by ``unsparsify`` if it was added then)."""

    name = "doubletake"
    priority = 10   # asked before the plain MDM family

    def matches(self, model: nn.Module) -> bool:
        return super().matches(model) and is_doubletake_model(model)

    def mismatch(self, model: nn.Module) -> str:
        return super().mismatch(model) if not super().matches(model) else "class name has no 'doubletake'"

    def install(self, model: nn.Module, state: SparseState) -> None:
        super().install(model, state)
        handle = _attach(model)
        if handle is not None:            # attached here: unsparsify removes it again
            state.handles.append(handle)

