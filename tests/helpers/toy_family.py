"""A whole model family in one module, registered with one call and touching no other file: the
example of docs/architecture.md ("A new family"). ``ToyMDM`` is a TinyMDM under another name; its
family reuses MDM's surgery (as DoubleTake's does) and brings its own compile preparer, benchmark
workload (none) and conformance case. Loaded as a pytest plugin (``-p helpers.toy_family``), it
runs through the whole conformance suite (tests/adapters/test_toy_family.py)."""
from smdm_plugin import FamilySpec, TinyMDM, register_family
from smdm_plugin.families.mdm.conformance import MDMCase
from smdm_plugin.families.mdm.model import MDMFamily
from smdm_plugin.families.mdm.prepare import prepare_mdm


class ToyMDM(TinyMDM):
    """The toy family's model."""


class ToyFamily(MDMFamily):
    name = "toy"
    priority = 50          # asked before MDM's (a ToyMDM is an MDM too)

    def matches(self, model):
        return isinstance(model, ToyMDM) and super().matches(model)

    def mismatch(self, model):
        return "not a ToyMDM" if not isinstance(model, ToyMDM) else super().mismatch(model)


CALLS = []


def prepare_toy(model, args, kwargs):
    """The toy's compile preparer: MDM's, counted."""
    CALLS.append(type(model).__name__)
    return prepare_mdm(model, args, kwargs)


def toy_cases():
    return [MDMCase("toy", "toy", cls=ToyMDM, arch="trans_enc")]


SPEC = register_family(FamilySpec(name="toy", family=ToyFamily(), preparer=prepare_toy, conformance=toy_cases),
                       replace=True)
