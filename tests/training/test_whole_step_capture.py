"""Whole steps captured by one flag (``smdm train --compile``, ``smdm bench --compile``;
docs/compile.md), on the CPU with ``aot_eager`` (Dynamo + AOTAutograd, no code generation): the
training loss (forward and backward), the guided sampling call (both guidance passes) and the
ancestral sampling step each trace as one ``fullgraph`` graph for sparse models, capture once and
never again over other timesteps (early and late: the dynamic update's VW on x_t), other lengths
and other batches, equal eager (on the static-shape path a GPU runs), and a last partial batch
still runs (eagerly, no new graph).
"""
from __future__ import annotations

import copy
import warnings

import pytest
import torch

pytest.importorskip("torch._dynamo")
from torch._dynamo.utils import counters  # noqa: E402

from smdm_plugin.core.checks import static_mode  # noqa: E402
from smdm_plugin.runtime import compile as C
from smdm_plugin.training import benchmark, graphwork, workloads  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread", "fresh_dynamo")
BACKEND = "aot_eager"
CPU = torch.device("cpu")
T, N, B = 20, 40, 3                         # late steps (VW on x_t): t < round(0.1 * T) = 2
CASES = [("mdm", "trans_enc"), ("mdm", "dip"), ("motiondiffuse", "motiondiffuse")]
IDS = [a for _, a in CASES]


def graphs() -> int:
    return counters["stats"]["unique_graphs"]


def build(family: str, arch: str):
    """A tiny sparse model (no dropout, no condition dropout: eager and compiled draw nothing), an
    eager twin, its diffusion and workload."""
    model, diffusion = workloads.build(arch, 0.8, CPU, True, T, family=family, frames=N, dynamic_update=True)
    workloads.without_dropout(model)
    return model, copy.deepcopy(model), diffusion, workloads.WORKLOADS.get(family)


def batch(work, arch: str, seed: int, size: int = B) -> workloads.WorkloadBatch:
    return work.batch(size, N, CPU, True, arch, seed=seed)


@pytest.mark.parametrize("family,arch", CASES, ids=IDS)
def test_training_step_is_one_graph_equal_to_eager(family, arch):
    """Loss and every gradient of four steps (other batches, lengths, timesteps) equal the eager
    step's; the first runs eagerly, the second captures, none after; then a partial batch."""
    model, ref, diffusion, work = build(family, arch)
    loss_fn = benchmark.training_loss(work, model, diffusion, CPU, "default", BACKEND)
    s = C.compile_setting(loss_fn)
    assert s.fullgraph and s.captures == C.CAPTURES_TRAIN
    model.train(), ref.train()
    for i, size in enumerate((B, B, B, B, B - 1)):
        data = batch(work, arch, seed=i, size=size)
        t = (torch.tensor([17, 1, 9][:size]) + 5 * i) % T
        noise = torch.randn(data.x.shape, generator=torch.Generator().manual_seed(i))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            got = loss_fn(data.x, t, work.kwargs(data), noise)
        assert any("runs eagerly" in str(w.message) for w in caught) == (size != B)
        with static_mode():
            want = diffusion.training_losses(ref, data.x, t, work.kwargs(data), noise=noise)["loss"].mean()
        got.backward(), want.backward()
        assert torch.allclose(got, want, rtol=1e-5, atol=1e-6), i
        for (name, p), q in zip(model.named_parameters(), ref.parameters()):
            assert (p.grad is None) == (q.grad is None), name
            if p.grad is not None:
                assert torch.allclose(p.grad, q.grad, rtol=1e-4, atol=1e-6), (i, name)
        model.zero_grad(), ref.zero_grad()
    assert (s.warm_calls, s.compiled_calls, s.eager_calls, s.recompiles) == (1, 3, 1, 0) and graphs() == 1


