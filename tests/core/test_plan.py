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
