"""The packaged presets: where they are (the top-level ``configs/``, or ``<prefix>/share/smdm_plugin/configs``
when installed), their names, one loaded by name or path."""
from __future__ import annotations

import os
from typing import List

from .config import SparseConfig
from .values import closest


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


def load_preset(name: str) -> SparseConfig:
    """A packaged preset by name or any YAML/JSON path.

    Packaged (top-level ``configs/``): ``smdm_paper`` (App. B.1: trans_dec-ready, 50 steps, FSQ
    keys, lambda 0, no dynamic update), ``sdip_paper`` (App. B.2: 10 steps, 20 past + 40 future
    frames), ``smdm_humanml`` and ``sdip`` (earlier measured variants, kept by name),
    ``smotiondiffuse``; ``preset_names()`` lists them all."""
    if os.path.exists(name):
        return SparseConfig.load(name)
    fname = name if name.endswith((".yaml", ".yml")) else f"{name}.yaml"
    for d in preset_dirs():
        if os.path.isfile(os.path.join(d, fname)):
            return SparseConfig.load(os.path.join(d, fname))
    if os.sep in name or name.endswith((".yaml", ".yml", ".json")):
        raise FileNotFoundError(f"load_preset: no such file: {name!r}")
    names = preset_names()
    raise ValueError(f"load_preset: unknown preset {name!r}{closest(name, names)} (packaged: "
                     f"{', '.join(names)}; or pass a YAML/JSON path)")
