"""Lipschitz MLP: the reported ∞-norm bound holds, the parametrization, loss, bake, state dict."""
import copy

import pytest
import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils import parametrize

from smdm_plugin.core.lipschitz import (LipschitzMLP, LipschitzWeight, SineActivation,
                                   bake_lipschitz, is_lipschitz, lipschitz_linear,
                                   lipschitz_loss)
from smdm_plugin.core.lipschitz import _inverse_softplus


def _ratio(f, x, y):
    """``||f(x) - f(y)||_∞ / ||x - y||_∞`` per pair, ``x, y [P, D]``."""
    return (f(x) - f(y)).abs().amax(-1) / (x - y).abs().amax(-1)


def _worst_ratio(mlp: LipschitzMLP, in_f: int, pairs: int = 64, steps: int = 40,
                 seed: int = 0) -> float:
    """Largest ratio over random pairs (wide and close) and pairs improved by gradient ascent."""
    g = torch.Generator().manual_seed(seed)
    dt = next(mlp.parameters()).dtype
    x = torch.randn(pairs, in_f, generator=g, dtype=dt) * 2
    y = torch.cat([torch.randn(pairs // 2, in_f, generator=g, dtype=dt) * 2,
                   x[pairs // 2:] + 1e-3 * torch.randn(pairs - pairs // 2, in_f, generator=g,
                                                       dtype=dt)])
    with torch.no_grad():
        worst = _ratio(mlp, x, y).max().item()
    x, y = x.clone().requires_grad_(), y.clone().requires_grad_()
    opt = torch.optim.Adam([x, y], lr=0.05)
    for _ in range(steps):
        r = _ratio(mlp, x, y)
        worst = max(worst, r.max().item())
        opt.zero_grad()
        (-r.sum()).backward()
        opt.step()
    with torch.no_grad():
        worst = max(worst, _ratio(mlp, x, y).max().item())
    return worst


@pytest.mark.parametrize("layers,w0", [(1, 1.0), (2, 1.0), (2, 5.0), (3, 30.0)])
def test_bound_holds_random_and_adversarial(layers, w0):
    torch.manual_seed(layers * 100 + int(w0))
    mlp = LipschitzMLP(12, 5, hidden=16, layers=layers, w0=w0).double()
    bound = mlp.lipschitz_bound().item()
    assert _worst_ratio(mlp, 12) <= bound * (1 + 1e-9)


def test_bound_holds_after_training_changes_c():
    torch.manual_seed(1)
    mlp = LipschitzMLP(8, 4, hidden=16, layers=3, w0=5.0).double()
    c0 = [p.c.detach().clone() for m in mlp.net if isinstance(m, nn.Linear)
          for p in m.parametrizations.weight]
    opt = torch.optim.Adam(mlp.parameters(), lr=0.05)
    x = torch.randn(64, 8, dtype=torch.float64)
    target = torch.sin(3 * x[:, :4]) * 4          # a steep target pushes weights up
    for _ in range(60):
        loss = F.mse_loss(mlp(x), target) + 1e-2 * lipschitz_loss(mlp)
        opt.zero_grad()
        loss.backward()
        opt.step()
    c1 = [p.c.detach() for m in mlp.net if isinstance(m, nn.Linear)
          for p in m.parametrizations.weight]
    assert any((a - b).abs().item() > 1e-3 for a, b in zip(c0, c1))
    bound = mlp.lipschitz_bound().item()
    assert _worst_ratio(mlp, 8, seed=3) <= bound * (1 + 1e-9)


def test_single_layer_bound_is_tight():
    torch.manual_seed(2)
    lin = lipschitz_linear(10, 6).double()
    p = lin.parametrizations.weight[0]
    with torch.no_grad():
        p.c.fill_(_inverse_softplus(torch.tensor(0.5, dtype=torch.float64)).item())
    w = lin.weight
    row = w.abs().sum(1).argmax()
    d = torch.sign(w[row]).unsqueeze(0)              # ||d||_∞ = 1, attains row's abs sum
    x = torch.randn(1, 10, dtype=torch.float64)
    r = _ratio(lin, x + d, x).item()
    assert r == pytest.approx(F.softplus(p.c).item(), rel=1e-12)


def test_rows_below_bound_unchanged_and_rows_above_clipped():
    torch.manual_seed(3)
    lin = lipschitz_linear(20, 30)
    raw = lin.parametrizations.weight.original.detach().clone()
    rows = raw.abs().sum(1)
    thr = rows.median()
    with torch.no_grad():
        lin.parametrizations.weight[0].c.copy_(_inverse_softplus(thr))
    bound = F.softplus(lin.parametrizations.weight[0].c).detach()
    w = lin.weight.detach()
    below = rows <= bound
    assert below.any() and (~below).any()
    assert torch.equal(w[below], raw[below])
    torch.testing.assert_close(w[~below].abs().sum(1), bound.expand(int((~below).sum())),
                               rtol=1e-6, atol=0)


def test_c_initialisation():
    torch.manual_seed(4)
    lin = lipschitz_linear(33, 17)
    raw = lin.parametrizations.weight.original.detach()
    c = lin.parametrizations.weight[0].c
    assert c.shape == ()
    top = raw.abs().sum(1).max()
    assert top < F.softplus(c).detach() <= top * (1 + 1e-5)        # a few ulps above the largest row
    assert torch.equal(lin.weight.detach(), raw)                    # every scale exactly 1
    lin(torch.randn(5, 33)).square().sum().backward()               # no row at the kink: no gradient
    assert c.grad == 0 and lin.parametrizations.weight.original.grad.abs().sum() > 0
    # inverse softplus is finite and accurate over a wide range
    y = torch.tensor([1e-12, 1e-6, 0.1, 1.0, 30.0, 1e4], dtype=torch.float64)
    x = _inverse_softplus(y)
    assert torch.isfinite(x).all()
    torch.testing.assert_close(F.softplus(x), y, rtol=1e-9, atol=0)
    assert torch.isfinite(_inverse_softplus(torch.tensor([0.0, 1e-30, 1e30]))).all()


def test_structure_and_init():
    mlp = LipschitzMLP(263, 64, layers=3, w0=30.0)
    kinds = [type(m) for m in mlp.net]
    assert kinds[1] is SineActivation and kinds[3] is SineActivation and len(kinds) == 5
    assert not isinstance(mlp.net[-1], SineActivation)
    assert mlp.hidden == 263 and mlp.num_sines == 2
    assert LipschitzMLP(512, 263).hidden == 512          # hidden=None: latent width
    one = LipschitzMLP(7, 3, layers=1)
    assert len(one.net) == 1 and one.num_sines == 0
    # first layer: sine argument ~unit std for unit-variance input
    x = torch.randn(4096, 263)
    with torch.no_grad():
        pre = 30.0 * F.linear(x, mlp.net[0].weight)
    assert 0.7 < pre.std().item() < 1.3
    with pytest.raises(ValueError):
        LipschitzMLP(3, 3, layers=0)


def test_loss_is_product_of_softplus_c_and_sums_over_mlps():
    torch.manual_seed(5)
    a = LipschitzMLP(6, 4, hidden=8, layers=3, w0=2.0)
    b = LipschitzMLP(4, 6, hidden=8, layers=2)
    cs = [F.softplus(m.parametrizations.weight[0].c) for m in a.net if isinstance(m, nn.Linear)]
    expected_a = torch.stack(cs).prod()
    torch.testing.assert_close(lipschitz_loss(a), expected_a)
    torch.testing.assert_close(a.lipschitz_bound(), expected_a * 2.0 ** 2)
    model = nn.ModuleDict({"inp": a, "out": b, "other": nn.Linear(3, 3)})
    torch.testing.assert_close(lipschitz_loss(model), expected_a + b.lipschitz_product())
    z = lipschitz_loss(nn.Linear(3, 3).double())
    assert z.shape == () and z.item() == 0.0 and z.device.type == "cpu"
    assert lipschitz_loss(nn.Module()).item() == 0.0


def test_gradients_reach_c():
    torch.manual_seed(6)
    mlp = LipschitzMLP(6, 4, hidden=8, layers=2)
    cs = [m.parametrizations.weight[0].c for m in mlp.net if isinstance(m, nn.Linear)]
    lipschitz_loss(mlp).backward()
    assert all(c.grad is not None and c.grad.abs().item() > 0 for c in cs)
    mlp.zero_grad()
    with torch.no_grad():                         # make c bind so the task loss reaches it
        for c in cs:
            c.sub_(1.0)
    mlp(torch.randn(10, 6)).pow(2).sum().backward()
    assert all(c.grad is not None and c.grad.abs().item() > 0 for c in cs)


def test_bake_keeps_outputs_and_removes_parametrizations():
    torch.manual_seed(7)
    mlp = LipschitzMLP(6, 4, hidden=8, layers=3, w0=5.0)
    with torch.no_grad():
        for m in mlp.net:
            if isinstance(m, nn.Linear):
                m.parametrizations.weight[0].c.sub_(0.5)   # clipping active
    x = torch.randn(10, 6)
    with torch.no_grad():
        y = mlp(x)
        bound = mlp.lipschitz_bound()
    assert is_lipschitz(mlp) and not mlp.baked
    out = bake_lipschitz(mlp)
    assert out is mlp and mlp.baked and not is_lipschitz(mlp)
    assert not any(parametrize.is_parametrized(m) for m in mlp.modules())
    assert not any(isinstance(m, LipschitzWeight) for m in mlp.modules())
    assert all(".parametrizations." not in k for k in mlp.state_dict())
    with torch.no_grad():
        assert torch.equal(mlp(x), y)
        assert mlp.lipschitz_bound().item() <= bound.item() * (1 + 1e-6)
    assert lipschitz_loss(mlp).item() == 0.0


def test_state_dict_round_trip():
    torch.manual_seed(8)
    a = LipschitzMLP(6, 4, hidden=8, layers=3, w0=5.0)
    with torch.no_grad():
        a.net[2].parametrizations.weight[0].c.sub_(1.0)
    torch.manual_seed(9)
    b = LipschitzMLP(6, 4, hidden=8, layers=3, w0=5.0)
    x = torch.randn(10, 6)
    assert not torch.allclose(a(x), b(x))
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    with torch.no_grad():
        assert torch.equal(a(x), b(x))
    torch.testing.assert_close(a.lipschitz_bound(), b.lipschitz_bound(), rtol=0, atol=0)
    c = copy.deepcopy(a)
    with torch.no_grad():
        assert torch.equal(c(x), a(x))


def test_zero_row_has_finite_gradients():
    lin = lipschitz_linear(4, 3)
    with torch.no_grad():
        lin.parametrizations.weight.original[1].zero_()
    lin(torch.randn(5, 4)).sum().backward()
    assert torch.isfinite(lin.parametrizations.weight.original.grad).all()
    assert torch.isfinite(lin.parametrizations.weight[0].c.grad).all()


def test_dtype_follows_module():
    mlp = LipschitzMLP(5, 3, layers=2).double()
    assert all(p.dtype == torch.float64 for p in mlp.parameters())
    assert mlp(torch.randn(2, 7, 5, dtype=torch.float64)).shape == (2, 7, 3)
    assert lipschitz_loss(mlp).dtype == torch.float64


def test_normalised_weight_is_reused_without_autograd_and_never_stale():
    torch.manual_seed(0)
    mlp = LipschitzMLP(8, 4, hidden=16)
    x = torch.randn(5, 8)
    lin = mlp.net[0]
    with torch.no_grad():
        w1 = lin.weight
        assert lin.weight is w1                                   # cached: the same tensor
        kept = w1.clone()
        out1 = mlp(x)
    opt = torch.optim.SGD(mlp.parameters(), lr=0.5)
    mlp(x).pow(2).sum().backward()                                # with autograd: computed afresh
    opt.step()                                                    # in-place update of W and c
    with torch.no_grad():
        w2 = lin.weight
        out2 = mlp(x)
        assert w2 is not w1 and not torch.equal(out2, out1)
        assert torch.equal(w1, kept)                              # a weight handed out is never changed
        fresh = lin.parametrizations.weight.original
        p = lin.parametrizations.weight[0]
        expect = fresh * torch.clamp(p.bound() / fresh.abs().sum(1, keepdim=True), max=1.0)
        assert torch.allclose(w2, expect)
        lin.parametrizations.weight.original.mul_(0.5)           # any in-place change invalidates
        assert not torch.equal(lin.weight, w2)


@pytest.mark.parametrize("shift", [-0.7, 0.0, 25.0])
def test_lipschitz_weight_op_equals_the_parametrization(shift):
    """``lipschitz_weight`` (the parametrization's operations under autograd; with the Triton
    kernels switched on, on CUDA one op each way, its backward written out): the parametrization's normalised weight bit for
    bit, and the gradients of W and c of autograd through the parametrization, with clipped,
    unclipped and zero rows and ``c`` past softplus's threshold; the written-out backward (CUDA's
    fallback) too."""
    from smdm_plugin.core.kernels.lipschitz_op import lipschitz_weight

    torch.manual_seed(0)
    lin = lipschitz_linear(11, 9).double()
    p = lin.parametrizations.weight[0]
    W = lin.parametrizations.weight.original
    with torch.no_grad():
        p.c.add_(shift)                                           # -0.7: some rows clipped
        W[2].zero_()
    g = torch.randn(9, 11, dtype=torch.float64)
    ref = p(W)
    (ref * g).sum().backward()
    ref_grads = (W.grad.clone(), p.c.grad.clone())
    W.grad, p.c.grad = None, None
    out = lipschitz_weight(W, p.c)
    assert torch.equal(out, ref)
    (out * g).sum().backward()
    torch.testing.assert_close(W.grad, ref_grads[0], rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(p.c.grad, ref_grads[1], rtol=1e-10, atol=1e-14)
    from smdm_plugin.core.kernels.lipschitz_op import _Weight

    W.grad, p.c.grad = None, None
    out = _Weight.apply(W, p.c)                                  # the written-out backward
    assert torch.equal(out, ref)
    (out * g).sum().backward()
    torch.testing.assert_close(W.grad, ref_grads[0], rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(p.c.grad, ref_grads[1], rtol=1e-10, atol=1e-14)


def test_lipschitz_triton_kernels_equal_the_composite_in_interpreter_mode(triton_interpreter):
    """The CUDA kernels of ``smdm::lipschitz_weight`` and its backward, run by Triton's interpreter on
    the CPU: the composite's values (rows wider than one block, strided weights, a zero row, ``c``
    below, around and past softplus's threshold)."""
    code = (
        "import torch\n"
        "from smdm_plugin.core.kernels.lipschitz_op import lipschitz_weight_composite, lipschitz_weight_grad_composite\n"
        "from smdm_plugin.core.kernels.lipschitz_triton import lipschitz_weight_triton, lipschitz_weight_backward_triton\n"
        "torch.manual_seed(0)\n"
        "bad = 0\n"
        "for R, n in ((5, 7), (9, 1500), (3, 64)):\n"
        "    for c in (-30.0, -3.0, 0.5, 2.0, 25.0):\n"
        "        W = torch.randn(R, 2 * n)[:, ::2]\n"
        "        W[0] = 0.0\n"
        "        c = torch.tensor(c)\n"
        "        g = torch.randn(R, n)\n"
        "        bad += int(not torch.allclose(lipschitz_weight_triton(W, c), lipschitz_weight_composite(W, c), rtol=1e-5, atol=1e-6))\n"
        "        for a, b in zip(lipschitz_weight_backward_triton(g, W, c), lipschitz_weight_grad_composite(g, W, c)):\n"
        "            bad += int(not torch.allclose(a, b, rtol=1e-4, atol=1e-6))\n"
        "print('mismatches', bad)\n")
    out = triton_interpreter(code)
    assert "mismatches 0" in out, out


def test_lipschitz_weight_runs_its_composite_under_autograd_unless_triton_is_switched_on():
    """0.9.4: with autograd, the normalised weight is the composite's ops under autograd on CUDA too
    (counted as CUDA runs them: no fused op, no Python autograd function: less host time per
    training step than the Triton pair, docs/gpu.md); ``use_triton_kernels(True, ...)`` brings the
    pair back (one launch forward, its kernel and a sum backward); the gradients agree."""
    from smdm_plugin.core.kernels.dispatch import use_triton_kernels
    from smdm_plugin.core.kernels.lipschitz_op import lipschitz_weight
    from smdm_plugin.runtime.launches import count_launches

    torch.manual_seed(0)
    lin = lipschitz_linear(11, 9)
    p, W = lin.parametrizations.weight[0], lin.parametrizations.weight.original
    g = torch.randn(9, 11)
    grads = {}
    names = ["Lipschitz weight", "Lipschitz weight gradient"]
    for triton in (False, True):
        before = use_triton_kernels(triton, names)
        try:
            W.grad, p.c.grad = None, None
            out = {}
            ops = count_launches(lambda: out.setdefault("w", lipschitz_weight(W, p.c)).mul(g).sum().backward(),
                                 warmup=0).ops
        finally:
            for name, on in before.items():
                use_triton_kernels(on, [name])
        grads[triton] = (W.grad.clone(), p.c.grad.clone())
        if triton:
            assert ops["smdm.lipschitz_weight"] == 1 and ops["smdm.lipschitz_weight_backward"] == 1, ops
            assert out["w"].grad_fn.name().startswith("_Weight")
        else:
            assert not any(k.startswith("smdm.") for k in ops), ops
            assert ops["aten.linalg_vector_norm.default"] == 1 and "_Weight" not in out["w"].grad_fn.name()
    torch.testing.assert_close(grads[True][0], grads[False][0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(grads[True][1], grads[False][1], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("layout", ["contiguous", "permuted"])
def test_mlp_equals_its_parametrized_modules_on_any_input_layout(layout):
    """The MLP's forward (the normalised weights read directly; a contiguous input of more than two
    dimensions as its rows) equals its modules run as they are (``mlp.net``: each layer's
    parametrization and ``F.linear`` on the input as it comes) bit for bit: outputs and every
    gradient, with and without autograd; a permuted input (``F.linear``'s other route) too."""
    torch.manual_seed(0)
    mlp = LipschitzMLP(12, 6, hidden=24)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(5, 3, 12, generator=g)
    if layout == "permuted":
        x = torch.randn(3, 5, 12, generator=g).transpose(0, 1)
    assert x.is_contiguous() == (layout == "contiguous")
    x.requires_grad_()
    out, ref = mlp(x), mlp.net(x)
    assert out.shape == (5, 3, 6) and torch.equal(out, ref)
    wrt = [x] + list(mlp.parameters())
    grad = torch.randn(out.shape, generator=g)
    for a, b in zip(torch.autograd.grad(out, wrt, grad), torch.autograd.grad(ref, wrt, grad)):
        assert torch.equal(a, b)
    with torch.no_grad():
        assert torch.equal(mlp(x), mlp.net(x))
