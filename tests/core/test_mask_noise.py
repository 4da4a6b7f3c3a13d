"""Training mask noise draws nothing from torch's global RNG (core/noise.py): a sparse training step
leaves the global stream where a dense one leaves it; the noise is still uniform, new at every step
and for every sample; the same seed gives the same masks, and the step counter travels with the
weights (so a resumed run continues the same sequence)."""
import copy
import importlib.util
import subprocess
import sys

import numpy as np
import pytest
import torch

from smdm_plugin import SimpleDiffusion, SparseConfig, TinyMDM, sparsify
from smdm_plugin.adapters.diffusion_wrapper import model_noise
from smdm_plugin.core.noise import NOISE_STEP, NOISE_TABLE, TABLE_SIZE, CounterNoise, noise_table
from smdm_plugin.core.schedule import MaskSchedule
from smdm_plugin.core.selection import keyframe_count

from helpers.noise import noise_cases, slow_perturb
from helpers.paths import TESTS

B, N = 4, 60


def make(sparse: bool, seed: int = 0, **cfg):
    torch.manual_seed(seed)
    model = TinyMDM(njoints=12, latent_dim=32, ff_size=64, num_layers=2, dropout=0.0, cond_mode="no_cond")
    diffusion = SimpleDiffusion(50)
    if sparse:
        sparsify(model, SparseConfig(**{"reduction": 0.8, "feature": "raw", "mask_noise": 0.2, **cfg}),
                 diffusion=diffusion)
    return model.train(), diffusion


