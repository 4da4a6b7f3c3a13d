"""Which real motions, crops and captions one replication of an evaluation reads: upstream's protocol
(MDM ``eval/eval_humanml.py`` over ``Text2MotionDatasetV2`` with ``shuffle=True, drop_last=True``)
or today's deterministic one."""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence

import numpy as np

#: the protocols :func:`replication` knows
PROTOCOLS = ("upstream", "fixed")
#: upstream's eval modes (``eval_humanml --eval_mode``): replications and multimodality
EVAL_MODES = {"debug": (5, False), "wo_mm": (20, False), "mm_short": (5, True), "full": (20, True)}


@dataclass(frozen=True)
class Draw:
    """``index [P]`` rows of the split, crop ``start [P]`` and ``length [P]`` (frames), ``caption [P]``
    (which of each motion's captions)."""

    index: np.ndarray
    start: np.ndarray
    length: np.ndarray
    caption: np.ndarray

    def motions(self, motions: Sequence[np.ndarray]) -> List[np.ndarray]:
        """The cropped motions ``[length_i, D]``."""
        return [motions[i][s:s + n] for i, s, n in zip(self.index, self.start, self.length)]

    def captions(self, captions: Sequence[Sequence]) -> List:
        """The drawn caption of each row (whatever objects ``captions[i]`` holds)."""
        return [captions[i][c] for i, c in zip(self.index, self.caption)]


@dataclass(frozen=True)
class Replication:
    """``reference``: the real draw FID is measured against; ``scored``: the captions, lengths and
    real motions of the set scored."""

    reference: Draw
    scored: Draw


def upstream_crop(length: int, rng: np.random.Generator, max_frames: int = 196, unit: int = 4):
    """``(start, n)``: upstream's random crop of a motion of ``length`` frames."""
    L = min(length, max_frames)
    n = (L // unit - (1 if rng.random() < 1 / 3 else 0)) * unit
    n = max(n, unit)
    return int(rng.integers(0, length - n + 1)), n


def _draw(lengths: Sequence[int], n_captions: Sequence[int], rng: np.random.Generator, pool: int,
          max_frames: int) -> Draw:
    N = len(lengths)
    size = min(pool, N)
    order = rng.permutation(N)[:N // size * size]
    crops = [upstream_crop(int(lengths[i]), rng, max_frames) for i in order]
    caption = np.array([int(rng.integers(n_captions[i])) for i in order])
    return Draw(order, np.array([c[0] for c in crops]), np.array([c[1] for c in crops]), caption)


def replication(protocol: str, lengths: Sequence[int], n_captions: Sequence[int], seed: int, pool: int = 32,
                max_frames: int = 196) -> Replication:
    """The draws of one replication (docs/modules.md) for a split of motions of ``lengths`` frames
    with ``n_captions`` captions each; a function of ``seed``."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
    if len(lengths) != len(n_captions) or len(lengths) < 2:
        raise ValueError(f"replication: need >= 2 motions with one caption count each, got {len(lengths)} and "
                         f"{len(n_captions)}")
    rng = np.random.default_rng(seed)
    if protocol == "fixed":
        N = len(lengths)
        d = Draw(np.arange(N), np.zeros(N, np.int64), np.array([int(v) for v in lengths]),
                 np.array([int(rng.integers(c)) for c in n_captions]))
        return Replication(d, d)
    ref = _draw(lengths, n_captions, rng, pool, max_frames)
    return Replication(ref, _draw(lengths, n_captions, rng, pool, max_frames))
