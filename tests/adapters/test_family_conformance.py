"""One conformance suite run over every registered model family (PEFT's common-tester idea).

The cases come from the family registry (``smdm_plugin.adapters.families.families()``): each registered
family's ``FamilySpec.conformance`` names its case factory (smdm_plugin/families/<name>/conformance.py;
tests/helpers/conformance.py collects them), and a registered family without one fails ``test_every_registered_family_has_a_conformance_case``. The built-in cases:
MDM trans_enc, MDM trans_dec, DiP (TinyMDM with a dense prefix), priorMDM's DoubleTake (a TinyMDM
subclass named like doubleTake_MDM) and MotionDiffuse (the stand-in of
smdm_plugin/families/motiondiffuse/standin.py). Each case must pass every test: the family detected;
sparsify/unsparsify round trip with a bit-identical state dict; all keyframes equals dense;
save/load through ``load_checkpoint``; every sparse call under ``torch.compile(fullgraph=True)``;
no host sync on the static path; the lifecycle with the diffusion in any order; a failed
``sparsify`` leaves the model exactly as before.
"""
import copy
import warnings

import pytest
import torch

from smdm_plugin import (SparseConfig, attach_diffusion, is_sparse, load_checkpoint, register_family,
                         save_sparse_config, sparsify, unsparsify)
from smdm_plugin.adapters.families import FAMILIES, families, family_for
from smdm_plugin.families.mdm.model import MDMFamily
from smdm_plugin.adapters.state import SparseState
from smdm_plugin.core.checks import static_mode
from smdm_plugin.runtime.launches import LaunchCounter as Dispatched

from helpers.conformance import (MotionDiffuseCase, assert_every_family_has_cases, conformance_cases,
                                 families_without_cases)

CASES = conformance_cases()


def test_every_registered_family_has_a_conformance_case():
    assert_every_family_has_cases()
    assert {c.family for c in CASES.values()} == {f.name for f in families()}   # and each is run below


def test_a_family_registered_without_a_case_is_named():
    class ToyFamily(MDMFamily):
        name = "toy-without-a-case"
        priority = -100

        def matches(self, model):
            return type(model).__name__ == "ToyModel"

    register_family(ToyFamily())
    try:
        assert families_without_cases() == ["toy-without-a-case"]
        with pytest.raises(AssertionError, match="without a conformance case: toy-without-a-case"):
            assert_every_family_has_cases()
    finally:
        FAMILIES.unregister("toy-without-a-case")
    assert families_without_cases() == []


@pytest.fixture(params=list(CASES))
def case(request):
    return CASES[request.param]


def snapshot(model):
    return ({k: v.clone() for k, v in model.state_dict().items()}, dict(model.named_modules()),
            {k: v for k, v in model.__dict__.items() if not k.startswith("_")},
            [len(m._forward_pre_hooks) + len(m._forward_hooks) for m in model.modules()])


def assert_same(model, snap, same_objects=True):
    """State dict bit-identical, attributes and hooks as before; ``same_objects``: every module the
    same object (unsparsify rebuilds FSQ self-attention as a new ``nn.MultiheadAttention`` with the
    trained weights, so only a rolled-back sparsify keeps every object)."""
    sd, modules, attrs, hooks = snap
    now = model.state_dict()
    assert list(now) == list(sd)
    for k, v in sd.items():
        assert torch.equal(now[k], v), k
    assert list(dict(model.named_modules())) == list(modules)
    assert [type(m) for m in model.modules()] == [type(m) for m in modules.values()]
    if same_objects:
        assert dict(model.named_modules()) == modules
    assert {k: v for k, v in model.__dict__.items() if not k.startswith("_")} == attrs
    assert [len(m._forward_pre_hooks) + len(m._forward_hooks) for m in model.modules()] == hooks
    assert not is_sparse(model) and not hasattr(model, "_smdm_state")


