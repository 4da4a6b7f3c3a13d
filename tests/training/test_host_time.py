"""The host-time budget (issue 36): what a sparse call costs the host against the dense upstream
model's, measured on the CPU with the kernels made as good as free and a Triton launch charged what
the H200 paid for one (``training/hosttime.py``; at MDM's size a GPU step in bf16 is bound by host
time: docs/gpu.md). A training step and a sampling call, fp32 and bf16, every model variant. The
budgets are what 0.8 reached with a margin for a busy machine (0.9.2's meter, with its Triton charge:
trans_enc 1.28-1.34 / 1.14-1.15, the others 0.92-1.09); 0.7.0 measured 1.36-1.82 in MDM's cells
and 1.02-1.19 in MotionDiffuse's; the issue's target is 1.0 everywhere (trans_enc does not reach it)."""
import pytest
import torch

from smdm_plugin.core.checks import static_mode
from smdm_plugin.training.hosttime import HOST_VARIANTS, charging_kernels, host_cells, host_times, launch_charge

#: sparse / dense host time, by (variant, call): what 0.8 reached (docs/gpu.md) plus a margin
HOST_BUDGET = {
    ("trans_enc", "train"): 1.45,        # reached 1.21-1.32 (the fixed per-step work of the method:
    ("trans_enc", "sample"): 1.30,       # selection, plan, FSQ fold, Lipschitz weights; 1.11-1.17)
    ("trans_dec", "train"): 1.20,        # 0.96-1.05
    ("trans_dec", "sample"): 1.15,       # 0.89-0.98
    ("dip", "train"): 1.20,              # 1.01-1.05
    ("dip", "sample"): 1.20,             # 1.01-1.06
    ("doubletake", "train"): 1.45,       # trans_enc's training step
    ("doubletake", "sample"): 1.30,      # forced frames: 1.35-1.46 (0.9.3: a plan per call), 1.14-1.24 (0.9.4)
    ("motiondiffuse", "train"): 1.12,    # 0.97-1.09
    ("motiondiffuse", "sample"): 1.12,   # 0.94-1.03
}


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("variant", HOST_VARIANTS)
def test_sparse_host_time_within_budget_of_the_dense_model(variant, precision, one_thread):
    with static_mode():
        dense, sparse = host_cells(variant, False, precision), host_cells(variant, True, precision)
        for call in ("train", "sample"):
            r = host_times({"dense": dense[call], "sparse": sparse[call]}, repeats=30)
            ratio = r.ratio("sparse", "dense")
            assert ratio <= HOST_BUDGET[variant, call], \
                f"{variant} {precision} {call}: {r.ms['sparse']:.2f} vs {r.ms['dense']:.2f} ms ({ratio:.2f}x)"


def test_charged_kernels_count_what_a_gpu_host_pays():
    """The meter's rule: a fused op that CUDA runs as a Triton kernel is timed apart and charged
    ``TRITON_LAUNCH_OPS`` small ops, an SDPA call and a foreach op one each; plain ops, and a fused
    op whose Triton kernel is off (CUDA runs its composite: the FSQ codes), are measured as they run."""
    from smdm_plugin.core.kernels.dispatch import use_triton_kernels
    from smdm_plugin.core.kernels.fsq_code import fsq_code
    from smdm_plugin.core.kernels.plan_op import keyframe_plan
    from smdm_plugin.training.hosttime import TRITON_LAUNCH_OPS

    mask = torch.rand(3, 20) < 0.3
    mask[:, 0] = True
    q = torch.randn(1, 2, 5, 8)
    z, c = torch.randn(4, 8), torch.ones(8)
    with charging_kernels() as charges:
        keyframe_plan(mask, 20)
        assert charges.count == TRITON_LAUNCH_OPS > 1
        torch.nn.functional.scaled_dot_product_attention(q, q, q)
        torch._foreach_add_([torch.zeros(2), torch.zeros(3)], 1.0)
        assert charges.count == TRITON_LAUNCH_OPS + 2 and charges.seconds > 0
        torch.ones(3) + 1
        fsq_code(z, -c, c)
        assert charges.count == TRITON_LAUNCH_OPS + 2
        before = use_triton_kernels(True, ["FSQ code"])
        try:
            fsq_code(z, -c, c)
        finally:
            use_triton_kernels(before["FSQ code"], ["FSQ code"])
        assert charges.count == 2 * TRITON_LAUNCH_OPS + 2
    assert torch.nn.functional.scaled_dot_product_attention.__name__ == "scaled_dot_product_attention"
    assert 0 < launch_charge(200) < 1e-3


def test_the_meter_sees_host_work():
    """A call that does the same kernels plus Python work measures more host time (the meter
    would not see a regression of the kind it guards against otherwise)."""
    x = torch.ones(4)

    def lean():
        x + 1

    def heavy():
        x + 1
        sum(i * i for i in range(3000))

    r = host_times({"lean": lean, "heavy": heavy}, repeats=30)
    assert r.ms["heavy"] > r.ms["lean"] + 0.05
