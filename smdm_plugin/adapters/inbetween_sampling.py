"""Keyframe-conditioned in-betweening for any MDM-family model, dense or sparse."""
from __future__ import annotations

import inspect
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Dict, Optional, Sequence, Tuple, Union

import torch

from ..core.checks import as_lengths, host_checkable, require
from .request import with_forced

#: which given frames become forced keyframes (:func:`forced_keyframes`)
POLICIES = ("ends", "all", "none")

IntsLike = Union[torch.Tensor, Sequence[int]]


@dataclass(frozen=True)
class KeyframeConstraint:
    """What a sampled motion must pass through.

    ``target [B, N, D]`` holds the values of the given entries (the rest is ignored), ``given`` is
    bool ``[B, N, D]`` (True = imposed; whole frames for keyframes), ``lengths [B]`` long the
    valid frames per sample. Build it with :func:`keyframe_constraint`.
    """

    target: torch.Tensor
    given: torch.Tensor
    lengths: torch.Tensor

    @property
    def frames(self) -> torch.Tensor:
        """bool ``[B, N]``: frames whose every channel is given (the keyframes)."""
        return self.given.all(dim=-1)


def _lengths(lengths: Optional[IntsLike], B: int, N: int, device: torch.device, fn: str) -> torch.Tensor:
    """Valid frames per sample ``[B]`` long (None: all ``N``; an int: every sample), in ``[2, N]``."""
    return as_lengths(lengths, B, N, device, fn, broadcast=True)


def keyframe_constraint(target: torch.Tensor, given: Union[torch.Tensor, IntsLike],
                        lengths: Optional[IntsLike] = None) -> KeyframeConstraint:
    """Validate and build a :class:`KeyframeConstraint`.

    Args:
        target: ``[B, N, D]`` (or ``[N, D]`` for one sample) motion holding the given values.
        given: frame indices shared by the batch (a list / 1-D integer tensor), bool ``[B, N]``
            (whole frames) or bool ``[B, N, D]`` (single channels, e.g. the root trajectory only).
        lengths: valid frames per sample ``[B]`` (None: all ``N``); given frames must lie within.
    """
    fn = "keyframe_constraint"
    target = torch.as_tensor(target)
    if target.dim() == 2:
        target = target.unsqueeze(0)
    if target.dim() != 3 or not target.dtype.is_floating_point:
        raise ValueError(f"{fn}: target must be a float motion [B, N, D] (or [N, D]), got "
                         f"{target.dtype} {tuple(target.shape)}")
    B, N, D = target.shape
    L = _lengths(lengths, B, N, target.device, fn)
    g = given if isinstance(given, torch.Tensor) else torch.as_tensor(list(given), dtype=torch.long)
    g = g.to(target.device)
    if g.dtype == torch.bool:
        if g.dim() == 2 and tuple(g.shape) != (B, N) and B == 1 and tuple(g.shape) == (N, D):
            g = g.unsqueeze(0)  # channels of one sample
        elif g.dim() == 1:
            g = g.unsqueeze(0).expand(B, -1)
        if g.dim() == 2:
            if tuple(g.shape) != (B, N):
                raise ValueError(f"{fn}: given must be bool [B, N]=[{B}, {N}] or [B, N, D], got {tuple(g.shape)}")
            g = g.unsqueeze(-1).expand(B, N, D)
        if tuple(g.shape) != (B, N, D):
            raise ValueError(f"{fn}: given must be bool [B, N]=[{B}, {N}] or [B, N, D]=[{B}, {N}, {D}], "
                             f"got {tuple(g.shape)}")
    else:
        if g.dtype.is_floating_point or g.dim() != 1:
            raise ValueError(f"{fn}: given must be frame indices (1-D integers) or a bool mask, got "
                             f"{g.dtype} {tuple(g.shape)}")
        if g.numel() and (int(g.min()) < 0 or int(g.max()) >= N):
            raise ValueError(f"{fn}: given frame indices must be in [0, N={N}), got {g.tolist()}")
        frames = torch.zeros(B, N, dtype=torch.bool, device=target.device)
        frames[:, g] = True
        g = frames.unsqueeze(-1).expand(B, N, D)
    beyond = g.any(-1) & (torch.arange(N, device=g.device)[None] >= L[:, None])
    if bool(beyond.any()):
        b = int(beyond.any(1).nonzero()[0])
        raise ValueError(f"{fn}: sample {b} has a given frame at {int(beyond[b].nonzero()[0])}, at or "
                         f"beyond its length {int(L[b])}")
    if not bool(g.any(-1).any(-1).all()):
        b = int((~g.any(-1).any(-1)).nonzero()[0])
        raise ValueError(f"{fn}: sample {b} has no given frame")
    if not bool(torch.isfinite(target[g]).all()):
        raise ValueError(f"{fn}: target holds NaN or inf at given entries")
    return KeyframeConstraint(target=target, given=g.contiguous(), lengths=L)


