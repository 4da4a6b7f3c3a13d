"""Small BVH reader and forward kinematics (tests, demo, keyframe studies on real motion).

Conventions: BVH rotation channels are Euler angles in degrees, applied intrinsically in the
order listed (``Zrotation Yrotation Xrotation`` -> ``R = Rz @ Ry @ Rx``). A joint's world
position is ``parent_pos + parent_R @ (offset + translation)``; its world rotation is
``parent_R @ R``. Lengths are in file units unless scaled (CMU: × 0.056444 = metres).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np

# the largest |value| an OFFSET or motion channel may hold (cm or degrees): every motion reader's bound
from .validate import MAX_ABS_VALUE

CMU_TO_METRES = 0.056444  # (1 / 0.45) * 2.54 / 100, CMU's FAQ

# HumanML3D 22-joint order; a tuple of CMU names is a synthesised midpoint
HUMANML22_FROM_CMU: Tuple[Union[str, Tuple[str, str]], ...] = (
    "Hips", "LeftUpLeg", "RightUpLeg", "Spine", "LeftLeg", "RightLeg", ("Spine", "Spine1"),
    "LeftFoot", "RightFoot", "Spine1", "LeftToeBase", "RightToeBase", "Neck1",
    ("Spine1", "LeftArm"), ("Spine1", "RightArm"), "Head", "LeftArm", "RightArm",
    "LeftForeArm", "RightForeArm", "LeftHand", "RightHand",
)


@dataclass
class BVH:
    """Parsed BVH. ``offsets [J, 3]`` (file units), ``channels[j]`` the channel names of joint
    ``j`` (e.g. ``["Zrotation", "Yrotation", "Xrotation"]``), ``motion [T, C]`` with the
    channels of all joints in hierarchy order, ``frame_time`` in seconds. ``end_sites`` lists
    ``(parent joint, offset [3])``; End Sites are not joints."""

    names: List[str]
    parents: List[int]
    offsets: np.ndarray
    channels: List[List[str]]
    frame_time: float
    motion: np.ndarray
    end_sites: List[Tuple[int, np.ndarray]] = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time


_VALID_CHANNELS = {"Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation"}


#: Frame Time limits in seconds: 100 kHz to one frame a minute (the frame rate stays a normal float)
MIN_FRAME_TIME, MAX_FRAME_TIME = 1e-5, 60.0


class BVHError(ValueError):
    """A BVH file that cannot be read correctly; the message names the file (and the line)."""

    def __init__(self, path: Union[str, Path], message: str, line: Optional[int] = None) -> None:
        self.path, self.line = str(path), line
        where = f"{path}" + (f", line {line}" if line is not None else "")
        super().__init__(f"read_bvh: {where}: {message}")


class BVHWarning(UserWarning):
    """A BVH file that is read with a tolerance other readers also apply (e.g. one motion row more
    than ``Frames:`` declares); the message names the file."""


def _decode(raw: bytes) -> str:
    """UTF-8 with or without a byte-order mark; Latin-1 (every byte valid) otherwise."""
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _tokens(lines: Sequence[str]) -> List[Tuple[str, int]]:
    """Whitespace-separated tokens (spaces, tabs) with their 1-based line numbers."""
    return [(t, n) for n, line in enumerate(lines, 1) for t in line.split()]


def read_bvh(path: Union[str, Path]) -> BVH:
    """Read a BVH file.

    Tolerant where other readers are: a UTF-8 byte-order mark, LF / CRLF / CR line endings, tabs,
    blank lines, and one motion row more than ``Frames:`` declares (Debian's ``Boxing_Toes.bvh``:
    3069 declared, 3070 present), which is ignored with a :class:`BVHWarning`. Strict otherwise:
    :class:`BVHError` (a ``ValueError`` naming the file and line) for a malformed HIERARCHY, wrong
    channel counts, unparsable or non-finite numbers, ``Frame Time`` <= 0 or non-finite, and a
    truncated motion.
    """
    try:
        raw = Path(path).read_bytes()
    except IsADirectoryError:
        raise BVHError(path, "is a folder, expected a .bvh file") from None
    lines = _decode(raw).splitlines()
    ml = next((k for k, ln in enumerate(lines) if ln.split()[:1] == ["MOTION"]), None)
    if ml is None:
        raise BVHError(path, "no MOTION section")
    head = _tokens(lines[:ml])
    # MOTION, Frames: n, Frame Time: t: the tokens of the next few lines (line numbers kept)
    tail = [(t, n + ml) for t, n in _tokens(lines[ml:ml + 8])]
    if not head or head[0][0] != "HIERARCHY":
        raise BVHError(path, "file must start with HIERARCHY", head[0][1] if head else None)

    def number(k: int, what: str, kind: type = float) -> float:
        if k >= len(head):
            raise BVHError(path, f"{what}: expected a number, got the end of the HIERARCHY", head[-1][1])
        t, n = head[k]
        try:
            v = kind(t)
        except ValueError:
            raise BVHError(path, f"{what}: expected {'an integer' if kind is int else 'a number'}, got {t!r}",
                           n) from None
        if not np.isfinite(v):
            raise BVHError(path, f"{what}: expected a finite number, got {t!r}", n)
        if abs(v) > MAX_ABS_VALUE:
            raise BVHError(path, f"{what}: {t} is beyond +-{MAX_ABS_VALUE:g} (not a real skeleton)", n)
        return v

    names: List[str] = []
    parents: List[int] = []
    offsets: List[List[float]] = []
    channels: List[List[str]] = []
    end_sites: List[Tuple[int, np.ndarray]] = []
    stack: List[int] = []          # joint index per open brace (-2 for an End Site)
    pending: int = -1              # joint / End Site opened by the next "{"
    i = 1
    while i < len(head):
        t, line = head[i]
        if t in ("ROOT", "JOINT"):
            if t == "ROOT" and stack:
                raise BVHError(path, "ROOT inside another joint", line)
            if i + 1 >= len(head) or head[i + 1][0] in ("{", "}"):
                raise BVHError(path, f"{t} without a name", line)
            parent = next((s for s in reversed(stack) if s >= 0), -1)
            names.append(head[i + 1][0])
            parents.append(parent)
            offsets.append([0.0, 0.0, 0.0])
            channels.append([])
            pending = len(names) - 1
            i += 2
        elif t == "End":
            if i + 1 >= len(head) or head[i + 1][0].lower() != "site":
                raise BVHError(path, "expected 'End Site'", line)
            parent = next((s for s in reversed(stack) if s >= 0), -1)
            end_sites.append((parent, np.zeros(3)))
            pending = -2
            i += 2
        elif t == "{":
            stack.append(pending)
            i += 1
        elif t == "}":
            if not stack:
                raise BVHError(path, "unbalanced braces in HIERARCHY", line)
            stack.pop()
            i += 1
        elif t == "OFFSET":
            if not stack:
                raise BVHError(path, "OFFSET outside a joint", line)
            vals = [number(i + k, "OFFSET") for k in (1, 2, 3)]
            if stack[-1] == -2:
                end_sites[-1] = (end_sites[-1][0], np.array(vals))
            else:
                offsets[stack[-1]] = vals
            i += 4
        elif t == "CHANNELS":
            n = int(number(i + 1, "CHANNELS count", int))
            ch = [c for c, _ in head[i + 2:i + 2 + n]]
            bad = [c for c in ch if c not in _VALID_CHANNELS]
            if n < 0 or len(ch) < n or bad or not stack or stack[-1] < 0:
                raise BVHError(path, f"bad CHANNELS {n} {' '.join(ch)} (expected {n} of "
                               f"{sorted(_VALID_CHANNELS)} inside a joint)", line)
            channels[stack[-1]] = ch
            i += 2 + n
        else:
            raise BVHError(path, f"unexpected token {t!r} in HIERARCHY", line)
    if stack:
        raise BVHError(path, "unbalanced braces in HIERARCHY (a '}' is missing)", ml + 1)
    if not names:
        raise BVHError(path, "no joints in HIERARCHY")
    n_ch = sum(len(c) for c in channels)
    n_frames, frame_time, first_row = _motion_header(path, tail)
    motion = _motion_rows(path, lines, first_row, n_frames, n_ch)
    return BVH(names, parents, np.array(offsets, dtype=np.float64), channels, frame_time, motion, end_sites)


def _motion_header(path: Union[str, Path], tok: Sequence[Tuple[str, int]]) -> Tuple[int, float, int]:
    """``(frames, frame time in s, line index of the first motion row)`` from ``MOTION Frames: n
    Frame Time: t`` (each on its own line, as every writer puts them)."""
    words = [t for t, _ in tok[1:6]]
    line = tok[0][1]
    if len(words) < 5 or words[0] != "Frames:" or words[2:4] != ["Frame", "Time:"]:
        raise BVHError(path, "MOTION needs 'Frames: n' and 'Frame Time: t'", line)
    try:
        n_frames = int(words[1])
    except ValueError:
        raise BVHError(path, f"Frames: expected an integer, got {words[1]!r}", tok[2][1]) from None
    if n_frames < 0:
        raise BVHError(path, f"Frames: must be >= 0, got {n_frames}", tok[2][1])
    try:
        frame_time = float(words[4])
    except ValueError:
        raise BVHError(path, f"Frame Time: expected a number (seconds), got {words[4]!r}", tok[5][1]) from None
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise BVHError(path, f"Frame Time: must be a finite number of seconds > 0, got {words[4]}", tok[5][1])
    if not MIN_FRAME_TIME <= frame_time <= MAX_FRAME_TIME:  # 1 / frame_time is the frame rate
        raise BVHError(path, f"Frame Time: {words[4]} s is outside [{MIN_FRAME_TIME:g}, {MAX_FRAME_TIME:g}] s "
                             f"(a frame rate of {1 / frame_time:.3g} fps)", tok[5][1])
    if n_frames < 2:
        raise BVHError(path, f"Frames: {n_frames}: a motion needs at least 2 frames", tok[2][1])
    return n_frames, frame_time, tok[5][1]  # rows start on the line after Frame Time


def _motion_rows(path: Union[str, Path], lines: Sequence[str], first: int, n_frames: int,
                 n_ch: int) -> np.ndarray:
    """The motion ``[n_frames, n_ch]``: one row per non-blank line from line index ``first``."""
    rows = [(k + 1, ln.split()) for k, ln in enumerate(lines[first:], first) if ln.strip()]
    for line, vals in rows:
        if len(vals) != n_ch:
            raise BVHError(path, f"motion row has {len(vals)} values, expected {n_ch} (the channels "
                           "declared in HIERARCHY)", line)
    if len(rows) < n_frames:
        raise BVHError(path, f"truncated motion: Frames: {n_frames} declared, {len(rows)} row(s) present")
    if len(rows) == n_frames + 1 and n_frames > 0:
        warnings.warn(BVHWarning(f"read_bvh: {path}: Frames: {n_frames} declared, {n_frames + 1} rows present; "
                                 f"the last row (line {rows[-1][0]}) is ignored, as other BVH readers do"),
                      stacklevel=3)
        rows = rows[:-1]
    elif len(rows) > n_frames:
        raise BVHError(path, f"Frames: {n_frames} declared, {len(rows)} motion rows present")
    try:
        motion = np.array([v for _, v in rows], dtype=np.float64).reshape(n_frames, n_ch)
    except ValueError:
        line, bad = next((ln, t) for ln, vals in rows for t in vals if not _is_float(t))
        raise BVHError(path, f"motion value {bad!r} is not a number", line) from None
    if not np.isfinite(motion).all():
        r = int(np.argwhere(~np.isfinite(motion))[0, 0])
        raise BVHError(path, "motion value is not finite (nan/inf)", rows[r][0])
    if n_frames and np.abs(motion).max() > MAX_ABS_VALUE:
        r = int(np.argwhere(np.abs(motion) > MAX_ABS_VALUE)[0, 0])
        raise BVHError(path, f"motion value beyond +-{MAX_ABS_VALUE:g} (not a real motion)", rows[r][0])
    return motion


def _is_float(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def _axis_rotation(axis: str, deg: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[T, 3, 3]`` about ``axis`` ('X', 'Y' or 'Z') by ``deg`` degrees."""
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    if axis == "X":
        m = [[o, z, z], [z, c, -s], [z, s, c]]
    elif axis == "Y":
        m = [[c, z, s], [z, o, z], [-s, z, c]]
    else:
        m = [[c, -s, z], [s, c, z], [z, z, o]]
    return np.stack([np.stack(r, -1) for r in m], -2)


