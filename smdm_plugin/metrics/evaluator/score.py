"""Scoring motions with an evaluator: :func:`score_motions` (features in, :class:`EvalResult` out),
:func:`score_embeddings` (the same from embeddings computed once), :func:`motion_quality` (jitter,
jitter per unit speed, foot skating of HumanML3D features)."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from ..t2m import (DIVERSITY_TIMES, MULTIMODALITY_TIMES, R_PRECISION_POOL, diversity, frechet_distance,
                   multimodality, retrieval)
from .model import Evaluator

Motions = Union[Sequence[np.ndarray], np.ndarray, torch.Tensor]


@dataclass
class EvalResult:
    """The field's numbers for one set of generated motions against the real ones.

    ``fid`` (generated vs real embeddings); ``diversity`` (``diversity_times`` pairs);
    ``r_precision_top1..3`` and ``matching_score`` (pool of ``pool_size``, ``n_scored`` motions in
    full batches); ``multimodality`` (``None`` unless several generations per caption were given);
    ``real_*``: the real motions' diversity, R-precision and matching score (the ground-truth row),
    ``real_fid`` their FID against ``real`` (the floor: 0 when they are the same motions);
    ``n_real``/``n_generated``: motions embedded."""

    fid: float
    diversity: float
    r_precision_top1: float
    r_precision_top2: float
    r_precision_top3: float
    matching_score: float
    real_diversity: float
    real_r_precision_top1: float
    real_r_precision_top2: float
    real_r_precision_top3: float
    real_matching_score: float
    pool_size: int
    n_scored: int
    n_real: int
    n_generated: int
    diversity_times: int
    multimodality: Optional[float] = None
    multimodality_times: Optional[int] = None
    real_fid: float = 0.0

    def to_dict(self) -> Dict[str, Any]:
        return asdict(self)


def as_padded(features: Motions, lengths: Optional[Sequence[int]] = None, name: str = "motions"
              ) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(x [B, N, D] float32, lengths [B] long)`` from a list of ``[L_i, D]`` or a padded batch."""
    if isinstance(features, (list, tuple)):
        if not features:
            raise ValueError(f"{name}: no motions given")
        arrs = [np.asarray(f, np.float32) for f in features]
        D = {a.shape[-1] for a in arrs if a.ndim == 2}
        if any(a.ndim != 2 for a in arrs) or len(D) != 1:
            raise ValueError(f"{name}: every motion must be [L, D] with one D, got shapes "
                             f"{sorted({a.shape for a in arrs})[:4]}")
        L = [len(a) for a in arrs] if lengths is None else [int(v) for v in lengths]
        x = np.zeros((len(arrs), max(len(a) for a in arrs), D.pop()), np.float32)
        for i, a in enumerate(arrs):
            x[i, :len(a)] = a
        return torch.from_numpy(x), torch.tensor(L, dtype=torch.long)
    x = torch.as_tensor(np.asarray(features) if not isinstance(features, torch.Tensor) else features).float()
    if x.dim() != 3:
        raise ValueError(f"{name}: expected [B, N, D] (or a list of [L, D]), got shape {tuple(x.shape)}")
    L = torch.full((x.shape[0],), x.shape[1], dtype=torch.long) if lengths is None else \
        torch.as_tensor(lengths).long().reshape(-1)
    return x, L


@torch.no_grad()
def embed_motions(evaluator: Evaluator, features: Motions, lengths: Optional[Sequence[int]] = None,
                  batch_size: int = 128) -> np.ndarray:
    """Co-embeddings ``[B, C]`` (float64 numpy) of raw motions, ``batch_size`` at a time."""
    x, L = as_padded(features, lengths)
    dev = evaluator.mean.device
    out = [evaluator.encode_motion(x[s:s + batch_size].to(dev), L[s:s + batch_size].to(dev)).double().cpu()
           for s in range(0, len(L), batch_size)]
    return torch.cat(out).numpy()


@torch.no_grad()
def embed_captions(evaluator: Evaluator, captions: Sequence[Sequence[str]], batch_size: int = 256) -> np.ndarray:
    """Co-embeddings ``[B, C]`` (float64 numpy) of captions (``word/POS`` token lists)."""
    out = [evaluator.encode_text(captions[s:s + batch_size]).double().cpu()
           for s in range(0, len(captions), batch_size)]
    return torch.cat(out).numpy()