def forced_keyframes(frames: torch.Tensor, lengths: Optional[IntsLike] = None, policy: str = "ends"
                     ) -> torch.Tensor:
    """Which given frames become keyframe tokens of a sparse model: bool ``[B, N]``.

    ``frames`` bool ``[B, N]``: the fully given frames. Policies:

    * ``"ends"`` (default): the first and last frame of every run of consecutive given frames.
      Isolated keyframes are their own run, so sparse user keyframes are all forced; a long given
      segment (MDM's in-between prefix / suffix) adds its two ends only, where it meets the
      generated part, and leaves the keyframe budget to the rest.
    * ``"all"``: every given frame (a long given segment then fills the keyframe budget).
    * ``"none"``: no forced keyframe (the model's own schedule; imputation alone imposes the frames).
    """
    if policy not in POLICIES:
        raise ValueError(f"forced_keyframes: policy must be one of {POLICIES}, got {policy!r}")
    frames = torch.as_tensor(frames)
    if frames.dtype != torch.bool or frames.dim() != 2:
        raise ValueError(f"forced_keyframes: frames must be bool [B, N], got {frames.dtype} {tuple(frames.shape)}")
    B, N = frames.shape
    L = _lengths(lengths, B, N, frames.device, "forced_keyframes")
    valid = torch.arange(N, device=frames.device)[None] < L[:, None]
    frames = frames & valid
    if policy == "none":
        return torch.zeros_like(frames)
    if policy == "all":
        return frames
    pad = frames.new_zeros(B, 1)
    before = torch.cat([pad, frames[:, :-1]], 1)   # frame n-1 given
    after = torch.cat([frames[:, 1:], pad], 1)     # frame n+1 given (False past N)
    return frames & (~before | ~after)


def frames_from_inpainting_mask(inpainting_mask: torch.Tensor, shape: Sequence[int]) -> torch.Tensor:
    """bool ``[B, N]``: the frames whose every channel MDM's ``y['inpainting_mask']`` gives (it is
    bool, broadcastable to the motion ``shape = [B, J, F, N]``). MDM's ``in_between`` edit mode gives
    whole frames (prefix and suffix); ``upper_body`` gives channels of every frame, so no whole frame."""
    mask = torch.as_tensor(inpainting_mask)
    if mask.dtype != torch.bool:
        raise TypeError(f"frames_from_inpainting_mask: inpainting_mask must be bool, got {mask.dtype}")
    B, N = int(shape[0]), int(shape[-1])
    mask = mask.expand(*shape)
    return mask.reshape(B, -1, N).all(dim=1)


# --------------------------------------------------------------------------- MDM layout
def to_frame_last(x: torch.Tensor, njoints: int, nfeats: int) -> torch.Tensor:
    """``[B, N, D]`` -> MDM's ``[B, J, F, N]`` (``D = J * F``)."""
    B, N, D = x.shape
    if njoints * nfeats != D:
        raise ValueError(f"to_frame_last: D={D} != njoints * nfeats = {njoints} * {nfeats}")
    return x.reshape(B, N, njoints, nfeats).permute(0, 2, 3, 1).contiguous()


