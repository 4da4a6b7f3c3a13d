"""Keyframe selection: batched VW == heap reference, counts/endpoints, other selectors, noise."""
from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import torch

from smdm_plugin.core.selection_features import extract_selection_features
from smdm_plugin.core.selection import (METHODS, keyframe_count, perturb_mask, select_keyframes,
                                   vw_reference)

from helpers.paths import SHARED as DATA


def _kept(mask_row: torch.Tensor) -> np.ndarray:
    return np.flatnonzero(mask_row.cpu().numpy())


def _assert_vw_equals_reference(feats: torch.Tensor, lengths: torch.Tensor, reduction: float):
    mask = select_keyframes(feats, lengths, reduction)
    for b in range(feats.shape[0]):
        L = int(lengths[b])
        ref = vw_reference(feats[b, :L].double().numpy(), keyframe_count(L, reduction))
        np.testing.assert_array_equal(_kept(mask[b]), ref, err_msg=f"sample {b}, L={L}")


# ----------------------------------------------------------------------------- VW exactness
@pytest.mark.parametrize("B,N,F", [(1, 2, 1), (3, 17, 2), (8, 60, 3), (5, 120, 64), (16, 196, 64)])
@pytest.mark.parametrize("reduction", [0.0, 0.5, 0.8, 0.95])
def test_vw_equals_heap_reference_random(B, N, F, reduction):
    g = torch.Generator().manual_seed(B * 1000 + N + F)
    feats = torch.randn(B, N, F, generator=g).cumsum(1)               # random walks
    lengths = torch.randint(2, N + 1, (B,), generator=g)
    lengths[0] = N
    _assert_vw_equals_reference(feats, lengths, reduction)
    _assert_vw_equals_reference(feats.double(), lengths, reduction)  # float64 input path


def test_vw_equals_reference_with_ties_and_duplicates():
    # frozen stretches (zero areas, exact ties) and an exactly collinear segment
    x = torch.zeros(2, 40, 3)
    x[0, 10:20] = 1.0
    x[0, 25:] = torch.linspace(0, 1, 15)[:, None]
    x[1, :, 0] = torch.arange(40.0)                                   # straight line: all ties
    lengths = torch.tensor([40, 33])
    for red in (0.3, 0.8, 0.9):
        _assert_vw_equals_reference(x, lengths, red)
    # on a straight line every area is 0: ties go to the lowest frame index
    mask = select_keyframes(x[1:], None, 0.9)
    np.testing.assert_array_equal(_kept(mask[0]), vw_reference(x[1].numpy(), 4))
    assert _kept(mask[0]).tolist() == [0, 37, 38, 39]


def test_vw_keeps_a_corner():
    t = torch.arange(30.0)
    path = torch.stack([torch.minimum(t, torch.tensor(12.0)), (t - 12).clamp_min(0)], -1)
    mask = select_keyframes(path[None], None, 0.9)                     # K = 3
    assert _kept(mask[0]).tolist() == [0, 12, 29]


def _hml_features(scale: float = 0.01):
    root = DATA / "cmu-humanml3d"
    if not (root / "Mean.npy").exists():
        pytest.skip("shared/data/cmu-humanml3d not available")
    mean, std = np.load(root / "Mean.npy"), np.load(root / "Std.npy")
    ids = (root / "all.txt").read_text().split()
    N = 196
    x = np.zeros((len(ids), N, 263), np.float32)
    lengths = []
    for b, i in enumerate(ids):
        m = np.load(root / "new_joint_vecs" / f"{i}.npy")[:N]
        x[b, :len(m)] = (m - mean) / std
        lengths.append(len(m))
    feats = extract_selection_features(torch.from_numpy(x), "humanml3d", mean, std, scale)
    return feats, torch.tensor(lengths)


@pytest.mark.parametrize("scale", [0.0, 0.01])
def test_vw_equals_reference_on_real_humanml3d(scale):
    feats, lengths = _hml_features(scale)
    for red in (0.0, 0.8, 0.95):
        _assert_vw_equals_reference(feats, lengths, red)


def test_vw_equals_reference_on_real_bvh():
    from smdm_plugin.io.bvh import load_cmu_clip
    clips = ["01_01", "05_02", "49_06"]                               # LF, CRLF, LF files
    if not all((DATA / "cmu-mocap" / f"{c}.bvh").exists() for c in clips):
        pytest.skip("shared/data/cmu-mocap not available")
    segs = []
    for c in clips:
        j = load_cmu_clip(DATA / "cmu-mocap" / f"{c}.bvh")
        segs += [j[s:s + 196] for s in range(0, len(j) - 40, 150)][:4]
    N = max(len(s) for s in segs)
    feats = torch.zeros(len(segs), N, 64, dtype=torch.float64)
    for b, s in enumerate(segs):
        x = torch.from_numpy(np.asarray(s, np.float64).reshape(1, len(s), 66))
        feats[b, :len(s)] = extract_selection_features(x, "joints", frame_index_scale=0.01)[0]
    lengths = torch.tensor([len(s) for s in segs])
    for red in (0.6, 0.8, 0.95):
        _assert_vw_equals_reference(feats.float(), lengths, red)