def _our_attributes(model):
    """``(module name, attribute)`` of every ``_smdm*`` instance attribute inside ``model``."""
    return [(name, k) for name, m in model.named_modules() for k in vars(m) if k.startswith("_smdm")]


def test_the_state_is_the_only_attribute_sparse_mode_puts_on_the_model(case):
    model = case.build()
    sparsify(model, case.config(), diffusion=case.diffusion())
    assert _our_attributes(model) == [("", "_smdm_state")]
    unsparsify(model)
    assert _our_attributes(model) == []


def test_every_builtin_family_is_registered_and_detected(case):
    assert {f.name for f in families()} >= {"mdm", "doubletake", "motiondiffuse"}
    assert family_for(case.build()).name == case.family


def test_round_trip_is_bit_identical(case):
    model = case.build()
    snap = snapshot(model)
    diffusion = case.diffusion()
    sparsify(model, case.config(), diffusion=diffusion)
    assert is_sparse(model) and "smdm_sparse_version" in model.state_dict()
    unsparsify(model)
    assert_same(model, snap, same_objects=False)
    assert "training_losses" not in vars(diffusion)                     # the diffusion restored


def test_all_keyframes_equals_dense(case):
    model = case.build().eval()
    x, y = case.inputs()
    t = torch.tensor([40, 20, 2])
    with torch.no_grad():
        dense = case.out_frames(case.call(model, x, t, y))
        sparsify(model, case.config(reduction=0.0, lipschitz=False, fsq=False, mask_noise=0.0))
        out = case.out_frames(case.call(model, x, t, y))
    valid = case.valid(y)
    assert (out - dense)[valid].abs().max() < 1e-5


def test_save_and_load_checkpoint(case, tmp_path):
    model = case.build().eval()
    sparsify(model, case.config(), diffusion=case.diffusion())
    with torch.no_grad():
        for p in model.parameters():                     # weights that differ from a fresh model
            p.add_(0.01 * torch.randn_like(p))
    torch.save(model.state_dict(), tmp_path / "model.pt")
    save_sparse_config(model, str(tmp_path))
    loaded, config = load_checkpoint(str(tmp_path / "model.pt"), case.build().eval())
    assert is_sparse(loaded) and config == model._smdm_state.config
    x, y = case.inputs(1)
    with torch.no_grad():
        for step in (40, 2):
            t = torch.full((3,), step)
            assert torch.equal(case.call(loaded, x, t, y), case.call(model, x, t, y)), step


@pytest.fixture
def fresh_dynamo():
    """Compiled frames of one model class accumulate across tests (dynamo's recompile limit counts
    per code object): start and leave clean."""
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


def test_every_sparse_call_compiles_fullgraph(case, fresh_dynamo):
    model = case.build()
    diffusion = case.diffusion()
    sparsify(model, case.config(mask_noise=0.1), diffusion=diffusion)
    compiled = torch.compile(model, fullgraph=True, backend="eager")
    x, y = case.inputs()
    model.train()
    model.smdm_mask_noise_step.zero_()                   # the masks are a function of (seed, step)
    out = case.loss(diffusion, compiled, x, y)
    model.smdm_mask_noise_step.zero_()
    assert torch.allclose(out, case.loss(diffusion, model, x, y), atol=1e-5)
    model.eval()
    with torch.no_grad():
        for step in (40, 2):                             # uniform mask / VW on x_t in the late steps
            t = torch.full((3,), step)
            assert torch.allclose(case.call(compiled, x, t, y), case.call(model, x, t, y), atol=1e-5), step


def test_static_path_has_no_host_sync(case):
    model = case.build()
    diffusion = case.diffusion()
    sparsify(model, case.config(), diffusion=diffusion)
    x, y = case.inputs()
    with static_mode():
        model.train()
        case.loss(diffusion, model, x, y).backward()                 # warm-up: per-device tables
        with Dispatched() as d:
            case.loss(diffusion, model, x, y).backward()
        assert not d.syncs, f"training step: {dict(d.syncs)}"
        model.eval()
        for step in (40, 2):
            with torch.no_grad(), Dispatched() as d:
                case.call(model, x, torch.full((3,), step), y)
            assert not d.syncs, f"sampling t={step}: {dict(d.syncs)}"


