"""The package layout: dependencies point one way, old import paths still work (and warn), the
public API resolves. See docs/architecture.md."""
import ast
import importlib
import json
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import smdm_plugin

PKG = Path(smdm_plugin.__file__).resolve().parent

# layer -> the layers it may import from (itself included)
ALLOWED = {
    "support": {"support"},
    "core": {"core", "support"},
    "reference": {"reference", "core", "support"},
    "io": {"io", "core", "reference", "support"},
    "metrics": {"metrics", "io", "core", "support"},
    "adapters": {"adapters", "core", "io", "support"},
    "runtime": {"runtime", "adapters", "core", "io", "reference", "support"},
    "integrations": {"integrations", "runtime", "adapters", "core", "io", "reference", "metrics", "support"},
    "training": {"training", "runtime", "adapters", "core", "io", "reference", "metrics", "support"},
    "families": {"families", "training", "integrations", "runtime", "adapters", "core", "io", "reference", "metrics",
                 "support"},
    "apps": {"apps", "families", "training", "integrations", "runtime", "adapters", "core", "io", "reference",
             "metrics", "support"},
}
#: the one name a registry may give to modules above it: the family registry's built-in family
#: packages (imported on its first lookup; each registers itself). Checked by
#: test_the_family_registry_names_only_family_packages, left out of the layer and circle checks.
PLUGIN_LISTS = {"smdm_plugin.adapters.families": "BUILTIN_FAMILIES"}


def layer_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ALLOWED else "<root>"


