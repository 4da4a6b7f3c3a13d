"""The conformance cases of the model families (tests/adapters/test_family_conformance.py): each
registered family names its case factory in its ``FamilySpec.conformance``
(``smdm_plugin/families/<name>/conformance.py`` for the built-in ones: how to build a model of the
family, its diffusion, its inputs, call it and take its loss; one case per variant worth checking).
A family registered without one fails ``test_every_registered_family_has_a_conformance_case``.
"""
from __future__ import annotations

from typing import Dict, List

from smdm_plugin.adapters.families import FAMILY_SPECS, families, family_part
from smdm_plugin.families.mdm.conformance import STEPS, MDMCase  # noqa: F401  (the built-in cases' types)
from smdm_plugin.families.motiondiffuse.conformance import MotionDiffuseCase  # noqa: F401


def _factory(name: str):
    return family_part(FAMILY_SPECS.get(name), "conformance") if name in FAMILY_SPECS else None


def families_without_cases() -> List[str]:
    """The registered families (registry order) that have no conformance case factory."""
    return [f.name for f in families() if _factory(f.name) is None]


def conformance_cases() -> Dict[str, object]:
    """Case name -> case, for every registered family that has a factory (registry order)."""
    cases: Dict[str, object] = {}
    for fam in families():
        factory = _factory(fam.name)
        for case in (factory() if factory is not None else []):
            if case.name in cases:
                raise ValueError(f"two conformance cases are named {case.name!r}")
            cases[case.name] = case
    return cases


def assert_every_family_has_cases() -> None:
    """An ``AssertionError`` naming every registered family without a conformance case factory."""
    missing = families_without_cases()
    assert not missing, (f"registered model famil{'y' if len(missing) == 1 else 'ies'} without a conformance case: "
                         f"{', '.join(missing)} (give its FamilySpec a conformance case factory)")
