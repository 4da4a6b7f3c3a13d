"""Import hooks of the upstream integrations: a small ``sys.meta_path`` finder that runs a callback
right after a named module executes (:func:`on_import`), and the one way an upstream function is
replaced by our wrapper, once (:func:`wrap_once`).

The integrations' ``install_hooks()`` use both to wrap functions of an upstream module before any
other module imports them by name (``from utils.model_util import ...``).
"""
from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys
from typing import Any, Callable, Dict, List

_CALLBACKS: Dict[str, List[Callable]] = {}


class _Loader(importlib.abc.Loader):
    def __init__(self, inner, name: str) -> None:
        self.inner, self.name = inner, name

    def create_module(self, spec):
        return self.inner.create_module(spec)

    def exec_module(self, module) -> None:
        self.inner.exec_module(module)
        for cb in _CALLBACKS.get(self.name, []):
            cb(module)

    def __getattr__(self, item):  # get_source, is_package, ... of the wrapped loader
        return getattr(self.inner, item)


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path, target=None):
        if fullname not in _CALLBACKS:
            return None
        for finder in sys.meta_path:
            if finder is self or isinstance(finder, _Finder):
                continue
            find = getattr(finder, "find_spec", None)
            if find is None:
                continue
            spec = find(fullname, path, target)
            if spec is not None:
                if spec.loader is not None and hasattr(spec.loader, "exec_module"):
                    spec.loader = _Loader(spec.loader, fullname)
                return spec
        return None


_FINDER = _Finder()


def on_import(module_name: str, callback: Callable) -> None:
    """Call ``callback(module)`` right after ``module_name`` executes (now, if already imported).
    Registering the same callback twice has no effect."""
    cbs = _CALLBACKS.setdefault(module_name, [])
    if callback in cbs:
        return
    cbs.append(callback)
    if _FINDER not in sys.meta_path:
        sys.meta_path.insert(0, _FINDER)
    mod = sys.modules.get(module_name)
    if mod is not None:
        callback(mod)


WRAPPED = "_smdm_wrapped"  # the marker on our wrappers (docs/architecture.md, "State")


def wrap_once(owner: Any, name: str, make: Callable[[Callable], Callable], marker: str = WRAPPED) -> bool:
    """Replace ``owner.<name>`` (a module's function, a class's method) by ``make(original)`` and
    mark the wrapper with ``marker`` so that installing twice (the patch and the launcher, two
    ``install_hooks()`` calls) does not wrap twice. Nothing happens when ``owner`` has no such
    attribute or it already carries ``marker``. ``make`` keeps the original's signature and return
    value (``functools.wraps``). Returns whether it wrapped."""
    original = getattr(owner, name, None)
    if original is None or getattr(original, marker, False):
        return False
    wrapped = make(original)
    setattr(wrapped, marker, True)
    setattr(owner, name, wrapped)
    return True
