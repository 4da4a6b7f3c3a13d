"""One line in the user's own run (upstream's log) saying that sparse keyframe mode is on and with
which settings: the files beside the checkpoint say it too, but a user reading the training or
sampling log should not have to look there."""
from __future__ import annotations

import sys
import weakref
from typing import Any

from ..adapters.state import sparse_config_of

_ANNOUNCED: "weakref.WeakSet[Any]" = weakref.WeakSet()  # models already announced (nothing put on them)


def announce_sparse_mode(model: Any, family: str) -> None:
    """Print ``smdm: sparse keyframe mode ON (<family>): <settings>`` to stderr once per model
    (the settings are those the model runs with); nothing for a dense model."""
    config = sparse_config_of(model)
    if config is None or model in _ANNOUNCED:
        return
    print(f"smdm: sparse keyframe mode ON ({family}): {config.summary()}", file=sys.stderr, flush=True)
    _ANNOUNCED.add(model)
