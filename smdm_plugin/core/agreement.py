"""Whether a run's ``sparse_*`` options (MDM's ``args.json``, MotionDiffuse's ``opt.txt``) agree with
the ``sparse_config.json`` saved beside the same checkpoint."""
from __future__ import annotations

import dataclasses
import os
from typing import Any, Iterable, Mapping, Optional

from .config import SparseConfig


#: fields an adapter sets from the model when it attaches (a run's command-line value may differ)
SET_WHEN_ATTACHED = ("diffusion_steps", "prefix_frames", "version")


def disagreement(saved: "SparseConfig", options: Mapping[str, Any], config_file: str, options_file: str,
                 ignore: Iterable[str] = SET_WHEN_ATTACHED) -> Optional[str]:
    """None when a run's ``sparse_*`` options (``args.json``, ``opt.txt``: ``options``, with
    ``sparse`` true) agree with its ``sparse_config.json`` (``saved``) on every field they give
    (``ignore`` aside), else a one-line message naming both files and each differing field."""
    try:
        given = SparseConfig.from_args(options)
    except ValueError as e:
        return f"{options_file}: {e}"
    keys = {f.name for f in dataclasses.fields(SparseConfig) if f"sparse_{f.name}" in options} - set(ignore)
    diff = {k: v for k, v in saved.differences(given, ignore=tuple(ignore)).items() if k in keys}
    if not diff:
        return None
    return f"{options_file} and {config_file} disagree: " + "; ".join(
        f"{k}: {os.path.basename(options_file)} {b!r}, {os.path.basename(config_file)} {a!r}" for k, (a, b) in diff.items())