def to_batch_major(x: torch.Tensor) -> torch.Tensor:
    """MDM's ``[B, J, F, N]`` -> ``[B, N, J * F]``."""
    B, J, F_, N = x.shape
    return x.permute(0, 3, 1, 2).reshape(B, N, J * F_)


def conditioning(constraint: KeyframeConstraint, njoints: int, nfeats: int = 1,
                 y: Optional[Dict[str, Any]] = None, policy: str = "ends") -> Dict[str, Any]:
    """MDM's ``y`` for in-betweening: a copy of ``y`` (text conditioning etc.) with
    ``inpainting_mask`` / ``inpainted_motion`` (``[B, J, F, N]``), forced keyframes (``[B, N]``,
    per ``policy``, :func:`~smdm_plugin.adapters.request.with_forced`), and the valid frames
    ``mask [B, 1, 1, N]`` / ``lengths [B]`` unless ``y`` has them (then they must agree with the
    constraint's lengths)."""
    return _conditioning(constraint, njoints, nfeats, y, policy, "conditioning")


def _expect(value: Any, kind: Union[type, Tuple[type, ...]], fn: str, what: str, expected: str) -> None:
    """``TypeError`` naming ``what`` unless ``value`` is a ``kind``."""
    if not isinstance(value, kind):
        raise TypeError(f"{fn}: {what} must be {expected}, got {type(value).__name__}")


def _check_y_lengths(y: Dict[str, Any], L: torch.Tensor, N: int, fn: str) -> None:
    """``y['lengths']`` and a ``y['mask'] [B, 1, 1, N]`` (what the model reads instead of the
    constraint's lengths) give the constraint's valid frames ``L``: checked on the host for CPU
    tensors, else with ``torch._assert_async`` (once per call, no sync)."""
    B = L.shape[0]
    mask = y.get("mask")
    found: Dict[str, torch.Tensor] = {}
    if y.get("lengths") is not None:
        found["y['lengths']"] = as_lengths(y["lengths"], B, N, L.device, f"{fn}: y['lengths']")
    if isinstance(mask, torch.Tensor) and mask.shape[-1:] == (N,) and mask.numel() == B * N:
        found["y['mask']"] = mask.reshape(B, N).to(device=L.device, dtype=torch.long).sum(1)
    for name, got in found.items():
        shown = f" {got.tolist()}" if host_checkable(got) and host_checkable(L) else ""
        want = f" {L.tolist()}" if shown else ""
        require(got == L, f"{fn}: {name} gives lengths{shown} but the constraint's lengths are{want} "
                          "(keyframe_constraint(lengths=)); pass the same, or leave them out of y")


def _conditioning(constraint: KeyframeConstraint, njoints: int, nfeats: int, y: Optional[Dict[str, Any]],
                  policy: str, fn: str) -> Dict[str, Any]:
    """:func:`conditioning`, its errors naming ``fn``."""
    _expect(constraint, KeyframeConstraint, fn, "constraint", "a KeyframeConstraint (from keyframe_constraint)")
    _expect(y, (dict, type(None)), fn, "y", "a dict of conditions (text_embed, text, scale...) or None")
    out = dict(y or {})
    B, N, _ = constraint.target.shape
    out["inpainting_mask"] = to_frame_last(constraint.given, njoints, nfeats)
    out["inpainted_motion"] = to_frame_last(constraint.target, njoints, nfeats)
    out = with_forced(out, forced_keyframes(constraint.frames, constraint.lengths, policy))
    L = constraint.lengths
    if "mask" not in out and "lengths" not in out:
        out["lengths"] = L
        out["mask"] = (torch.arange(N, device=L.device)[None] < L[:, None]).view(B, 1, 1, N)
    else:
        _check_y_lengths(out, L, N, fn)
    return out