# ----------------------------------------------------------------------------- contract
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("reduction", [0.0, 0.25, 0.8, 0.95])
def test_count_endpoints_and_length(method, reduction):
    g = torch.Generator().manual_seed(3)
    B, N = 9, 41
    feats = torch.randn(B, N, 5, generator=g)
    lengths = torch.tensor([41, 2, 3, 4, 5, 10, 17, 40, 33])
    mask = select_keyframes(feats, lengths, reduction, method, generator=g)
    assert mask.dtype == torch.bool and mask.shape == (B, N)
    for b in range(B):
        L = int(lengths[b])
        kept = _kept(mask[b])
        assert len(kept) == min(L, max(2, round((1 - reduction) * L)))
        assert kept[0] == 0 and kept[-1] == L - 1


def test_keyframe_count_formula():
    assert keyframe_count(196, 0.8) == 39
    assert keyframe_count(196, 0.0) == 196
    assert keyframe_count(2, 0.95) == 2
    assert keyframe_count(10, 0.95) == 2
    assert keyframe_count(40, 0.9) == 4
    assert keyframe_count(3, 0.0) == 3


def test_uniform_evenly_spaced_and_distinct():
    lengths = torch.arange(2, 60)
    for red in (0.0, 0.3, 0.5, 0.8, 0.95):
        mask = select_keyframes(torch.zeros(len(lengths), 59, 1), lengths, red, "uniform")
        for b, L in enumerate(lengths.tolist()):
            K = keyframe_count(L, red)
            expect = np.floor(np.arange(K) * (L - 1) / (K - 1) + 0.5).astype(int)
            np.testing.assert_array_equal(_kept(mask[b]), expect)
    assert _kept(select_keyframes(torch.zeros(1, 11, 1), None, 0.7, "uniform")[0]).tolist() == \
        [0, 5, 10]


def test_random_deterministic_and_spread():
    x = torch.zeros(4, 100, 2)
    m1 = select_keyframes(x, None, 0.8, "random", torch.Generator().manual_seed(7))
    m2 = select_keyframes(x, None, 0.8, "random", torch.Generator().manual_seed(7))
    m3 = select_keyframes(x, None, 0.8, "random", torch.Generator().manual_seed(8))
    assert torch.equal(m1, m2) and not torch.equal(m1, m3)
    assert not torch.equal(m1[0], m1[1])                              # samples differ
    # every interior frame is chosen sometimes (uniform over interior frames)
    counts = torch.zeros(100)
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        counts += select_keyframes(x, None, 0.8, "random", g).sum(0)
    assert (counts[1:-1] > 0).all() and counts[0] == counts[-1] == 200


def _mdo_brute(P: np.ndarray, K: int) -> float:
    L = len(P)
    best = -1.0
    for c in itertools.combinations(range(1, L - 1), K - 2):
        idx = (0,) + c + (L - 1,)
        best = max(best, sum(np.linalg.norm(P[idx[i + 1]] - P[idx[i]]) for i in range(K - 1)))
    return best


def test_mdo_matches_brute_force():
    g = torch.Generator().manual_seed(11)
    for _ in range(6):
        x = torch.randn(4, 10, 3, generator=g)
        lengths = torch.randint(2, 11, (4,), generator=g)
        for red in (0.0, 0.4, 0.6, 0.8):
            mask = select_keyframes(x, lengths, red, "mdo")
            for b in range(4):
                L = int(lengths[b])
                P = x[b, :L].double().numpy()
                idx = _kept(mask[b])
                got = sum(np.linalg.norm(P[idx[i + 1]] - P[idx[i]]) for i in range(len(idx) - 1))
                assert got == pytest.approx(_mdo_brute(P, keyframe_count(L, red)), abs=1e-9)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
def test_cuda_matches_cpu():
    x = torch.randn(8, 196, 64).cumsum(1)
    lengths = torch.randint(40, 197, (8,))
    for method in ("vw", "uniform", "mdo"):
        cpu = select_keyframes(x, lengths, 0.8, method)
        gpu = select_keyframes(x.cuda(), lengths.cuda(), 0.8, method)
        assert gpu.device.type == "cuda" and torch.equal(cpu, gpu.cpu())


