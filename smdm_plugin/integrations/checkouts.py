"""The integration registry: the upstream checkouts ``smdm run`` knows, each registered by its own
model family (its ``FamilySpec.integration``: ``families/<name>/upstream.py``) with how to recognise
a checkout and how to hook it; an integration without a model family with

    register_integration(Integration("mine", detect=is_my_repo, install_hooks=install_hooks,
                                     layout="model/mine.py (MyModel)", priority=5))

:func:`detect_repo` asks the registered integrations in descending ``priority`` (a more specific
layout first: priorMDM's checkout also has MDM's files). The launcher's child process installs the
hooks of the integration it is named (``SMDM_INTEGRATION``), after importing the module that
registers it (``SMDM_INTEGRATION_MODULE``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Tuple

from ..core.registry import Registry

__all__ = ["Integration", "INTEGRATIONS", "register_integration", "integrations", "detect_repo"]


@dataclass(frozen=True)
class Integration:
    """One upstream code base: ``detect(path)`` says whether a folder is its checkout; ``layout``
    says what ``detect`` looks for, in words (the launcher's error message); ``install_hooks()``
    wraps the upstream functions as they are imported (idempotent); ``priority``: asked first when
    higher."""

    name: str
    detect: Callable[[str], bool]
    install_hooks: Callable[[], None]
    layout: str
    priority: int = 0

    @property
    def module(self) -> str:
        """The module that registers it (imported by the launcher's child process)."""
        return self.install_hooks.__module__


_FROM_FAMILIES: Dict[str, Tuple[Any, str]] = {}   # family name -> (its spec, its integration's name)


def _from_families() -> None:
    """Keep :data:`INTEGRATIONS` in step with the registered families' ``FamilySpec.integration``."""
    from ..adapters.families import family_part, family_specs

    specs = {s.name: s for s in family_specs() if s.integration is not None}
    for name, (spec, integration) in list(_FROM_FAMILIES.items()):
        if specs.get(name) is not spec:              # unregistered or replaced
            del _FROM_FAMILIES[name]
            INTEGRATIONS.unregister(integration)
    for name, spec in specs.items():
        if name not in _FROM_FAMILIES:
            integration = family_part(spec, "integration")
            _FROM_FAMILIES[name] = (spec, integration.name)
            INTEGRATIONS.register(integration.name, integration, replace=True)


#: the integrations by name: the registered model families' (``FamilySpec.integration``) and any
#: registered alone with :func:`register_integration`
INTEGRATIONS: Registry[Integration] = Registry("integration", fill=_from_families)


def register_integration(integration: Integration, *, replace: bool = False) -> Integration:
    """Add ``integration`` under its name (a taken name is a ``ValueError`` unless ``replace``)."""
    return INTEGRATIONS.register(integration.name, integration, replace=replace)


def integrations() -> List[Integration]:
    """The registered integrations in the order :func:`detect_repo` asks them (priority, then name)."""
    return sorted(INTEGRATIONS.entries(), key=lambda i: (-i.priority, i.name))


def detect_repo(path: str) -> str:
    """The name of the integration whose ``detect`` accepts the checkout at ``path`` (the first in
    :func:`integrations` order). A ``ValueError`` names every layout looked for."""
    for integration in integrations():
        if integration.detect(path):
            return integration.name
    layouts = ", ".join(i.layout for i in sorted(INTEGRATIONS.entries(), key=lambda i: i.priority))
    raise ValueError(f"smdm run: --repo {path!r} is not a checkout smdm-plugin knows: expected {layouts}")
