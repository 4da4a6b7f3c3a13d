"""Reading a motion from a file the way a user has it (``smdm render``, ``smdm inbetween``)."""
from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ...io.validate import F32_MAX, check_magnitude

ACCEPTED = ("joints [N, 22|21, 3] or [B, N, J, 3], HumanML3D features [N, 263], KIT features [N, 251], "
            "joints66 features [N, 66] (features also batched [S, N, D], as smdm inbetween writes them), "
            "MDM results.npy (with --allow-pickle), or a .bvh file")
#: feature widths a .npy of per-frame features may have: HumanML3D, KIT-ML, joints66
FEATURE_DIMS = (263, 251, 66)


@dataclass
class LoadedMotion:
    """``joints [N, J, 3]`` (y up) and, when the file held features, ``features [N, D]`` of ``kind``
    (``humanml3d`` | ``kit`` | ``joints66``; else ``joints``, ``bvh`` or ``mdm-results``). ``chains``
    is set for a non-CMU BVH skeleton (None: the 22 / 21-joint default)."""

    joints: np.ndarray
    kind: str
    source: str
    fps: float
    features: Optional[np.ndarray] = None
    chains: Optional[tuple] = None

    @property
    def humanml22(self) -> bool:
        """Whether the joints are HumanML3D's 22 (metres), usable as keyframes of a 22-joint model."""
        return self.joints.shape[1] == 22 and self.chains is None


def _load_bvh(path: str, fps: float) -> LoadedMotion:
    """A BVH file's joints every :func:`~smdm_plugin.io.bvh.frame_step`-th frame for ``fps``, with the
    rate they then have (``fps`` when the file's rate is a multiple of it: check
    :func:`rate_differs`): a CMU skeleton as HumanML3D's 22 joints, another with its own joints."""
    from ...io.bvh import bvh_joint_positions, cmu_clip, frame_step, missing_cmu_joints, read_bvh
    from .animation import chains_from_parents

    bvh = read_bvh(path)
    step = frame_step(bvh.fps, fps)
    rate = bvh.fps / step
    rate = fps if _same_rate(rate, fps) else round(rate, 2)   # (a frame time is rounded: 120.0048 fps is 120)
    if not missing_cmu_joints(bvh):
        return LoadedMotion(cmu_clip(bvh, step, path=path), "bvh", path, rate)
    pos = bvh_joint_positions(bvh)[::step]  # another skeleton: draw its own joints
    return LoadedMotion(pos, "bvh", path, rate, chains=chains_from_parents(bvh.parents))


