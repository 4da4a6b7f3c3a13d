"""The package layout: dependencies point one way, old import paths still work (and warn), the
public API resolves. See docs/architecture.md."""
import ast
import importlib
import json
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import smdm_plugin

PKG = Path(smdm_plugin.__file__).resolve().parent

# layer -> the layers it may import from (itself included)
ALLOWED = {
    "core": {"core"},
    "reference": {"reference", "core"},
    "adapters": {"adapters", "core", "io"},
    "io": {"io", "core", "reference"},
    "metrics": {"metrics", "io", "core"},
    "integrations": {"integrations", "adapters", "core", "io", "reference", "metrics"},
    "training": {"training", "integrations", "adapters", "core", "io", "reference", "metrics"},
    "apps": {"apps", "training", "integrations", "adapters", "core", "io", "reference", "metrics"},
}


def layer_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ALLOWED else "<root>"


def module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imports_of(path: Path):
    """Every smdm_plugin module a file imports (module level and inside functions), resolved."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("smdm_plugin"):
                    yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.startswith("smdm_plugin"):
                if node.module is None or target.count(".") == 1 and target.split(".")[1] not in ALLOWED:
                    # `from . import x` / `from .. import core`: the names are the modules
                    for a in node.names:
                        yield node.lineno, f"{target}.{a.name}" if target != "smdm_plugin" else f"smdm_plugin.{a.name}"
                else:
                    yield node.lineno, target


def test_every_module_is_in_a_layer_folder():
    loose = sorted(p.name for p in PKG.glob("*.py") if p.name not in ("__init__.py", "__main__.py"))
    assert loose == [], f"modules outside the layer folders: {loose}"


def test_dependencies_point_one_way():
    bad = []
    for path in sorted(PKG.rglob("*.py")):
        src_layer = layer_of(module_name(path))
        if src_layer == "<root>":
            continue
        for line, target in imports_of(path):
            dst = layer_of(target)
            if dst == "<root>":
                if target not in ("smdm_plugin", "smdm_plugin.__version__") and not target.startswith(
                        "smdm_plugin.__version__"):
                    bad.append(f"{path.relative_to(PKG)}:{line} imports {target} (the package root)")
                continue
            if dst not in ALLOWED[src_layer]:
                bad.append(f"{path.relative_to(PKG)}:{line}: {src_layer} -> {dst} ({target})")
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)


OPTIONAL_EXTRAS = {"triton", "transformers"}   # setup.cfg's [gpu] / [hf]: the core installs without them


@pytest.mark.parametrize("layer", ["core", "reference", "adapters", "io", "metrics", "integrations", "training"])
def test_importing_a_layer_pulls_in_only_what_it_may(layer):
    modules = sorted(module_name(p) for p in (PKG / layer).rglob("*.py"))
    # a module that needs an optional extra (core/kernels/vw_triton.py: triton) is left out where
    # the extra is not installed; any other missing module is an error
    code = ("import importlib, json, sys\n"
            f"for m in {modules!r}:\n"
            "    try: importlib.import_module(m)\n"
            "    except ModuleNotFoundError as e:\n"
            f"        if (e.name or '').split('.')[0] not in {sorted(OPTIONAL_EXTRAS)!r}: raise\n"
            "print(json.dumps(sorted({m.split('.')[1] for m in sys.modules "
            "if m.startswith('smdm_plugin.') and len(m.split('.')) > 1})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    loaded = set(json.loads(out.strip().splitlines()[-1]))
    assert loaded <= ALLOWED[layer], f"importing {layer} loaded {sorted(loaded - ALLOWED[layer])}"


def test_old_flat_module_paths_are_gone():
    """The 0.1 flat paths (smdm_plugin.selection, ...) were aliases until 0.3 (CHANGELOG.md)."""
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("smdm_plugin.selection")


def test_public_api_resolves_every_name():
    for name in smdm_plugin.__all__:
        assert getattr(smdm_plugin, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        smdm_plugin.nope  # noqa: B018


def test_architecture_doc_names_every_command_and_family():
    """docs/architecture.md (the one-page map) lists every `smdm` command and every built-in family."""
    from smdm_plugin import families
    from smdm_plugin.apps.cli import COMMANDS

    doc = (PKG.parent / "docs" / "architecture.md").read_text()
    missing = [c for c in COMMANDS if c not in doc] + [f"`{f.name}`" for f in families() if f"`{f.name}`" not in doc]
    assert not missing, f"docs/architecture.md does not mention {missing}"


def command_of(module: str) -> str:
    """The command a module of apps/ belongs to: ``apps.<x>`` (module or package ``<x>``);
    ``common`` for the shared support package, ``cli`` for the dispatcher, ``""`` for apps/ itself."""
    parts = module.split(".")
    return parts[2] if len(parts) > 2 else ""


def test_commands_do_not_import_each_other():
    """A command (a module or package of apps/: every COMMANDS entry and its pieces, e.g.
    apps/ablate/study.py) imports apps/common/ and the layers below, never another command;
    common imports no command; cli.py reaches the commands only by name (importlib)."""
    from smdm_plugin.apps.cli import COMMANDS

    commands = {t.split(":")[0].split(".")[2] for t, _ in COMMANDS.values() if t.startswith("smdm_plugin.apps.")}
    on_disk = {p.stem if p.suffix == ".py" else p.name for p in (PKG / "apps").iterdir()
               if p.name not in ("__init__.py", "__pycache__", "cli.py", "common")}
    assert on_disk == commands, f"apps/ holds {sorted(on_disk - commands)} that are not commands (shared code: apps/common/)"
    bad = []
    for path in sorted((PKG / "apps").rglob("*.py")):
        src = command_of(module_name(path))
        for line, target in imports_of(path):
            if not target.startswith("smdm_plugin.apps."):
                continue
            dst = command_of(target)
            if dst != src and dst != "common":
                bad.append(f"{path.relative_to(PKG)}:{line} imports {target} (command {src or 'apps'} -> {dst})")
    assert not bad, "commands import each other (move shared code to apps/common/ or training/):\n" + "\n".join(bad)


def test_io_knows_no_model_family():
    """io sits below adapters: loading a sparse checkpoint reaches the families only through the
    hook adapters register (no import of adapters anywhere in io, also not inside functions)."""
    bad = [f"{p.relative_to(PKG)}:{line} {t}" for p in sorted((PKG / "io").rglob("*.py"))
           for line, t in imports_of(p) if layer_of(t) == "adapters"]
    assert not bad, bad
