"""The text-to-motion metrics of Guo et al. (CVPR 2022, "Generating Diverse and Natural 3D Human
Motions from Text"), as MDM, priorMDM and MotionDiffuse compute them on the T2M evaluator's
embeddings: FID, diversity, multimodality, R-precision top-1/2/3 and matching score (MM-Dist)."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Dict, Tuple, Union

import numpy as np
import torch

ArrayLike = Union[np.ndarray, torch.Tensor]

#: T2M's protocol constants (MDM ``eval_humanml``: batch 32, diversity 300 pairs, multimodality 10 pairs)
R_PRECISION_POOL = 32
DIVERSITY_TIMES = 300
MULTIMODALITY_TIMES = 10


def _matrix(fn: str, x: ArrayLike, name: str, dims: int = 2, min_rows: int = 1) -> np.ndarray:
    """``x`` as a finite float64 array of ``dims`` dimensions with at least ``min_rows`` rows."""
    a = x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)
    shape = "[N, D]" if dims == 2 else "[C, R, D]"
    if a.ndim != dims or a.shape[-1] < 1:
        raise ValueError(f"{fn}: {name} must be embeddings {shape}, got shape {a.shape}")
    if a.shape[0] < min_rows:
        raise ValueError(f"{fn}: {name} needs at least {min_rows} rows, got {a.shape[0]}")
    if not np.isfinite(a).all():
        raise ValueError(f"{fn}: {name} has non-finite values")
    return a


def _rng(seed: Union[int, np.random.Generator, None]) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


# ----------------------------------------------------------------------------------------- FID
def gaussian_stats(embeddings: ArrayLike) -> Tuple[np.ndarray, np.ndarray]:
    """Mean ``[D]`` and unbiased covariance ``[D, D]`` (``np.cov(rowvar=False)``) of ``[N, D]``, N >= 2."""
    a = _matrix("gaussian_stats", embeddings, "embeddings", min_rows=2)
    return a.mean(0), np.atleast_2d(np.cov(a, rowvar=False))


def _psd_sqrt(s: np.ndarray) -> np.ndarray:
    """Symmetric square root of a symmetric positive semi-definite matrix (eigenvalues clipped at 0)."""
    w, v = np.linalg.eigh((s + s.T) / 2)
    return (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T


def frechet_distance_from_stats(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray) -> float:
    """Fréchet distance of ``N(mu1, sigma1)`` and ``N(mu2, sigma2)`` (``[D]``, ``[D, D]``)."""
    mu1, mu2 = np.atleast_1d(mu1).astype(np.float64), np.atleast_1d(mu2).astype(np.float64)
    sigma1, sigma2 = np.atleast_2d(sigma1).astype(np.float64), np.atleast_2d(sigma2).astype(np.float64)
    D = mu1.shape[0]
    if mu2.shape != (D,) or sigma1.shape != (D, D) or sigma2.shape != (D, D):
        raise ValueError(f"frechet_distance: means must be [D] and covariances [D, D] with one D, got {mu1.shape}, "
                         f"{sigma1.shape}, {mu2.shape}, {sigma2.shape}")
    r1 = _psd_sqrt(sigma1)
    inner = r1 @ sigma2 @ r1
    tr_covmean = float(np.sqrt(np.clip(np.linalg.eigvalsh((inner + inner.T) / 2), 0.0, None)).sum())
    diff = mu1 - mu2
    fid = float(diff @ diff + np.trace(sigma1) + np.trace(sigma2) - 2.0 * tr_covmean)
    # identical sets give 0 up to round-off (larger when N <= D: the square roots of ~0 eigenvalues);
    # only that round-off, never a real negative, is clipped
    return 0.0 if -1e-6 * (1.0 + np.trace(sigma1) + np.trace(sigma2)) < fid < 0.0 else fid


def frechet_distance(a: ArrayLike, b: ArrayLike) -> float:
    """FID between two embedding sets ``a [N1, D]`` and ``b [N2, D]`` (N1, N2 >= 2), T2M's formula.

    With fewer motions than dimensions (``N1 + N2 <= D``, e.g. 40 motions in T2M's 512-D space) it is
    computed in the samples' space, exactly the same quantity: with ``Xi`` the centred rows over
    ``sqrt(Ni - 1)`` (so ``Si = XiᵀXi``), ``Tr sqrt(S1 S2)`` is the sum of the singular values of
    ``X1 X2ᵀ`` ``[N1, N2]`` and ``Tr Si = ||Xi||²`` (one small SVD instead of two ``D × D`` eigen-
    decompositions: what makes the bootstrap of :func:`fid_bootstrap` cheap)."""
    a = _matrix("frechet_distance", a, "a", min_rows=2)
    b = _matrix("frechet_distance", b, "b", min_rows=2)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"frechet_distance: a and b must have the same D, got {a.shape[1]} and {b.shape[1]}")
    if a.shape[0] + b.shape[0] > a.shape[1]:
        return frechet_distance_from_stats(*gaussian_stats(a), *gaussian_stats(b))
    return _frechet_sample_space(a, b)


def _frechet_sample_space(a: np.ndarray, b: np.ndarray) -> float:
    """:func:`frechet_distance` of ``a [N1, D]``, ``b [N2, D]`` through ``X1 X2ᵀ`` (its docstring)."""
    mu1, mu2 = a.mean(0), b.mean(0)
    x1 = (a - mu1) / np.sqrt(a.shape[0] - 1)
    x2 = (b - mu2) / np.sqrt(b.shape[0] - 1)
    nuclear = float(np.linalg.svd(x1 @ x2.T, compute_uv=False).sum())
    t1, t2 = float((x1 * x1).sum()), float((x2 * x2).sum())
    diff = mu1 - mu2
    fid = float(diff @ diff + t1 + t2 - 2.0 * nuclear)
    return 0.0 if -1e-9 * (1.0 + t1 + t2) < fid < 0.0 else fid


@dataclass(frozen=True)
class FIDInterval:
    """A FID with its bootstrap: ``fid`` (of the sets as given), ``low``/``high`` (its 95% interval:
    the 2.5% and 97.5% percentiles of ``resamples`` bootstrap FIDs, re-centred on ``fid``), ``boot_mean``
    (the bootstrap FIDs' mean). A resample repeats motions, which shrinks its spread and *raises* its
    FID (40 motions in 512-D: by several percent), so the raw percentiles can lie wholly above the FID;
    the interval keeps their distances to ``boot_mean`` and moves them onto ``fid``. ``boot_low`` /
    ``boot_high``: the raw percentiles (of a real set against a resample of itself, ``boot_mean`` and
    these are the floor: the FID of a second draw of the same motions)."""

    fid: float
    low: float
    high: float
    boot_mean: float
    boot_low: float
    boot_high: float
    resamples: int

    def to_dict(self) -> Dict[str, Any]:
        return asdict(self)


def fid_bootstrap(a: ArrayLike, b: ArrayLike, resamples: int = 200, paired: bool = False,
                  seed: Union[int, np.random.Generator, None] = 0) -> FIDInterval:
    """FID of ``a [N1, D]`` against ``b [N2, D]`` and its bootstrap over motions: each resample draws
    the rows of each set with replacement (``paired=True``, N1 = N2: the same row indices in both,
    for sets matched row by row, e.g. generated motion ``i`` for test caption ``i``)."""
    a = _matrix("fid_bootstrap", a, "a", min_rows=2)
    b = _matrix("fid_bootstrap", b, "b", min_rows=2)
    if paired and a.shape[0] != b.shape[0]:
        raise ValueError(f"fid_bootstrap: paired sets need the same N, got {a.shape[0]} and {b.shape[0]}")
    if isinstance(resamples, bool) or not isinstance(resamples, int) or resamples < 2:
        raise ValueError(f"fid_bootstrap: resamples must be an int >= 2, got {resamples!r}")
    rng = _rng(seed)
    boots = []
    for _ in range(resamples):
        i = rng.integers(0, a.shape[0], a.shape[0])
        j = i if paired else rng.integers(0, b.shape[0], b.shape[0])
        boots.append(frechet_distance(a[i], b[j]))
    lo, hi = np.percentile(boots, [2.5, 97.5])
    fid, mean = frechet_distance(a, b), float(np.mean(boots))
    return FIDInterval(fid, max(0.0, fid - (mean - float(lo))), fid + (float(hi) - mean), mean, float(lo), float(hi),
                       resamples)


# ----------------------------------------------------------------------------------------- diversity
def diversity(embeddings: ArrayLike, times: int = DIVERSITY_TIMES,
              seed: Union[int, np.random.Generator, None] = 0) -> Tuple[float, int]:
    """T2M's diversity of ``[N, D]``: two independent draws of ``times`` indices (each without
    replacement), mean distance of the paired rows. Upstream needs ``N > times``; with fewer motions
    ``times`` becomes ``N - 1``. Returns ``(diversity, times used)``."""
    a = _matrix("diversity", embeddings, "embeddings", min_rows=2)
    i, j = _pair_draws("diversity", a.shape[0], times, seed)
    return float(np.linalg.norm(a[i] - a[j], axis=1).mean()), len(i)


def _pair_draws(fn: str, n: int, times: int, seed: Union[int, np.random.Generator, None]
                ) -> Tuple[np.ndarray, np.ndarray]:
    """T2M's random pairs: two independent draws of ``min(times, n - 1)`` of ``n`` indices, each
    without replacement."""
    if isinstance(times, bool) or not isinstance(times, int) or times < 1:
        raise ValueError(f"{fn}: times must be an int >= 1, got {times!r}")
    k = min(times, n - 1)
    rng = _rng(seed)
    return rng.choice(n, k, replace=False), rng.choice(n, k, replace=False)


def multimodality(embeddings: ArrayLike, times: int = MULTIMODALITY_TIMES,
                  seed: Union[int, np.random.Generator, None] = 0) -> Tuple[float, int]:
    """T2M's multimodality of ``[C, R, D]`` (R generations for each of C captions): two draws of
    ``times`` generation indices (without replacement, shared by all captions), mean distance of
    the pairs. ``times`` becomes ``R - 1`` when ``R <= times``. Returns ``(multimodality, times used)``."""
    a = _matrix("multimodality", embeddings, "embeddings", dims=3)
    if a.shape[1] < 2:
        raise ValueError(f"multimodality: embeddings must be [C, R, D] with R >= 2 generations per caption, "
                         f"got {a.shape}")
    i, j = _pair_draws("multimodality", a.shape[1], times, seed)
    return float(np.linalg.norm(a[:, i] - a[:, j], axis=2).mean()), len(i)


# ----------------------------------------------------------------------------------------- retrieval
@dataclass(frozen=True)
class Retrieval:
    """R-precision and matching score of one set: ``top1..top3`` fractions of captions whose motion is
    among the k nearest of its batch; ``matching_score`` mean caption-motion distance of true pairs;
    ``pool_size`` motions per batch (32, or N when N < 32); ``n_scored`` motions in full batches."""

    top1: float
    top2: float
    top3: float
    matching_score: float
    pool_size: int
    n_scored: int

    def to_dict(self) -> Dict[str, Any]:
        return asdict(self)


def pairwise_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distances ``[Na, Nb]`` between rows of ``a [Na, D]`` and ``b [Nb, D]``."""
    d2 = (a * a).sum(1)[:, None] - 2.0 * a @ b.T + (b * b).sum(1)[None, :]
    return np.sqrt(np.clip(d2, 0.0, None))


def retrieval(text: ArrayLike, motion: ArrayLike, pool: int = R_PRECISION_POOL, top_k: int = 3,
              seed: Union[int, np.random.Generator, None] = 0, shuffle: bool = True) -> Retrieval:
    """R-precision top-1..``top_k`` and matching score of caption embeddings ``text [N, D]`` against
    their motions ``motion [N, D]`` (row ``i`` of each is one pair), T2M's protocol (docs/modules.md):
    batches of ``pool`` after a seeded shuffle (``shuffle=False``: in the given order), the last
    incomplete batch left out, one batch of all N when ``N < pool``."""
    t = _matrix("retrieval", text, "text", min_rows=2)
    m = _matrix("retrieval", motion, "motion", min_rows=2)
    if t.shape != m.shape:
        raise ValueError(f"retrieval: text and motion must both be [N, D] with one N and D, got {t.shape} and {m.shape}")
    if isinstance(pool, bool) or not isinstance(pool, int) or pool < 2:
        raise ValueError(f"retrieval: pool must be an int >= 2, got {pool!r}")
    if top_k not in (1, 2, 3):
        raise ValueError(f"retrieval: top_k must be 1, 2 or 3, got {top_k!r}")
    N = t.shape[0]
    order = _rng(seed).permutation(N) if shuffle else np.arange(N)
    size = min(pool, N)
    batches = [order[s:s + size] for s in range(0, N - size + 1, size)]
    hits = np.zeros(3)
    match = 0.0
    for idx in batches:
        dist = pairwise_distances(t[idx], m[idx])
        true = np.diag(dist)
        rank = (dist < true[:, None]).sum(1)  # motions strictly nearer than the true one
        hits += [(rank < k).sum() for k in (1, 2, 3)]
        match += true.sum()
    n = size * len(batches)
    return Retrieval(top1=float(hits[0] / n), top2=float(hits[1] / n), top3=float(hits[2] / n),
                     matching_score=float(match / n), pool_size=size, n_scored=n)


def r_precision(text: ArrayLike, motion: ArrayLike, pool: int = R_PRECISION_POOL,
                seed: Union[int, np.random.Generator, None] = 0) -> Tuple[float, float, float]:
    """``(top1, top2, top3)`` of :func:`retrieval`."""
    r = retrieval(text, motion, pool=pool, seed=seed)
    return r.top1, r.top2, r.top3


def matching_score(text: ArrayLike, motion: ArrayLike, pool: int = R_PRECISION_POOL,
                   seed: Union[int, np.random.Generator, None] = 0) -> float:
    """Mean caption-motion distance of the true pairs scored by :func:`retrieval` (MM-Dist)."""
    return retrieval(text, motion, pool=pool, seed=seed).matching_score


def mean_interval(values: ArrayLike) -> Tuple[float, float]:
    """The field's summary of ``R`` replications: ``(mean, 1.96 * std / sqrt(R))`` (population std,
    as ``np.std`` in T2M's ``get_metric_statistics``); interval 0 for one replication."""
    v = np.asarray(values, np.float64).reshape(-1)
    if v.size == 0:
        raise ValueError("mean_interval: no values")
    return float(v.mean()), float(1.96 * v.std() / np.sqrt(v.size))
