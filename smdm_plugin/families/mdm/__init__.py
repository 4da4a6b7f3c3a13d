"""MDM (trans_enc / trans_dec), DiP and the in-package TinyMDM: one model family.

``model.py`` the ModelFamily (surgery, state, how a call is read), ``upstream.py`` (+ ``train.py``,
``text.py``, ``edit.py``) the hooks into an MDM / DiP checkout and the patch entry points,
``prepare.py`` the call made ready for graph capture, ``workload.py`` what ``smdm bench`` times,
``conformance.py`` the cases of the conformance suite."""
from ...adapters.families import FamilySpec, register_family

register_family(FamilySpec(
    name="mdm",
    family="smdm_plugin.families.mdm.model:MDMFamily",
    integration="smdm_plugin.families.mdm.upstream:INTEGRATION",
    preparer="smdm_plugin.families.mdm.prepare:PREPARER",
    workload="smdm_plugin.families.mdm.workload:MDMWorkload",
    conformance="smdm_plugin.families.mdm.conformance:cases",
))
