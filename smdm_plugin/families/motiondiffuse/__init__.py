"""MotionDiffuse's ``MotionTransformer``: one model family.

``model.py`` the ModelFamily (surgery, state, how a call is read), ``upstream.py`` the hooks into a
MotionDiffuse checkout and the patch entry points, ``prepare.py`` the call made ready for graph
capture, ``workload.py`` what ``smdm bench`` times, ``conformance.py`` (with ``standin.py``, a
model with MotionDiffuse's interface) the cases of the conformance suite."""
from ...adapters.families import FamilySpec, register_family

register_family(FamilySpec(
    name="motiondiffuse",
    family="smdm_plugin.families.motiondiffuse.model:MotionDiffuseFamily",
    integration="smdm_plugin.families.motiondiffuse.upstream:INTEGRATION",
    preparer="smdm_plugin.families.motiondiffuse.prepare:PREPARER",
    workload="smdm_plugin.families.motiondiffuse.workload:MotionDiffuseWorkload",
    conformance="smdm_plugin.families.motiondiffuse.conformance:cases",
))
