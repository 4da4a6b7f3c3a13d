import pytest
import torch

from smdm_plugin import SparseConfig, select_keyframes
from smdm_plugin.core.selection import keyframe_count
from smdm_plugin.core.schedule import MaskSchedule
from smdm_plugin.core.losses import dense_loss, keyframe_loss, lipschitz_term
from smdm_plugin.core.lipschitz import LipschitzMLP


def test_dense_loss_ignores_padding_and_keyframe_loss_ignores_non_keyframes():
    pred, target = torch.zeros(2, 10, 3), torch.zeros(2, 10, 3)
    target[0, 8:] = 100.0  # beyond length 8: must not count
    target[1, 3] = 1.0
    lengths = torch.tensor([8, 10])
    assert torch.allclose(dense_loss(pred, target, lengths), torch.tensor([0.0, 1.0 / 10]))
    kf = torch.zeros(2, 10, dtype=torch.bool)
    kf[:, [0, 5]] = True
    assert torch.allclose(keyframe_loss(pred, target, kf), torch.tensor([0.0, 0.0]))
    kf[1, 3] = True
    assert torch.allclose(keyframe_loss(pred, target, kf)[1], torch.tensor(1.0 / 3))
    with pytest.raises(ValueError, match="keyframes must be"):
        keyframe_loss(pred, target, kf[:, :4])


def test_lipschitz_term_is_lambda_times_product():
    mlp = LipschitzMLP(4, 4, hidden=8, layers=3)
    cs = [p for n, p in mlp.named_parameters() if n.endswith(".c") or n.split(".")[-1] == "c"]
    prod = torch.stack([torch.nn.functional.softplus(c).reshape(()) for c in cs]).prod()
    assert len(cs) == 3 and torch.allclose(lipschitz_term(mlp, 0.1), 0.1 * prod)


def test_training_mask_from_x0_keeps_forced_inside_the_budget():
    cfg = SparseConfig(reduction=0.8, mask_noise=0.0, feature="raw")
    sched = MaskSchedule(cfg)
    x0 = torch.randn(3, 50, 12)
    lengths = torch.tensor([50, 30, 12])
    forced = torch.zeros(3, 50, dtype=torch.bool)
    forced[:, 5] = True
    forced[0, 20:24] = True
    m = sched.training_mask(x0, lengths, forced)
    assert m[forced].all()
    protected = [3 + 4 * (b == 0) for b in range(3)]               # both ends + the forced frames
    # K (not K + forced), or every protected frame when they are more than K (L=12: K=2 < 3)
    assert m.sum(1).tolist() == [max(keyframe_count(int(L), 0.8), p) for L, p in zip(lengths, protected)]
    assert torch.equal(m, select_keyframes(sched.features(x0), lengths, 0.8, "vw", forced=forced))
    noisy = MaskSchedule(cfg.replace(mask_noise=0.5)).training_mask(x0, lengths, forced,
                                                                    generator=torch.Generator().manual_seed(0))
    assert not torch.equal(noisy, m) and noisy[:, 0].all() and noisy[forced].all()


@pytest.mark.parametrize("T,late", [(10, 1), (50, 5), (100, 10), (1000, 100)])
def test_exactly_round_gamma_T_late_steps_use_vw(T, late):
    cfg = SparseConfig(reduction=0.8, gamma=0.1, diffusion_steps=T, dynamic_update=True, feature="raw")
    sched = MaskSchedule(cfg)
    x = torch.randn(1, 40, 5).cumsum(1)
    uniform = select_keyframes(torch.zeros(1, 40, 1), None, 0.8, "uniform")
    vw = select_keyframes(sched.features(x), None, 0.8, "vw")
    assert not torch.equal(uniform, vw)
    used_vw = [t for t in range(T) if torch.equal(sched.sampling_mask(x, torch.tensor([t])), vw)]
    assert used_vw == list(range(late))            # t = late-1 ... 0: the paper's t = late ... 1


def test_sampling_mask_switches_per_sample_at_gamma_T():
    cfg = SparseConfig(reduction=0.8, gamma=0.1, diffusion_steps=100, feature="raw", dynamic_update=True)
    sched = MaskSchedule(cfg)
    x = torch.randn(3, 60, 5)
    m = sched.sampling_mask(x, torch.tensor([50, 9, 10]))
    uniform = select_keyframes(torch.zeros(1, 60, 1), None, 0.8, "uniform")[0]
    assert torch.equal(m[0], uniform) and torch.equal(m[2], uniform)
    assert torch.equal(m[1], select_keyframes(sched.features(x[1:2]), None, 0.8, "vw")[0])


def test_schedule_input_errors():
    sched = MaskSchedule(SparseConfig(feature="raw"))
    with pytest.raises(ValueError, match="lengths must be <= N=10"):
        sched.training_mask(torch.randn(1, 10, 3), torch.tensor([11]))
    with pytest.raises(ValueError, match=r"lengths must have shape \[B=2\]"):
        sched.training_mask(torch.randn(2, 10, 3), torch.tensor([10]))
    with pytest.raises(ValueError, match=r"forced keyframes must be a bool tensor \[B, N\]=\[2, 10\]"):
        sched.training_mask(torch.randn(2, 10, 3), None, torch.zeros(2, 9, dtype=torch.bool))
