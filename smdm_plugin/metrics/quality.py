"""Motion quality on joint positions: foot skating ratio, jitter (mean jerk), mean speed, jitter per
unit speed, keyframe error."""
from __future__ import annotations

import warnings
from typing import Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.nn.functional as F

from .motion import ArrayLike, _as_tensor
from ..core.checks import as_lengths
from ..core.scalars import as_float

#: HumanML3D 22-joint (SMPL order) feet: l_foot (10), r_foot (11).
HUMANML3D_FEET: Tuple[int, ...] = (10, 11)

#: GMD's thresholds (``calculate_skating_ratio``): a foot is on the ground below 5 cm, and skates
#: when its horizontal speed exceeds 0.5 m/s (2.5 cm per frame at 20 fps) both in the frame and on
#: average over a 5-frame window.
SKATING_HEIGHT_M = 0.05
SKATING_SPEED_M_S = 0.5
SKATING_WINDOW = 5

Lengths = Union[int, Sequence[int], ArrayLike, None]


# --------------------------------------------------------------------------- input checks
def _positions(fn: str, motion: ArrayLike, name: str = "motion") -> torch.Tensor:
    """``[B, N, J, 3]`` floating tensor from ``[N, J, 3]`` / ``[B, N, J, 3]``."""
    x = _as_tensor(motion)
    if x.dim() not in (3, 4) or x.shape[-1] != 3:
        raise ValueError(f"{fn}: {name} must be joint positions [N, J, 3] or [B, N, J, 3] in metres, "
                         f"got shape {tuple(x.shape)}")
    x = x if torch.is_floating_point(x) else x.double()
    return x.unsqueeze(0) if x.dim() == 3 else x


def _lengths(fn: str, lengths: Lengths, B: int, N: int, minimum: int, device: torch.device
             ) -> torch.Tensor:
    """Valid frames per motion ``[B]`` (long), each in ``[minimum, N]`` (an int: every motion)."""
    return as_lengths(lengths, B, N, device, fn, minimum=minimum, broadcast=True)


def _fps(fn: str, fps: float) -> float:
    x = as_float(fps)
    if x is None or not np.isfinite(x) or x <= 0:
        raise ValueError(f"{fn}: fps must be a finite number > 0 (frames per second), got {fps!r}")
    return x


def _joints(fn: str, joints: Optional[Sequence[int]], J: int, name: str = "joints") -> list:
    idx = list(range(J)) if joints is None else [int(j) for j in joints]
    if not idx or min(idx) < -J or max(idx) >= J:
        raise ValueError(f"{fn}: {name} {tuple(idx)} must be non-empty indices into J={J} joints")
    return idx


def _inputs(fn: str, motion: ArrayLike, fps: float, lengths: Lengths, min_length: int,
            joints: Optional[Sequence[int]], joints_name: str = "joints"
            ) -> Tuple[torch.Tensor, float, torch.Tensor, list]:
    """Checked ``(positions [B, N, J, 3], fps, lengths [B], joint indices)``."""
    pos = _positions(fn, motion)
    B, N, J, _ = pos.shape
    return (pos, _fps(fn, fps), _lengths(fn, lengths, B, N, min_length, pos.device),
            _joints(fn, joints, J, joints_name))


class MetricOverflowWarning(RuntimeWarning):
    """A metric of finite positions came out inf / NaN: the values overflowed (not metres?)."""


def _warn_overflow(fn: str, pos: torch.Tensor, values: torch.Tensor) -> None:
    """Warn (:class:`MetricOverflowWarning`) when ``values``, computed from finite ``pos``, are not
    all finite: positions so large (1e30) that the differences overflow. The caller would otherwise
    report a silent inf / NaN (a "—" in a table)."""
    if values.numel() and not bool(torch.isfinite(values).all()) and bool(torch.isfinite(pos).all()):
        big = float(pos.abs().max())
        warnings.warn(f"{fn}: the result overflowed (inf / NaN) for finite joint positions reaching {big:.3g}; "
                      "positions are expected in metres", MetricOverflowWarning, stacklevel=3)


def _reduce(fn: str, per_motion: torch.Tensor, reduce: str) -> torch.Tensor:
    if reduce == "none":
        return per_motion
    if reduce == "mean":
        return per_motion.mean()
    raise ValueError(f"{fn}: reduce must be 'mean' or 'none', got {reduce!r}")


