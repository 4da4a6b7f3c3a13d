"""recover_from_ric against the data set's new_joints, EES, and the motion/transition split."""
import glob
import os

import numpy as np
import pytest
import torch

from smdm_plugin.metrics import (doubletake_ees, end_effector_speed, motion_transition_masks,
                                 recover_from_ric, to_joint_positions, unfolded_step_sizes)

# the ../shared lookup of conftest.py (the shared data beside the repository)
DATA = os.environ.get("SMDM_HUMANML3D_DIR", os.path.join(
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "shared", "data", "cmu-humanml3d"))
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


# --------------------------------------------------------------------------- foot skating, jitter, keyframe error
from scipy.ndimage import uniform_filter1d  # noqa: E402

from smdm_plugin.metrics import foot_skating_ratio, jitter, keyframe_error  # noqa: E402


def _gmd_skating_ratio(motion: np.ndarray, fps: float = 20.0) -> float:
    """GMD's calculate_skating_ratio, restated for one motion ``[L, 22, 3]`` cut to its length
    (feet 10 and 11, y up, 5 cm, 0.5 m/s, 5-frame uniform_filter1d with zeros outside)."""
    feet = motion[:, [10, 11]]                                            # [L, 2, 3]
    vel = np.linalg.norm(feet[1:][..., [0, 2]] - feet[:-1][..., [0, 2]], axis=-1) * fps   # [L-1, 2]
    avg = uniform_filter1d(vel, size=5, axis=0, mode="constant", origin=0)
    h = feet[..., 1]
    contact = (h[:-1] < 0.05) & (h[1:] < 0.05)
    skating = contact & (vel > 0.5) & (avg > 0.5)
    return float(np.logical_or(skating[:, 0], skating[:, 1]).sum() / skating.shape[0])


def _dno_jitter(motion: np.ndarray, fps: float = 20.0) -> float:
    """DNO's compute_jitter for one motion ``[L, J, 3]`` (loops, no vectorisation)."""
    vals = []
    for k in range(len(motion) - 3):
        for j in range(motion.shape[1]):
            d = motion[k + 3, j] - 3 * motion[k + 2, j] + 3 * motion[k + 1, j] - motion[k, j]
            vals.append(np.linalg.norm(d * fps ** 3))
    return float(np.mean(vals))


def _walker(N: int = 60, foot_height: float = 0.0, foot_speed: float = 0.0, fps: float = 20.0) -> torch.Tensor:
    """``[N, 22, 3]``: a body gliding along x at 1 m/s 1 m above the floor, both feet at
    ``foot_height`` moving along z at ``foot_speed`` m/s."""
    t = torch.arange(N, dtype=torch.float64) / fps
    pos = torch.zeros(N, 22, 3, dtype=torch.float64)
    pos[:, :, 0] = t[:, None]
    pos[:, :, 1] = 1.0
    pos[:, [10, 11], 0] = 0.0
    pos[:, [10, 11], 1] = foot_height
    pos[:, [10, 11], 2] = (foot_speed * t)[:, None]
    return pos


def _random_motions(B: int = 6, N: int = 50, seed: int = 0) -> torch.Tensor:
    """Random-walk joints with feet near the floor: some steps skate, some do not."""
    g = torch.Generator().manual_seed(seed)
    steps = torch.randn(B, N, 22, 3, generator=g, dtype=torch.float64) * 0.02
    pos = steps.cumsum(1)
    pos[..., 1] = (pos[..., 1] - pos[..., 1].amin(dim=1, keepdim=True)) * 0.8
    return pos


