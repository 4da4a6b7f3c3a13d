"""Selection features: HumanML3D / KIT slices, de-normalisation, index column, layouts, errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from smdm_plugin.core.selection_features import extract_selection_features, from_mdm_layout, to_mdm_layout

from helpers.paths import SHARED as DATA


def test_humanml3d_layout_synthetic():
    x = torch.arange(263.0).repeat(2, 5, 1)                           # feature value = its index
    f = extract_selection_features(x, "humanml3d", frame_index_scale=0.5)
    assert f.shape == (2, 5, 64)
    assert torch.equal(f[0, 0, :63], torch.arange(4.0, 67.0))
    assert torch.equal(f[1, :, 63], torch.arange(5.0) * 0.5)


def test_kit_and_raw_layout():
    x = torch.arange(251.0).repeat(3, 4, 1)
    f = extract_selection_features(x, "kit", frame_index_scale=1.0)
    assert f.shape == (3, 4, 61)
    assert torch.equal(f[0, 0, :60], torch.arange(4.0, 64.0))
    assert torch.equal(f[2, :, 60], torch.arange(4.0))
    r = extract_selection_features(torch.ones(2, 7, 5), "raw", frame_index_scale=0.0)
    assert r.shape == (2, 7, 6) and torch.equal(r[..., :5], torch.ones(2, 7, 5))
    assert (r[..., 5] == 0).all()


def test_denormalisation_and_dtype_device():
    g = torch.Generator().manual_seed(0)
    raw = torch.randn(2, 9, 263, generator=g)
    mean, std = torch.randn(263, generator=g), torch.rand(263, generator=g) + 0.5
    f1 = extract_selection_features((raw - mean) / std, "humanml3d", mean, std)
    f2 = extract_selection_features(raw, "humanml3d")
    torch.testing.assert_close(f1, f2, atol=1e-5, rtol=1e-5)
    f3 = extract_selection_features(((raw - mean) / std).double(), "humanml3d",
                                    mean.numpy(), std.numpy())
    assert f3.dtype == torch.float64
    torch.testing.assert_close(f3.float(), f2, atol=1e-5, rtol=1e-5)


def test_mdm_layout_roundtrip():
    x = torch.randn(2, 263, 1, 30)
    b = from_mdm_layout(x)
    assert b.shape == (2, 30, 263) and torch.equal(b[1, 7], x[1, :, 0, 7])
    assert torch.equal(to_mdm_layout(b), x)
    f = extract_selection_features(from_mdm_layout(x), "humanml3d")
    assert f.shape == (2, 30, 64)


def test_humanml3d_slice_matches_real_joints():
    """Features 4:67 are the ric positions of joints 1..21: heights equal new_joints' heights and
    distances between joints equal those of the recovered global positions."""
    root = DATA / "cmu-humanml3d"
    if not (root / "Mean.npy").exists():
        pytest.skip("shared/data/cmu-humanml3d not available")
    mean, std = np.load(root / "Mean.npy"), np.load(root / "Std.npy")
    for i in ("000000", "000030", "000070"):
        vec = np.load(root / "new_joint_vecs" / f"{i}.npy")
        joints = np.load(root / "new_joints" / f"{i}.npy")            # [T, 22, 3]
        x = torch.from_numpy((vec - mean) / std)[None]
        f = extract_selection_features(x, "humanml3d", mean, std, 0.01)[0].numpy()
        ric = f[:, :63].reshape(-1, 21, 3)
        np.testing.assert_allclose(ric[..., 1], joints[:, 1:, 1], atol=1e-4)
        d_f = np.linalg.norm(ric[:, :, None] - ric[:, None], axis=-1)
        d_j = np.linalg.norm(joints[:, 1:, None] - joints[:, None, 1:], axis=-1)
        np.testing.assert_allclose(d_f, d_j, atol=1e-4)
        np.testing.assert_allclose(f[:, 63], np.arange(len(vec)) * 0.01, atol=1e-6)


@pytest.mark.parametrize("call,match", [
    (lambda: extract_selection_features(torch.zeros(2, 5, 262)), r"x must have D=263 features"),
    (lambda: extract_selection_features(torch.zeros(2, 5, 263), "kit"),
     r"x must have D=251 features for kind='kit', got D=263"),
    (lambda: extract_selection_features(torch.zeros(2, 263, 1, 5)),
     r"x must be 3-D \[B, N, D\].*from_mdm_layout"),
    (lambda: extract_selection_features(torch.zeros(2, 5, 263), mean=np.zeros(262)),
     r"mean must have shape \[D=263\]"),
    (lambda: extract_selection_features(torch.zeros(2, 5, 263), std=np.zeros((263, 1))),
     r"std must have shape \[D=263\]"),
    (lambda: extract_selection_features(torch.zeros(2, 5, 263), "smpl"),
     r"unknown kind 'smpl'; known: \('humanml3d', 'kit', 'raw', 'joints'\)"),
    (lambda: extract_selection_features(torch.zeros(2, 5, 263), frame_index_scale=-1.0),
     r"frame_index_scale must be >= 0"),
    (lambda: from_mdm_layout(torch.zeros(2, 263, 5)), r"from_mdm_layout: x must have MDM layout"),
])
def test_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()