# ----------------------------------------------------------------------------- mask noise
def test_perturb_mask_invariants():
    g = torch.Generator().manual_seed(5)
    B, N = 64, 196
    lengths = torch.randint(2, N + 1, (B,), generator=g)
    base = select_keyframes(torch.randn(B, N, 4, generator=g), lengths, 0.8, "random", g)
    i = torch.arange(N)[None]
    added = dropped = 0
    for amount in (0.0, 0.1, 0.5, 1.0):
        for _ in range(10):
            out = perturb_mask(base, lengths, amount, g)
            k0, k1 = base.sum(1), out.sum(1)
            assert out.dtype == torch.bool and out.shape == (B, N)
            assert not (out & (i >= lengths[:, None])).any()               # nothing at/after L
            assert out[:, 0].all() and out[torch.arange(B), lengths - 1].all()
            assert (k1 >= 2).all()
            assert ((k1 - k0).abs() <= torch.round(amount * k0.double()).long()).all()
            grew, shrank = (out & ~base).any(1), (base & ~out).any(1)
            assert not (grew & shrank).any()                               # one direction
            added += int(grew.sum())
            dropped += int(shrank.sum())
            if amount == 0.0:
                assert torch.equal(out, base)
    assert added > 0 and dropped > 0


def test_perturb_mask_deterministic_and_keeps_input():
    base = select_keyframes(torch.randn(8, 50, 2), None, 0.7, "uniform")
    before = base.clone()
    a = perturb_mask(base, None, 0.5, torch.Generator().manual_seed(1))
    b = perturb_mask(base, None, 0.5, torch.Generator().manual_seed(1))
    assert torch.equal(a, b) and torch.equal(base, before)


def test_perturb_mask_two_keyframes_never_drop():
    base = select_keyframes(torch.zeros(16, 30, 1), None, 0.95, "uniform")   # K = 2
    out = perturb_mask(base, None, 1.0, torch.Generator().manual_seed(0))
    assert (out.sum(1) >= 2).all() and out[:, 0].all() and out[:, -1].all()


# ----------------------------------------------------------------------------- errors
@pytest.mark.parametrize("kwargs,match", [
    (dict(features=torch.zeros(2, 10)), r"features must be 3-D \[B, N, F\]"),
    (dict(reduction=1.0), r"reduction must be a float in \[0, 1\)"),
    (dict(reduction=-0.1), r"reduction must be a float in \[0, 1\)"),
    (dict(lengths=torch.tensor([10])), r"lengths must have shape \[B=2\]"),
    (dict(lengths=torch.tensor([10, 1])), r"lengths must be >= 2, got min 1"),
    (dict(lengths=torch.tensor([10, 11])), r"lengths must be <= N=10, got max 11"),
    (dict(lengths=torch.tensor([10.0, 5.0])), r"lengths must be an integer tensor"),
    (dict(method="foo"), r"unknown method 'foo'; known: \('vw', 'uniform', 'random', 'mdo'\)"),
    (dict(features=torch.zeros(2, 1, 3)), r"N must be >= 2"),
])
def test_select_errors(kwargs, match):
    args = dict(features=torch.zeros(2, 10, 3), lengths=None, reduction=0.8, method="vw")
    args.update(kwargs)
    with pytest.raises(ValueError, match="select_keyframes: " + match):
        select_keyframes(**args)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_select_rejects_nonfinite_in_valid_frames(method, bad):
    for frame in (0, 5, 7):
        x = torch.randn(2, 10, 3)
        x[1, frame, 1] = bad
        with pytest.raises(ValueError, match="select_keyframes: features contain NaN or inf"):
            select_keyframes(x, torch.tensor([10, 8]), 0.5, method)
    x = torch.randn(2, 10, 3)
    x[1, 9] = bad                                                      # padding: ignored
    assert select_keyframes(x, torch.tensor([10, 8]), 0.5, method).shape == (2, 10)


def test_perturb_and_reference_errors():
    with pytest.raises(ValueError, match=r"perturb_mask: mask must be a 2-D bool tensor \[B, N\]"):
        perturb_mask(torch.zeros(2, 3, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"perturb_mask: amount must be a float in \[0, 1\]"):
        perturb_mask(torch.zeros(2, 4, dtype=torch.bool), amount=1.5)
    with pytest.raises(ValueError, match=r"perturb_mask: lengths must be <= N=4"):
        perturb_mask(torch.zeros(2, 4, dtype=torch.bool), torch.tensor([4, 5]))
    with pytest.raises(ValueError, match=r"vw_reference: k must be in \[2, L=5\]"):
        vw_reference(np.zeros((5, 2)), 6)
    with pytest.raises(ValueError, match=r"vw_reference: points must be 2-D \[L, F\]"):
        vw_reference(np.zeros(5), 2)