# --------------------------------------------------------------------------- foot skating
def foot_skating_ratio(motion: ArrayLike, *, fps: float = 20.0, lengths: Lengths = None,
                       feet: Sequence[int] = HUMANML3D_FEET, up_axis: int = 1,
                       height: float = SKATING_HEIGHT_M, speed: float = SKATING_SPEED_M_S,
                       window: int = SKATING_WINDOW, reduce: str = "mean") -> torch.Tensor:
    """Fraction of frame steps in which a foot on the ground slides (a number in [0, 1]).

    Definition (GMD's ``calculate_skating_ratio``, used unchanged by CondMDI and DNO): for every
    step ``n -> n + 1`` (``n = 0 .. L-2``) and foot ``f``, the horizontal speed is
    ``v = |p_f(n+1) - p_f(n)|_xz * fps`` (m/s) and ``v̄`` its moving average over ``window``
    steps (zeros outside the motion, as ``scipy.ndimage.uniform_filter1d(mode="constant")``).
    The foot skates in that step when it is in contact — its height is below ``height`` metres in
    both frames — and ``v > speed`` and ``v̄ > speed``. The ratio is the number of steps in which
    either foot skates, over ``L - 1``. Defaults are GMD's: 5 cm, 0.5 m/s (2.5 cm/frame at 20 fps),
    5-frame window, HumanML3D feet 10 and 11, y up; heights are measured from ``y = 0`` (HumanML3D
    puts the floor there).

    Difference from the reference code: CondMDI scores every motion over the padded 196 frames;
    here only the ``lengths`` valid frames count (as DNO, which cuts each motion to its length).

    Args:
        motion: joint positions ``[N, J, 3]`` / ``[B, N, J, 3]`` in metres.
        fps: frames per second (HumanML3D: 20).
        lengths: valid frames per motion (int or ``[B]``, each >= 2); None = all ``N``.
        feet: foot joint indices (KIT-ML's 21 joints: ``(15, 20)``).
        up_axis: the vertical axis of the positions (0, 1 or 2).
        height, speed, window: contact height (m), sliding speed (m/s), averaging window (steps).
        reduce: ``"mean"`` (mean of the per-motion ratios) or ``"none"`` (``[B]``).
    """
    fn = "foot_skating_ratio"
    pos, rate, L, idx = _inputs(fn, motion, fps, lengths, 2, feet, "feet")
    B, N = pos.shape[:2]
    if up_axis not in (0, 1, 2):
        raise ValueError(f"{fn}: up_axis must be 0, 1 or 2, got {up_axis!r}")
    if not (height > 0 and speed > 0) or int(window) < 1:
        raise ValueError(f"{fn}: height and speed must be > 0 and window >= 1, got {height}, {speed}, {window}")
    plane = [a for a in range(3) if a != up_axis]
    f = pos[:, :, idx]                                                    # [B, N, F, 3]
    v = (f[:, 1:, :, plane] - f[:, :-1, :, plane]).norm(dim=-1) * rate    # [B, N-1, F]
    step_valid = torch.arange(N - 1, device=pos.device)[None] < (L - 1)[:, None]  # [B, N-1]
    v = v * step_valid[..., None].to(v.dtype)                             # as if cut to length
    w = int(window)
    left, right = w // 2, w - 1 - w // 2                                  # scipy's origin=0 window
    flat = v.permute(0, 2, 1).reshape(-1, 1, N - 1)
    v_avg = F.avg_pool1d(F.pad(flat, (left, right)), w, stride=1).reshape(B, len(idx), N - 1)
    v_avg = v_avg.permute(0, 2, 1)
    h = f[..., up_axis]
    contact = (h[:, :-1] < height) & (h[:, 1:] < height)                  # [B, N-1, F]
    skating = contact & (v > speed) & (v_avg > speed)
    any_foot = skating.any(dim=-1) & step_valid                           # [B, N-1]
    per_motion = any_foot.sum(dim=1).to(pos.dtype) / (L - 1).to(pos.dtype)
    return _reduce(fn, per_motion, reduce)