def _same_rate(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-3 * b


def rate_differs(motion: LoadedMotion, fps: float) -> Optional[str]:
    """None when ``motion`` has the rate ``fps`` asked for, else why not (a BVH recorded at a rate
    that is no multiple of it, or below it: frames are never made up)."""
    if _same_rate(motion.fps, fps):
        return None
    return (f"{motion.source} gives {motion.fps:g} fps, not {fps:g}: a BVH's frames are only skipped, every "
            "n-th kept (a file recorded at a multiple of the rate gives it exactly)")


def _load_pickled(path: str, sample: int) -> LoadedMotion:
    obj = np.load(path, allow_pickle=True)
    obj = obj.item() if obj.dtype == object and obj.shape == () else obj
    if not isinstance(obj, dict) or "motion" not in obj:
        raise ValueError(f"{path}: a pickled .npy without a 'motion' entry (expected MDM's results.npy)")
    motion = check_real_values(np.asarray(obj["motion"]), path)  # [B, J, 3, N]
    if motion.ndim != 4 or motion.shape[2] != 3:
        raise ValueError(f"{path}: 'motion' must be [B, J, 3, N] (MDM's results.npy), got {motion.shape}")
    if not 0 <= sample < motion.shape[0]:
        raise ValueError(f"{path}: sample must be in [0, {motion.shape[0]}), got {sample}")
    lengths = obj.get("lengths")
    n = int(lengths[sample]) if lengths is not None else motion.shape[-1]
    return check_plausible(LoadedMotion(motion[sample].transpose(2, 0, 1)[:n], "mdm-results", path, 20.0))


def load_motion(path: str, fps: float = 20.0, sample: int = 0, allow_pickle: bool = False) -> LoadedMotion:
    """Read ``path`` (see the module docstring); ``fps`` is the rate a BVH is resampled to and
    the rate assumed for ``.npy`` files. Raises ValueError / OSError with a one-line message."""
    from ...io.representation import Representation

    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such file")
    if path.lower().endswith(".bvh"):
        _one_motion(path, sample)
        return _load_bvh(path, fps)
    if not path.lower().endswith(".npy"):
        raise ValueError(f"{path}: expected a .npy or .bvh file ({ACCEPTED})")
    try:
        arr = np.load(path, allow_pickle=False)
    except ValueError as e:
        if "allow_pickle" not in str(e):
            raise ValueError(f"{path}: not a readable .npy file ({' '.join(str(e).split())})") from None
        if not allow_pickle:
            raise ValueError(f"{path} holds pickled Python objects (MDM's results.npy?); pass --allow-pickle "
                             "to read it, only if you trust the file") from None
        return _load_pickled(path, sample)
    except (EOFError, OSError) as e:  # an empty (0-byte) or truncated file
        raise ValueError(f"{path}: not a readable .npy file ({' '.join(str(e).split()) or 'empty file'})") from None
    arr = check_real_values(arr, path, "joint positions" if arr.shape[-1:] == (3,) else "features")
    if arr.ndim == 4 and arr.shape[-1] == 3:
        if not 0 <= sample < arr.shape[0]:
            raise ValueError(f"{path}: sample must be in [0, {arr.shape[0]}) for a [B, N, J, 3] file, got {sample}")
        arr = arr[sample]
    elif arr.ndim == 3 and arr.shape[-1] in FEATURE_DIMS:  # [S, N, D] features (smdm inbetween's *_features.npy)
        if not 0 <= sample < arr.shape[0]:
            raise ValueError(f"{path}: sample must be in [0, {arr.shape[0]}) for a [S, N, {arr.shape[-1]}] file, "
                             f"got {sample}")
        arr = arr[sample]
    else:
        _one_motion(path, sample)
    if arr.ndim == 3 and arr.shape[-1] == 3 and arr.shape[1] in (21, 22):
        out = LoadedMotion(arr, "joints", path, fps)
    elif arr.ndim == 2 and arr.shape[1] in (263, 251):
        from ...io.humanml3d import recover_from_ric

        kind = "humanml3d" if arr.shape[1] == 263 else "kit"
        out = LoadedMotion(recover_from_ric(arr, 22 if kind == "humanml3d" else 21), kind, path, fps, features=arr)
    elif arr.ndim == 2 and arr.shape[1] == 66:
        out = LoadedMotion(Representation("joints66").to_joints(arr), "joints66", path, fps, features=arr)
    else:
        raise ValueError(f"{path}: shape {arr.shape} is not a motion; expected {ACCEPTED}")
    if len(out.joints) < 1 or not np.isfinite(out.joints).all():
        raise ValueError(f"{path}: the motion is empty or holds NaN / inf")
    return check_plausible(out)


def _one_motion(path: str, sample: int) -> None:
    """A file of one motion has only sample 0: another ``sample`` cannot apply (an error, not ignored)."""
    if sample != 0:
        raise ValueError(f"{path} holds one motion: --sample {sample} applies to batched files only "
                         "([B, N, J, 3] joints, [S, N, D] features, MDM's results.npy)")


def check_real_values(arr: np.ndarray, path: str, what: str = "joint positions") -> np.ndarray:
    """``arr`` as float64 when it holds real, finite numbers that float32 (what the models and
    metrics compute in) can hold and a motion can be (``io.validate.check_magnitude``); else a
    ``ValueError`` naming ``path`` and the cause: complex or non-numeric dtypes, NaN / inf, a value
    beyond float32's range, an absurd one (``what`` the values are, and its index)."""
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{path}: expected real numbers, got dtype {arr.dtype}"
                         + (" (complex values are not a motion)" if arr.dtype.kind == "c" else ""))
    arr = arr.astype(np.float64)
    if arr.size and not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0].tolist()
        raise ValueError(f"{path}: holds a non-finite value ({arr[tuple(bad)]} at index {bad})")
    big = float(np.abs(arr).max()) if arr.size else 0.0
    if big > F32_MAX:
        raise ValueError(f"{path}: holds {big:.3g}, beyond float32's range (±{F32_MAX:.3g})")
    return check_magnitude(arr, path, what)


def check_plausible(m: LoadedMotion) -> LoadedMotion:
    """``m`` when its joint positions (also those computed from features) are within
    ``io.validate.MAX_ABS_VALUE``; a ``ValueError`` naming the file and the index otherwise (1e30 m
    is no motion: every metric of it would overflow)."""
    check_magnitude(m.joints, m.source, "joint positions")
    return m


def add_motion_file_options(p: argparse.ArgumentParser) -> None:
    """``--sample`` and ``--allow-pickle``, the options of :func:`load_motion` a command exposes."""
    from .args import int_range

    p.add_argument("--sample", type=int_range(0), default=0, help="which motion of a batched file, 0-based (default 0)")
    p.add_argument("--allow-pickle", action="store_true",
                   help="read pickled .npy files (MDM's results.npy); only for files you trust")
