"""``smdm::vw_perturb_mask`` (a training mask: VW, then its mask noise, as one op) and the eager
training plan made with it: every case equals the heap VW reference followed by the noise rule
written out; the training schedule makes the same masks, plans and draws as the separate steps, and a
training step the same loss; one launch (two or three with its kernel off); one node under
``torch.compile``; the CUDA kernel's code, run by Triton's interpreter on the CPU, equals the ops."""
import dataclasses

import pytest
import torch

from smdm_plugin import SimpleDiffusion, SparseConfig, TinyMDM, sparsify
from smdm_plugin.core.plan import KeyframePlan
from smdm_plugin.core.schedule import MaskSchedule

from smdm_plugin.core.kernels import use_triton_kernels
from smdm_plugin.core.kernels.vw_perturb import vw_perturb_mask, vw_perturb_plan
from smdm_plugin.core.noise import CounterNoise, noise_table
from smdm_plugin.core.selection import perturb_checked, select_checked, select_perturbed_checked
from smdm_plugin.runtime.launches import count_launches

from helpers.noise import slow_perturb
from helpers.paths import TESTS
from helpers.vw import AMOUNTS, reference_mask, torch_case

@pytest.mark.parametrize("seed", range(12))
def test_op_equals_the_heap_reference_then_the_rule_written_out(seed):
    (X, L, K, f), u = torch_case(seed)
    vw = torch.from_numpy(reference_mask(X.numpy(), L.numpy(), K.numpy(), None if f is None else f.numpy()))
    for amount in AMOUNTS:
        assert torch.equal(vw_perturb_mask(X, L, K, f, u, amount), slow_perturb(vw, L, u, amount, f))


@pytest.mark.parametrize("make", [lambda s: torch.Generator().manual_seed(s), lambda s: CounterNoise(torch.tensor(s), noise_table(0))],
                         ids=["torch.Generator", "CounterNoise"])
@pytest.mark.parametrize("method", ["vw", "random", "uniform"])
def test_training_mask_has_the_two_steps_values_and_draws(make, method):
    """:func:`select_perturbed_checked` (one op for VW) against :func:`select_checked` then
    :func:`perturb_checked`: the same masks, and a ``torch.Generator`` left in the same state."""
    (X, L, K, f), _ = torch_case(3)
    for amount in (0.0, 0.2):
        g1, g2 = make(7), make(7)
        one = select_perturbed_checked(X, L, K, method, amount, g1, f)
        two = select_checked(X, L, K, method, g2, f)
        two = perturb_checked(two, L, amount, g2, f) if amount else two
        assert torch.equal(one, two)
        if isinstance(g1, torch.Generator):
            assert torch.equal(g1.get_state(), g2.get_state())


def assert_same_plan(a: KeyframePlan, b: KeyframePlan) -> None:
    for f in dataclasses.fields(KeyframePlan):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert (x is None and y is None) if x is None or y is None else torch.equal(x, y), f.name


@pytest.mark.parametrize("prefix", [0, 3])
@pytest.mark.parametrize("seed", range(4))
def test_training_plan_is_the_training_mask_and_the_plan_built_from_it(seed, prefix):
    """:meth:`MaskSchedule.training_plan` against :meth:`MaskSchedule.training_mask` and
    ``KeyframePlan.build`` of ``[prefix kept frames | mask]`` (every field), with the same draws:
    a :class:`CounterNoise` advanced once either way."""
    g = torch.Generator().manual_seed(seed)
    B, N = 5, 48
    x0 = torch.randn(B, N, 263, generator=g)
    lengths = torch.randint(2, N + 1, (B,), generator=g)
    schedule = MaskSchedule(SparseConfig(mask_noise=0.3))
    slots = schedule.capacity(N, training=True) + prefix
    g1, g2 = (CounterNoise(torch.tensor(seed), noise_table(0)) for _ in range(2))
    mask, plan = schedule.training_plan(x0, lengths, slots, prefix, g1)
    ref = schedule.training_mask(x0, lengths, None, g2)
    assert torch.equal(mask, ref) and torch.equal(g1.step, g2.step)
    kept = torch.cat([ref.new_ones(B, prefix), ref], 1)
    assert_same_plan(plan, KeyframePlan.build(kept, slots, check=False))
    assert torch.equal(plan.mask, kept)


def test_training_plan_is_none_where_no_op_makes_both():
    x0, lengths = torch.randn(2, 20, 263), torch.tensor([20, 12])
    for config in (SparseConfig(mask_noise=0.0), SparseConfig(selector="random")):
        assert MaskSchedule(config).training_plan(x0, lengths, 20) is None


