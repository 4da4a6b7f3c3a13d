"""The integration registry (which checkout `smdm run` hooks, how) and the one wrap-once helper."""
import argparse
import os
import sys
import types

import pytest

from smdm_plugin.families.mdm import upstream as mdm
from smdm_plugin.families.motiondiffuse import upstream as motiondiffuse
from smdm_plugin.families.doubletake import upstream as priormdm
from smdm_plugin.integrations._hooks import WRAPPED, wrap_once
from smdm_plugin.integrations.launcher import make_environment, run
from smdm_plugin.integrations.checkouts import (INTEGRATIONS, Integration, detect_repo, integrations,
                                               register_integration)


def layout(root, *files):
    for f in files:
        path = root / f
        if f.endswith("/"):
            path.mkdir(parents=True, exist_ok=True)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("")
    return str(root)


# ------------------------------------------------------------------------------ registry
def test_the_built_in_integrations_register_themselves():
    assert set(INTEGRATIONS.names()) >= {"mdm", "priormdm", "motiondiffuse"}
    assert INTEGRATIONS.get("mdm").install_hooks is mdm.install_hooks
    assert INTEGRATIONS.get("priormdm").install_hooks is priormdm.install_hooks
    assert INTEGRATIONS.get("motiondiffuse").install_hooks is motiondiffuse.install_hooks
    assert INTEGRATIONS.get("priormdm").module == "smdm_plugin.families.doubletake.upstream"
    names = [i.name for i in integrations()]
    assert names.index("priormdm") < names.index("mdm")  # priorMDM has MDM's files too: asked first


@pytest.mark.parametrize("files, expected", [
    (("model/mdm.py", "utils/model_util.py"), "mdm"),
    (("model/mdm.py", "utils/model_util.py", "model/DoubleTake_MDM.py"), "priormdm"),
    (("text2motion/",), "motiondiffuse"),
    (("trainers/ddpm_trainer.py", "models/transformer.py"), "motiondiffuse"),
])
def test_detect_repo(tmp_path, files, expected):
    assert detect_repo(layout(tmp_path, *files)) == expected


def test_an_unknown_checkout_names_every_registered_layout(tmp_path):
    with pytest.raises(ValueError, match="is not a checkout smdm-plugin knows") as e:
        detect_repo(str(tmp_path))
    for integration in INTEGRATIONS.entries():
        assert integration.layout in str(e.value)
    with pytest.raises(ValueError, match="already registered"):
        register_integration(INTEGRATIONS.get("mdm"))


TOY = '''
import os
from smdm_plugin.integrations.checkouts import Integration, register_integration

def install_hooks():
    with open(os.environ["TOY_MARK"], "w") as f:
        f.write("hooked")

register_integration(Integration("toy", detect=lambda p: os.path.isfile(os.path.join(p, "toy.cfg")),
                                 install_hooks=install_hooks, layout="toy.cfg (Toy)", priority=100))
'''


@pytest.fixture
def toy(tmp_path, monkeypatch):
    """A third-party integration in its own module, registered by importing it."""
    pkg = tmp_path / "site"
    pkg.mkdir()
    (pkg / "toy_integration.py").write_text(TOY)
    monkeypatch.syspath_prepend(str(pkg))
    import toy_integration  # noqa: F401
    yield pkg
    INTEGRATIONS.unregister("toy")
    sys.modules.pop("toy_integration", None)


def test_a_registered_integration_is_detected_and_its_hooks_run_in_the_command(toy, tmp_path):
    repo = layout(tmp_path / "repo", "toy.cfg", "model/mdm.py", "utils/model_util.py")
    assert detect_repo(repo) == "toy"  # priority 100 is asked before MDM
    assert "toy" in INTEGRATIONS.choices("auto")
    env = make_environment("toy", str(tmp_path), base={"PYTHONPATH": str(toy)})
    assert env["SMDM_INTEGRATION"] == "toy" and env["SMDM_INTEGRATION_MODULE"] == "toy_integration"
    mark = tmp_path / "mark.txt"
    base = dict(os.environ, PYTHONPATH=os.pathsep.join([str(toy), os.environ.get("PYTHONPATH", "")]),
                TOY_MARK=str(mark))
    assert run(repo, [sys.executable, "-c", "import sys; sys.exit(5)"], env=base) == 5
    assert mark.read_text() == "hooked"  # the child process installed the toy's hooks


def test_the_launcher_child_installs_a_built_in_integration(tmp_path):
    """The generated sitecustomize finds MDM's hooks through the registry (the command sees them)."""
    repo = layout(tmp_path, "model/mdm.py", "utils/model_util.py")
    code = ("import sys; from smdm_plugin.integrations._hooks import _CALLBACKS; "
            "sys.exit(0 if 'utils.model_util' in _CALLBACKS else 9)")
    assert run(repo, [sys.executable, "-c", code]) == 0


