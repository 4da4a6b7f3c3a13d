"""Bad input to the selection entry points and the registries is one ``TypeError`` / ``ValueError``
naming the argument and what was expected: never a silent coercion or an error from deep inside."""
import pytest
import torch

from smdm_plugin import available_backends, register_backend, register_selector, select_keyframes
from smdm_plugin.core import attention_backends as ab
from smdm_plugin.core.checks import static_mode
from smdm_plugin.core.registry import Registry
from smdm_plugin.core.selection import SELECTORS, perturb_mask

F = torch.randn(2, 10, 3)


def _backend(*args, **kwargs):
    return ab.compact_backend(*args, **kwargs)


@pytest.fixture
def registered():
    """Names registered by a test, unregistered after it (whether or not registration failed)."""
    names = []
    yield names
    for name in names:
        SELECTORS.unregister(name)
        ab.BACKENDS.unregister(name)


# ----------------------------------------------------------------------------- a selector's output
@pytest.mark.parametrize("out,error,match", [
    (lambda f: None, TypeError, r"its mask must be a bool tensor \[B, N\]=\[2, 10\], got NoneType"),
    (lambda f: torch.zeros(3, 3, dtype=torch.bool), ValueError, r"\[B, N\]=\[2, 10\], got shape \(3, 3\)"),
    (lambda f: torch.ones(f.shape[:2]), TypeError, r"\[B, N\]=\[2, 10\], got torch.float32"),
    (lambda f: torch.zeros(f.shape[:2], dtype=torch.bool), ValueError, r"must keep frames 0 and L - 1"),
])
def test_a_selector_returning_no_valid_mask_is_an_error_naming_it(registered, out, error, match):
    registered.append("_bad")
    register_selector("_bad", lambda f, lengths, k, g, forced, active: out(f))
    with pytest.raises(error, match=r"keyframe selector '_bad'.*" + match):
        select_keyframes(F, method="_bad")


def test_selector_output_values_are_read_on_the_cpu_only(registered):
    registered.append("_empty")
    register_selector("_empty", lambda f, lengths, k, g, forced, active: torch.zeros(f.shape[:2], dtype=torch.bool))
    with static_mode():                        # the GPU path: no reads of values (shapes still checked)
        assert not select_keyframes(F, method="_empty").any()


# ----------------------------------------------------------------------------- masks
@pytest.mark.parametrize("kwargs,error,match", [
    (dict(forced=torch.full((2, 10), 0.5)), TypeError,
     r"select_keyframes: forced must be a bool tensor \[B, N\]=\[2, 10\], got torch.float32"),
    (dict(forced=torch.zeros(2, 9, dtype=torch.bool)), ValueError,
     r"select_keyframes: forced must be a bool tensor \[B, N\]=\[2, 10\], got shape \(2, 9\)"),
    (dict(active=torch.tensor([True, False, True])), ValueError,
     r"select_keyframes: active must be a bool tensor \[B\]=\[2\], got shape \(3,\)"),
    (dict(active=torch.ones(2)), TypeError, r"select_keyframes: active must be a bool tensor \[B\]=\[2\], got torch"),
])
def test_masks_must_be_bool_of_their_shape(kwargs, error, match):
    with pytest.raises(error, match=match):
        select_keyframes(F, **kwargs)


def test_bool_masks_as_lists_still_work():
    forced = [[False] * 10, [False] * 4 + [True] + [False] * 5]
    assert select_keyframes(F, reduction=0.8, forced=forced)[1, 4]


# ----------------------------------------------------------------------------- features, method, generator
@pytest.mark.parametrize("kwargs,match", [
    (dict(features=F.to(torch.complex64)), r"features must be a real floating tensor.*got torch.complex64"),
    (dict(features=None), r"features must be a real floating tensor.*got NoneType"),
    (dict(method=[]), r"method must be a str .*got list"),
    (dict(method="random", generator=5), r"generator must be a torch.Generator, a CounterNoise or None, got int"),
])
def test_wrong_types_are_type_errors_naming_the_argument(kwargs, match):
    args = dict(features=F)
    args.update(kwargs)
    with pytest.raises(TypeError, match="select_keyframes: " + match):
        select_keyframes(**args)


def test_perturb_mask_checks_its_generator_and_masks():
    mask = torch.ones(2, 4, dtype=torch.bool)
    with pytest.raises(TypeError, match="perturb_mask: generator must be a torch.Generator"):
        perturb_mask(mask, amount=0.5, generator=5)
    with pytest.raises(TypeError, match=r"perturb_mask: mask must be a bool tensor \[B, N\]=\[2, 4\], got torch.float"):
        perturb_mask(mask.float(), amount=0.5)
    with pytest.raises(TypeError, match=r"perturb_mask: protected must be a bool tensor \[B, N\]=\[2, 4\], got"):
        perturb_mask(mask, amount=0.5, protected=torch.ones(2, 4, dtype=torch.long))


# ----------------------------------------------------------------------------- registries
@pytest.mark.parametrize("register,kwargs,match", [
    (register_selector, dict(fn=5), "fn must be callable, got 5"),
    (register_selector, dict(fn=lambda *a: None, handles_forced="no"), "handles_forced must be a bool, got 'no'"),
    (register_selector, dict(fn=lambda *a: None, with_noise=1), "with_noise must be callable or None, got 1"),
    (register_backend, dict(fn=5), "fn must be callable, got 5"),
    (register_backend, dict(fn=_backend, available=5), "available must be callable, got 5"),
    (register_backend, dict(fn=_backend, supports=None), "supports must be callable, got None"),
    (register_backend, dict(fn=_backend, padded_lead="no"), "padded_lead must be a bool, got 'no'"),
])
def test_registration_checks_what_the_entry_holds(registered, register, kwargs, match):
    registered.append("_e")
    with pytest.raises(TypeError, match=r"'_e': " + match):
        register("_e", **kwargs)
    assert "_e" not in SELECTORS and "_e" not in ab.BACKENDS
    assert "compact" in available_backends("cpu")                 # nothing half-registered breaks reads


@pytest.mark.parametrize("name", [" x ", "", "x ", 5])
@pytest.mark.parametrize("register,fn", [(register_selector, lambda *a: None), (register_backend, _backend)])
def test_names_are_non_empty_strings_without_surrounding_spaces(registered, register, fn, name):
    registered.append(name if isinstance(name, str) else "_")
    with pytest.raises(ValueError, match="name must be a non-empty string without surrounding spaces"):
        register(name, fn)


def test_auto_is_a_reserved_backend_name():
    with pytest.raises(ValueError, match="register attention backend: 'auto' is a reserved name"):
        register_backend("auto", _backend)
    assert "auto" not in ab.BACKENDS


def test_a_registry_checks_the_type_of_its_entries_and_others_hold_anything(registered):
    registered.append("x")
    with pytest.raises(TypeError, match=r"register keyframe selector 'x': expected a Selector, got int"):
        SELECTORS.register("x", 5)
    anything = Registry("thing")                                  # (e.g. the model families: any object)
    assert anything.register("x", 5) == 5 and anything.get("x") == 5
