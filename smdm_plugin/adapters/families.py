"""The registry of model families: one :class:`FamilySpec` per family, registered with one call
(``register_family(FamilySpec(name=..., family=..., integration=..., preparer=..., workload=...,
conformance=...))``), which fills every registry that knows a family. The built-in families are the
packages of :data:`BUILTIN_FAMILIES`, imported on the first lookup; a model's family is found once,
here (:func:`family_for`, :func:`family_of`). Details: docs/modules.md."""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple

from ..core.registry import Registry

__all__ = ["FamilySpec", "BUILTIN_FAMILIES", "FAMILY_SPECS", "FAMILIES", "register_family", "family_specs",
           "families", "get_family", "get_spec", "family_for", "family_of", "family_part", "load_builtin_families"]

#: the built-in family packages, imported (each registers itself) on the first lookup
BUILTIN_FAMILIES = ("smdm_plugin.families.mdm", "smdm_plugin.families.doubletake",
                    "smdm_plugin.families.motiondiffuse")

#: what a :class:`FamilySpec` holds besides its name and :class:`~smdm_plugin.adapters.family.ModelFamily`
PARTS = ("family", "integration", "preparer", "workload", "conformance")


@dataclass(frozen=True)
class FamilySpec:
    """Everything one model family is, registered with one :func:`register_family` call.

    Each part is the object or ``"module:attribute"`` (loaded on first use; a class is
    instantiated once); every part but ``family`` may be None.

    Attributes:
        name: the family's name (``ModelFamily.name``).
        family: its :class:`~smdm_plugin.adapters.family.ModelFamily` (surgery, state, call reading).
        integration: the upstream checkout ``smdm run`` hooks
            (:class:`~smdm_plugin.integrations.checkouts.Integration`).
        preparer: ``prepare(model, args, kwargs) -> (args, kwargs)``, a call made ready for graph
            capture (:class:`~smdm_plugin.runtime.compile.CallPreparer` or a function).
        workload: ``smdm bench``'s :class:`~smdm_plugin.training.workloads.Workload`.
        conformance: ``factory() -> [case, ...]``, the conformance cases
            (``tests/adapters/test_family_conformance.py``).
    """

    name: str
    family: Any = None
    integration: Any = None
    preparer: Any = None
    workload: Any = None
    conformance: Any = None


#: the registered families' specs by name (the built-in ones imported on the first read)
FAMILY_SPECS: Registry[FamilySpec] = Registry("model family", fill=lambda: load_builtin_families())
_LOADED: Dict[Tuple[str, str], Any] = {}
_BUILTINS_LOADED = False


def load_builtin_families() -> None:
    """Import the built-in family packages (:data:`BUILTIN_FAMILIES`) once: each registers itself."""
    global _BUILTINS_LOADED
    if _BUILTINS_LOADED:
        return
    _BUILTINS_LOADED = True
    for name in BUILTIN_FAMILIES:
        importlib.import_module(name)


def _load(ref: str) -> Any:
    module, _, attr = ref.partition(":")
    value = getattr(importlib.import_module(module), attr)
    return value() if isinstance(value, type) else value


def family_part(spec: FamilySpec, part: str) -> Any:
    """``spec``'s ``part`` (one of :data:`PARTS`), loaded if it was given by name; None if absent."""
    value = getattr(spec, part)
    if not isinstance(value, str):
        return value
    key = (spec.name, part)
    if key not in _LOADED:
        _LOADED[key] = _load(value)
    return _LOADED[key]


def register_family(spec: Any, *, replace: bool = False) -> FamilySpec:
    """Register a model family: its :class:`FamilySpec` (or a bare
    :class:`~smdm_plugin.adapters.family.ModelFamily`: a spec with nothing but the family). A name
    taken is a ``ValueError`` unless ``replace``. Returns the spec."""
    if not isinstance(spec, FamilySpec):
        from .family import ModelFamily   # here: a spec naming its parts loads no torch (`smdm run`)

        if not isinstance(spec, ModelFamily):
            raise TypeError("register_family: family must be a ModelFamily instance (or a FamilySpec), "
                            f"got {type(spec).__name__}")
        spec = FamilySpec(name=spec.name, family=spec)
    elif spec.family is not None and not isinstance(spec.family, str):
        from .family import ModelFamily

        if not isinstance(spec.family, ModelFamily):
            raise TypeError(f"register_family: family must be a ModelFamily instance, got {type(spec.family).__name__}")
    FAMILY_SPECS.register(spec.name, spec, replace=replace)
    for key in [k for k in _LOADED if k[0] == spec.name]:
        del _LOADED[key]
    return spec


def family_specs() -> List[FamilySpec]:
    """The registered specs, in registration order (built-in ones first)."""
    return FAMILY_SPECS.entries()


class _Families:
    """The registered :class:`~smdm_plugin.adapters.family.ModelFamily` objects by name: a view of
    :data:`FAMILY_SPECS` (``register`` adds a spec with the family alone, ``unregister`` removes
    the spec)."""

    what = "model family"

    def _map(self) -> Dict[str, Any]:
        return {s.name: family_part(s, "family") for s in family_specs() if s.family is not None}

    def register(self, name: str, family: Any, *, replace: bool = False) -> Any:
        register_family(FamilySpec(name=name, family=family), replace=replace)
        return family

    def unregister(self, name: str) -> None:
        FAMILY_SPECS.unregister(name)
        for key in [k for k in _LOADED if k[0] == name]:
            del _LOADED[key]

    def get(self, name: str) -> Any:
        fams = self._map()
        if name not in fams:
            raise ValueError(f"unknown model family {name!r}; registered: {', '.join(fams)}")
        return fams[name]

    def names(self) -> Tuple[str, ...]:
        return tuple(s.name for s in family_specs() if s.family is not None)

    def entries(self) -> List[Any]:
        return list(self._map().values())

    def __contains__(self, name: object) -> bool:
        return name in self.names()

    def choices(self, *extra: str) -> Any:
        from ..core.registry import Choices

        return Choices(self.names, extra)


#: the model families by name (a view of :data:`FAMILY_SPECS`)
FAMILIES = _Families()


def families() -> List[Any]:
    """The registered families, in the order they are asked (priority, then registration)."""
    return sorted(FAMILIES.entries(), key=lambda f: -f.priority)


def get_family(name: str) -> Any:
    return FAMILIES.get(name)


def get_spec(name: str) -> FamilySpec:
    """The :class:`FamilySpec` registered under ``name`` (``ValueError`` naming the registered ones)."""
    return FAMILY_SPECS.get(name)


def family_for(model: Any, fn: str = "sparsify") -> Any:
    """The first registered family that matches ``model``; a ``TypeError`` says why none does."""
    import torch.nn as nn

    if not isinstance(model, nn.Module):
        raise TypeError(f"{fn}: model must be a torch.nn.Module, got {type(model).__name__}")
    fams = families()
    for fam in fams:
        if fam.matches(model):
            return fam
    why = "; ".join(f"{f.name}: {f.mismatch(model)}" for f in fams)
    raise TypeError(f"{fn}: {type(model).__name__} belongs to no registered model family ({why}). "
                    "Register one with smdm_plugin.register_family")


def family_of(model: Any) -> Optional[Any]:
    """The family of ``model``: the one that converted it when it is sparse (its state says), else
    the first registered family that matches it; None when none does."""
    from .state import find_sparse_model, get_state

    sparse = find_sparse_model(model)
    if sparse is not None:
        return get_state(sparse).family
    try:
        return family_for(model)
    except TypeError:
        return None
