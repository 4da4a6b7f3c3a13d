"""Keyframes of motion capture, shared by ``smdm demo`` and ``smdm keyframes``: where the motion
comes from (BVH files, ``$SMDM_MOCAP``, the embedded CMU clips), its windows, and the keyframe
study (reconstruction error per selection method and reduction; a figure of one window)."""
from __future__ import annotations

import glob
import os
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from ...core.config import SparseConfig

#: metres per frame of VW's time axis: the library's default (SparseConfig.frame_index_scale, docs/defaults.md)
FRAME_INDEX_SCALE: float = SparseConfig.frame_index_scale

METHODS = ("vw", "uniform", "random", "mdo")
# the 22-joint skeleton (HumanML3D / SMPL order) as parent indices, for the stick figures
PARENTS22 = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)


# ----------------------------------------------------------------------------------------- data
def find_bvh(paths: Optional[Sequence[str]] = None) -> List[str]:
    """The BVH files to use: ``paths`` (files, or folders: their ``*.bvh``), else the ``*.bvh`` of
    the folder ``$SMDM_MOCAP``; ``[]`` when neither is given."""
    if not paths:
        env = os.environ.get("SMDM_MOCAP")
        paths = [os.path.abspath(env)] if env else []
    out: List[str] = []
    for p in paths:
        out += sorted(glob.glob(os.path.join(p, "*.bvh"))) if os.path.isdir(p) else [p]
    return out


def motion_source(bvh: Optional[Sequence[str]], max_clips: Optional[int] = None, log=print,
                  skipped: Optional[List[Tuple[str, str]]] = None, min_frames: int = 20
                  ) -> Tuple[str, List[str], List[Tuple[str, np.ndarray]]]:
    """The demo's motion: ``(source, files, clips)`` — ``clips`` ``[(name, joints [T, 22, 3] metres,
    20 fps)]`` from the BVH files of ``bvh`` (files or folders), else of the folder ``$SMDM_MOCAP``,
    else the embedded CMU clips (``files`` empty; with ``max_clips``, the first that have
    ``min_frames`` frames). Raises ``ValueError`` when a given source holds
    no ``.bvh`` file; BVH files that cannot be used are logged and listed in ``skipped``."""
    env = os.environ.get("SMDM_MOCAP")
    if bvh:
        source = "--bvh " + " ".join(bvh)
    elif env:
        if not os.path.isdir(env):
            raise ValueError(f"SMDM_MOCAP={env!r} is not a folder (unset it to use the embedded clips)")
        source = f"$SMDM_MOCAP ({os.path.abspath(env)})"
    else:
        from ...io.embedded import PATH, embedded_clips

        clips = embedded_clips()
        source = f"the {len(clips)} CMU clips embedded in the package ({PATH})"
        if max_clips:
            clips = [c for c in clips if len(c[1]) >= min_frames][:max_clips]
        return source, [], clips
    files = find_bvh(bvh or [env])
    if not files:
        raise ValueError(f"no .bvh file in {source}")
    return source, files, load_clips(files, max_clips=max_clips, log=log, skipped=skipped)


def load_clips(files: Sequence[str], fps: int = 20, max_clips: Optional[int] = None, log=print,
               skipped: Optional[List[Tuple[str, str]]] = None) -> List[Tuple[str, np.ndarray]]:
    """``[(name, joints [T, 22, 3] metres)]``. A file that cannot be used (unreadable, malformed,
    not a CMU skeleton — the 22-joint mapping needs CMU's joint names —, too short) is skipped and
    logged with the full reason (and appended to ``skipped`` as ``(file, reason)``); oddities the
    reader tolerates (its warnings, ``BVHWarning``) are logged with their category."""
    from ...io.bvh import load_cmu_clip

    clips = []
    for f in files:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                j = load_cmu_clip(f, fps=fps)
                reason = None if len(j) >= 20 else f"only {len(j)} frames at {fps} fps (20 needed)"
            except (ValueError, OSError, IndexError, KeyError) as e:  # malformed, unreadable, not CMU
                reason = " ".join(str(e).split()) or type(e).__name__
        for w in caught:
            if issubclass(w.category, UserWarning):
                msg = " ".join(str(w.message).split())
                log(f"  note: {msg if f in msg else f'{f}: {msg}'} ({w.category.__name__})")
            else:  # not ours to judge: hand it back
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        if reason is not None:
            log(f"  skipping {f}: {reason}")
            if skipped is not None:
                skipped.append((f, reason))
            continue
        clips.append((Path(f).stem, j.astype(np.float32)))
        if max_clips and len(clips) >= max_clips:
            break
    return clips


