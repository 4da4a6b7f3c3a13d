"""The host-work budget (issue 36): what a sparse call costs the host against the dense upstream
model's (at MDM's size a GPU step in bf16 is bound by host time: docs/gpu.md), counted, not timed:
the aten ops the dispatcher runs (a fused op that CUDA runs as a Triton kernel counted what the
H200 paid for its launch) and the Python frames entered (``training/hosttime.py: host_work``). A
training step and a sampling call, fp32 and bf16, every model variant. Counts are the same on any
machine, so a budget holds without a margin for load; the time itself is measured by the meter
(``scripts/host_time.py``, dense and sparse side by side), never in a test. 0.10.2's counts, sparse /
dense: trans_enc training 1.11-1.12 ops / 0.95-0.96 frames (FSQ keys and Lipschitz layers, the
keyframe selection and plan), the others 0.55-1.08 ops / 0.42-1.06 frames."""
import pytest
import torch

from smdm_plugin.core.checks import static_mode
from smdm_plugin.training.hosttime import (HOST_VARIANTS, TRITON_LAUNCH_OPS, HostWork, charging_kernels, host_cells,
                                           host_times, host_work, launch_charge)

#: sparse / dense (aten ops, Python frames), by (variant, call): 0.10.4's counts (the larger of fp32
#: and bf16) plus 0.005, rounded up: a change that adds host work to a sparse call fails (0.9.4's
#: dropout call in eval, 48 per trans_enc guided call: frames 0.70 -> 0.74). Counts depend on the
#: torch version (CI pins one); a change that lowers a count lowers its budget. 0.10.0: SDPA counted
#: one op (0.9.x counted the CPU's math composite forward); the FSQ key maps as one bank per stack.
#: 0.10.1: SDPA's backward counted one op too and dropout in training one, as CUDA runs them (the
#: same trees: trans_enc training 1.210 -> 1.244, trans_dec 0.928 -> 0.971); the stacks' tokens as
#: rows, each layer written out (trans_enc training 1.244 / 1.053 -> 1.171 / 0.964, guided call
#: 0.903 / 0.710 -> 0.779 / 0.490). 0.10.2: a training step's VW, mask noise and plan one fused op
#: (three Triton launches -> one: trans_enc training 1.171 -> 1.123 ops). 0.10.4: the row operations
#: as native ops (no Python autograd function: training frames 0.957 -> 0.941 fp32).
WORK_BUDGET = {
    ("trans_enc", "train"): (1.13, 0.96),      # 1.122 / 0.950
    ("trans_enc", "sample"): (0.78, 0.50),     # 0.774 / 0.493
    ("trans_dec", "train"): (0.90, 0.90),      # 0.889 / 0.894
    ("trans_dec", "sample"): (0.56, 0.44),     # 0.554 / 0.426
    ("dip", "train"): (0.91, 0.91),            # 0.897 / 0.901
    ("dip", "sample"): (0.58, 0.45),           # 0.573 / 0.438
    ("doubletake", "train"): (1.13, 0.96),     # trans_enc's training step
    ("doubletake", "sample"): (0.78, 0.50),    # 0.774 / 0.489: forced frames cost no more
    ("motiondiffuse", "train"): (1.08, 1.06),  # 1.071 / 1.054 (linear attention: no SDPA)
    ("motiondiffuse", "sample"): (1.04, 1.06),  # 1.031 / 1.055
}


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("variant", HOST_VARIANTS)
def test_sparse_host_work_within_budget_of_the_dense_model(variant, precision):
    with static_mode():
        dense, sparse = host_cells(variant, False, precision), host_cells(variant, True, precision)
        for call in ("train", "sample"):
            d, s = host_work(dense[call]), host_work(sparse[call])
            assert host_work(sparse[call]) == s, f"{variant} {precision} {call}: the count is not repeatable"
            r = s.ratio(d)
            ops, frames = WORK_BUDGET[variant, call]
            assert r["ops"] <= ops and r["calls"] <= frames, f"{variant} {precision} {call}: {s} vs {d} ({r})"