def test_lifecycle_with_the_diffusion_in_any_order(case):
    x, y = case.inputs()
    reference = case.loss(case.diffusion(), case.build(), x, y)      # dense, never sparsified
    model, diffusion = case.build(), case.diffusion()
    # attached at sparsify, unsparsified, trained dense with the same diffusion: upstream's loss
    torch.manual_seed(7)                                             # the same new Lipschitz layers
    sparsify(model, case.config(), diffusion=diffusion)
    sparse_loss = case.loss(diffusion, model, x, y)
    unsparsify(model)
    assert torch.equal(case.loss(diffusion, model, x, y), reference)
    # sparsified without the diffusion, attached afterwards; re-sparsified with another config
    torch.manual_seed(7)
    sparsify(model, case.config())
    attach_diffusion(diffusion, model=model)
    assert torch.equal(case.loss(diffusion, model, x, y), sparse_loss)
    unsparsify(model)
    torch.manual_seed(7)
    sparsify(model, case.config(reduction=0.5), diffusion=diffusion)
    assert not torch.equal(case.loss(diffusion, model, x, y), sparse_loss)
    unsparsify(model)
    assert torch.equal(case.loss(diffusion, model, x, y), reference)
    assert "training_losses" not in vars(diffusion)


class BrokenDiffusion:
    """Has a step count (read first) but no ``training_losses`` (needed last, when attaching)."""

    num_timesteps = 50


def test_failed_sparsify_leaves_the_model_as_before_and_a_retry_works(case, monkeypatch):
    """A diffusion without ``training_losses`` is refused before any change (a TypeError naming the
    argument); a failure at the last step (attaching the diffusion) rolls the surgery back."""
    import smdm_plugin.adapters.surgery as surgery

    model = case.build()
    snap = snapshot(model)
    with pytest.raises(TypeError, match="diffusion"):
        sparsify(model, case.config(lipschitz=True), diffusion=BrokenDiffusion())
    assert_same(model, snap)

    def broken_attach(*args, **kwargs):
        raise RuntimeError("attach failed")

    monkeypatch.setattr(surgery, "attach_diffusion", broken_attach)
    with pytest.raises(RuntimeError, match="attach failed"):
        sparsify(model, case.config(lipschitz=True), diffusion=case.diffusion())
    assert_same(model, snap)
    assert not is_sparse(model)
    monkeypatch.undo()
    sparsify(model, case.config(), diffusion=case.diffusion())
    assert is_sparse(model)


def test_motiondiffuse_fsq_request_is_a_warning_not_silent():
    model = MotionDiffuseCase().build()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        sparsify(model, SparseConfig(feature="raw", fsq=True))
    assert any("fsq=True cannot apply" in str(w.message) for w in seen)
    assert model._smdm_state.config.fsq is False


def test_sparse_state_is_deep_copied_with_the_model(case):
    model = case.build()
    sparsify(model, case.config())
    twin = copy.deepcopy(model)
    assert twin._smdm_state is not model._smdm_state and twin._smdm_state.family is model._smdm_state.family
    for m in twin.modules():                 # hooks bound to a state (functools.partial) hold the twin's
        for hook in [*m._forward_pre_hooks.values(), *m._forward_hooks.values()]:
            bound = [a for a in getattr(hook, "args", ()) if isinstance(a, SparseState)]
            assert all(a is twin._smdm_state for a in bound)
    x, y = case.inputs()
    model.eval(), twin.eval()
    with torch.no_grad():
        t = torch.full((3,), 40)
        assert torch.equal(case.call(twin, x, t, y), case.call(model, x, t, y))