def inputs():
    g = torch.Generator().manual_seed(1)
    lengths = torch.tensor([N, 50, 41, 30])
    y = {"mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N), "lengths": lengths}
    return torch.randn(B, 12, 1, N, generator=g).cumsum(-1), y


def test_a_sparse_training_step_leaves_the_global_stream_where_a_dense_one_does():
    x, y = inputs()
    t = torch.tensor([3, 10, 20, 40])
    after = {}
    for sparse in (False, True):
        model, diffusion = make(sparse)
        torch.manual_seed(123)
        # upstream's draw outside the model (the diffusion noise) + the loss + backward
        diffusion.training_losses(model, x, t, {"y": dict(y)})["loss"].mean().backward()
        after[sparse] = (torch.get_rng_state(), torch.randn(8))
    assert torch.equal(after[True][0], after[False][0]) and torch.equal(after[True][1], after[False][1])


def test_the_old_global_stream_draw_would_have_shifted_it():
    """The test above can fail: drawing the noise from torch's stream (generator=None) moves it."""
    x, y = inputs()
    model, _ = make(True)
    sched = model._smdm_state.schedule
    frames = x.squeeze(2).transpose(1, 2)
    torch.manual_seed(123)
    before = torch.get_rng_state()
    sched.training_mask(frames, y["lengths"])                     # no step: torch's stream (explicit API)
    assert not torch.equal(torch.get_rng_state(), before)
    torch.manual_seed(123)
    sched.training_mask(frames, y["lengths"], None, sched.noise(torch.zeros((), dtype=torch.long)))
    assert torch.equal(torch.get_rng_state(), before)


def test_counter_noise_is_uniform_and_new_per_step_row_and_draw():
    table = noise_table(5)
    assert table.shape == (TABLE_SIZE,) and 0 <= table.min() and table.max() < 1
    step = torch.zeros((), dtype=torch.long)
    draws = []
    for _ in range(200):
        noise = CounterNoise(step, table)
        first, second = noise.uniform((16, 61)), noise.uniform((16,))
        assert not torch.equal(first[:, 0], second)              # two draws of one mask differ
        draws.append(first)
        noise.advance()
    assert int(step) == 200
    u = torch.stack(draws).double()
    assert abs(u.mean() - 0.5) < 0.005 and abs(u.var() - 1 / 12) < 0.003
    hist = torch.histc(u.float(), bins=10, min=0, max=1) / u.numel()
    assert (hist - 0.1).abs().max() < 0.005
    # new per step and per row: no two windows of 61 numbers equal
    rows = u.reshape(-1, 61)
    assert torch.unique(rows, dim=0).shape[0] == rows.shape[0]
    # adjacent steps are uncorrelated
    r = np.corrcoef(u[:-1].flatten().numpy(), u[1:].flatten().numpy())[0, 1]
    assert abs(r) < 0.02
    # the same step again: the same numbers (a new object at the same step)
    step.fill_(17)
    assert torch.equal(CounterNoise(step, table).uniform((16, 61)), draws[17].float())


def test_mask_noise_changes_the_masks_per_step_and_per_sample():
    model, _ = make(True)
    sched = model._smdm_state.schedule
    x = torch.randn(1, N, 12).cumsum(1).expand(8, N, 12).contiguous()   # 8 identical samples
    lengths = torch.full((8,), N)
    step = torch.zeros((), dtype=torch.long)
    masks = [sched.training_mask(x, lengths, None, sched.noise(step)) for _ in range(20)]
    assert int(step) == 20
    counts = torch.stack([m.sum(1) for m in masks])            # [steps, samples]
    assert len({tuple(m[0].tolist()) for m in masks}) > 10      # per step
    assert len({tuple(r.tolist()) for r in masks[0]}) > 3       # per sample (same motion)
    K = keyframe_count(N, 0.8)
    assert counts.float().mean().sub(K).abs() < 1.0 and (counts != K).any()     # +- round(0.2 K), mean K
    assert counts.min() >= K - round(0.2 * K) and counts.max() <= K + round(0.2 * K)


def test_same_seed_same_masks_and_the_step_travels_with_the_weights():
    x, y = inputs()
    a, b, c = make(True, seed=4)[0], make(True, seed=4)[0], make(True, seed=5)[0]
    frames = x.squeeze(2).transpose(1, 2)

    def next_mask(model):
        return model._smdm_state.schedule.training_mask(frames, y["lengths"], None, model_noise(model))

    seq_a = [next_mask(a) for _ in range(5)]
    seq_b = [next_mask(b) for _ in range(5)]
    seq_c = [next_mask(c) for _ in range(5)]
    assert all(torch.equal(p, q) for p, q in zip(seq_a, seq_b))
    assert not all(torch.equal(p, q) for p, q in zip(seq_a, seq_c))
    # the step is in the state dict: a model loaded from a's weights continues a's sequence
    sd = copy.deepcopy(a.state_dict())
    assert int(sd[NOISE_STEP]) == 5
    d, _ = make(True, seed=4)
    d.load_state_dict(sd)
    assert torch.equal(next_mask(d), next_mask(a))
    # a state dict without the step (saved before it existed) still loads strictly
    old = {k: v for k, v in sd.items() if k != NOISE_STEP}
    e, _ = make(True, seed=4)
    e.load_state_dict(old)
    assert int(getattr(e, NOISE_STEP)) == 0


def test_the_table_is_a_buffer_that_moves_with_the_model_and_is_not_saved():
    model, _ = make(True)
    table = getattr(model, NOISE_TABLE)
    assert torch.equal(table.view(torch.float32), model._smdm_state.schedule.noise_table)
    assert NOISE_TABLE not in model.state_dict()
    before = model_noise(model).uniform((4, 61))
    model.half()                                     # float buffers would be rounded: this one is not
    assert torch.equal(model_noise(model).uniform((4, 61)), before)
    assert getattr(model, NOISE_STEP).dtype == torch.long


def test_schedules_without_draws_make_no_table():
    assert MaskSchedule(SparseConfig(mask_noise=0.0)).noise_table is None
    assert MaskSchedule(SparseConfig(mask_noise=0.1)).noise_table is not None


@pytest.mark.parametrize("seed", [0, 2 ** 64 - 1])
def test_any_torch_seed_gives_a_table(seed):
    torch.manual_seed(seed)
    assert MaskSchedule(SparseConfig()).noise_seed == seed


def test_ranks_draw_other_masks_from_equal_buffers(monkeypatch):
    """Under torch.distributed every rank holds the same table and step (the trainer's
    max_divergence compares buffers) but reads its windows at its own offset."""
    x, y = inputs()
    frames = x.squeeze(2).transpose(1, 2)
    models = []
    for rank in (0, 1):
        monkeypatch.setattr(torch.distributed, "is_initialized", lambda: True)
        monkeypatch.setattr(torch.distributed, "get_rank", lambda group=None, r=rank: r)
        models.append(make(True, seed=4)[0])
        monkeypatch.undo()
    a, b = models
    assert all(torch.equal(p, q) for p, q in zip(a.buffers(), b.buffers()))
    ma = a._smdm_state.schedule.training_mask(frames, y["lengths"], None, model_noise(a))
    mb = b._smdm_state.schedule.training_mask(frames, y["lengths"], None, model_noise(b))
    assert not torch.equal(ma, mb) and int(getattr(a, NOISE_STEP)) == int(getattr(b, NOISE_STEP)) == 1


# ----------------------------------------------------------------------------- smdm::perturb_mask (issue 27)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_perturb_op_equals_the_rule_written_out(seed):
    """``smdm::perturb_mask`` (one op: the composite on the CPU) equals the per-sample rule, with
    protected frames and tied uniforms, for several amounts."""
    from smdm_plugin.core.kernels.perturb import perturb_mask_op
    from smdm_plugin.runtime.launches import count_launches

    mask, lengths, u, protected = noise_cases(seed)
    for amount in (0.1, 0.5, 1.0):
        for prot in (None, protected):
            assert torch.equal(perturb_mask_op(mask, lengths, u, amount, prot),
                               slow_perturb(mask, lengths, u, amount, prot))
    assert count_launches(lambda: perturb_mask_op(mask, lengths, u, 0.1, protected)).count == 1


def test_perturb_triton_kernel_equals_the_composite_in_interpreter_mode(triton_interpreter):
    """The CUDA kernel's code, run by Triton's interpreter on the CPU, gives the composite's masks."""
    code = (
        "import torch, sys\n"
        f"sys.path.insert(0, {str(TESTS)!r})\n"
        "from helpers.noise import noise_cases\n"
        "from smdm_plugin.core.kernels.perturb import perturb_composite\n"
        "from smdm_plugin.core.kernels.perturb_triton import perturb_triton\n"
        "bad = 0\n"
        "for seed in (0, 1, 2):\n"
        "    mask, lengths, u, protected = noise_cases(seed)\n"
        "    for amount in (0.1, 0.5, 1.0):\n"
        "        for prot in (None, protected):\n"
        "            bad += int(not torch.equal(perturb_triton(mask, lengths, u, amount, prot),\n"
        "                                       perturb_composite(mask, lengths, u, amount, prot)))\n"
        "print('mismatches', bad)\n")
    out = triton_interpreter(code)
    assert "mismatches 0" in out, out