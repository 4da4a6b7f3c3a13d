"""A module path 0.9 moved fails to import with a message naming the new one; every new path is real."""
import importlib
import subprocess
import sys

import pytest

from smdm_plugin.support.moved import MOVED, moved_message


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_path_names_the_new_one(old):
    new = "smdm_plugin." + MOVED[old]
    assert importlib.util.find_spec(new) is not None, new          # the table points at a real module
    with pytest.raises(ModuleNotFoundError, match=new.replace(".", r"\.")):
        importlib.import_module("smdm_plugin." + old)


def test_a_module_that_never_existed_is_the_usual_error():
    assert moved_message("smdm_plugin.integrations.nope") is None
    with pytest.raises(ModuleNotFoundError, match="No module named"):
        importlib.import_module("smdm_plugin.integrations.nope")


def test_an_old_patch_line_fails_with_one_line():
    """What a checkout patched by 0.8's patches/mdm.patch runs."""
    r = subprocess.run([sys.executable, "-c", "from smdm_plugin.integrations.mdm import sparsify_mdm"],
                       capture_output=True, text=True)
    assert r.returncode == 1
    assert "smdm_plugin.families.mdm.upstream" in r.stderr.strip().splitlines()[-1]