def test_a_named_integration_that_another_recognises_is_refused_and_a_fork_is_said(tmp_path, capsys):
    """0.10.5 ran an MDM checkout with MotionDiffuse's hooks when asked (nothing hooked: the flags did
    nothing). A checkout another integration recognises is refused, naming both; one none recognises (a
    fork) runs with the named hooks, with a warning."""
    mdm_repo = layout(tmp_path / "mdm", "model/mdm.py", "utils/model_util.py")
    with pytest.raises(ValueError, match=r"--integration motiondiffuse: --repo '.*mdm' is a mdm checkout"):
        run(mdm_repo, [sys.executable, "-c", "pass"], integration="motiondiffuse")
    assert run(mdm_repo, [sys.executable, "-c", "pass"], integration="mdm") == 0
    fork = str(tmp_path / "fork")
    os.makedirs(fork)
    capsys.readouterr()
    assert run(fork, [sys.executable, "-c", "import sys; sys.exit(4)"], integration="mdm") == 4
    assert "does not have mdm's layout" in capsys.readouterr().err


# ------------------------------------------------------------------------------ wrap_once
def test_wrap_once_wraps_once_and_keeps_the_return_value():
    calls = []

    def original(x):
        return x + 1

    owner = types.SimpleNamespace(f=original)

    def make(inner):
        def f(x):
            calls.append(x)
            return inner(x) * 10
        return f

    assert wrap_once(owner, "f", make) is True
    first = owner.f
    assert getattr(first, WRAPPED) is True and owner.f(1) == 20 and calls == [1]
    assert wrap_once(owner, "f", make) is False and owner.f is first  # installed twice: wrapped once
    assert owner.f(2) == 30 and calls == [1, 2]
    assert wrap_once(owner, "missing", make) is False and not hasattr(owner, "missing")
    assert wrap_once(None, "f", make) is False
    # another marker is another wrapper (mdm_train's DDP hooks keep their own)
    assert wrap_once(owner, "f", make, marker="_smdm_ddp") is True
    assert owner.f(1) == 200 and getattr(owner.f, "_smdm_ddp") is True


def test_wrap_once_wraps_methods_of_a_class():
    class Upstream:
        def run(self):
            return "upstream"

    assert wrap_once(Upstream, "run", lambda original: lambda self: "ours+" + original(self))
    assert wrap_once(Upstream, "run", lambda original: lambda self: "twice") is False
    assert Upstream().run() == "ours+upstream"


@pytest.mark.parametrize("integration", [mdm, priormdm])
def test_add_model_options_hook_keeps_upstream_return_value(integration):
    """MDM and priorMDM share one parser hook; it returns what upstream's function returns."""
    def add_model_options(parser):
        parser.add_argument_group("model").add_argument("--layers", type=int, default=8)
        return "upstream result"

    mod = types.SimpleNamespace(add_model_options=add_model_options)
    integration.patch_model_options(mod)
    integration.patch_model_options(mod)  # idempotent
    parser = argparse.ArgumentParser()
    assert mod.add_model_options(parser) == "upstream result"
    args = parser.parse_args(["--sparse", "--sparse_reduction", "0.7"])
    assert args.sparse and args.sparse_reduction == 0.7 and args.layers == 8
    model_group = next(g for g in parser._action_groups if g.title == "model")
    assert "--sparse" in {s for a in model_group._group_actions for s in a.option_strings}


def test_hooks_installed_twice_wrap_once():
    """Each integration's module hooks, called twice (the patch and the launcher), wrap once."""
    gd = types.SimpleNamespace(GaussianDiffusion=type("GaussianDiffusion", (), {
        "p_sample_loop": lambda self, model, shape, model_kwargs=None: model_kwargs}))
    from smdm_plugin.families.mdm import upstream_edit as mdm_edit

    mdm_edit._patch_gaussian_diffusion(gd)
    first = gd.GaussianDiffusion.p_sample_loop
    mdm_edit._patch_gaussian_diffusion(gd)
    assert gd.GaussianDiffusion.p_sample_loop is first and getattr(first, WRAPPED)

    class Trainer:
        def __init__(self, args, encoder):
            self.opt = args

        def backward_G(self):
            return {"loss_mot_rec": 1.0}

    md = types.SimpleNamespace(DDPMTrainer=Trainer)
    motiondiffuse._patch_trainer(md)
    init, backward = Trainer.__init__, Trainer.backward_G
    motiondiffuse._patch_trainer(md)
    assert (Trainer.__init__, Trainer.backward_G) == (init, backward)
    assert Trainer.backward_G.__name__ == "backward_G"  # functools.wraps: upstream's name kept
