"""priorMDM's DoubleTake (``doubleTake_MDM``): a specialisation of the ``mdm`` family.

``model.py`` the ModelFamily (MDM's, plus the forced frames of the transitions), ``upstream.py``
the hooks into a priorMDM checkout and the patch entry points, ``conformance.py`` the cases of
the conformance suite; calls are prepared for graph capture as MDM's, and ``smdm bench`` times it
as the ``mdm`` workload's ``doubletake`` variant."""
from ...adapters.families import FamilySpec, register_family

register_family(FamilySpec(
    name="doubletake",
    family="smdm_plugin.families.doubletake.model:DoubleTakeFamily",
    integration="smdm_plugin.families.doubletake.upstream:INTEGRATION",
    preparer="smdm_plugin.families.mdm.prepare:PREPARER",
    conformance="smdm_plugin.families.doubletake.conformance:cases",
))