def score_embeddings(real: np.ndarray, text: np.ndarray, generated: np.ndarray, mm: Optional[np.ndarray] = None,
                     seed: int = 0, pool: int = R_PRECISION_POOL, diversity_times: int = DIVERSITY_TIMES,
                     mm_times: int = MULTIMODALITY_TIMES, scored_real: Optional[np.ndarray] = None) -> EvalResult:
    """:class:`EvalResult` from embeddings: ``real [Nr, C]`` (the statistics FID is measured
    against), ``text [Ng, C]`` (caption ``i`` of generated motion ``i``), ``generated [Ng, C]``,
    ``mm [Cm, R, C]`` (R generations per caption) or None, ``scored_real [Ng, C]``: the real motions
    the captions belong to (the ground-truth row; default ``real`` when it has ``Ng`` rows)."""
    if text.shape != generated.shape:
        raise ValueError(f"score_embeddings: text and generated must both be [N, C], got {text.shape}, "
                         f"{generated.shape}")
    if scored_real is not None and scored_real.shape != text.shape:
        raise ValueError(f"score_embeddings: scored_real must be [N, C] as text, got {scored_real.shape}, {text.shape}")
    own = scored_real if scored_real is not None else (real if real.shape == text.shape else None)
    rg = retrieval(text, generated, pool=pool, seed=seed)
    rr = retrieval(text, own, pool=pool, seed=seed) if own is not None else None
    div, times = diversity(generated, diversity_times, seed=seed)
    rdiv, _ = diversity(own if own is not None else real, diversity_times, seed=seed)
    mmv, mmt = multimodality(mm, mm_times, seed=seed) if mm is not None else (None, None)
    nan = float("nan")
    return EvalResult(fid=frechet_distance(real, generated), diversity=div,
                      r_precision_top1=rg.top1, r_precision_top2=rg.top2, r_precision_top3=rg.top3,
                      matching_score=rg.matching_score, real_diversity=rdiv,
                      real_r_precision_top1=rr.top1 if rr else nan, real_r_precision_top2=rr.top2 if rr else nan,
                      real_r_precision_top3=rr.top3 if rr else nan,
                      real_matching_score=rr.matching_score if rr else nan,
                      pool_size=rg.pool_size, n_scored=rg.n_scored, n_real=len(real), n_generated=len(generated),
                      diversity_times=times, multimodality=mmv, multimodality_times=mmt,
                      real_fid=0.0 if scored_real is None else frechet_distance(real, scored_real))


def score_motions(evaluator: Evaluator, real_features: Motions, real_lengths: Optional[Sequence[int]],
                  captions: Sequence[Sequence[str]], generated_features: Motions,
                  generated_lengths: Optional[Sequence[int]] = None, mm_features: Optional[Sequence[Motions]] = None,
                  mm_lengths: Optional[Sequence[Sequence[int]]] = None, seed: int = 0, pool: int = R_PRECISION_POOL,
                  diversity_times: int = DIVERSITY_TIMES, mm_times: int = MULTIMODALITY_TIMES) -> EvalResult:
    """Score generated motions (one per caption) against the real ones with ``evaluator``; with
    ``mm_features`` (per caption, R generations ``[R, N, D]`` or a list), also multimodality."""
    if len(captions) != len(as_padded(generated_features, generated_lengths, "generated")[1]):
        raise ValueError(f"score_motions: need one caption per generated motion, got {len(captions)} captions")
    real = embed_motions(evaluator, real_features, real_lengths)
    gen = embed_motions(evaluator, generated_features, generated_lengths)
    text = embed_captions(evaluator, captions)
    mm = None
    if mm_features is not None:
        mm = np.stack([embed_motions(evaluator, f, None if mm_lengths is None else mm_lengths[i])
                       for i, f in enumerate(mm_features)])
    return score_embeddings(real, text, gen, mm, seed=seed, pool=pool, diversity_times=diversity_times,
                            mm_times=mm_times)


def motion_quality(features: Motions, lengths: Optional[Sequence[int]] = None, fps: float = 20.0,
                   representation: str = "humanml3d") -> Dict[str, float]:
    """Joint-space quality of raw features of ``representation`` (``humanml3d``: joints by
    ``recover_from_ric``; ``joints66``; see :class:`~smdm_plugin.io.representation.Representation`):
    ``jitter`` (m/s³, :func:`~smdm_plugin.metrics.jitter`), ``speed`` (mean joint speed, m/s),
    ``jitter_per_speed`` (jitter / speed, 1/s²: raw jitter grows with how fast the motion is, so
    compare motions of different speed by this ratio), ``foot_skating``
    (:func:`~smdm_plugin.metrics.foot_skating_ratio`). Each is the mean over motions."""
    from ...io.representation import Representation
    from ..quality import foot_skating_ratio, jitter

    x, L = as_padded(features, lengths)
    j = torch.as_tensor(Representation(representation).to_joints(x))
    jit = jitter(j, fps=fps, lengths=L, reduce="none")
    v = (j[:, 1:] - j[:, :-1]).norm(dim=-1).mean(-1) * fps  # [B, N - 1] mean joint speed per step
    steps = torch.arange(j.shape[1] - 1)[None, :] < (L - 1)[:, None]
    speed = (v * steps).sum(1) / steps.sum(1).clamp(min=1)
    return {"jitter": float(jit.mean()), "speed": float(speed.mean()),
            "jitter_per_speed": float(jit.mean() / speed.mean().clamp(min=1e-9)),
            "foot_skating": float(foot_skating_ratio(j, fps=fps, lengths=L))}
