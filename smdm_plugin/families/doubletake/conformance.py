"""The ``doubletake`` family's conformance case (``FamilySpec.conformance``): a TinyMDM subclass
named like priorMDM's ``doubleTake_MDM``, run as MDM's cases are."""
from __future__ import annotations

from ...reference.backbone import TinyMDM
from ..mdm.conformance import MDMCase


class DoubleTakeTinyMDM(TinyMDM):
    """priorMDM's doubleTake_MDM is an MDM subclass; the family is recognised by the class name."""


def cases():
    return [MDMCase("doubletake", "doubletake", cls=DoubleTakeTinyMDM, arch="trans_enc")]
