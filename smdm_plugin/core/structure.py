"""A counter of module registrations: what a structure cached per model is checked against."""
from __future__ import annotations

from typing import Optional

import torch.nn as nn

__all__ = ["structure_version"]

#: bumped whenever any module registers a submodule, parameter or buffer (torch's global
#: registration hooks): a layout cached against it is rebuilt after one
_STRUCTURE = [0]


def _registered(*args) -> None:
    _STRUCTURE[0] += 1


_HOOKS = ("register_module_module_registration_hook", "register_module_parameter_registration_hook",
          "register_module_buffer_registration_hook")
_WATCHED = all(hasattr(nn.modules.module, h) for h in _HOOKS)   # torch >= 2.1 (else: rebuilt per call)
if _WATCHED:
    for _hook in _HOOKS:
        getattr(nn.modules.module, _hook)(_registered)


def structure_version() -> Optional[int]:
    """The number of module registrations so far in this process, or None where torch cannot tell
    (before 2.1: rebuild at every use)."""
    return _STRUCTURE[0] if _WATCHED else None