# --------------------------------------------------------------------------- jitter
def jitter(motion: ArrayLike, *, fps: float = 20.0, lengths: Lengths = None,
           joints: Optional[Sequence[int]] = None, frame_mask: Optional[ArrayLike] = None,
           reduce: str = "mean") -> torch.Tensor:
    """Mean jerk magnitude of the joints, in m/s³ (lower is smoother).

    Definition (DNO's ``compute_jitter``): the jerk of joint ``j`` at step ``k``
    (``k = 0 .. L-4``) is the third finite difference
    ``(p_j(k+3) - 3 p_j(k+2) + 3 p_j(k+1) - p_j(k)) * fps³``; jitter is the mean of its Euclidean
    norm over the counted steps and the ``joints`` (default: all ``J``). A motion moving at
    constant velocity or constant acceleration has jitter 0.

    Args:
        motion: joint positions ``[N, J, 3]`` / ``[B, N, J, 3]`` in metres.
        fps: frames per second (HumanML3D: 20). Jitter scales with ``fps³``.
        lengths: valid frames per motion (int or ``[B]``, each >= 4); None = all ``N``.
        joints: joint indices to average over (None: all).
        frame_mask: bool ``[N]`` or ``[B, N]``, e.g. frames around keyframes: a jerk step counts
            when any of its four frames ``k .. k+3`` is in the mask (and all four are valid).
            A motion with no counted step gets NaN (``reduce="none"``) and is left out of the mean.
        reduce: ``"mean"`` (mean of the per-motion values) or ``"none"`` (``[B]``).
    """
    fn = "jitter"
    pos, rate, L, idx = _inputs(fn, motion, fps, lengths, 4, joints)
    B, N = pos.shape[:2]
    p = pos[:, :, idx]
    jerk = (p[:, 3:] - 3 * p[:, 2:-1] + 3 * p[:, 1:-2] - p[:, :-3]) * rate ** 3   # [B, N-3, J', 3]
    mag = jerk.norm(dim=-1).mean(dim=-1)                                  # [B, N-3]
    counted = torch.arange(N - 3, device=pos.device)[None] < (L - 3)[:, None]
    if frame_mask is not None:
        fm = _as_tensor(frame_mask).to(pos.device)
        if fm.dtype != torch.bool:
            raise TypeError(f"{fn}: frame_mask must be bool, got dtype {fm.dtype}")
        fm = fm.unsqueeze(0).expand(B, -1) if fm.dim() == 1 else fm
        if tuple(fm.shape) != (B, N):
            raise ValueError(f"{fn}: frame_mask must be [N]=[{N}] or [B, N]=[{B}, {N}], got {tuple(fm.shape)}")
        touches = fm[:, :-3] | fm[:, 1:-2] | fm[:, 2:-1] | fm[:, 3:]
        counted = counted & touches
    _warn_overflow(fn, p, mag[counted])
    w = counted.to(mag.dtype)
    n = w.sum(dim=1)
    per_motion = (mag * w).sum(dim=1) / n                                 # NaN: no counted step
    if reduce == "mean":
        return per_motion[n > 0].mean()
    return _reduce(fn, per_motion, reduce)


# --------------------------------------------------------------------------- speed, jitter per speed
def mean_speed(motion: ArrayLike, *, fps: float = 20.0, lengths: Lengths = None,
               joints: Optional[Sequence[int]] = None, reduce: str = "mean") -> torch.Tensor:
    """Mean joint speed in m/s: the norm of the first finite difference
    ``(p_j(k+1) - p_j(k)) * fps`` averaged over the steps ``k = 0 .. L-2`` and the ``joints``
    (default: all). Arguments as :func:`jitter` (``lengths`` each >= 2)."""
    fn = "mean_speed"
    pos, rate, L, idx = _inputs(fn, motion, fps, lengths, 2, joints)
    B, N = pos.shape[:2]
    p = pos[:, :, idx]
    mag = ((p[:, 1:] - p[:, :-1]) * rate).norm(dim=-1).mean(dim=-1)      # [B, N-1]
    counted = torch.arange(N - 1, device=pos.device)[None] < (L - 1)[:, None]
    _warn_overflow(fn, p, mag[counted])
    w = counted.to(mag.dtype)
    return _reduce(fn, (mag * w).sum(dim=1) / w.sum(dim=1), reduce)


def jitter_per_speed(motion: ArrayLike, *, fps: float = 20.0, lengths: Lengths = None,
                     joints: Optional[Sequence[int]] = None, reduce: str = "mean") -> torch.Tensor:
    """Jitter relative to how fast the motion moves, in 1/s² ("j/s"): :func:`jitter` (m/s³) over
    :func:`mean_speed` (m/s). Raw jitter grows with the speed of the motion (a model that moves
    more jitters more in m/s³), so sets of motions are compared by this ratio, reported beside the
    speed it is relative to.

    ``reduce="mean"``: the ratio of the set's means, ``mean_b jitter_b / mean_b speed_b`` (one
    near-still motion cannot blow it up); ``reduce="none"``: per motion ``jitter_b / speed_b``
    ``[B]``. Arguments as :func:`jitter` (``lengths`` each >= 4)."""
    fn = "jitter_per_speed"
    if reduce not in ("mean", "none"):
        raise ValueError(f"{fn}: reduce must be 'mean' or 'none', got {reduce!r}")
    pos, rate, L, idx = _inputs(fn, motion, fps, lengths, 4, joints)
    j = jitter(pos, fps=rate, lengths=L, joints=idx, reduce="none")
    v = mean_speed(pos, fps=rate, lengths=L, joints=idx, reduce="none")
    return j.mean() / v.mean() if reduce == "mean" else j / v


