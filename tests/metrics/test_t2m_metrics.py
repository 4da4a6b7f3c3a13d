"""T2M metrics (smdm_plugin.metrics.t2m) against slow, obviously correct references."""
import importlib.util
import os

import numpy as np
import pytest
import torch

from smdm_plugin.metrics import (diversity, frechet_distance, matching_score, mean_interval, multimodality,
                                 r_precision, retrieval)


def _fid_reference(a, b):
    """FID with the matrix square root of S1 S2 itself: scipy.linalg.sqrtm when installed, else
    the eigenvalues of the (non-symmetric) product S1 S2, whose square roots sum to Tr sqrt(S1 S2)."""
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    try:
        from scipy import linalg

        tr = np.trace(linalg.sqrtm(s1 @ s2)).real
    except ImportError:
        tr = np.sqrt(np.clip(np.linalg.eigvals(s1 @ s2).real, 0, None)).sum()
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * tr)


def _fid_eig_reference(a, b):
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    tr = np.sqrt(np.clip(np.linalg.eigvals(s1 @ s2).real, 0, None)).sum()
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * tr)


@pytest.mark.parametrize("n1,n2,d", [(200, 150, 8), (64, 80, 16), (40, 40, 64)])
def test_fid_matches_references(n1, n2, d):
    rng = np.random.default_rng(n1 + d)
    mix = rng.normal(size=(d, d))
    a = rng.normal(size=(n1, d)) @ mix
    b = rng.normal(size=(n2, d)) @ (mix + 0.3 * rng.normal(size=(d, d))) + 0.5
    got = frechet_distance(a, b)
    assert got == pytest.approx(_fid_eig_reference(a, b), rel=1e-6, abs=1e-6)
    if n1 > d and n2 > d:  # sqrtm of a full-rank product is well conditioned
        assert got == pytest.approx(_fid_reference(a, b), rel=1e-6, abs=1e-6)
    assert frechet_distance(torch.from_numpy(a).float(), torch.from_numpy(b).float()) == pytest.approx(got, rel=1e-4)


def test_fid_closed_form_and_identity():
    # diagonal covariances: FID = |mu1 - mu2|^2 + sum (sqrt(v1) - sqrt(v2))^2
    rng = np.random.default_rng(0)
    a = rng.normal(size=(5000, 3))
    a = (a - a.mean(0)) / a.std(0, ddof=1)
    # decorrelate exactly so the sample covariance is diagonal
    w, v = np.linalg.eigh(np.cov(a, rowvar=False))
    a = a @ v / np.sqrt(w)
    scale = np.array([1.0, 2.0, 0.5])
    b = a * scale + np.array([1.0, 0.0, -2.0])
    expected = 1.0 + 4.0 + sum((1.0 - s) ** 2 for s in scale)
    assert frechet_distance(a, b) == pytest.approx(expected, rel=1e-9)
    assert abs(frechet_distance(a, a)) < 1e-9


def test_diversity_and_multimodality_follow_t2m_draws():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(50, 4))
    got, n = diversity(a, times=20, seed=7)
    r = np.random.default_rng(7)
    i, j = r.choice(50, 20, replace=False), r.choice(50, 20, replace=False)
    ref = np.mean([np.sqrt(((a[p] - a[q]) ** 2).sum()) for p, q in zip(i, j)])
    assert n == 20 and got == pytest.approx(ref)
    assert diversity(a, times=300)[1] == 49  # fewer motions than pairs: N - 1
    mm = rng.normal(size=(6, 12, 4))
    got, n = multimodality(mm, times=10, seed=3)
    r = np.random.default_rng(3)
    i, j = r.choice(12, 10, replace=False), r.choice(12, 10, replace=False)
    ref = np.mean([np.sqrt(((mm[c, p] - mm[c, q]) ** 2).sum()) for c in range(6) for p, q in zip(i, j)])
    assert n == 10 and got == pytest.approx(ref)
    # identical generations: no multimodality; spread-out set: diversity near sqrt(2 D)
    assert multimodality(np.repeat(mm[:, :1], 12, 1))[0] == 0.0
    big = rng.normal(size=(4000, 16))
    assert diversity(big)[0] == pytest.approx(np.sqrt(2 * 16), rel=0.05)


def _retrieval_reference(t, m, pool, order):
    """Brute force: every caption against every motion of its batch, one by one."""
    n_batches = len(order) // pool if len(order) >= pool else 1
    size = pool if len(order) >= pool else len(order)
    hits, match, count = [0, 0, 0], 0.0, 0
    for b in range(n_batches):
        idx = order[b * size:(b + 1) * size]
        for i in idx:
            d_true = np.sqrt(((t[i] - m[i]) ** 2).sum())
            nearer = 0
            for j in idx:
                if j != i and np.sqrt(((t[i] - m[j]) ** 2).sum()) < d_true:
                    nearer += 1
            for k in range(3):
                hits[k] += nearer <= k
            match += d_true
            count += 1
    return [h / count for h in hits], match / count, size, count


