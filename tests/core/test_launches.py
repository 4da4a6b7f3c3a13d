"""The CUDA-equivalent launch counter (runtime/launches.py) against hand-counted tiny programs."""
import torch
import torch.nn.functional as F

from smdm_plugin.runtime.launches import LaunchCounter, count_launches


def test_linear_forward_and_backward():
    """addmm; sum; ones_like (the seed grad); mm (dW); sum (db); dx is not needed (x is no leaf)."""
    torch.manual_seed(0)
    lin, x = torch.nn.Linear(8, 8), torch.randn(4, 8)

    def step():
        lin.zero_grad(set_to_none=True)
        lin(x).sum().backward()
    got = count_launches(step)
    assert got.count == 5, got.ops
    assert got.ops["aten.addmm.default"] == 1 and got.ops["aten.mm.default"] == 1
    assert not got.syncs


def test_views_and_allocations_are_free():
    x = torch.randn(4, 6)
    with LaunchCounter() as c:
        x.view(2, 12).transpose(0, 1).unsqueeze(0).expand(3, 12, 2)
        x.detach()[1:]
        torch.empty(5)
        torch.empty_like(x)
    assert c.count == 0, c.ops
    with LaunchCounter() as c:
        x.t().contiguous()                        # a copy
        x.clone()
        torch.zeros(3)                            # a fill
        x.fill_(1.0)
    assert c.count == 4, c.ops


def test_scaled_dot_product_attention_is_one_kernel_each_way():
    """Whatever the CPU runs (its flash kernel, or the math decomposition with dropout): 1 + 1, and
    the gradient is the CPU graph's."""
    torch.manual_seed(0)
    q, k, v = (torch.randn(2, 4, 16, 8, requires_grad=True) for _ in range(3))
    for p in (0.0, 0.3):
        def step():
            for t in (q, k, v):
                t.grad = None
            F.scaled_dot_product_attention(q, k, v, dropout_p=p).backward(torch.ones(2, 4, 16, 8))
        got = count_launches(step)
        assert got.ops["aten.scaled_dot_product_attention"] == 1, got.ops
        assert got.ops["aten.scaled_dot_product_attention.backward"] == 1, got.ops
        # + the ones the grad is, + AccumulateGrad's copies into q/k/v's layout (the CPU kernel's too)
        assert got.count - got.ops["aten.copy_.default"] == 3, got.ops
    ref = [t.grad for t in (q, k, v)]
    for t in (q, k, v):
        t.grad = None
    F.scaled_dot_product_attention(q, k, v).backward(torch.ones(2, 4, 16, 8))
    with LaunchCounter():
        for t in (q, k, v):
            t.grad = None
        F.scaled_dot_product_attention(q, k, v).backward(torch.ones(2, 4, 16, 8))
    assert all(torch.allclose(a.grad, b) for a, b in zip((q, k, v), [t.grad for t in (q, k, v)]))
    with torch.no_grad(), LaunchCounter() as c:
        F.scaled_dot_product_attention(q, k, v)
    assert c.count == 1, c.ops


def test_multihead_attention_uses_one_attention_kernel():
    """nn.MultiheadAttention (need_weights=False, dropout in training) reaches the counted SDPA."""
    m = torch.nn.MultiheadAttention(8, 2, dropout=0.1)
    s = torch.randn(5, 3, 8)
    with LaunchCounter() as c:
        m(s, s, s, need_weights=False)[0].sum().backward()
    assert c.ops["aten.scaled_dot_product_attention"] == 1
    assert c.ops["aten.scaled_dot_product_attention.backward"] == 1
    assert not any("bmm" in name or "softmax" in name for name in c.ops), c.ops


def test_dropout_is_native_dropout_one_each_way():
    x = torch.randn(4, 8, requires_grad=True)
    with LaunchCounter() as c:
        F.dropout(x, 0.2).backward(torch.ones(4, 8))
    assert c.ops["aten.native_dropout"] == 1
    assert c.count == 1 + 1 + 1, c.ops                                # + ones + the backward mul
    with LaunchCounter() as c:
        F.dropout(x, 0.2, training=False)
        torch.nn.Dropout(0.0)(x)
    assert c.count == 0, c.ops


def test_autocast_casts_count():
    """bf16 autocast Linear: casts of x, W, b (3) + addmm. Within one region autocast caches the
    casts of leaf tensors that require grad: a second call casts only x."""
    lin, x = torch.nn.Linear(8, 8), torch.randn(4, 8)
    with torch.no_grad(), LaunchCounter() as c, torch.autocast("cpu", torch.bfloat16):
        lin(x)
        lin(x)
    assert c.ops["aten._to_copy.default"] == 3 + 1 and c.ops["aten.addmm.default"] == 2, c.ops
    # SDPA under autocast: its inputs' casts are counted, the kernel is one
    q = torch.randn(2, 2, 8, 4)
    with torch.no_grad(), LaunchCounter() as c, torch.autocast("cpu", torch.bfloat16):
        out = F.scaled_dot_product_attention(q, q, q)
    assert out.dtype == torch.bfloat16
    assert c.ops == {"aten._to_copy.default": 3, "aten.scaled_dot_product_attention": 1}, c.ops


def test_adamw_foreach_is_one_kernel_per_foreach_op_and_its_steps_stay_on_the_host():
    """AdamW(foreach=True): weight decay, lerp, mul, addcmul, sqrt, div, add, addcdiv = 8 foreach
    kernels; the step counters are CPU tensors on every device (0 kernels, .item() no sync)."""
    lin, x = torch.nn.Linear(8, 8), torch.randn(4, 8)
    opt = torch.optim.AdamW(lin.parameters(), foreach=True)

    def step():
        opt.zero_grad(set_to_none=True)
        lin(x).sum().backward()
        opt.step()
    got = count_launches(step)
    foreach = sum(n for name, n in got.ops.items() if "_foreach_" in name)
    assert foreach == 8, got.ops
    assert got.count == 5 + 8 and not got.syncs, (got.ops, got.syncs)


def test_host_scalars_launch_nothing_and_host_data_on_the_device_is_a_sync():
    x = torch.randn(3)
    with LaunchCounter() as c:
        s = torch.tensor(2.0) * 3 + 1                 # all on the host
        s.item()
    assert c.count == 0 and not c.syncs, (c.ops, c.syncs)
    with LaunchCounter() as c:
        x * torch.tensor([1.0, 2.0, 3.0])             # host data fed to a device op
    assert c.count == 1 and c.syncs, (c.ops, c.syncs)
    with LaunchCounter() as c:
        torch.where(x > 0, x, 0.0)                    # a wrapped Python scalar: passed by value
        x * torch.tensor(2.0)                         # a 0-d host tensor: passed by value
    assert c.count == 3 and not c.syncs, (c.ops, c.syncs)
    with LaunchCounter() as c:
        x.sum().item()                                # device value read on the host
        x[x > 0]                                      # boolean-mask indexing
    assert c.syncs["aten._local_scalar_dense.default"] == 1
    assert c.syncs["aten.index.Tensor"] == 1


def test_counter_restores_torch_functions_and_nests():
    sdpa, dropout = F.scaled_dot_product_attention, F.dropout
    x = torch.randn(2, 2, 4, 4)
    with LaunchCounter() as outer:
        with LaunchCounter() as inner:
            F.scaled_dot_product_attention(x, x, x)
        x + 1
    assert F.scaled_dot_product_attention is sdpa and F.dropout is dropout
    assert inner.count == 1 and outer.count == 2, (inner.ops, outer.ops)
