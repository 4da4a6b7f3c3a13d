"""The keyframe plan: slots, capacity and interpolation indices against the plain formulation."""
import pytest
import torch

from smdm_plugin.core.interpolation import neighbour_keyframes
from smdm_plugin.core.plan import KeyframePlan


def random_masks(seed, B=4):
    g = torch.Generator().manual_seed(seed)
    N = int(torch.randint(2, 40, (), generator=g))
    mask = torch.rand(B, N, generator=g) < float(torch.rand((), generator=g))
    mask[torch.arange(B), torch.randint(0, N, (B,), generator=g)] = True  # >= 1 keyframe per row
    return mask


@pytest.mark.parametrize("seed", range(40))
def test_plan_matches_neighbour_keyframes_and_holds_every_keyframe(seed):
    mask = random_masks(seed)
    B, N = mask.shape
    K = min(N, int(mask.sum(1).max()) + seed % 3)
    plan = KeyframePlan.build(mask, K)
    prev, nxt, w = neighbour_keyframes(mask)
    assert torch.equal(plan.index.gather(1, plan.prev_slot), prev)
    assert torch.equal(plan.index.gather(1, plan.next_slot), nxt)
    between = prev != nxt
    assert torch.allclose(plan.weight[between], w[between])
    assert ((plan.weight >= 0) & (plan.weight <= 1)).all()
    for b in range(B):
        c = int(mask[b].sum())
        assert plan.count[b] == c and plan.valid[b].sum() == c
        assert plan.index[b, :c].tolist() == mask[b].nonzero().flatten().tolist()  # frame order
        assert len(set(plan.index[b].tolist())) == K                               # distinct slots
    assert (plan.valid.gather(1, plan.prev_slot) & plan.valid.gather(1, plan.next_slot)).all()


def test_plan_rejects_masks_over_capacity_or_empty_rows():
    mask = torch.zeros(2, 10, dtype=torch.bool)
    mask[:, [0, 3, 9]] = True
    KeyframePlan.build(mask, 3)
    with pytest.raises(ValueError, match="every sample needs 1..2 keyframes"):
        KeyframePlan.build(mask, 2)
    mask[1] = False
    with pytest.raises(ValueError, match="every sample needs 1..3 keyframes"):
        KeyframePlan.build(mask, 3)
    with pytest.raises(ValueError, match=r"capacity must be in \[1, N=10\]"):
        KeyframePlan.build(mask, 11)


@pytest.mark.parametrize("seed", range(6))
def test_built_plan_carries_its_key_bias(seed):
    """``KeyframePlan.build`` makes the additive key padding mask with the plan: 0 for a lead token,
    then 0 for each slot holding a keyframe and -inf for the others."""
    mask = random_masks(seed)
    K = mask.shape[1]
    plan = KeyframePlan.build(mask, K)
    assert plan.key_bias.dtype == torch.float32 and plan.key_bias.shape == (mask.shape[0], 1 + K)
    assert (plan.key_bias[:, 0] == 0).all()
    for b in range(mask.shape[0]):
        c = int(mask[b].sum())
        assert (plan.key_bias[b, 1:1 + c] == 0).all() and torch.isneginf(plan.key_bias[b, 1 + c:]).all()


def test_plan_triton_kernel_equals_the_composite_in_interpreter_mode(triton_interpreter):
    """The CUDA kernel of ``smdm::keyframe_plan``, run by Triton's interpreter on the CPU: every output
    equals the composite's, for frame counts that are not powers of two, capacities below and at
    ``N``, a single keyframe and dense masks."""
    code = (
        "import torch\n"
        "from smdm_plugin.core.kernels.plan_op import keyframe_plan_composite\n"
        "from smdm_plugin.core.kernels.plan_triton import keyframe_plan_triton\n"
        "torch.manual_seed(0)\n"
        "bad = 0\n"
        "for B, N, K, p in ((4, 30, 12, 0.3), (3, 196, 60, 0.2), (2, 7, 7, 0.9), (3, 50, 50, 0.05), (2, 17, 5, 0.0)):\n"
        "    m = torch.rand(B, N) < p\n"
        "    m[-1] = False\n"
        "    m[-1, N // 2] = True\n"
        "    m = m & (m.cumsum(1) <= K)\n"
        "    m[:, 0] |= ~m.any(1)\n"
        "    for x, y in zip(keyframe_plan_triton(m, K), keyframe_plan_composite(m, K)):\n"
        "        bad += int(not (x.dtype == y.dtype and torch.equal(x, y)))\n"
        "print('mismatches', bad)\n")
    out = triton_interpreter(code)
    assert "mismatches 0" in out, out