def windows(clips: Sequence[Tuple[str, np.ndarray]], length: int = 196, min_len: int = 40,
            max_windows: Optional[int] = None) -> List[Tuple[str, int, np.ndarray]]:
    """Consecutive non-overlapping windows of up to ``length`` frames (the tail if >= min_len)."""
    out = []
    for name, j in clips:
        for s in range(0, len(j), length):
            w = j[s:s + length]
            if len(w) >= min_len:
                out.append((name, s, w))
            if max_windows and len(out) >= max_windows:
                return out
    return out


def require_windows(wins: Sequence[Tuple[str, int, np.ndarray]], clips: Sequence[Tuple[str, np.ndarray]],
                    min_len: int = 40) -> None:
    """``ValueError`` (one line) when no clip gave a window of ``min_len`` frames: the keyframe study
    of no window would be a table of NaN."""
    if wins:
        return
    longest = max(clips, key=lambda c: len(c[1]), default=None)
    have = f"the longest, {longest[0]}, has {len(longest[1])}" if longest is not None else "no clip was given"
    raise ValueError(f"no clip has the {min_len} frames (at 20 fps) a keyframe window needs ({have}); "
                     "give longer clips")


def selection_features(joints: np.ndarray, frame_index_scale: float = FRAME_INDEX_SCALE) -> torch.Tensor:
    """``[1, T, 67]`` float32: the 22 global joint positions (metres) + frame index × scale
    (:func:`~smdm_plugin.core.selection_features.extract_selection_features`, kind ``raw``)."""
    from ...core.selection_features import extract_selection_features

    T = joints.shape[0]
    x = torch.from_numpy(np.asarray(joints).reshape(1, T, -1)).double()
    return extract_selection_features(x, "raw", frame_index_scale=frame_index_scale).float()


def reconstruction_error(joints: np.ndarray, mask: np.ndarray) -> Tuple[float, np.ndarray]:
    """Mean joint position error (mm) over all frames of linear interpolation from the keyframes
    ``mask [T]``, and the reconstruction ``[T, 22, 3]``."""
    from ...core.interpolation import interpolate_keyframes

    T = joints.shape[0]
    x = torch.from_numpy(joints.reshape(1, T, -1)).double()
    rec = interpolate_keyframes(x, torch.from_numpy(mask).view(1, T)).reshape(T, -1, 3).numpy()
    err = np.linalg.norm(rec - joints, axis=-1).mean() * 1000.0
    return float(err), rec


def keyframe_study(wins, reductions: Sequence[float], methods: Sequence[str] = METHODS, seed: int = 0,
                   frame_index_scale: float = FRAME_INDEX_SCALE) -> Dict[str, Any]:
    """Reconstruction error (mm) per method and reduction, averaged over the windows (at least one:
    ``ValueError`` otherwise)."""
    from ...core.selection import select_keyframes

    if not wins:
        raise ValueError("keyframe_study: no window of motion (every clip is shorter than a window)")

    g = torch.Generator().manual_seed(seed)
    table: Dict[str, Dict[float, float]] = {m: {} for m in methods}
    for r in reductions:
        for m in methods:
            errs = []
            for _, _, w in wins:
                f = selection_features(w, frame_index_scale)
                mask = select_keyframes(f, None, r, m, generator=g)[0].numpy()
                errs.append(reconstruction_error(w, mask)[0])
            table[m][r] = float(np.mean(errs))
    return {"reductions": list(reductions), "methods": list(methods), "mpjpe_mm": table,
            "frame_index_scale": frame_index_scale,
            "windows": len(wins), "frames": int(sum(len(w) for _, _, w in wins))}