def module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def is_type_checking(node: ast.AST) -> bool:
    """``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``): imports for type checkers, never run."""
    test = node.test if isinstance(node, ast.If) else None
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def run_time_nodes(tree: ast.AST, type_checking: bool = False):
    """Every node of ``tree`` that runs: module level and inside functions, the bodies of
    ``if TYPE_CHECKING:`` left out (their ``else`` kept) unless ``type_checking``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        if is_type_checking(node) and not type_checking:
            stack.extend(node.orelse)
            continue
        stack.extend(ast.iter_child_nodes(node))


def plugin_list_nodes(tree: ast.AST, name: str) -> set:
    """The ids of the string constants in the module-level assignment to ``PLUGIN_LISTS[name]``."""
    target = PLUGIN_LISTS.get(name)
    ids = set()
    for node in getattr(tree, "body", []):
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == target for t in node.targets):
            ids |= {id(n) for n in ast.walk(node.value) if isinstance(n, ast.Constant)}
    return ids


def resolve(name: str, modules) -> str:
    """The longest prefix of the dotted ``name`` that is a module of the package (``""``: none
    below the root)."""
    parts = name.split(".")
    for i in range(len(parts), 1, -1):
        if ".".join(parts[:i]) in modules:
            return ".".join(parts[:i])
    return ""


DOTTED = re.compile(r"smdm_plugin(\.[A-Za-z_]\w*)+(:[A-Za-z_]\w*)?")
#: a module named relatively, ``".plan_triton"`` (``importlib.import_module(name, __package__)``)
RELATIVE = re.compile(r"(\.+)([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)(:[A-Za-z_]\w*)?")


def imports_in(source: str, name: str, is_package: bool, modules, type_checking: bool = False, plugins: bool = False):
    """``(line, module)`` for every module of the package that the module ``name`` loads at run
    time: import statements (module level and inside functions, not under ``if TYPE_CHECKING:``
    unless ``type_checking``), ``importlib.import_module`` / ``__import__`` of a name, and strings
    that name a module (a registry importing its entries by dotted name,
    ``"smdm_plugin.apps.train:main"``; a module of the same package named relatively,
    ``".plan_triton"``). The names in a :data:`PLUGIN_LISTS` entry are left out (only they with
    ``plugins``)."""
    package = name if is_package else name.rsplit(".", 1)[0]
    tree = ast.parse(source)
    docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                  if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
                  and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    listed = plugin_list_nodes(tree, name)
    for node in run_time_nodes(tree, type_checking):
        if (id(node) in listed) != plugins:
            continue
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("smdm_plugin."):
                    yield node.lineno, resolve(a.name, modules) or a.name
                elif a.name == "smdm_plugin":
                    yield node.lineno, "smdm_plugin"
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target != "smdm_plugin" and not target.startswith("smdm_plugin."):
                continue
            for a in node.names:   # `from . import x`: the names are modules
                sub = f"{target}.{a.name}"
                yield node.lineno, sub if sub in modules else (resolve(target, modules) or target)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            if DOTTED.fullmatch(node.value):   # importlib.import_module / __import__ / a registry's name
                target = resolve(node.value.split(":")[0], modules)
                if target:
                    yield node.lineno, target
            elif RELATIVE.fullmatch(node.value):   # import_module(".x", __package__)
                m = RELATIVE.fullmatch(node.value)
                base = package.split(".")
                target = ".".join(base[:len(base) - len(m.group(1)) + 1] + [m.group(2)])
                if target in modules:
                    yield node.lineno, target


MODULES = {module_name(p): p for p in PKG.rglob("*.py")}


def imports_of(path: Path, type_checking: bool = False, plugins: bool = False):
    """Every smdm_plugin module a file of the package loads at run time (see :func:`imports_in`)."""
    return imports_in(path.read_text(), module_name(path), path.name == "__init__.py", MODULES, type_checking,
                      plugins)


def layer_violations(name: str, edges) -> list:
    """``edges`` (``(line, target)``) of module ``name`` that go against the layer order."""
    src_layer = layer_of(name)
    bad = []
    if src_layer == "<root>":
        return bad
    for line, target in edges:
        dst = layer_of(target)
        if dst == "<root>":
            if target not in ("smdm_plugin", "smdm_plugin.__version__"):
                bad.append(f"{name}:{line} imports {target} (the package root)")
        elif dst not in ALLOWED[src_layer]:
            bad.append(f"{name}:{line}: {src_layer} -> {dst} ({target})")
    return bad


def import_cycles(graph) -> list:
    """The import circles of ``graph`` (module -> modules it loads): each strongly connected
    component of more than one module (or a module loading itself), sorted."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(v):   # Tarjan, iterative over each node's successors
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph.get(v, ()):
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def package_graph(type_checking: bool = True):
    """module -> the package modules it loads at run time, and (``type_checking``) those it names
    for type checkers (``if TYPE_CHECKING:``: a static circle is one too); the root package left
    out (it loads its public names lazily, on first use)."""
    return {name: {t for _, t in imports_of(path, type_checking) if t in MODULES and t != "smdm_plugin"}
            for name, path in MODULES.items() if name != "smdm_plugin"}


def test_every_module_is_in_a_layer_folder():
    loose = sorted(p.name for p in PKG.glob("*.py") if p.name not in ("__init__.py", "__main__.py"))
    assert loose == [], f"modules outside the layer folders: {loose}"


def test_dependencies_point_one_way():
    """Every import (also inside functions, by ``importlib`` / ``__import__``, or by a registry's
    dotted name) goes down the layer order."""
    bad = []
    for name, path in sorted(MODULES.items()):
        bad += layer_violations(name, imports_of(path))
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)


#: circles owned by another part of issue 31 (apps/ablate: `study` imports the package, whose run
#: imports `study` inside a function); remove the entry with the circle
KNOWN_CIRCLES: set = set()


