"""Captioned motion for training and scoring evaluators: :class:`CaptionedMotions` from a
HumanML3D-format folder (``new_joint_vecs/<id>.npy`` ``[T, D]``, ``texts/<id>.txt``, ``Mean.npy``,
``Std.npy``, ``<split>.txt``) or from the CMU clips embedded in the package (``joints66`` features,
the representation ``smdm demo`` trains on, captioned with CMU's one-line descriptions).

As HumanML3D's loader: a caption line with a ``from#to`` span (seconds) is a motion of its own (the
span, cut at 20 fps); motions shorter than ``min_frames`` (40) are left out, longer ones are cut to
their first ``max_frames`` (196) by the evaluator.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ...io.captions import Caption, plain_tokens


@dataclass
class CaptionedMotions:
    """``ids`` (M names), ``motions`` (raw features ``[L_i, D]``), ``captions`` (per motion, >= 1),
    ``mean``/``std`` ``[D]`` (the data set's normalisation), ``representation`` (``humanml3d`` or
    ``joints66``), ``fps``."""

    ids: List[str]
    motions: List[np.ndarray]
    captions: List[List[Caption]]
    mean: np.ndarray
    std: np.ndarray
    representation: str = "humanml3d"
    fps: float = 20.0

    def __len__(self) -> int:
        return len(self.ids)

    def first_captions(self, seed: Optional[int] = None) -> List[List[str]]:
        """One caption per motion (token lists): the first, or a seeded random one (as upstream draws)."""
        if seed is None:
            return [c[0].tokens for c in self.captions]
        rng = np.random.default_rng(seed)
        return [c[int(rng.integers(len(c)))].tokens for c in self.captions]


def load_captioned(root: str, split: str = "test", min_frames: int = 40, fps: float = 20.0) -> CaptionedMotions:
    """The ``split`` of a HumanML3D-format folder (see the module docstring), read with
    :func:`~smdm_plugin.io.humanml3d.load_humanml3d` (motions kept whole; a motion without
    ``texts/<id>.txt`` is left out)."""
    from ...io.humanml3d import load_humanml3d

    if not os.path.isdir(os.path.join(root, "texts")):
        raise FileNotFoundError(f"--data {root!r}: not a HumanML3D-format folder with captions (missing texts)")
    data = load_humanml3d(root, split, None, min_frames, captions=True)
    ids, motions, captions = [], [], []
    for name, motion, caps in zip(data.ids, data.motions, data.captions):
        whole: List[Caption] = []
        for k, c in enumerate(caps):
            if c.start == 0.0 and c.end == 0.0:
                whole.append(c)
                continue
            part = motion[int(c.start * fps):int(c.end * fps)]
            if len(part) >= min_frames:
                ids.append(f"{name}#{k}")
                motions.append(part)
                captions.append([c])
        if whole:
            ids.append(name)
            motions.append(motion)
            captions.append(whole)
    if not ids:
        raise ValueError(f"--data {root!r}: split {split!r} has no captioned motion of >= {min_frames} frames")
    return CaptionedMotions(ids, motions, captions, data.mean, data.std)


def embedded_captioned(split: str, window: int = 40, stride: int = 8) -> CaptionedMotions:
    """The embedded CMU clips as ``joints66`` windows of ``window`` frames, captioned with CMU's
    description. The split is by time inside each clip (every clip's motion style is in train): the
    first 60% of a clip's frames give ``train`` windows, the next 20% ``val``, the last 20% ``test``
    (windows never cross those borders; a clip too short for a window in a part gives none there)."""
    from ...io.embedded import embedded_clips, embedded_descriptions

    if split not in ("train", "val", "test"):
        raise ValueError(f"embedded data: split must be train, val or test, got {split!r}")
    parts = {"train": (0.0, 0.6), "val": (0.6, 0.8), "test": (0.8, 1.0)}
    return clips_captioned(embedded_clips(), embedded_descriptions(), parts[split], window, stride,
                           what=f"embedded data: no {split} window")


def clips_captioned(clips: Sequence[Tuple[str, np.ndarray]], descriptions: Dict[str, str],
                    part: Tuple[float, float], window: int = 40, stride: int = 8,
                    what: str = "clips: no window") -> CaptionedMotions:
    """``joints66`` windows of ``window`` frames (every ``stride``) of the part ``part`` (fractions
    ``(from, to)`` of each clip's frames; windows never cross its borders, a part shorter than 40
    frames gives none) of ``clips`` ``[(name, joints [T, 22, 3] metres, 20 fps)]``, each captioned
    with ``descriptions[name]`` (the name itself when absent). Mean/std: over all frames of all clips."""
    from ...io.representation import canonical_xz, joints_to_joints66

    feats_all = [joints_to_joints66(canonical_xz(np.asarray(j, np.float32))) for _, j in clips]
    allf = np.concatenate(feats_all)
    mean, std = allf.mean(0).astype(np.float32), (allf.std(0) + 1e-4).astype(np.float32)
    ids, motions, captions = [], [], []
    for name, j in clips:
        T = len(j)
        a, b = int(part[0] * T), int(part[1] * T)
        w = min(window, b - a)
        if w < 40:
            continue
        text = descriptions.get(name) or name
        for s in range(a, b - w + 1, stride):
            seg = np.asarray(j[s:s + w], np.float32)
            ids.append(f"{name}@{s}")
            motions.append(joints_to_joints66(canonical_xz(seg)).astype(np.float32))
            captions.append([Caption(text, plain_tokens(text))])
    if not ids:
        raise ValueError(what)
    return CaptionedMotions(ids, motions, captions, mean, std, representation="joints66")


def load_split(data: Optional[str], split: str) -> CaptionedMotions:
    """``load_captioned(data, split)``, or the embedded clips when ``data`` is None."""
    return embedded_captioned(split) if data is None else load_captioned(data, split)


def split_names(data: Optional[str]) -> Tuple[str, ...]:
    """The held-out splits present: ``val`` and/or ``test``."""
    if data is None:
        return ("val", "test")
    return tuple(s for s in ("val", "test") if os.path.isfile(os.path.join(data, f"{s}.txt")))