def keyframe_markdown(study: Dict[str, Any]) -> str:
    reds = study["reductions"]
    lines = [f"Mean joint position error (mm) of linear interpolation from the keyframes, "
             f"{study['windows']} windows, {study['frames']} frames at 20 fps (selection features: "
             f"global joint positions + frame index × {study.get('frame_index_scale', FRAME_INDEX_SCALE)} m)",
             "", "| method | " + " | ".join(f"{int(round(r * 100))}% dropped" for r in reds) + " |",
             "| --- |" + " ---: |" * len(reds)]
    for m in study["methods"]:
        lines.append(f"| {m} | " + " | ".join(f"{study['mpjpe_mm'][m][r]:.1f}" for r in reds) + " |")
    return "\n".join(lines)


def plot_keyframes(win: np.ndarray, title: str, reduction: float, path: str, joint: int = 21,
                   frame_index_scale: float = FRAME_INDEX_SCALE) -> None:
    """Trajectory of ``joint`` (default: right wrist) with VW keyframes and reconstructions, and
    a stick-figure strip of the original vs. the VW reconstruction."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...core.selection import select_keyframes

    T = len(win)
    f = selection_features(win, frame_index_scale)
    vw = select_keyframes(f, None, reduction, "vw")[0].numpy()
    uni = select_keyframes(f, None, reduction, "uniform")[0].numpy()
    e_vw, rec_vw = reconstruction_error(win, vw)
    e_uni, rec_uni = reconstruction_error(win, uni)
    fig = plt.figure(figsize=(13, 7.5))
    t = np.arange(T) / 20.0
    for i, (axis, lab) in enumerate(((1, "height (y)"), (0, "x"))):
        ax = fig.add_subplot(2, 2, i + 1)
        ax.plot(t, win[:, joint, axis], color="0.2", lw=2, label="motion capture")
        ax.plot(t, rec_vw[:, joint, axis], color="tab:red", lw=1.2, label=f"VW interpolation ({e_vw:.0f} mm)")
        ax.plot(t, rec_uni[:, joint, axis], color="tab:blue", lw=1.0, ls="--",
                label=f"uniform interpolation ({e_uni:.0f} mm)")
        ax.scatter(t[vw], win[vw, joint, axis], color="tab:red", s=22, zorder=3, label="VW keyframes")
        ax.set_xlabel("time (s)")
        ax.set_ylabel(f"right wrist {lab} (m)")
        if i == 0:
            ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 1, 2)
    n = 10
    frames = np.linspace(0, T - 1, n).round().astype(int)
    spread = 0.9
    for k, fr in enumerate(frames):
        for src, col, lw in ((win, "0.3", 2.2), (rec_vw, "tab:red", 1.0)):
            p = src[fr] - np.array([src[fr, 0, 0], 0, src[fr, 0, 2]]) + np.array([k * spread, 0, 0])
            for j, par in enumerate(PARENTS22):
                if par >= 0:
                    ax.plot([p[j, 0], p[par, 0]], [p[j, 1], p[par, 1]], color=col, lw=lw)
        ax.text(k * spread, -0.1, f"{fr}{'*' if vw[fr] else ''}", ha="center", fontsize=8)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title("stick figures (x-y view, root-centred): grey = motion capture, red = VW reconstruction; "
                 "* = keyframe", fontsize=9)
    fig.suptitle(f"{title}: {T} frames, {int(vw.sum())} VW keyframes ({int(round(reduction * 100))}% dropped)")
    fig.tight_layout()
    from ...io.files import atomic_open

    try:  # atomic: never a half-written figure; a failed write names the file
        with atomic_open(path, "wb") as f:
            fig.savefig(f, format=os.path.splitext(path)[1][1:].lower() or "png", dpi=110)
    finally:
        plt.close(fig)
