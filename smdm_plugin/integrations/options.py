"""The options the integrations add to upstream's parsers: ``--sparse`` / ``--sparse_<field>`` (every
:class:`~smdm_plugin.core.config.SparseConfig` field, with a family's own defaults where the
dataclass's cannot apply to it) and ``--sparse_preset`` / ``--sparse_init_from`` (:mod:`.start`).

This is all a flag-off run of a patched checkout loads of the integration while upstream parses its
options (with the config these options describe): what runs lives in the integration modules
(:mod:`.mdm`, :mod:`.start`, ...), imported when the model is built.
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import sys
from typing import Any, Dict, List, Mapping, Optional, Tuple

from ..core.config import SparseConfig

PRESET_OPTION, INIT_OPTION = "--sparse_preset", "--sparse_init_from"
START_GROUP_TITLE = "sparse start (from a dense checkpoint; read from this command line, never from args.json)"

#: a model family's own defaults of ``SparseConfig`` fields that cannot apply to it, and why (in
#: ``--help``): the family's runs use them without a warning; asking for the dataclass's value
#: explicitly still gets the family's warning that it cannot apply
FAMILY_DEFAULTS: Dict[str, Tuple[Dict[str, Any], str]] = {
    "motiondiffuse": ({"fsq": False}, "MotionDiffuse's self-attention is linear: FSQ keys cannot apply"),
}


#: ``--sparse_<field>`` options that apply to a dense run too (the sMDM-stella text encoder), or that
#: an integration sets from the model: never "dropped" without ``--sparse``
APPLY_WITHOUT_SPARSE = ("text_encoder", "diffusion_steps", "prefix_frames", "version", "enabled")


def dropped_sparse_options(args: Any, family: Optional[str] = None) -> List[str]:
    """The ``--sparse_<field>`` options of ``args`` (a run without ``--sparse``) set to another value
    than their default (``family``'s own where it has one): what such a run would drop."""
    defaults, _ = _defaults_of(family)
    norm = lambda v: list(v) if isinstance(v, (list, tuple)) else v      # noqa: E731 (nargs="+": a list)
    out = []
    for f in dataclasses.fields(SparseConfig):
        key = f"sparse_{f.name}"
        if f.name not in APPLY_WITHOUT_SPARSE and hasattr(args, key) \
                and norm(getattr(args, key)) != norm(defaults.get(f.name, f.default)):
            out.append(f"--{key}")
    return out


def refuse_dropped_sparse_options(args: Any, family: Optional[str] = None) -> None:
    """A run without ``--sparse`` given ``--sparse_<field>`` settings: one line naming the first,
    exit status 2 (a dense run would drop them silently)."""
    dropped = dropped_sparse_options(args, family)
    if dropped:
        more = f" (and {', '.join(dropped[1:])})" if len(dropped) > 1 else ""
        sys.stderr.write(f"error: argument {dropped[0]}{more}: has no effect without --sparse (this run is dense); "
                         "add --sparse, or leave it out\n")
        raise SystemExit(2)


def _defaults_of(family: Optional[str]) -> Tuple[Dict[str, Any], str]:
    """``family``'s own defaults and why (none for an unknown family or None)."""
    return FAMILY_DEFAULTS.get(family or "", ({}, ""))


def add_sparse_options(group: Any, family: Optional[str] = None) -> Any:
    """Add ``--sparse`` / ``--sparse_<field>`` to an argparse parser or group (MDM's ``model``
    group, priorMDM's, MotionDiffuse's options parser) with ``family``'s own defaults
    (:data:`FAMILY_DEFAULTS`); on a group (MDM / DiP / priorMDM) also the start options
    (:func:`add_start_options`). Idempotent: the patch and the launcher may both call it."""
    if "--sparse" in getattr(group, "_option_string_actions", {}):
        return group
    SparseConfig.add_argparse_args(group)
    defaults, why = _defaults_of(family)
    for name, value in defaults.items():
        action = group._option_string_actions[f"--sparse_{name}"]
        action.default = value
        action.help = f"{(action.help or '').rsplit(' (default ', 1)[0]} (default {value}: {why})"
    if not isinstance(group, argparse.ArgumentParser):
        add_start_options(group)
    return group


def _parser_of(group: Any) -> Optional[argparse.ArgumentParser]:
    """The parser ``group`` belongs to: itself, or the ``parser`` of the caller that passed it
    (upstream's ``add_model_options(parser)``, patched or hooked)."""
    if isinstance(group, argparse.ArgumentParser):
        return group
    frame = inspect.currentframe()
    try:
        f = frame.f_back if frame is not None else None
        for _ in range(5):
            if f is None:
                break
            candidate = f.f_locals.get("parser")
            if isinstance(candidate, argparse.ArgumentParser) and candidate._actions is group._actions:
                return candidate
            f = f.f_back
    finally:
        del frame
    return None


def add_start_options(group: Any) -> Any:
    """Add ``--sparse_preset`` / ``--sparse_init_from`` (idempotent) in a group of their own on
    ``group``'s parser; when that parser cannot be found, on ``group`` and then taken out of its
    list, so that ``load_args_from_model`` does not restore them either way."""
    if PRESET_OPTION in getattr(group, "_option_string_actions", {}):
        return group
    parser = _parser_of(group)
    target = parser.add_argument_group(START_GROUP_TITLE) if parser is not None else group
    a1 = target.add_argument(PRESET_OPTION, default=None, metavar="NAME",
                             help="sparse settings from a preset (configs/*.yaml or a YAML/JSON path). Sampling / "
                                  "evaluation: wrap a DENSE checkpoint for sparse sampling (zero_shot: every trained "
                                  "weight kept). Training: the run's sparse settings (implies --sparse)")
    a2 = target.add_argument(INIT_OPTION, default=None, metavar="PATH",
                             help="training: start sparse from this DENSE checkpoint (model*.pt): its weights "
                                  "loaded, the recipe's new layers fitted to the dense ones, fresh optimiser")
    if parser is None:
        for a in (a1, a2):
            group._group_actions.remove(a)
    return group


def with_family_defaults(options: Mapping[str, Any], family: Optional[str]) -> Dict[str, Any]:
    """``options`` (``sparse_*`` keys: a parsed namespace's or an options file's) with ``family``'s
    defaults for the keys it lacks (an ``opt.txt`` written before the option existed)."""
    out = dict(options)
    for name, value in _defaults_of(family)[0].items():
        out.setdefault(f"sparse_{name}", value)
    return out