# --------------------------------------------------------------------------- keyframe error
def keyframe_error(motion: ArrayLike, target: ArrayLike, keyframes: ArrayLike, *, fps: float = 20.0,
                   lengths: Lengths = None, joints: Optional[Sequence[int]] = None,
                   reduce: str = "mean") -> torch.Tensor:
    """Mean joint position error at the keyframes, in metres.

    Definition (CondMDI's keyframe error): at every keyframe ``k`` of a motion, the Euclidean
    distance ``|p_j(k) - q_j(k)|`` between the motion's and the target's joint ``j``, averaged
    over the ``joints`` (default: all ``J``), then over that motion's keyframes.

    Args:
        motion: generated joint positions ``[N, J, 3]`` / ``[B, N, J, 3]`` in metres.
        target: the positions the keyframes were taken from, same shape as ``motion``.
        keyframes: bool ``[N]`` / ``[B, N]`` (True = keyframe, as ``KeyframeRequest.mask``), or
            frame indices: a list / 1-D integer tensor for every motion, or one list per motion.
            Every motion needs at least one keyframe, all within its length.
        fps: frames per second; accepted so that every metric takes ``fps`` and ``lengths``
            alike, unused (the error is per frame).
        lengths: valid frames per motion (int or ``[B]``); None = all ``N``.
        joints: joint indices to average over (None: all; ``[0]`` gives the root error).
        reduce: ``"mean"`` (mean of the per-motion errors) or ``"none"`` (``[B]``).
    """
    fn = "keyframe_error"
    pos, _, L, idx = _inputs(fn, motion, fps, lengths, 1, joints)
    ref = _positions(fn, target, "target")
    if ref.shape != pos.shape:
        raise ValueError(f"{fn}: target must have the shape of motion {tuple(pos.shape)}, "
                         f"got {tuple(ref.shape)}")
    B, N = pos.shape[:2]
    mask = _keyframe_mask(fn, keyframes, B, N, pos.device)
    beyond = mask & (torch.arange(N, device=pos.device)[None] >= L[:, None])
    if bool(beyond.any()):
        b = int(beyond.any(dim=1).nonzero()[0])
        raise ValueError(f"{fn}: keyframes must lie within lengths; motion {b} has one at frame "
                         f"{int(beyond[b].nonzero()[0])} >= length {int(L[b])}")
    empty = ~mask.any(dim=1)
    if bool(empty.any()):
        raise ValueError(f"{fn}: keyframes must hold at least one frame per motion; motion "
                         f"{int(empty.nonzero()[0])} has none")
    err = (pos[:, :, idx] - ref[:, :, idx].to(pos)).norm(dim=-1).mean(dim=-1)   # [B, N]
    w = mask.to(err.dtype)
    per_motion = (err * w).sum(dim=1) / w.sum(dim=1)
    return _reduce(fn, per_motion, reduce)


def _keyframe_mask(fn: str, keyframes: ArrayLike, B: int, N: int, device: torch.device) -> torch.Tensor:
    """bool ``[B, N]`` from a mask ``[N]`` / ``[B, N]`` or frame indices (shared or per motion)."""
    per_motion = (list, tuple, np.ndarray, torch.Tensor)
    if isinstance(keyframes, (list, tuple)) and keyframes and isinstance(keyframes[0], per_motion):
        if len(keyframes) != B:
            raise ValueError(f"{fn}: keyframes given per motion must list B={B} motions, got {len(keyframes)}")
        rows = [_keyframe_mask(fn, k, 1, N, device) for k in keyframes]
        return torch.cat(rows, dim=0)
    if isinstance(keyframes, (list, tuple)):
        k = torch.tensor(list(keyframes)) if keyframes else torch.zeros(0, dtype=torch.long)
    else:
        k = _as_tensor(keyframes)
    k = k.to(device)
    if k.dtype == torch.bool:
        k = k.unsqueeze(0).expand(B, -1) if k.dim() == 1 else k
        if tuple(k.shape) != (B, N):
            raise ValueError(f"{fn}: a keyframe mask must be [N]=[{N}] or [B, N]=[{B}, {N}], got {tuple(k.shape)}")
        return k
    if torch.is_floating_point(k) or k.dim() != 1:
        raise ValueError(f"{fn}: keyframes must be a bool mask [N] / [B, N] or integer frame indices, "
                         f"got dtype {k.dtype}, shape {tuple(k.shape)}")
    if k.numel() and (int(k.min()) < 0 or int(k.max()) >= N):
        raise ValueError(f"{fn}: keyframe indices must be in [0, N={N}), got {k.tolist()}")
    mask = torch.zeros(B, N, dtype=torch.bool, device=device)
    mask[:, k.long()] = True
    return mask