@pytest.mark.parametrize("family,arch", CASES, ids=IDS)
def test_guided_sampling_call_is_one_graph_equal_to_eager(family, arch):
    """MDM: both classifier-free guidance passes in one graph; early and late steps (uniform
    keyframes, then VW on x_t) and other batches share it; a partial batch runs eagerly."""
    model, ref, _, work = build(family, arch)
    call = benchmark.guided_call(work, model, CPU, "default", BACKEND)
    eager = work.denoiser(ref)
    s = C.compile_setting(call)
    assert s.fullgraph and s.captures == C.CAPTURES_GUIDED
    with torch.no_grad():
        for i, (t, size) in enumerate(((15, B), (1, B), (15, B), (0, B), (1, B - 1))):
            data = batch(work, arch, seed=i, size=size)
            tt = torch.full((size,), t)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                got = call(data.x, tt, **work.sample_kwargs(data))
            with static_mode():
                want = eager(data.x, tt, **work.sample_kwargs(data))
            assert torch.allclose(got, want, rtol=1e-5, atol=1e-5), (i, t)
    assert (s.warm_calls, s.compiled_calls, s.eager_calls, s.recompiles) == (1, 3, 1, 0) and graphs() == 1


@pytest.mark.parametrize("family,arch", CASES[:2], ids=IDS[:2])
def test_whole_sampling_loop_replays_one_step_graph_and_equals_p_sample_loop(family, arch):
    """Every step of the loop (t = T-1 .. 0: the posterior draw, the last step's clean prediction,
    the dynamic update's late steps) runs one captured graph; the samples equal
    ``SimpleDiffusion.p_sample_loop`` with the same generator."""
    model, ref, diffusion, work = build(family, arch)
    step = benchmark.sampling_step(work, model, diffusion, CPU, "default", BACKEND)
    data = batch(work, arch, seed=0)
    shape = tuple(data.x.shape)
    with torch.no_grad():
        got = benchmark.sample_loop(step, shape, T, work.sample_kwargs(data), CPU, torch.Generator().manual_seed(5))
        with static_mode():
            want = diffusion.p_sample_loop(work.denoiser(ref), shape, work.sample_kwargs(data), device=CPU,
                                           generator=torch.Generator().manual_seed(5))
    s = C.compile_setting(step)
    assert (s.warm_calls, s.compiled_calls, s.recompiles) == (1, T - 1, 0) and graphs() == 1
    assert s.captures == C.CAPTURES_SAMPLE_STEP
    assert torch.allclose(got, want, rtol=1e-4, atol=1e-4)


def compiled_calls_follow_updates(model, ref, work, arch: str, bf16: bool) -> list:
    """Four compiled guided calls of ``model`` (eval, under bf16 autocast when ``bf16``: entered per
    call, as within one block autocast keeps its first cast of each parameter), each equal to eager
    on ``ref`` and followed by an in-place update of every weight of both (an optimizer step, a
    reload); one graph, no recompile. Returns the counts of its graph and of the same model traced
    by ``torch.compile`` itself (unarmed)."""
    backend, graphs_seen = graphwork.aot_counter(model)
    call = benchmark.guided_call(work, model, CPU, "default", backend)
    eager = work.denoiser(ref)
    data = batch(work, arch, seed=0)
    tt = torch.full((B,), 15)
    gen = torch.Generator().manual_seed(3)
    tol = 2e-2 if bf16 else 1e-5
    with torch.no_grad():
        for i in range(4):
            with torch.autocast("cpu", torch.bfloat16, enabled=bf16):
                got = call(data.x, tt, **work.sample_kwargs(data))
                with static_mode():
                    want = eager(data.x, tt, **work.sample_kwargs(data))
            torch.testing.assert_close(got, want, rtol=tol, atol=tol, msg=f"call {i}")
            for p, q in zip(model.parameters(), ref.parameters()):        # every weight moves
                p.add_(torch.randn(p.shape, generator=gen), alpha=0.05), q.copy_(p)
    s = C.compile_setting(call)
    assert (s.warm_calls, s.compiled_calls, s.recompiles) == (1, 3, 0) and len(graphs_seen) == 1
    unarmed = torch.compile(lambda *a, **k: work.denoiser(model)(*a, **k), backend=backend, fullgraph=True)
    with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=bf16), static_mode():
        unarmed(data.x, tt, **work.sample_kwargs(data))
    return graphs_seen


@pytest.mark.parametrize("family,arch", CASES, ids=IDS)
def test_a_compiled_sampling_call_makes_nothing_from_parameters_alone_and_follows_their_updates(family, arch):
    """FSQ's folded in-projections and the Lipschitz weights: the compiled guided call reads them
    from the stores its wrapper refreshed (no op of its graph works on parameters alone; the same
    model traced by ``torch.compile`` itself, unarmed, makes them in its graph: the count can fail);
    after in-place updates the next call equals eager with the new weights, in the same graph
    (refreshed in place: no recapture)."""
    model, ref, _, work = build(family, arch)
    armed, unarmed = compiled_calls_follow_updates(model, ref, work, arch, bf16=False)
    assert armed["param-only"] == 0 and unarmed["param-only"] > 5


