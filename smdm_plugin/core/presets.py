"""The packaged presets: where they are (the top-level ``configs/``, or ``<prefix>/share/smdm_plugin/configs``
when installed), their names, one loaded by name or path."""
from __future__ import annotations

import os
from typing import List

from .config import SparseConfig
from ..support.values import closest


def preset_dirs() -> List[str]:
    """Where presets are looked up: the project's top-level ``configs/`` (a source checkout, ``pip
    install -e .``), else where a regular install puts it (``<prefix>/share/smdm_plugin/configs``)."""
    import sys

    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    candidates = [os.path.join(os.path.dirname(package), "configs"),
                  os.path.join(sys.prefix, "share", "smdm_plugin", "configs")]
    return [d for d in candidates if os.path.isdir(d)][:1] or candidates[:1]


def preset_names() -> List[str]:
    """The packaged presets (``smdm_humanml``, ``sdip``, ``smotiondiffuse``...)."""
    return sorted(f.rsplit(".", 1)[0] for d in preset_dirs() if os.path.isdir(d) for f in os.listdir(d)
                  if f.endswith((".yaml", ".yml")))


def is_path(name: str) -> bool:
    """Whether a preset argument names a file rather than a packaged preset: it holds a path separator
    or ends in ``.json`` / ``.yaml`` / ``.yml``. A bare name is never looked up in the current folder."""
    seps = [os.sep] + ([os.altsep] if os.altsep else [])
    return any(sep in name for sep in seps) or name.endswith((".json", ".yaml", ".yml"))


def load_preset(name: "str | os.PathLike[str]") -> SparseConfig:
    """A packaged preset by bare name, or a YAML/JSON file by path (:func:`is_path`: a separator or
    a ``.json`` / ``.yaml`` ending; ``./zero_shot`` is the folder or file ``zero_shot`` here).

    Packaged (top-level ``configs/``): ``smdm_paper`` (App. B.1: trans_dec-ready, 50 steps, FSQ
    keys, lambda 0, no dynamic update), ``sdip_paper`` (App. B.2: 10 steps, 20 past + 40 future
    frames), ``smdm_humanml`` and ``sdip`` (earlier measured variants, kept by name),
    ``smotiondiffuse``, ``zero_shot``; ``preset_names()`` lists them all. A ``PathLike`` is a path."""
    if isinstance(name, os.PathLike) or (isinstance(name, str) and is_path(name)):
        path = os.fspath(name)
        if not os.path.exists(path):
            raise FileNotFoundError(f"load_preset: no such file: {path!r}")
        return SparseConfig.load(path)
    if not isinstance(name, str) or not name:
        raise TypeError(f"load_preset: expected a preset name or a path, got {name!r}")
    for d in preset_dirs():
        if os.path.isfile(os.path.join(d, f"{name}.yaml")):
            return SparseConfig.load(os.path.join(d, f"{name}.yaml"))
    names = preset_names()
    here = f"; for the file or folder {name!r} here, pass ./{name}" if os.path.exists(name) else ""
    raise ValueError(f"load_preset: unknown preset {name!r}{closest(name, names)} (packaged: "
                     f"{', '.join(names)}; or pass a YAML/JSON path){here}")
