"""In-betweening of a model bundle through keyframes taken from a motion file, shared by
``smdm inbetween`` and ``smdm demo``: where the keyframes go (:func:`plan_keyframes`), one model's
samples (:func:`run_inbetween`), and the summary table."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
import torch

from .motion_files import LoadedMotion


@dataclass
class Keyframes:
    """Where the keyframes go: ``frames`` (output indices, sorted) of an ``length``-frame output;
    ``source_frames`` the matching frames of the source file; ``segment`` the source frames
    ``[start, start + length)`` when the source covers them (the reference motion), else None."""

    frames: List[int]
    source_frames: List[int]
    length: int
    start: int
    placed: bool

    def segment(self, n_source: int) -> Optional[slice]:
        return None if self.placed or self.start + self.length > n_source else slice(self.start, self.start + self.length)


def plan_keyframes(n_source: int, frames: Optional[Sequence[int]], every: Optional[int], start: Optional[int],
                   length: Optional[int], max_frames: int) -> Keyframes:
    """Resolve ``--frames`` / ``--every`` / ``--start`` / ``--length`` against a source of
    ``n_source`` frames; ValueError with the option's name when they do not fit."""
    given_length = length is not None
    if frames:
        fr = sorted(set(int(f) for f in frames))
        if len(fr) != len(frames):
            raise ValueError(f"--frames: repeated frames in {list(frames)}")
        placed = len(fr) == n_source and fr[-1] >= n_source
        if placed:
            if list(frames) != fr:
                raise ValueError("--frames: give increasing frames (one per pose of the file, in order)")
            if start not in (None, 0):
                raise ValueError("--start: not used when poses are placed at --frames")
            start = 0
        elif fr[-1] >= n_source:
            raise ValueError(f"--frames: frame {fr[-1]} is beyond the {n_source} frames of the keyframe file "
                             f"(to place K poses, give K frames)")
        start = fr[0] if start is None else start
        if start > fr[0]:
            raise ValueError(f"--start {start} is after the first keyframe {fr[0]}")
        need = fr[-1] - start + 1
        length = need if length is None else length
        if length < need:
            raise ValueError(f"--length {length} is too short for keyframes up to frame {fr[-1]} from --start {start}")
        out = Keyframes([f - start for f in fr], list(range(len(fr))) if placed else fr, length, start, placed)
    else:
        start = 0 if start is None else start
        if start >= n_source:
            raise ValueError(f"--start {start} is beyond the {n_source} frames of the keyframe file")
        length = min(n_source - start, max_frames) if length is None else length
        if start + length > n_source:
            raise ValueError(f"--length {length} from --start {start} runs past the {n_source} frames of the "
                             "keyframe file")
        rel = sorted(set(range(0, length, every or 20)) | {length - 1})
        out = Keyframes(rel, [start + f for f in rel], length, start, False)
    if out.length > max_frames:
        raise ValueError(f"--length {out.length} exceeds the {max_frames} frames the model was trained on")
    if out.length < 2:   # (the length given, or what the other options leave)
        if given_length:
            raise ValueError(f"--length must be >= 2, got {out.length}")
        if frames:
            raise ValueError(f"--frames {list(frames)} from --start {out.start} span 1 frame; an in-between needs "
                             "at least 2: give --length")
        raise ValueError(f"--start {out.start} leaves 1 frame of the {n_source}-frame keyframe file; an in-between "
                         "needs at least 2")
    return out


@dataclass
class Result:
    """One model's in-betweens: ``features [S, N, D]`` (un-normalised), ``joints [S, N, 22, 3]``
    (metres, in the keyframe file's frame), ``target [N, 22, 3]`` the joints the keyframes come
    from (their segment of the file when it covers the output, else only keyframe frames are valid),
    ``feature_error`` max |output - keyframe| over the keyframes' features, ``seconds`` of sampling."""

    label: str
    features: np.ndarray
    joints: np.ndarray
    target: np.ndarray
    feature_error: float
    seconds: float


