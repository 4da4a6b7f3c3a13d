"""Tiny HumanML3D-format data folders for tests that must not depend on ../shared (or must edit it)."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np


def write_humanml3d(root: Path, train: Sequence[int] = (60, 52, 48, 70), val: Sequence[int] = (44, 56),
                    seed: int = 0, dim: int = 263, captions: bool = False) -> Path:
    """A HumanML3D-format folder: ``Mean.npy`` / ``Std.npy`` ``[dim]``, ``train.txt`` / ``val.txt``,
    ``new_joint_vecs/<id>.npy [T, dim]`` (263: HumanML3D features, 66: joints66) and
    ``new_joints/<id>.npy [T, 22, 3]`` (metres) with the given frame counts; smooth random motion;
    with ``captions``, ``texts/<id>.txt`` (two captions each)."""
    rng = np.random.default_rng(seed)
    (root / "new_joint_vecs").mkdir(parents=True, exist_ok=True)
    (root / "new_joints").mkdir(exist_ok=True)
    if captions:
        (root / "texts").mkdir(exist_ok=True)
    for split, lengths in (("train", train), ("val", val)):
        ids = [f"{split}{k:03d}" for k in range(len(lengths))]
        (root / f"{split}.txt").write_text("\n".join(ids) + "\n")
        for i, T in zip(ids, lengths):
            np.save(root / "new_joint_vecs" / f"{i}.npy", np.cumsum(rng.normal(0, 0.05, (T, dim)), 0).astype(np.float32))
            joints = np.cumsum(rng.normal(0, 0.01, (T, 22, 3)), 0) + rng.normal(0, 0.3, (1, 22, 3))
            np.save(root / "new_joints" / f"{i}.npy", joints.astype(np.float32))
            if captions:
                (root / "texts" / f"{i}.txt").write_text("a person walks#a/DET person/NOUN walk/VERB#0.0#0.0\n"
                                                         "someone waves#someone/PRON wave/VERB#0.0#0.0\n")
    np.save(root / "Mean.npy", np.zeros(dim, np.float32))
    np.save(root / "Std.npy", np.ones(dim, np.float32))
    return root