def test_no_import_circle():
    """No module loads, directly or through others, a module that loads it: also not at run time
    (an import inside a function, ``importlib``, a module named relatively for
    ``import_module(name, __package__)``), which the layer check alone does not see when the two
    modules sit in one layer; and not for type checkers (``if TYPE_CHECKING:``)."""
    cycles = [c for c in import_cycles(package_graph()) if frozenset(c) not in KNOWN_CIRCLES]
    assert not cycles, "import circles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_the_checks_see_run_time_imports():
    """The checks above see what a reading of module-level imports misses: the 0.6 back-edge
    (io/checkpoint_files.py loading the adapters by name inside a function, a circle with
    adapters/checkpoint.py), ``__import__``, a registry's dotted name, a function-level ``from``;
    and they leave out what never runs (``if TYPE_CHECKING:``)."""
    old_io = ("def default_preparer():\n"
              "    import importlib\n"
              "    importlib.import_module('smdm_plugin.adapters')\n")
    edges = list(imports_in(old_io, "smdm_plugin.io.checkpoint_files", False, MODULES))
    assert edges == [(3, "smdm_plugin.adapters")]
    assert layer_violations("smdm_plugin.io.checkpoint_files", edges) == [
        "smdm_plugin.io.checkpoint_files:3: io -> adapters (smdm_plugin.adapters)"]
    graph = {"smdm_plugin.io.checkpoint_files": {"smdm_plugin.adapters"},
             "smdm_plugin.adapters": {"smdm_plugin.adapters.checkpoint"},
             "smdm_plugin.adapters.checkpoint": {"smdm_plugin.io.checkpoint_files"}}
    assert import_cycles(graph) == [sorted(graph)]
    assert import_cycles({"a": {"b"}, "b": set()}) == []
    snippet = ("from typing import TYPE_CHECKING\n"
               "if TYPE_CHECKING:\n"
               "    from ..adapters.state import SparseState\n"
               "def f():\n"
               "    from ..training import trainer\n"
               "    return __import__('smdm_plugin.apps.cli')\n"
               "FAMILIES = Registry('family', builtins='smdm_plugin.families.mdm.model')\n"
               "COMMANDS = {'train': 'smdm_plugin.apps.train:main'}\n")
    assert sorted(imports_in(snippet, "smdm_plugin.core.x", False, MODULES)) == [
        (5, "smdm_plugin.training.trainer"), (6, "smdm_plugin.apps.cli"), (7, "smdm_plugin.families.mdm.model"),
        (8, "smdm_plugin.apps.train")]


def test_the_checks_see_static_circles_and_relative_names():
    """The 0.8 circles the checks did not see: the state, the family protocol and the call naming
    each other for type checkers (adapters/state.py -> family.py -> call.py -> state.py), and the
    plan op loading its Triton kernel by a short name while the kernel imported the op back."""
    state = ("from typing import TYPE_CHECKING\n"
             "if TYPE_CHECKING:\n"
             "    from .state import SparseState\n")
    assert list(imports_in(state, "smdm_plugin.adapters.call", False, MODULES)) == []
    assert list(imports_in(state, "smdm_plugin.adapters.call", False, MODULES, type_checking=True)) == [
        (3, "smdm_plugin.adapters.state")]
    op = "OP = FusedOp('keyframe_plan', cuda=TritonKernel('.plan_triton', 'keyframe_plan_triton', 'plan'))\n"
    assert list(imports_in(op, "smdm_plugin.core.kernels.plan_op", False, MODULES)) == [
        (1, "smdm_plugin.core.kernels.plan_triton")]
    graph = {"smdm_plugin.core.kernels.plan_op": {"smdm_plugin.core.kernels.plan_triton"},
             "smdm_plugin.core.kernels.plan_triton": {"smdm_plugin.core.kernels.plan_op"}}
    assert import_cycles(graph) == [sorted(graph)]
    graph = package_graph()
    assert "smdm_plugin.core.kernels.plan_triton" in graph["smdm_plugin.core.kernels.plan_op"]
    assert "smdm_plugin.core.kernels.plan_op" not in graph["smdm_plugin.core.kernels.plan_triton"]


def test_the_family_registry_names_only_family_packages():
    """The one name that points up: the family registry's built-in family packages
    (:data:`PLUGIN_LISTS`), imported on its first lookup. Each is a package of families/, and each
    imports alone in a fresh interpreter (no half-initialised module) and registers its one spec."""
    for name, const in PLUGIN_LISTS.items():
        named = [t for _, t in imports_of(MODULES[name], plugins=True)]
        assert named and all(t.startswith("smdm_plugin.families.") and t.count(".") == 2 for t in named), named
        code = ("import importlib, json, sys\n"
                f"from {name} import FAMILY_SPECS, {const}\n"
                f"for m in {const}:\n"
                "    importlib.import_module(m)\n"
                "print(json.dumps([s.name for s in FAMILY_SPECS._items.values()]))")
        for module in named:
            out = subprocess.run([sys.executable, "-c", f"import {module}"], capture_output=True, text=True)
            assert out.returncode == 0, out.stderr
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        assert len(json.loads(out.strip().splitlines()[-1])) == len(named)