@pytest.mark.parametrize("n", [100, 64, 20])
def test_retrieval_matches_brute_force(n):
    rng = np.random.default_rng(n)
    m = rng.normal(size=(n, 6))
    t = m + 0.9 * rng.normal(size=(n, 6))  # captions near their motion, not always nearest
    r = retrieval(t, m, seed=5)
    order = np.random.default_rng(5).permutation(n)
    tops, match, size, count = _retrieval_reference(t, m, 32, order)
    assert (r.top1, r.top2, r.top3) == pytest.approx(tops)
    assert r.matching_score == pytest.approx(match)
    assert (r.pool_size, r.n_scored) == (size, count)
    assert r.pool_size == min(32, n) and r.n_scored == ((n // 32) * 32 if n >= 32 else n)
    assert 0 < r.top1 < r.top2 <= r.top3 < 1
    assert r_precision(t, m, seed=5) == (r.top1, r.top2, r.top3)
    assert matching_score(t, m, seed=5) == r.matching_score


def test_retrieval_extremes():
    rng = np.random.default_rng(0)
    m = rng.normal(size=(64, 8)) * 10
    assert retrieval(m, m).top1 == 1.0  # captions on their motions
    t = rng.normal(size=(64, 8))
    chance = np.mean([retrieval(rng.normal(size=(64, 8)), t, seed=s).top1 for s in range(30)])
    assert chance == pytest.approx(1 / 32, abs=0.02)


def test_errors_and_interval():
    with pytest.raises(ValueError, match=r"frechet_distance: a must be embeddings \[N, D\]"):
        frechet_distance(np.zeros(5), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="same D"):
        frechet_distance(np.zeros((5, 2)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="retrieval: text and motion"):
        retrieval(np.zeros((5, 2)), np.zeros((6, 2)))
    with pytest.raises(ValueError, match="non-finite"):
        diversity(np.full((5, 2), np.nan))
    mean, ci = mean_interval([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5 and ci == pytest.approx(1.96 * np.std([1, 2, 3, 4]) / 2)


# ----------------------------------------------------------------------------------------- upstream
MDM_ROOT = os.environ.get("SMDM_MDM_ROOT")


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT (an MDM checkout) not set")
def test_same_numbers_as_upstream_metrics():
    """MDM's data_loaders/humanml/utils/metrics.py (needs scipy): calculate_frechet_distance on the
    activation statistics, and eval_humanml's matching-score loop (euclidean_distance_matrix, argsort,
    calculate_top_k, trace) over batches of 32 in order, against frechet_distance / retrieval."""
    pytest.importorskip("scipy")
    spec = importlib.util.spec_from_file_location(
        "mdm_metrics", os.path.join(MDM_ROOT, "data_loaders", "humanml", "utils", "metrics.py"))
    up = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(up)
    rng = np.random.default_rng(11)
    a = rng.normal(size=(300, 16)) @ rng.normal(size=(16, 16))
    b = rng.normal(size=(250, 16)) @ rng.normal(size=(16, 16)) + 0.2
    ref = up.calculate_frechet_distance(*up.calculate_activation_statistics(b), *up.calculate_activation_statistics(a))
    assert frechet_distance(a, b) == pytest.approx(ref, rel=1e-6)
    t = a[:96] + rng.normal(size=(96, 16)) * 3.0
    m = a[:96]
    top, match, size = np.zeros(3), 0.0, 0
    for s in range(0, 96, 32):
        dist = up.euclidean_distance_matrix(t[s:s + 32], m[s:s + 32])
        match += dist.trace()
        top += up.calculate_top_k(np.argsort(dist, axis=1), top_k=3).sum(axis=0)
        size += 32
    r = retrieval(t, m, shuffle=False)
    assert (r.top1, r.top2, r.top3) == pytest.approx(tuple(top / size))
    assert r.matching_score == pytest.approx(match / size)


@pytest.mark.parametrize("n1, n2, d", [(40, 40, 512), (12, 30, 64), (3, 5, 8)])
def test_fid_in_the_samples_space_equals_the_covariance_form(n1, n2, d):
    """With fewer motions than dimensions frechet_distance works through ``X1 X2ᵀ`` (nuclear norm): the
    same number as the covariance form (two D × D eigen-decompositions)."""
    from smdm_plugin.metrics.t2m import frechet_distance_from_stats, gaussian_stats

    rng = np.random.default_rng(n1 + d)
    a = rng.standard_normal((n1, d)) * 2.0
    b = rng.standard_normal((n2, d)) * 1.3 + 0.4
    assert n1 + n2 <= d  # the samples' space path
    ref = frechet_distance_from_stats(*gaussian_stats(a), *gaussian_stats(b))
    assert frechet_distance(a, b) == pytest.approx(ref, rel=1e-7)  # the covariance form's round-off: ~1e-8
    assert abs(frechet_distance(a, a)) < 1e-9


def test_fid_bootstrap_interval_and_floor():
    """fid_bootstrap: the FID of the sets as given, an interval that contains it (the resamples'
    percentiles re-centred on it), the raw percentiles around the bootstrap mean; the same set against
    resamples of itself: mean above 0 (the floor); paired resampling keeps row i with row i."""
    from smdm_plugin.metrics.t2m import fid_bootstrap

    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((40, 64)), rng.standard_normal((40, 64)) + 0.3
    r = fid_bootstrap(a, b, resamples=100, seed=1)
    assert r.fid == pytest.approx(frechet_distance(a, b)) and r.low <= r.fid <= r.high
    assert r.boot_low <= r.boot_mean <= r.boot_high and r.boot_mean > r.fid  # duplicates raise a resample's FID
    assert r.high - r.low == pytest.approx(r.boot_high - r.boot_low)
    assert fid_bootstrap(a, b, resamples=100, seed=1) == r                   # seeded
    floor = fid_bootstrap(a, a, resamples=100, seed=2)
    assert floor.fid == 0.0 and floor.boot_mean > 0 and floor.boot_low > 0
    same = fid_bootstrap(a, a.copy(), resamples=20, paired=True, seed=3)
    assert same.boot_mean == 0.0                                             # row i drawn with row i
    with pytest.raises(ValueError, match="paired sets need the same N"):
        fid_bootstrap(a, b[:10], paired=True)
    with pytest.raises(ValueError, match="resamples"):
        fid_bootstrap(a, b, resamples=1)