def test_foot_skating_known_answers():
    assert float(foot_skating_ratio(_walker(foot_speed=0.0))) == 0.0      # feet planted
    assert float(foot_skating_ratio(_walker(foot_speed=1.0))) == 1.0      # feet slide 5 cm/frame
    # lifted feet (10 cm) do not skate, however fast; nor does a foot that only moves up and down
    assert float(foot_skating_ratio(_walker(foot_height=0.1, foot_speed=3.0))) == 0.0
    bob = _walker()
    bob[:, [10, 11], 1] = 0.04 * (torch.arange(60) % 2)[:, None].double()
    assert float(foot_skating_ratio(bob)) == 0.0
    # 0.7 m/s: the zero-padded 5-step average is 0.42 m/s in the first and last step only
    N = 60
    assert float(foot_skating_ratio(_walker(N, foot_speed=0.7))) == pytest.approx((N - 3) / (N - 1))
    # thresholds scale with fps: the same positions at 10 fps slide at 0.35 m/s -> no skating
    assert float(foot_skating_ratio(_walker(N, foot_speed=0.7), fps=10)) == 0.0


def test_foot_skating_matches_gmd_reference():
    pos = _random_motions()
    lengths = torch.tensor([50, 49, 30, 12, 5, 2])
    ours = foot_skating_ratio(pos, lengths=lengths, reduce="none")
    ref = [_gmd_skating_ratio(pos[b, :L].numpy()) for b, L in enumerate(lengths.tolist())]
    assert ours.tolist() == pytest.approx(ref, abs=1e-12)
    assert 0.0 < float(ours.max())                                      # the test data does skate
    assert float(foot_skating_ratio(pos, lengths=lengths)) == pytest.approx(np.mean(ref))
    # [N, J, 3] and [B, N, J, 3] agree; padding beyond the length changes nothing
    one = foot_skating_ratio(pos[2, :30])
    padded = pos[2].clone()
    padded[30:] = 123.0
    assert float(foot_skating_ratio(padded, lengths=30)) == float(one) == pytest.approx(ref[2])
    assert float(foot_skating_ratio(pos[2:3, :30].float().numpy())) == pytest.approx(ref[2], abs=1e-6)


def test_jitter_known_answers():
    fps = 20.0
    t = torch.arange(40, dtype=torch.float64) / fps
    lin = _walker(40)                                                     # constant velocity
    assert float(jitter(lin, fps=fps)) == pytest.approx(0.0, abs=1e-6)
    acc = torch.zeros(40, 22, 3, dtype=torch.float64)
    acc[..., 2] = (4.9 * t ** 2)[:, None]                                 # constant acceleration
    assert float(jitter(acc, fps=fps)) == pytest.approx(0.0, abs=1e-6)
    cub = torch.zeros(40, 22, 3, dtype=torch.float64)
    cub[:, 3, 1] = 2.0 * t ** 3                                           # jerk 12 m/s^3 on joint 3
    assert float(jitter(cub, fps=fps, joints=[3])) == pytest.approx(12.0)
    assert float(jitter(cub, fps=fps)) == pytest.approx(12.0 / 22)
    # fps enters cubed: the same samples read at 40 fps are 8x as jerky
    assert float(jitter(cub, fps=2 * fps, joints=[3])) == pytest.approx(96.0)


def test_jitter_matches_dno_reference_and_lengths():
    pos = _random_motions(B=3, N=30)
    lengths = [30, 17, 4]
    per = jitter(pos, lengths=lengths, reduce="none")
    ref = [_dno_jitter(pos[b, :L].numpy()) for b, L in enumerate(lengths)]
    assert per.tolist() == pytest.approx(ref, rel=1e-10)
    assert float(jitter(pos, lengths=lengths)) == pytest.approx(np.mean(ref))
    assert float(jitter(pos[1, :17])) == pytest.approx(ref[1])            # [N, J, 3] == [B, N, J, 3]
    # frame_mask: only steps that touch a masked frame count
    spike = _walker(40)
    spike[20, 5, 1] += 0.1                                                # one bad frame
    fm = torch.zeros(40, dtype=torch.bool)
    fm[0:5] = True                                                        # far from the spike
    assert float(jitter(spike, frame_mask=fm)) == pytest.approx(0.0, abs=1e-6)
    fm[19] = True                                                         # steps 16..19 touch 19
    near = jitter(spike, frame_mask=fm, reduce="none")
    steps = [k for k in range(37) if any(fm[k:k + 4].tolist())]
    full = jitter(spike[None], reduce="none")
    assert float(near) > float(full) > 0
    mag = [_dno_jitter(spike[k:k + 4].numpy()) for k in steps]
    assert float(near) == pytest.approx(np.mean(mag))
    none = jitter(spike[None], frame_mask=torch.zeros(1, 40, dtype=torch.bool), reduce="none")
    assert torch.isnan(none).all()