def bvh_joint_positions(bvh: BVH, scale: float = 1.0) -> np.ndarray:
    """World joint positions ``[T, J, 3]`` (file units × ``scale``) by forward kinematics."""
    T = bvh.num_frames
    J = len(bvh.names)
    pos = np.zeros((T, J, 3))
    rot = np.zeros((T, J, 3, 3))
    col = 0
    for j in range(J):
        R = np.broadcast_to(np.eye(3), (T, 3, 3))
        trans = np.zeros((T, 3))
        for c in bvh.channels[j]:
            v = bvh.motion[:, col]
            col += 1
            if c.endswith("rotation"):
                R = R @ _axis_rotation(c[0], v)
            else:
                trans[:, "XYZ".index(c[0])] = v
        local = bvh.offsets[j][None] + trans
        p = bvh.parents[j]
        if p < 0:
            pos[:, j], rot[:, j] = local, R
        else:
            pos[:, j] = pos[:, p] + np.einsum("tij,tj->ti", rot[:, p], local)
            rot[:, j] = rot[:, p] @ R
    return pos * scale


def cmu_to_humanml22(positions: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """CMU (cgspeed MotionBuilder-friendly) joints ``[T, J, 3]`` -> HumanML3D 22-joint order
    ``[T, 22, 3]``; spine2 and the two collars are midpoints (see the cmu-humanml3d README)."""
    positions = np.asarray(positions)
    if positions.ndim != 3 or positions.shape[1:] != (len(names), 3):
        raise ValueError(f"cmu_to_humanml22: positions must be [T, J={len(names)}, 3], "
                         f"got {positions.shape}")
    where = {n: k for k, n in enumerate(names)}
    missing = sorted({n for e in HUMANML22_FROM_CMU for n in ((e,) if isinstance(e, str) else e)}
                     - set(where))
    if missing:
        raise ValueError(f"cmu_to_humanml22: names lack CMU joints {missing}")
    out = [positions[:, where[e]] if isinstance(e, str)
           else 0.5 * (positions[:, where[e[0]]] + positions[:, where[e[1]]])
           for e in HUMANML22_FROM_CMU]
    return np.stack(out, 1)


def frame_step(file_fps: float, fps: float) -> int:
    """Every how many frames a clip recorded at ``file_fps`` is sampled for about ``fps``:
    ``round(file_fps / fps)``, at least 1 (frames are never made up); the clip's rate is then
    ``file_fps / step``."""
    return max(1, int(round(file_fps / fps)))


def missing_cmu_joints(bvh: BVH) -> List[str]:
    """The CMU joint names the 22-joint (HumanML3D) mapping needs that ``bvh`` lacks (none: a CMU skeleton)."""
    where = {n for e in HUMANML22_FROM_CMU for n in ((e,) if isinstance(e, str) else e)}
    return sorted(where - set(bvh.names))


def cmu_clip(bvh: BVH, step: int, drop_first: bool = True, path: Union[str, Path] = "<bvh>") -> np.ndarray:
    """A read CMU clip as HumanML3D-ordered joints ``[T, 22, 3]`` in metres, every ``step``-th frame
    (frame 0, the converter's synthetic T-pose, dropped first); not a CMU skeleton: ``BVHError``."""
    missing = missing_cmu_joints(bvh)
    if missing:
        raise BVHError(path, f"not a CMU skeleton: lacks the joints {missing} that the 22-joint "
                       "(HumanML3D) mapping needs")
    pos = bvh_joint_positions(bvh, scale=CMU_TO_METRES)
    pos = pos[1:] if drop_first else pos
    return cmu_to_humanml22(pos[::step], bvh.names)


def load_cmu_clip(path: Union[str, Path], fps: int = 20, drop_first: bool = True) -> np.ndarray:
    """A CMU BVH clip as HumanML3D-ordered joints ``[T, 22, 3]`` in metres at about ``fps``: frame 0
    (the converter's synthetic T-pose) dropped, then every :func:`frame_step`-th frame (120 -> 20
    fps: file frames 1, 7, 13, ...)."""
    bvh = read_bvh(path)
    return cmu_clip(bvh, frame_step(bvh.fps, fps), drop_first, path)

