"""recover_from_ric against the data set's new_joints, EES, and the motion/transition split."""
import glob
import os

import numpy as np
import pytest
import torch

from smdm_plugin.metrics import (doubletake_ees, end_effector_speed, motion_transition_masks,
                                 recover_from_ric, to_joint_positions, unfolded_step_sizes)

DATA = os.environ.get("SMDM_HUMANML3D_DIR", os.path.join(
    os.path.dirname(__file__), "..", "..", "shared", "data", "cmu-humanml3d"))
if not os.path.isdir(DATA):
    DATA = "/work/shared/data/cmu-humanml3d"
HAVE_DATA = os.path.isdir(os.path.join(DATA, "new_joint_vecs"))


@pytest.mark.skipif(not HAVE_DATA, reason="cmu-humanml3d data not found")
def test_recover_from_ric_matches_new_joints():
    files = sorted(glob.glob(os.path.join(DATA, "new_joint_vecs", "*.npy")))
    assert len(files) > 50
    worst = 0.0
    for f in files:
        vec = np.load(f)
        ref = np.load(f.replace("new_joint_vecs", "new_joints"))
        out = recover_from_ric(vec)
        assert isinstance(out, np.ndarray) and out.shape == ref.shape
        worst = max(worst, float(np.abs(out - ref).max()))
    assert worst < 1e-4  # metres
    # torch, batched, normalised input
    mean, std = np.load(os.path.join(DATA, "Mean.npy")), np.load(os.path.join(DATA, "Std.npy"))
    vec = np.load(files[0])[None]
    pos = to_joint_positions(torch.from_numpy((vec - mean) / std), mean=mean, std=std)
    assert torch.allclose(pos[0], torch.from_numpy(np.load(files[0].replace(
        "new_joint_vecs", "new_joints"))), atol=1e-4)


@pytest.mark.skipif(not HAVE_DATA, reason="cmu-humanml3d data not found")
def test_ees_on_real_motion():
    f = sorted(glob.glob(os.path.join(DATA, "new_joints", "*.npy")))[0]
    pos = torch.from_numpy(np.load(f))[None]
    ees = float(end_effector_speed(pos))
    assert 0.05 < ees < 20.0  # cm per frame at 20 fps: 1 cm/s .. 4 m/s
    feats = np.load(f.replace("new_joints", "new_joint_vecs"))[None]
    assert float(end_effector_speed(feats)) == pytest.approx(ees, rel=1e-4)


def test_ees_values():
    N = 11
    pos = torch.zeros(2, N, 22, 3)
    # left foot moves 1 cm / frame along x, other end effectors still -> EES 0.25 cm/frame
    pos[0, :, 10, 0] = torch.arange(N) * 0.01
    pos[1, :, [10, 11, 20, 21], 2] = (torch.arange(N) * 0.02)[:, None]
    assert float(end_effector_speed(pos[:1])) == pytest.approx(0.25)
    per = end_effector_speed(pos, reduce="none")
    assert per.tolist() == pytest.approx([0.25, 2.0])
    # lengths exclude padded frames; the jump at the end is not counted
    pos[0, 6:, 10, 0] = 5.0
    assert float(end_effector_speed(pos[:1], lengths=[6])) == pytest.approx(0.25)
    mask = torch.zeros(N, dtype=torch.bool)
    mask[6] = True
    assert float(end_effector_speed(pos[:1], frame_mask=mask)) > 100


def test_motion_transition_split():
    steps = unfolded_step_sizes([50, 60, 40], 10)
    assert steps.tolist() == [50, 100, 130]
    motion, trans = motion_transition_masks([50, 60, 40], 10)
    assert motion.shape == trans.shape == (130,)
    assert trans.nonzero().flatten().tolist() == list(range(40, 50)) + list(range(90, 100))
    assert not bool((motion & trans).any()) and bool((motion | trans).all())
    _, wide = motion_transition_masks([50, 60, 40], 10, margin=4)
    assert wide.nonzero().flatten().tolist() == list(range(38, 52)) + list(range(88, 102))
    with pytest.raises(ValueError):
        unfolded_step_sizes([50, 15, 40], 10)


def test_doubletake_ees_split():
    T = 130
    pos = torch.zeros(1, T, 22, 3)
    speed = torch.full((T,), 0.01)
    speed[40:50] = 0.05  # fast transition 1
    speed[90:100] = 0.05
    pos[0, :, [10, 11, 20, 21], 0] = torch.cumsum(speed, 0)[:, None]
    out = doubletake_ees(pos, [50, 60, 40], 10)
    assert out["transition"] == pytest.approx(5.0, rel=1e-4)
    assert out["motion"] == pytest.approx(1.0, rel=1e-4)