@pytest.mark.parametrize("sparse", [False, True], ids=["dense", "sparse"])
@pytest.mark.parametrize("family,arch", CASES, ids=IDS)
def test_a_compiled_bf16_sampling_call_casts_no_weight_and_follows_their_updates(family, arch, sparse):
    """Under autocast a compiled guided call reads the linear layers' weights and biases in bf16 from
    the casts its wrapper refreshed (core/weight_casts.py), dense and sparse: no op of its graph works
    on parameters alone (0.10.3 and an unarmed trace: a cast per weight, bias and guidance pass); it
    equals eager autocast, follows in-place updates in the same graph, and leaves the model's
    parameters as they were."""
    if sparse:
        model, ref, _, work = build(family, arch)
    else:
        model, _ = workloads.build(arch, None, CPU, True, T, family=family, frames=N)
        workloads.without_dropout(model)
        ref, work = copy.deepcopy(model), workloads.WORKLOADS.get(family)
    params = [(n, p, p.requires_grad) for n, p in model.named_parameters()]
    armed, unarmed = compiled_calls_follow_updates(model, ref, work, arch, bf16=True)
    assert armed["param-only"] == 0 and unarmed["param-only"] > 10          # autocast's casts, at least
    assert [(n, p, p.requires_grad) for n, p in model.named_parameters()] == params
    assert all(type(p) is torch.nn.Parameter and p.dtype == torch.float32 for _, p, _ in params)


