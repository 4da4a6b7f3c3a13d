"""No tensor of another device, and no constant table, is built inside a traced graph (issue 36,
crash 2: ``reduce-overhead`` on CUDA stopped with "Unhandled FakeTensor Device Propagation for
aten.cat.default, found two different devices cuda:0, cpu": while Dynamo traced, the schedule's
per-device tables were not cached yet, so the graph built them on the CPU and moved them).

CI has no GPU, so the models and inputs live on the ``meta`` device (a device that is not the CPU:
shapes only), compiled with a backend that keeps every graph Dynamo captures; every tensor-valued
node of every graph must be on ``meta``. Covered: the model call (``compile_model``: sampling at an
early and a late step, both guidance passes, dynamic update on and off; a training step) and the
whole steps (``compile_function``: training loss, guided call, sampling step) of trans_enc,
trans_dec, DiP's prefix completion, DoubleTake's model and MotionDiffuse's layout. DoubleTake calls
carry their forced frames only under the workload's bound (without one they count them on the
host, which a ``meta`` tensor cannot give); MotionDiffuse's calls pass no ``length`` (all frames valid: its
lengths are validated on the host from values). VW's eager kernels read the removal counts on the host too, so on
``meta`` the test runs VW through its output shape (the fake the traced graph uses).
"""
from __future__ import annotations

from typing import Any, Dict, List

import pytest
import torch

pytest.importorskip("torch._dynamo")

from smdm_plugin.core.kernels import vw  # noqa: E402
from smdm_plugin.runtime import compile as C
from smdm_plugin.training import benchmark, workloads  # noqa: E402

META = torch.device("meta")
T = 50                                     # diffusion steps: the late steps (VW on x_t) are t < 5
CASES = [("mdm", "trans_enc", True), ("mdm", "trans_enc", False), ("mdm", "trans_dec", True),
         ("mdm", "dip", True), ("mdm", "doubletake", True), ("motiondiffuse", "motiondiffuse", True)]


@pytest.fixture(autouse=True)
def vw_on_meta(monkeypatch, fresh_dynamo):
    """VW on ``meta`` runs its output shape (the fused op's fake: its eager kernels read values)."""
    assert vw.OP.kernels["meta"] is not None


class Recorder:
    """A ``torch.compile`` backend that keeps every graph and runs it as traced."""

    def __init__(self) -> None:
        self.graphs: List[torch.fx.GraphModule] = []

    def __call__(self, gm: torch.fx.GraphModule, example_inputs: Any) -> Any:
        self.graphs.append(gm)
        return gm.forward

    def off_device(self) -> List[str]:
        """``op target: device`` of every tensor-valued node not on ``meta``."""
        bad = []
        for gm in self.graphs:
            for node in gm.graph.nodes:
                value = node.meta.get("example_value")
                values = value if isinstance(value, (tuple, list)) else [value]
                for v in values:
                    if isinstance(v, torch.Tensor) and v.device != META:
                        bad.append(f"{node.op} {node.target}: {v.device}")
        return bad


def _case(family: str, arch: str, dynamic: bool, train: bool):
    work = workloads.WORKLOADS.get(family)
    model, diffusion = workloads.build(arch, 0.8, torch.device("cpu"), True, T, family=family, frames=40,
                                       **({} if train else {"dynamic_update": dynamic}))
    return work, model.to(META), diffusion, work.batch(2, 40, META, True, arch)


def _kwargs(work: workloads.Workload, data: workloads.WorkloadBatch) -> Dict[str, Any]:
    """The call's keyword arguments without forced frames (DoubleTake's ``is_transition`` is only
    in ``work.sample_kwargs``) and without MotionDiffuse's ``length`` (see the module docstring)."""
    return {k: v for k, v in work.kwargs(data).items() if k != "length"}


def _steps(B: int) -> List[torch.Tensor]:
    return [torch.full((B,), t, dtype=torch.long, device=META) for t in (40, 2)]


@pytest.mark.parametrize("family,arch,dynamic", CASES, ids=[f"{a}-dyn{int(d)}" for _, a, d in CASES])
def test_compiled_model_calls_build_nothing_off_the_device(family, arch, dynamic):
    """The model compiled alone (``--sparse_compile``): guided sampling at t=40 and t=2 (three
    calls each: the first of the phase runs eagerly), then training steps."""
    rec = Recorder()
    work, model, diffusion, data = _case(family, arch, dynamic, train=False)
    C.compile_model(model, "default", backend=rec, device=META)
    den = work.denoiser(model)
    with torch.no_grad():
        for t in _steps(data.size) * 2:
            out = den(data.x, t, **_kwargs(work, data))
    assert out.device == META
    model.train()
    for _ in range(3):
        t = torch.full((data.size,), 7, device=META)
        diffusion.training_losses(model, data.x, t, _kwargs(work, data))["loss"].mean().backward()
    s = C.compile_setting(model)
    assert rec.graphs and s.compiled_calls > 0 and s.recompiles == 0
    assert not rec.off_device(), rec.off_device()[:10]


@pytest.mark.parametrize("family,arch,dynamic", CASES, ids=[f"{a}-dyn{int(d)}" for _, a, d in CASES])
def test_compiled_whole_steps_build_nothing_off_the_device(family, arch, dynamic):
    """``smdm train`` / ``smdm bench``'s whole steps: the training loss (forward; its backward is
    AOTAutograd's), the guided call and the ancestral sampling step."""
    rec = Recorder()
    work, model, diffusion, data = _case(family, arch, dynamic, train=True)
    loss = benchmark.training_loss(work, model, diffusion, META, "default", rec)
    model.train()
    for _ in range(3):
        loss(data.x, torch.full((data.size,), 7, device=META), _kwargs(work, data), torch.zeros_like(data.x)).backward()
    work, model, diffusion, data = _case(family, arch, dynamic, train=False)
    call = benchmark.guided_call(work, model, META, "default", rec)
    step = benchmark.sampling_step(work, model, diffusion, META, "default", rec)
    with torch.no_grad():
        for t in _steps(data.size) * 2:
            call(data.x, t, **_kwargs(work, data))
            step(data.x, t, torch.zeros_like(data.x), _kwargs(work, data))
    assert all(C.compile_setting(f).recompiles == 0 and C.compile_setting(f).compiled_calls > 0
               for f in (loss, call, step))
    assert rec.graphs and not rec.off_device(), rec.off_device()[:10]


def test_doubletake_calls_with_forced_frames_trace_whole_on_the_device():
    """DoubleTake's sampling calls with their forced frames (``is_transition``) under the bound the
    workload attaches (as the priorMDM integration does): traced whole (``fullgraph``), nothing off
    the device, no recompile."""
    rec = Recorder()
    work, model, diffusion, data = _case("mdm", "doubletake", True, train=False)
    C.compile_model(model, "default", backend=rec, device=META)
    assert C.compile_setting(model).fullgraph
    den = work.denoiser(model)
    with torch.no_grad():
        for t in _steps(data.size) * 2:
            out = den(data.x, t, **work.sample_kwargs(data))
    s = C.compile_setting(model)
    assert out.device == META and rec.graphs and s.compiled_calls > 0 and s.recompiles == 0
    assert not rec.off_device(), rec.off_device()[:10]