# --------------------------------------------------------------------------- imputation
def impute(x: torch.Tensor, mask: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The imputation step: ``x`` with its given entries (``mask`` True, broadcast to ``x``)
    replaced by ``target``. Used on the clean-motion prediction (MDM's edit mode) or, with a
    noised target, on ``x_t``."""
    return torch.where(mask.to(x.device).expand_as(x), target.to(x), x)


def _motion_dims(model: Any, D: int) -> Tuple[int, int]:
    """``(njoints, nfeats)`` of an MDM-family model (looked up through wrappers), else ``(D, 1)``;
    a model whose ``njoints * nfeats`` is not ``D`` is a ``ValueError``."""
    seen = set()
    found: Optional[Tuple[int, int]] = None
    m = model
    while m is not None and id(m) not in seen:
        seen.add(id(m))
        J, F_ = getattr(m, "njoints", None), getattr(m, "nfeats", None)
        if isinstance(J, int) and isinstance(F_, int):
            if J * F_ == D:
                return J, F_
            found = found or (J, F_)
        m = getattr(m, "model", None)
    if found is not None:
        raise ValueError(f"sample_inbetween: the constraint has D={D} features per frame but the model takes "
                         f"njoints * nfeats = {found[0]} * {found[1]} = {found[0] * found[1]}")
    return D, 1


def sample_inbetween(model: Callable, diffusion: Any, constraint: KeyframeConstraint, *,
                     y: Optional[Dict[str, Any]] = None, imputation: str = "x0", policy: str = "ends",
                     generator: Optional[torch.Generator] = None, progress: bool = False) -> torch.Tensor:
    """Sample motions ``[B, N, D]`` that pass through ``constraint`` (in the model's feature space).

    Args:
        model: an MDM-family model or a wrapper of one (classifier-free guidance); dense or sparse
            (a sparse model takes the forced keyframes; a dense one ignores them).
        diffusion: the in-package ``SimpleDiffusion`` (every ``imputation``), or a diffusion with
            MDM's ``p_sample_loop(model, shape, clip_denoised=..., model_kwargs=..., progress=...)``
            that honours the in-painting keys (MDM's ``GaussianDiffusion``: ``imputation="x0"``).
        y: extra conditioning (``text_embed``, ``text``, ``scale``...), copied, not changed; its
            ``lengths`` / ``mask``, if any, must agree with the constraint's lengths.
        imputation: ``"x0"`` (MDM's) or ``"xt"``; see ``smdm_plugin.reference.simple_diffusion``.
        policy: which given frames are forced keyframes (:func:`forced_keyframes`).
        generator: random generator (a diffusion whose ``p_sample_loop`` takes ``generator=``;
            with another a warning: it draws from torch's global generator).
    """
    fn = "sample_inbetween"
    _expect(constraint, KeyframeConstraint, fn, "constraint", "a KeyframeConstraint (from keyframe_constraint)")
    if not callable(getattr(diffusion, "p_sample_loop", None)):
        raise TypeError(f"{fn}: diffusion must have a p_sample_loop (SimpleDiffusion, MDM's GaussianDiffusion), "
                        f"got {type(diffusion).__name__}")
    _expect(generator, (torch.Generator, type(None)), fn, "generator", "a torch.Generator or None")
    B, N, D = constraint.target.shape
    J, F_ = _motion_dims(model, D)
    kwargs = {"y": _conditioning(constraint, J, F_, y, policy, fn)}
    shape = (B, J, F_, N)
    params = inspect.signature(diffusion.p_sample_loop).parameters
    if "imputation" in params:
        out = diffusion.p_sample_loop(model, shape, model_kwargs=kwargs, device=constraint.target.device,
                                      generator=generator, progress=progress, imputation=imputation)
    else:
        if imputation != "x0":
            raise ValueError(f"{fn}: imputation={imputation!r} needs a diffusion whose "
                             f"p_sample_loop takes imputation= (SimpleDiffusion); "
                             f"{type(diffusion).__name__} imputes the clean prediction only ('x0')")
        extra: Dict[str, Any] = {}
        if "generator" in params:
            extra["generator"] = generator
        elif generator is not None:
            warnings.warn(f"{fn}: generator is not used: {type(diffusion).__name__}.p_sample_loop takes no "
                          "generator= and draws from torch's global generator (seed it with torch.manual_seed)",
                          UserWarning, stacklevel=2)
        out = diffusion.p_sample_loop(model, shape, clip_denoised=False, model_kwargs=kwargs,
                                      progress=progress, **extra)
    return to_batch_major(out)