def test_keyframe_error_known_offsets():
    g = torch.Generator().manual_seed(1)
    target = torch.randn(2, 30, 22, 3, generator=g, dtype=torch.float64)
    motion = target.clone()
    motion[0, 5, :, 0] += 0.03                                            # 3 cm at keyframe 5
    motion[0, 9, :11, 1] -= 0.10                                          # 10 cm on half the joints
    motion[0, 12] += 7.0                                                  # not a keyframe
    motion[1, 2] += torch.tensor([0.0, 0.3, 0.4], dtype=torch.float64)    # 50 cm at keyframe 2
    e0 = (0.03 + 0.10 * 11 / 22) / 2
    per = keyframe_error(motion, target, [[5, 9], [2]], reduce="none")
    assert per.tolist() == pytest.approx([e0, 0.5])
    mask = torch.zeros(2, 30, dtype=torch.bool)
    mask[0, [5, 9]] = True
    mask[1, 2] = True
    assert float(keyframe_error(motion, target, mask)) == pytest.approx((e0 + 0.5) / 2)
    assert float(keyframe_error(motion[0], target[0], [5, 9])) == pytest.approx(e0)
    assert float(keyframe_error(motion[0], target[0], torch.tensor([9]), joints=[0])) == pytest.approx(0.10)
    assert float(keyframe_error(motion, target, [0, 29])) == 0.0
    with pytest.raises(ValueError, match="keyframes must lie within lengths"):
        keyframe_error(motion, target, [5, 20], lengths=[30, 20])


_Z, _Z2 = torch.zeros(10, 22, 3), torch.zeros(2, 10, 22, 3)


