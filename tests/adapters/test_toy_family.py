"""A new model family is one module and one registration call (tests/helpers/toy_family.py): the
registries fill from it, the family is detected, its preparer is the one graph capture uses, and
it passes the conformance suite (run here in a fresh pytest with the family loaded as a plugin)."""
import os
import subprocess
import sys

import torch

from smdm_plugin import SparseConfig, is_sparse, sparsify, unsparsify
from smdm_plugin.adapters.families import FAMILIES, FAMILY_SPECS, family_for, family_of, families
from smdm_plugin.runtime.compile import preparer_of

from helpers.paths import ROOT


def test_one_call_registers_the_family_everywhere():
    from helpers import toy_family

    try:
        assert FAMILY_SPECS.get("toy") is toy_family.SPEC
        assert families()[0].name == "toy"                     # priority 50: asked before MDM's
        model = toy_family.ToyMDM(latent_dim=32, ff_size=64, num_layers=2, dropout=0.0)
        assert isinstance(family_for(model), toy_family.ToyFamily) and family_of(model).name == "toy"
        x, y = toy_family.toy_cases()[0].inputs()
        preparer_of(model).prepare(model, (x, torch.tensor([1, 2, 3]), y), {})
        assert toy_family.CALLS == ["ToyMDM"]
        before = {k: v.clone() for k, v in model.state_dict().items()}
        sparsify(model, SparseConfig(reduction=0.8))
        assert is_sparse(model) and family_of(model).name == "toy"
        unsparsify(model)
        assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    finally:
        FAMILIES.unregister("toy")
    assert "toy" not in FAMILY_SPECS


def test_the_toy_family_passes_the_conformance_suite():
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "helpers.toy_family", "-k", "toy or every_registered_family",
                          "-p", "no:cacheprovider", str(ROOT / "tests" / "adapters" / "test_family_conformance.py")],
                         cwd=str(ROOT / "tests"), env=env, capture_output=True, text=True, timeout=1200)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert " passed" in out.stdout and "failed" not in out.stdout