FOLD_OPS = ("matmul", "bmm", "baddbmm")          # a trans_enc graph's batched matmuls: the FSQ folds'


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_a_compiled_training_step_folds_every_layers_keys_at_once(precision):
    """With autograd the compiled step runs the stock layers as functions (core/layers.py): every
    layer's FSQ fold made in one batch of matmuls, as eagerly (one fold per layer: four more per
    layer), and under autocast each matmul weight's role cast once for all layers (autocast: one
    cast per weight), so neither grows with the depth. Loss and gradients equal eager's."""
    from functorch.compile import make_boxed_func
    from torch._dynamo.backends.common import aot_autograd

    from smdm_plugin.adapters.surgery import sparsify
    from smdm_plugin.core.config import SparseConfig
    from smdm_plugin.reference.backbone import TinyMDM
    from smdm_plugin.reference.simple_diffusion import SimpleDiffusion

    bf16 = precision == "bf16"
    folds, casts = {}, {}
    for layers in (2, 4):
        torch._dynamo.reset()
        torch.manual_seed(layers)
        model = TinyMDM(arch="trans_enc", latent_dim=16, ff_size=32, num_layers=layers, num_heads=2,
                        dropout=0.0, cond_mask_prob=0.0)
        diffusion = SimpleDiffusion(T)
        sparsify(model, SparseConfig(mask_noise=0.0), diffusion=diffusion)
        ref = copy.deepcopy(model)
        names, forward = [], []

        def keep(gm, example_inputs):                   # the forward's casts of its inputs (weights)
            forward.extend(n for n in gm.graph.nodes if "_to_copy" in str(n.target)
                           and getattr(n.args[0], "op", None) == "placeholder")
            return make_boxed_func(gm.forward)

        aot = aot_autograd(fw_compiler=keep, bw_compiler=lambda gm, ex: make_boxed_func(gm.forward))

        def backend(gm, example_inputs):
            names.extend(str(n.target) for n in gm.graph.nodes if n.op == "call_function")
            return aot(gm, example_inputs)

        loss_fn = C.compile_function(
            lambda x, t, kw, noise: diffusion.training_losses(model, x, t, kw, noise=noise)["loss"].mean(),
            "default", model=model, backend=backend, captures=C.CAPTURES_TRAIN)
        lengths = torch.tensor([N, N - 9, N - 20])
        x = torch.randn(B, 263, 1, N)
        y = {"mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N), "lengths": lengths,
             "text_embed": torch.randn(1, B, 512)}
        t, noise = torch.tensor([3, 11, 17]), torch.randn(x.shape)
        for _ in range(2):                              # eager (the phase's first call), then traced
            with torch.autocast("cpu", torch.bfloat16, enabled=bf16):
                got = loss_fn(x, t, {"y": dict(y)}, noise)
            got.backward()
        with static_mode(), torch.autocast("cpu", torch.bfloat16, enabled=bf16):
            want = diffusion.training_losses(ref, x, t, {"y": dict(y)}, noise=noise)["loss"].mean()
        want.backward()
        tol = dict(rtol=2e-2, atol=2e-3) if bf16 else dict(rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(got, want, **tol)
        for (name, p), q in zip(model.named_parameters(), ref.parameters()):
            if q.grad is not None:                      # the compiled step ran twice: twice the gradient
                torch.testing.assert_close(p.grad / 2, q.grad, **tol, msg=name)
        assert C.compile_setting(loss_fn).compiled_calls == 1
        folds[layers] = sum(any(n.endswith(f" {m} of type object") or f"method {m} of" in n for m in FOLD_OPS)
                            for n in names)
        casts[layers] = len(forward)
    assert folds[4] == folds[2] > 0
    assert casts[4] == casts[2]


@pytest.mark.parametrize("arch", ["trans_enc", "dip"])
def test_upstream_training_losses_compiled_whole_equal_eager_with_upstream_noise_draws(arch):
    """``--sparse_compile`` in an upstream training run (``compile_training_losses`` with MDM's
    ``loss_preparer``): ``diffusion.training_losses(model, x, t, model_kwargs=...)`` as upstream's
    loop calls it, replaced in place: one graph over other batches and timesteps,
    loss and gradients equal to eager, and the global RNG drawn as eager draws it (upstream's
    noise, drawn before the graph; a given ``noise`` draws nothing)."""
    from smdm_plugin.families.mdm.prepare import loss_preparer

    model, ref, diffusion, work = build("mdm", arch)
    eager_losses = diffusion.training_losses
    traced = []

    def backend(gm, example_inputs):               # aot_eager, the graph's ops recorded
        traced.extend(str(node.target) for node in gm.graph.nodes)
        return torch._dynamo.lookup_backend(BACKEND)(gm, example_inputs)

    compiled = C.compile_training_losses(diffusion, model, "default", prepare=loss_preparer(model), backend=backend)
    assert diffusion.training_losses is compiled and compiled.setting.captures == C.CAPTURES_TRAIN
    model.train(), ref.train()
    for i in range(4):
        data = batch(work, arch, seed=i)
        t = (torch.tensor([17, 1, 9]) + 5 * i) % T
        given = torch.randn(data.x.shape) if i == 3 else None
        torch.manual_seed(100 + i)
        got = diffusion.training_losses(model, data.x, t, model_kwargs=work.kwargs(data), noise=given)["loss"].mean()
        after_compiled = torch.rand(4)
        torch.manual_seed(100 + i)
        with static_mode():
            want = eager_losses(ref, data.x, t, work.kwargs(data), noise=given)["loss"].mean()
        assert torch.equal(torch.rand(4), after_compiled), i           # the same draws, no more
        got.backward(), want.backward()
        assert torch.allclose(got, want, rtol=1e-5, atol=1e-6), i
        for (name, p), q in zip(model.named_parameters(), ref.parameters()):
            if p.grad is not None:
                assert torch.allclose(p.grad, q.grad, rtol=1e-4, atol=1e-6), (i, name)
        model.zero_grad(), ref.zero_grad()
    s = compiled.setting
    assert (s.warm_calls, s.compiled_calls, s.recompiles) == (1, 3, 0) and graphs() == 1
    assert traced and not [op for op in traced if "rand" in op], traced   # no draw in the graph
    again = C.compile_training_losses(diffusion, model, "default", prepare=loss_preparer(model), backend=BACKEND)
    assert again.fn is compiled.fn                         # compiled again: the same function, not nested
    assert C.compile_training_losses(diffusion, model, "none", prepare=loss_preparer(model)) is None


def test_none_returns_the_function_and_fused_adamw_only_when_captured_on_cuda():
    fn = lambda x: x  # noqa: E731
    assert C.compile_function(fn, "none") is fn and C.compile_setting(fn) is None
    assert C.fused_optimizer_kwargs("cuda", "reduce-overhead") == {"fused": True}
    assert C.fused_optimizer_kwargs("cuda", "none") == {} and C.fused_optimizer_kwargs("cpu", "default") == {}