def test_a_training_step_with_the_plan_made_in_one_op_has_the_same_loss_and_gradients(monkeypatch):
    """A sparse training step (DiP's prefix and MDM's trans_enc) with the plan made with its mask
    against the plan built by the model call from that mask."""
    def step(arch, fused):
        if not fused:
            monkeypatch.setattr(MaskSchedule, "training_plan", lambda *a, **k: None)
        torch.manual_seed(0)
        kw = dict(emb_trans_dec=True, context_len=4, pred_len=12) if arch == "dip" else {}
        model = TinyMDM(njoints=263, latent_dim=32, ff_size=64, num_layers=2, dropout=0.0, cond_mode="no_cond",
                        arch="trans_dec" if arch == "dip" else arch, **kw)
        diffusion = SimpleDiffusion(50)
        sparsify(model, SparseConfig(), diffusion=diffusion)
        N = 12 if arch == "dip" else 40
        x = torch.randn(3, 263, 1, N, generator=torch.Generator().manual_seed(1))
        lengths = torch.tensor([N, N - 3, 9]) if arch != "dip" else torch.full((3,), N)
        y = {"mask": (torch.arange(N) < lengths[:, None]).view(3, 1, 1, N), "lengths": lengths}
        if arch == "dip":
            y["prefix"] = torch.randn(3, 263, 1, 4, generator=torch.Generator().manual_seed(2))
        loss = diffusion.training_losses(model, x, torch.tensor([3, 20, 49]), {"y": y})["loss"].mean()
        loss.backward()
        monkeypatch.undo()
        return loss.detach(), [p.grad for p in model.parameters() if p.grad is not None]

    for arch in ("trans_enc", "dip"):
        (l1, g1), (l2, g2) = step(arch, True), step(arch, False)
        assert torch.equal(l1, l2) and len(g1) == len(g2) and all(torch.equal(a, b) for a, b in zip(g1, g2))


def test_one_launch_and_more_with_its_kernel_off():
    """One launch for the mask, one for the mask and its plan; with the kernel off two and three."""
    (X, L, K, f), u = torch_case(3)
    calls = (lambda: vw_perturb_mask(X, L, K, f, u, 0.1), lambda: vw_perturb_plan(X, L, K, None, u, 0.1, X.shape[1]))
    assert [count_launches(c).count for c in calls] == [1, 1]
    before = use_triton_kernels(False, ["VW with mask noise"])
    try:
        off = [count_launches(c).count for c in calls]
    finally:
        use_triton_kernels(before["VW with mask noise"], ["VW with mask noise"])
    assert off == [2, 3]


def test_op_registration_and_one_node_under_compile():
    (X, L, K, f), u = torch_case(3)
    op = torch.ops.smdm.vw_perturb_mask.default
    torch.library.opcheck(op, (X, L, K, f, u, 0.1))
    nodes = []

    def backend(gm, inputs):
        nodes.extend(n.target for n in gm.graph.nodes if n.op == "call_function")
        return gm.forward

    fn = torch.compile(lambda *a: vw_perturb_mask(*a), fullgraph=True, backend=backend)
    assert torch.equal(fn(X, L, K, f, u, 0.1), vw_perturb_mask(X, L, K, f, u, 0.1))
    assert nodes.count(op) == 1


def test_triton_kernel_equals_the_separate_ops_in_interpreter_mode(triton_interpreter):
    """The CUDA kernel's code, run by Triton's interpreter on the CPU (one program per sample: VW,
    its keyframes written and read back by the noise's rank loop, then the plan of the noisy mask
    after a prefix), gives the separate ops' masks and plans."""
    code = (
        "import sys, torch\n"
        f"sys.path.insert(0, {str(TESTS)!r})\n"
        "from helpers.vw import AMOUNTS, torch_case\n"
        "from smdm_plugin.core.kernels.vw_perturb import _three_kernels, _two_kernels\n"
        "from smdm_plugin.core.kernels.vw_perturb_triton import vw_perturb_triton\n"
        "same = lambda a, b: all(torch.equal(x, y) for x, y in zip(a, b))\n"
        "bad = 0\n"
        "for seed in (0, 1, 2, 3, 7):\n"
        "    (X, L, K, f), u = torch_case(seed)\n"
        "    for amount in AMOUNTS:\n"
        "        bad += int(not torch.equal(vw_perturb_triton(X, L, K, f, u, amount), _two_kernels(X, L, K, f, u, amount)))\n"
        "        for prefix in (0, 3):\n"
        "            got = vw_perturb_triton(X, L, K, None, u, amount, X.shape[1] + prefix, prefix)\n"
        "            ref = _three_kernels(X, L, K, None, u, amount, X.shape[1] + prefix, prefix)\n"
        "            bad += int(not (same(got[:2], ref[:2]) and same(got[2], ref[2])))\n"
        "print('mismatches', bad)\n")
    out = triton_interpreter(code)
    assert "mismatches 0" in out, out