def test_host_work_counts_ops_and_frames_and_a_fused_op_as_a_launch():
    """Exact counts: each aten op and Python frame once; a fused op that CUDA runs as a Triton kernel
    ``TRITON_LAUNCH_OPS`` ops, whatever its CPU composite runs; the count of a repeated call repeats."""
    from smdm_plugin.core.kernels.plan_op import keyframe_plan

    x = torch.ones(4)

    def two_ops():
        x + 1
        x * 2

    def ten_times():
        for _ in range(10):
            two_ops()

    assert host_work(two_ops) == HostWork(ops=2, calls=1)
    assert host_work(ten_times) == HostWork(ops=20, calls=11)
    mask = torch.rand(3, 20) < 0.3
    mask[:, 0] = True
    plan = host_work(lambda: keyframe_plan(mask, 20))
    assert plan.ops == TRITON_LAUNCH_OPS and plan.calls < 12
    assert HostWork(30, 10).ratio(HostWork(20, 20)) == {"ops": 1.5, "calls": 0.5}
    # SDPA one op, as CUDA launches it, whatever the CPU runs (a mask and unequal head sizes: its math
    # composite, a dozen ops); no frame of its own
    q, v = torch.randn(2, 4, 6, 8), torch.randn(2, 4, 6, 16)
    bias = torch.zeros(2, 1, 1, 6)

    def attend():
        torch.nn.functional.scaled_dot_product_attention(q, q, v, attn_mask=bias)
        x + 1

    assert host_work(attend) == HostWork(ops=2, calls=1)
    assert torch.nn.functional.scaled_dot_product_attention.__name__ == "scaled_dot_product_attention"


def test_host_work_counts_attention_and_dropout_as_cuda_runs_them():
    """Under autograd SDPA counts one op forward and one backward (CUDA's two kernels; the CPU's math
    composite runs about twenty ops backward), dropout in training one (CUDA's ``native_dropout``; the
    CPU runs four; ``F.dropout``'s Python frame counts, as a GPU runs it), the stand-ins no frame of
    their own; the gradients are SDPA's own; autocast's casts of its inputs count one each, as CUDA
    launches them."""
    F = torch.nn.functional
    q = torch.randn(2, 4, 6, 8, requires_grad=True)
    v = torch.randn(2, 4, 6, 16, requires_grad=True)
    bias = torch.zeros(2, 1, 1, 6)

    def doubled():                       # the same step with a plain op in place of SDPA / dropout
        (q * 2).sum().backward()

    def attention():
        F.scaled_dot_product_attention(q, q, v, attn_mask=bias, dropout_p=0.1).sum().backward()

    def dropout():
        F.dropout(q, 0.1, True).sum().backward()

    plain = host_work(doubled)
    # the plain step: mul, sum; backward's ones, expand, mul, q's accumulation. SDPA: one op each way
    # where the mul and its gradient were, plus the sum of q's two gradients (query and key) and v's
    # accumulation
    assert host_work(attention) == HostWork(plain.ops + 2, plain.calls)
    assert host_work(dropout) == HostWork(plain.ops, plain.calls + 1)     # F.dropout's own Python (a GPU runs it)
    with torch.autocast("cpu", torch.bfloat16):
        cast = host_work(lambda: F.scaled_dot_product_attention(q, q, v, attn_mask=bias))
    assert cast.ops == 1 + 3                  # q (once, as autocast's cache), v and the mask cast
    assert host_work(lambda: F.dropout(q, 0.1, False)).ops == 0          # eval: no op
    torch.manual_seed(0)
    want = torch.autograd.grad(F.scaled_dot_product_attention(q, q, v, attn_mask=bias).square().sum(), [q, v])
    counted = []

    def grads():
        counted.append(torch.autograd.grad(
            F.scaled_dot_product_attention(q, q, v, attn_mask=bias).square().sum(), [q, v]))
    host_work(grads)
    assert all(torch.equal(a, b) for g in counted for a, b in zip(g, want))
    assert F.scaled_dot_product_attention.__name__ == "scaled_dot_product_attention"
    assert "dropout" not in vars(torch._VF)                      # (looked up by name again)


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
        # under autograd SDPA is charged once each way, dropout once (its backward: one op anyway)
        leaf = q.clone().requires_grad_()
        torch.nn.functional.scaled_dot_product_attention(leaf, leaf, leaf).sum().backward()
        torch.nn.functional.dropout(leaf, 0.5, True).sum().backward()
        assert charges.count == 2 * TRITON_LAUNCH_OPS + 5
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
