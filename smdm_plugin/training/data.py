"""Training data: :class:`MotionSet` (normalised motions, unpadded), :class:`MotionData`
(``smdm ablate``'s train + validation splits with a fingerprint), the feature statistics, and the
check that clips are long enough for a reduction. Read from a HumanML3D-format folder with
:func:`~smdm_plugin.io.humanml3d.load_humanml3d` (the one reader of that layout)."""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, List, Optional, Sequence, Tuple

import numpy as np
import torch

from ..core.config import SparseConfig
from ..io.humanml3d import load_humanml3d

if TYPE_CHECKING:
    from ..io.humanml3d import HumanML3DSplit


@dataclass
class MotionSet:
    """Normalised motions, stored unpadded: ``frames [sum(lengths), D]`` float32 (sample ``i`` is
    rows ``offsets[i]:offsets[i + 1]``), ``lengths [M]`` long, ``ids`` (M names), ``mean``/``std``
    ``[D]`` (the normalisation, needed to select keyframes on de-normalised features), ``joints``
    (optional, per sample ``[L, 22, 3]`` metres), ``max_frames`` N (batches are padded to it),
    ``captions`` (optional, per sample its caption texts, for text conditioning)."""

    frames: torch.Tensor
    lengths: torch.Tensor
    ids: List[str]
    mean: np.ndarray
    std: np.ndarray
    max_frames: int
    joints: Optional[List[Optional[np.ndarray]]] = None
    captions: Optional[List[List[str]]] = None
    offsets: torch.Tensor = field(init=False)

    def __post_init__(self) -> None:
        if self.frames.dim() != 2:
            raise ValueError(f"MotionSet: frames must be [sum(lengths), D], got {tuple(self.frames.shape)}")
        D = self.frames.shape[1]
        if self.lengths.dim() != 1 or len(self.ids) != len(self.lengths):
            raise ValueError(f"MotionSet: lengths must be [M] with M={len(self.ids)} ids, got "
                             f"{tuple(self.lengths.shape)}")
        if int(self.lengths.sum()) != self.frames.shape[0]:
            raise ValueError(f"MotionSet: frames has {self.frames.shape[0]} rows but lengths sum to "
                             f"{int(self.lengths.sum())}")
        if len(self.lengths) and (int(self.lengths.min()) < 2 or int(self.lengths.max()) > self.max_frames):
            raise ValueError(f"MotionSet: lengths must be in [2, max_frames={self.max_frames}], got "
                             f"[{int(self.lengths.min())}, {int(self.lengths.max())}]")
        for name in ("mean", "std"):
            if np.shape(getattr(self, name)) != (D,):
                raise ValueError(f"MotionSet: {name} must be [D]=[{D}], got {np.shape(getattr(self, name))}")
        if self.captions is not None and (len(self.captions) != len(self.ids) or not all(self.captions)):
            raise ValueError(f"MotionSet: captions must hold a non-empty list of texts for each of the "
                             f"{len(self.ids)} motions, got {len(self.captions)} entries")
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.long), self.lengths.long().cumsum(0)])

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def feature_dim(self) -> int:
        return int(self.frames.shape[1])

    def padded(self, indices: Optional[Sequence[int]] = None) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(x [b, N, D], lengths [b])``: the samples ``indices`` (all when None), zero-padded to
        ``N = max_frames``."""
        idx = torch.arange(len(self)) if indices is None else torch.as_tensor(indices, dtype=torch.long)
        x = self.frames.new_zeros(len(idx), self.max_frames, self.feature_dim)
        for row, i in enumerate(idx.tolist()):
            a, b = int(self.offsets[i]), int(self.offsets[i + 1])
            x[row, :b - a] = self.frames[a:b]
        return x, self.lengths[idx].clone()

    @classmethod
    def from_motions(cls, motions: Sequence[np.ndarray], mean: np.ndarray, std: np.ndarray,
                     ids: Optional[Sequence[str]] = None, max_frames: int = 196,
                     joints: Optional[List[Optional[np.ndarray]]] = None) -> "MotionSet":
        """From raw (un-normalised) motions ``[L_i, D]``; each is cut to its first ``max_frames``."""
        mean, std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
        cut = [np.asarray(m, np.float32)[:max_frames] for m in motions]
        if not cut:
            raise ValueError("MotionSet.from_motions: no motions given")
        D = mean.shape[-1] if mean.ndim == 1 else -1
        for name, v in (("mean", mean), ("std", std)):
            if v.shape != (D,) or any(m.ndim != 2 or m.shape[1] != D for m in cut):
                raise ValueError(f"MotionSet: motions must be [L, D] and {name} [D]; got {name} {v.shape} and "
                                 f"motions {sorted({m.shape[1:] for m in cut})}")
        frames = torch.from_numpy(np.concatenate([(m - mean) / std for m in cut]).astype(np.float32))
        lengths = torch.tensor([len(m) for m in cut], dtype=torch.long)
        names = list(ids) if ids is not None else [str(i) for i in range(len(cut))]
        return cls(frames, lengths, names, mean, std, max_frames, joints)

    @classmethod
    def from_split(cls, split: "HumanML3DSplit", joints: bool = False, captions: bool = False) -> "MotionSet":
        """A split read by :func:`~smdm_plugin.io.humanml3d.load_humanml3d` (its mean/std, its
        ``max_frames``, 196 when it kept motions whole), normalised; ``joints`` / ``captions``: keep the
        split's joints / caption texts (every motion must have captions: ``FileNotFoundError`` naming
        the first ``texts/<id>.txt`` missing or empty)."""
        N = 196 if split.max_frames is None else split.max_frames
        out = cls.from_motions(split.motions, split.mean, split.std, split.ids, N,
                               split.joints if joints else None)
        if captions:
            if split.captions is None:
                raise ValueError("MotionSet.from_split: captions=True needs a split read with load_humanml3d(..., "
                                 "captions=True)")
            caps = [[c.text for c in cs] for cs in split.captions]
            for name, texts in zip(split.ids, caps):
                if not texts:
                    path = Path(split.root) / "texts" / f"{name}.txt"
                    raise FileNotFoundError(f"{path}: missing or empty (text conditioning needs captions for every "
                                            "motion)")
            out = dataclasses.replace(out, captions=caps)
        return out


class MotionData:
    """``smdm ablate``'s data: the train and validation splits of a HumanML3D-format folder
    (validation: ``val.txt``, else ``test.txt``) as :class:`MotionSet` s with joints, the
    normalisation ``mean``/``std`` ``[D]``, ``files`` (every file read) and ``fingerprint`` (a hash of
    their names, sizes and contents)."""

    def __init__(self, root: str, max_frames: int = 196, min_frames: int = 40) -> None:
        from ..io.files import fingerprint_files

        self.root = Path(root)
        self.max_frames = max_frames
        val = "val" if (self.root / "val.txt").exists() else "test"
        train, held = (load_humanml3d(root, s, max_frames, min_frames, joints=True) for s in ("train", val))
        self.mean, self.std = train.mean, train.std
        self.train = MotionSet.from_split(train, joints=True)
        self.val = MotionSet.from_split(held, joints=True)
        self.files: List[str] = sorted(set(train.files + held.files))
        self.fingerprint = fingerprint_files(str(root), self.files)


def check_clip_lengths(data: MotionSet, sparse: SparseConfig, root: str) -> None:
    """``ValueError`` naming the first clip so short that the ``sparse.reduction`` would keep fewer
    than 2 keyframes (the selection would then keep 2, silently not the reduction asked for)."""
    from ..core.selection import keyframe_count

    r = float(sparse.reduction)
    short = [(i, int(L)) for i, L in zip(data.ids, data.lengths.tolist()) if round((1.0 - r) * L) < 2]
    if short:
        need = next(L for L in range(2, 100000) if round((1.0 - r) * L) >= 2)
        name, L = short[0]
        raise ValueError(f"data: {os.path.join(root, 'new_joint_vecs', name + '.npy')} has {L} frames: at reduction "
                         f"{r:g} it would keep {keyframe_count(L, r)} of the round({1 - r:g} x {L}) keyframes asked "
                         f"for; pass --min-frames {need} (or more), or a smaller --sparse_reduction"
                         + (f" ({len(short)} clips are that short)" if len(short) > 1 else ""))



def feature_stats(features: Sequence[np.ndarray], eps: float = 1e-4) -> Tuple[np.ndarray, np.ndarray]:
    """Mean and std ``[D]`` over every frame of ``features`` (``[L_i, D]`` each); std floored at
    ``eps`` (a channel that never moves must not divide by zero)."""
    if not features:
        raise ValueError("feature_stats: no features given")
    allf = np.concatenate([np.asarray(f, np.float64) for f in features], 0)
    return allf.mean(0).astype(np.float32), (allf.std(0) + eps).astype(np.float32)
