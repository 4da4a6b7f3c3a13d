"""A flag-off run of the patched MDM loads no more of the plugin than adding the ``--sparse*`` options
to upstream's parser needs (issue 40: 0.7.0 loaded 5 plugin modules at import and 18 after argument
parsing, the ``mdm`` integration, ``start``, the presets and the integration registry among them).

The calls are the ones ``patches/mdm.patch`` adds, in the order upstream runs them: the import of
``train/train_mdm.py`` (the DDP hooks; with them the family's one registration), ``add_base_options`` (``--sparse_compile``),
``add_model_options`` (``--sparse*``), the parse with the flag off, then
``create_model_and_diffusion`` (``sparsify_mdm``). Each count is taken in a fresh interpreter."""
import json
import os
import re
import subprocess
import sys
import textwrap

from helpers.paths import ROOT

PATCH = ROOT / "patches" / "mdm.patch"
IMPORT = re.compile(r"^\+\s*from (smdm_plugin[\w.]*) import (\w+)")


def _patch_calls() -> dict:
    """``{name: module}`` of every plugin function ``patches/mdm.patch`` imports."""
    return {m.group(2): m.group(1) for m in map(IMPORT.match, PATCH.read_text().splitlines()) if m}


def _run(script: str) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    env.pop("SMDM_TEXT_CACHE", None)
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], env=env, capture_output=True, text=True,
                         check=True, timeout=300).stdout
    return json.loads(out.strip().splitlines()[-1])


COUNT = "sorted(m for m in sys.modules if m == 'smdm_plugin' or m.startswith('smdm_plugin.'))"


def test_a_flag_off_run_loads_only_what_the_options_need():
    calls = _patch_calls()
    assert {"install_hooks", "add_compile_options", "add_sparse_options", "sparsify_mdm"} <= set(calls)
    seen = _run(f"""
        import argparse, importlib, json, sys
        calls = {calls!r}
        def call(name, *a):
            return getattr(importlib.import_module(calls[name]), name)(*a)
        seen = {{}}
        call("install_hooks")                                  # train/train_mdm.py, at import
        seen["import"] = {COUNT}
        parser = argparse.ArgumentParser()
        call("add_compile_options", parser.add_argument_group("base"))
        call("add_sparse_options", parser.add_argument_group("model"))
        args = parser.parse_args([])                           # flag off
        seen["parse"] = {COUNT}
        import torch
        model = torch.nn.Linear(3, 3)
        before = [p.detach().clone() for p in model.parameters()]
        assert call("sparsify_mdm", model, args, None, None) is model
        assert all(torch.equal(a, b) for a, b in zip(before, model.parameters())) and not vars(model).get("_smdm_state")
        seen["build"] = {COUNT}
        print(json.dumps(seen))
    """)
    config_alone = set(_run(f"import json, sys, smdm_plugin.core.config; print(json.dumps({COUNT}))"))
    # the hooks' module, its family's package and the family's one registration (names, no torch)
    family = calls["install_hooks"].rsplit(".", 1)[0]
    registration = {"smdm_plugin.adapters", "smdm_plugin.adapters.families", "smdm_plugin.core",
                    "smdm_plugin.core.registry"}
    assert set(seen["import"]) == {"smdm_plugin", "smdm_plugin.families", family, calls["install_hooks"]} | registration, \
        seen["import"]
    # the options: their modules and the config they describe (whatever it imports), nothing else
    options = {calls["add_sparse_options"].rsplit(".", 1)[0], calls["add_compile_options"].rsplit(".", 1)[0],
               calls["add_sparse_options"], calls["add_compile_options"]}
    assert set(seen["parse"]) == config_alone | options | set(seen["import"]), \
        sorted(set(seen["parse"]) - config_alone - options - set(seen["import"]))
    # building the model: the entry point itself, which returns at once (nothing of what runs sparse)
    extra = set(seen["build"]) - set(seen["parse"])
    assert extra <= {"smdm_plugin.families.mdm.upstream", "smdm_plugin.families.mdm.upstream_text",
                     "smdm_plugin.integrations.checkouts", "smdm_plugin.integrations._hooks"}, sorted(extra)


def test_sparse_settings_without_the_flag_are_refused_not_dropped():
    """``--sparse_reduction 0.5`` without ``--sparse``: 0.10.6 trained dense and dropped it; now one line
    naming the option, exit status 2 (the sMDM-stella ``--sparse_text_encoder`` applies to dense runs)."""
    calls = _patch_calls()
    script = f"""
        import argparse, importlib, torch
        calls = {calls!r}
        def call(name, *a):
            return getattr(importlib.import_module(calls[name]), name)(*a)
        parser = argparse.ArgumentParser()
        call("add_compile_options", parser.add_argument_group("base"))
        call("add_sparse_options", parser.add_argument_group("model"))
        args = parser.parse_args(ARGV)
        call("sparsify_mdm", torch.nn.Linear(3, 3), args, None, None)
        print("built")
        """
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    run = lambda argv: subprocess.run([sys.executable, "-c", textwrap.dedent(script.replace("ARGV", repr(argv)))],
                                      env=env, capture_output=True, text=True, timeout=300)  # noqa: E731
    r = run(["--sparse_reduction", "0.5", "--sparse_fsq", "false"])
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip() == ("error: argument --sparse_reduction (and --sparse_fsq): has no effect without --sparse "
                                "(this run is dense); add --sparse, or leave it out")
    r = run(["--sparse_reduction", "0.8"])             # the default, given: nothing is dropped
    assert r.returncode == 0 and r.stdout.strip() == "built", r.stderr