@pytest.mark.parametrize("call, match", [
    (lambda: foot_skating_ratio(torch.zeros(10, 22)), "motion must be joint positions"),
    (lambda: jitter(torch.zeros(2, 10, 22, 2)), "motion must be joint positions"),
    (lambda: jitter(torch.zeros(5, 2, 10, 22, 3)), "motion must be joint positions"),
    (lambda: keyframe_error(torch.zeros(10, 22, 3), torch.zeros(11, 22, 3), [0]), "target must have the shape"),
    (lambda: foot_skating_ratio(torch.zeros(2, 10, 22, 3), lengths=[10, 11]), r"lengths must be <= N=10, got max 11"),
    (lambda: foot_skating_ratio(torch.zeros(2, 10, 22, 3), lengths=[10, 9, 8]), r"lengths must have shape \[B=2\] \(or be one int\)"),
    (lambda: jitter(torch.zeros(10, 22, 3), lengths=3), r"lengths must be >= 4, got min 3"),
    (lambda: jitter(torch.zeros(10, 22, 3), fps=0), "fps must be a finite number > 0"),
    (lambda: jitter(torch.zeros(10, 22, 3), frame_mask=torch.ones(9, dtype=torch.bool)), "frame_mask must be"),
    (lambda: foot_skating_ratio(torch.zeros(10, 5, 3)), "feet"),
    (lambda: keyframe_error(_Z, _Z, [3, 10]), r"keyframe indices must be in \[0, N=10\)"),
    (lambda: keyframe_error(_Z, _Z, []), "at least one frame"),
    (lambda: keyframe_error(_Z, _Z, [0.5]), "integer frame indices"),
    (lambda: keyframe_error(_Z2, _Z2, torch.zeros(2, 10, dtype=torch.bool)), "at least one frame"),
    (lambda: keyframe_error(_Z2, _Z2, [[1]]), "B=2 motions"),
    (lambda: jitter(torch.zeros(10, 22, 3), reduce="sum"), "reduce must be"),
])
def test_quality_metrics_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.skipif(not HAVE_DATA, reason="cmu-humanml3d data not found")
def test_quality_metrics_on_real_motion():
    files = sorted(glob.glob(os.path.join(DATA, "new_joints", "*.npy")))[:20]
    motions = [np.load(f) for f in files]
    N = max(len(m) for m in motions)
    pos = np.zeros((len(motions), N, 22, 3))
    for b, m in enumerate(motions):
        pos[b, :len(m)] = m
        pos[b, len(m):] = m[-1]
    lengths = [len(m) for m in motions]
    skate = foot_skating_ratio(pos, lengths=lengths, reduce="none")
    assert skate.tolist() == pytest.approx([_gmd_skating_ratio(pos[b, :L]) for b, L in enumerate(lengths)],
                                           abs=1e-12)
    assert 0.0 < float(skate.mean()) < 0.5       # real mocap: some, but little, foot sliding
    jit = jitter(pos, lengths=lengths, reduce="none")
    assert jit.tolist() == pytest.approx([_dno_jitter(pos[b, :L]) for b, L in enumerate(lengths)], rel=1e-9)
    # the interpolation of real motion from 20% of its frames is exact at those frames
    from smdm_plugin.core.interpolation import interpolate_keyframes
    mask = torch.zeros(len(motions), N, dtype=torch.bool)
    for b, L in enumerate(lengths):
        mask[b, torch.linspace(0, L - 1, max(2, L // 5)).round().long()] = True
    rec = interpolate_keyframes(torch.from_numpy(pos).reshape(len(motions), N, -1), mask).reshape(pos.shape)
    assert float(keyframe_error(rec, pos, mask, lengths=lengths)) < 1e-9
    # ... and interpolation is smoother than the real motion, with less skating
    assert float(jitter(rec, lengths=lengths)) < float(jit.mean())


def _loop_speed_and_jitter(motion: np.ndarray, fps: float = 20.0):
    """Plain loops over frames and joints: mean |velocity| (m/s) and mean |jerk| (m/s³)."""
    N, J, _ = motion.shape
    v = [np.linalg.norm((motion[k + 1, j] - motion[k, j]) * fps) for k in range(N - 1) for j in range(J)]
    jerk = [np.linalg.norm((motion[k + 3, j] - 3 * motion[k + 2, j] + 3 * motion[k + 1, j] - motion[k, j]) * fps ** 3)
            for k in range(N - 3) for j in range(J)]
    return float(np.mean(v)), float(np.mean(jerk))


def test_mean_speed_and_jitter_per_speed_match_a_loop_reference():
    from smdm_plugin.metrics import jitter_per_speed, mean_speed

    pos = _random_motions(B=3, N=30)
    lengths = [30, 17, 4]
    ref = [_loop_speed_and_jitter(pos[b, :L].numpy()) for b, L in enumerate(lengths)]
    speed = mean_speed(pos, lengths=lengths, reduce="none")
    assert speed.tolist() == pytest.approx([r[0] for r in ref], rel=1e-10)
    per = jitter_per_speed(pos, lengths=lengths, reduce="none")
    assert per.tolist() == pytest.approx([r[1] / r[0] for r in ref], rel=1e-10)
    # the set's value is the ratio of the set's means (not the mean of the ratios)
    want = np.mean([r[1] for r in ref]) / np.mean([r[0] for r in ref])
    assert float(jitter_per_speed(pos, lengths=lengths)) == pytest.approx(want, rel=1e-10)
    # invariant to playing the same path faster in space: scaling positions leaves j/s unchanged
    assert float(jitter_per_speed(3 * pos)) == pytest.approx(float(jitter_per_speed(pos)), rel=1e-10)
    # a walker at constant velocity: speed known, no jerk
    walk = _walker(40, foot_speed=1.0)
    assert float(jitter_per_speed(walk)) == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ValueError, match="jitter_per_speed: lengths must be >= 4, got min 3"):
        jitter_per_speed(pos, lengths=[30, 17, 3])
    with pytest.raises(ValueError, match="reduce must be"):
        jitter_per_speed(pos, reduce="sum")