def test_a_module_name_says_which_one_it_is():
    """No two modules share a file name, except each family's folder (families/<name>/model.py,
    upstream.py, ...: the folder says which) and the names listed here."""
    known = {"data.py", "evaluator.py", "train.py"}
    seen: dict = {}
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(PKG)
        if path.name in ("__init__.py", "__main__.py") or (rel.parts[0] == "families" and len(rel.parts) == 3):
            continue
        seen.setdefault(path.name, []).append(str(rel))
    twice = {n: sorted(p) for n, p in seen.items() if len(p) > 1 and n not in known}
    assert not twice, twice


def test_training_knows_no_upstream_checkout():
    """training/ (the in-package trainer, smdm bench's loop) imports nothing of integrations/: graph
    capture and distributed training are runtime/."""
    bad = [f"{p.relative_to(PKG)}:{line} {t}" for p in sorted((PKG / "training").rglob("*.py"))
           for line, t in imports_of(p) if layer_of(t) in ("integrations", "families")]
    assert not bad, bad


OPTIONAL_EXTRAS = {"triton", "transformers"}   # setup.cfg's [gpu] / [hf]: the core installs without them


@pytest.mark.parametrize("layer", ["support", "core", "reference", "adapters", "io", "metrics", "runtime",
                                   "integrations", "training", "families"])
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
    from smdm_plugin.adapters.families import families
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
        if src == "cli":   # the dispatcher: every command by its name in COMMANDS, loaded on use
            continue
        for line, target in imports_of(path):
            if not target.startswith("smdm_plugin.apps."):
                continue
            dst = command_of(target)
            if dst != src and dst != "common":
                bad.append(f"{path.relative_to(PKG)}:{line} imports {target} (command {src or 'apps'} -> {dst})")
    assert not bad, "commands import each other (move shared code to apps/common/ or training/):\n" + "\n".join(bad)


def test_io_knows_no_model_family():
    """io sits below adapters: io reads and checks checkpoint files, adapters/checkpoint.py's
    ``load_checkpoint`` (the only one) makes the model; io names no adapters module, also not
    inside functions or by name, and keeps no slot the adapters fill in."""
    bad = [f"{p.relative_to(PKG)}:{line} {t}" for p in sorted((PKG / "io").rglob("*.py"))
           for line, t in imports_of(p) if layer_of(t) == "adapters"]
    assert not bad, bad
    from smdm_plugin.io import checkpoint_files as io_checkpoint

    assert not hasattr(io_checkpoint, "load_checkpoint") and not hasattr(io_checkpoint, "register_model_preparer")


def test_public_namespace_is_the_public_api():
    import smdm_plugin

    names = dir(smdm_plugin)
    assert "SparseConfig" in names and "sparsify" in names
    assert not {"Any", "Dict", "List", "importlib", "TYPE_CHECKING", "annotations"} & set(names)
    assert set(names) == set(smdm_plugin.__all__)


@pytest.mark.parametrize("entry", ["smdm_plugin.integrations.launcher", "smdm_plugin.apps.cli"])
def test_smdm_run_starts_without_torch(entry):
    """`smdm run`'s own process only writes a sitecustomize and starts the command (whose Python
    imports torch itself): importing its entry points must not import torch (0.6 did, through the
    priorMDM integration: ~1.4-1.9 s more start-up per `smdm run` command, the extra wall time of a
    sparse DiP `sample.generate` at the harness's size)."""
    code = f"import sys, {entry}\nprint(sorted(m for m in ('torch', 'numpy.linalg') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "torch" not in out.strip().splitlines()[-1], out