def model_inputs(bundle: Any, source: LoadedMotion, kf: Keyframes) -> tuple:
    """``(features [N, D] un-normalised, target joints [N, 22, 3], xz offset [3])`` for ``bundle``'s
    representation: the source's frames ``[start, start + length)`` (placed poses: at the keyframes,
    zeros elsewhere); ValueError when the source cannot give that representation."""
    rep = bundle.representation
    N, D = kf.length, rep.dim
    src = np.asarray(kf.source_frames)
    dst = np.asarray(kf.frames)
    feats = np.zeros((N, D), np.float32)
    if rep.name == "humanml3d":
        if source.kind != "humanml3d":
            raise ValueError(f"{bundle.path} is a HumanML3D (263-D) model: give the keyframes as HumanML3D "
                             f"features .npy [N, 263], got {source.kind} from {source.source}")
        feats[dst] = source.features[src]
        seg = kf.segment(len(source.features))
        ref = rep.to_joints(source.features[seg] if seg else feats)  # segment re-integrated from its frame 0
        return feats, np.asarray(ref, np.float32), np.zeros(3, np.float32)
    if not source.humanml22:
        raise ValueError(f"{source.source}: {source.joints.shape[1]} joints; a joints66 model needs HumanML3D's "
                         "22 joints (a CMU BVH, joints [N, 22, 3] or features [N, 263])")
    joints = np.asarray(source.joints, np.float32)
    offset = joints[src[0], 0].copy()
    offset[1] = 0.0
    feats[dst] = rep.from_joints(joints[src] - offset)
    seg = kf.segment(len(joints))
    ref = joints[seg] if seg else rep.to_joints(feats) + offset
    return feats, np.asarray(ref, np.float32), offset


def run_inbetween(bundle: Any, source: LoadedMotion, kf: Keyframes, samples: int = 1, seed: int = 0,
                  imputation: str = "x0", policy: str = "ends", device: Any = "cpu",
                  progress: bool = False) -> Result:
    """Sample ``samples`` in-betweens from ``bundle`` (:class:`~smdm_plugin.training.bundle.ModelBundle`)."""
    from ...adapters.inbetween_sampling import keyframe_constraint, sample_inbetween

    feats, target, offset = model_inputs(bundle, source, kf)
    x = bundle.normalise(torch.from_numpy(feats)).to(device).unsqueeze(0).expand(samples, -1, -1)
    constraint = keyframe_constraint(x.contiguous(), kf.frames)
    gen = torch.Generator(device=device).manual_seed(seed)
    bundle.model.to(device).eval()
    t0 = time.perf_counter()
    out = sample_inbetween(bundle.model, bundle.diffusion, constraint, imputation=imputation, policy=policy,
                           generator=gen, progress=progress)
    seconds = time.perf_counter() - t0
    out = bundle.denormalise(out.float()).cpu().numpy()
    err = float(np.abs(out[:, kf.frames] - feats[kf.frames][None]).max())
    joints = np.asarray(bundle.representation.to_joints(out), np.float32) + offset
    return Result(bundle.label, out, joints, target, err, seconds)


COLUMNS = (("keyframe feature error (max)", "feature_error", "{:.2g}"),
           ("keyframe error (mm)", "keyframe_error_mm", "{:.1f}"),
           ("root-relative keyframe error (mm)", "keyframe_error_root_relative_mm", "{:.1f}"),
           ("jitter at transitions (m/s³)", "jitter_transitions", "{:.0f}"),
           ("jitter (m/s³)", "jitter", "{:.0f}"),
           ("foot skating", "foot_skating", "{:.3f}"),
           ("in-between error vs source (mm)", "inbetween_error_mm", "{:.0f}"),
           ("sampling (s)", "seconds", "{:.2f}"))


def summary_markdown(rows: List[Dict[str, Any]]) -> str:
    cols = [c for c in COLUMNS if any(c[1] in r for r in rows)]
    lines = ["| model | " + " | ".join(c[0] for c in cols) + " |", "| --- |" + " ---: |" * len(cols)]
    for r in rows:
        lines.append(f"| {r['model']} | " + " | ".join(c[2].format(r[c[1]]) if c[1] in r else "—" for c in cols) + " |")
    ref = next((r for r in rows if "reference_jitter" in r), None)
    if ref:
        lines.append(f"\nthe source motion: jitter {ref['reference_jitter']:.0f} m/s³, at the transitions "
                     f"{ref['reference_jitter_transitions']:.0f} m/s³, foot skating {ref['reference_foot_skating']:.3f}")
    return "\n".join(lines)
