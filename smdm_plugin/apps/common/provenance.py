"""Provenance of a result: what produced it, so that a cached result is reused only when it would
come out the same (``smdm ablate``'s results folder).

A provenance is a flat JSON mapping. The keys in :data:`MATCH_KEYS` decide whether two runs are
the same: a hash of the settings, a fingerprint of the data files' contents, the package
version, the step count, the seed and the device type. The rest (``settings`` itself, torch
version, data folder, time) is recorded to explain a mismatch and for the reader.
"""
from __future__ import annotations

import hashlib
import json
import time
from typing import Any, Dict, List, Mapping, Optional


#: the keys that must be equal for a cached result to count as current
MATCH_KEYS = ("config_hash", "data_fingerprint", "package_version", "steps", "seed", "device")


def stable_hash(obj: Any) -> str:
    """sha256 (first 16 hex digits) of ``obj`` as canonical JSON (sorted keys, tuples as lists)."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=repr)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def make_provenance(settings: Mapping[str, Any], data_fingerprint: str, steps: int, seed: int, device: str,
                    **extra: Any) -> Dict[str, Any]:
    """A provenance record for a run with these ``settings`` (everything that shapes the result
    but the data), on data with ``data_fingerprint``."""
    import torch

    from ... import __version__

    return {"config_hash": stable_hash(settings), "data_fingerprint": data_fingerprint,
            "package_version": __version__, "steps": int(steps), "seed": int(seed), "device": str(device),
            "torch_version": torch.__version__, "settings": json.loads(json.dumps(settings, default=repr)),
            "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **extra}


def differences(stored: Optional[Mapping[str, Any]], current: Mapping[str, Any]) -> List[str]:
    """Why ``stored`` does not match ``current``, one phrase per reason (empty: they match).
    A changed config hash names the settings that changed (``lr 0.0003 -> 0.0002``)."""
    if not isinstance(stored, Mapping):
        return ["no provenance recorded (written by an older smdm-plugin)"]
    out: List[str] = []
    for key in MATCH_KEYS:
        a, b = stored.get(key), current.get(key)
        if a == b:
            continue
        if key == "config_hash":
            changed = _changed(_flat(stored.get("settings")), _flat(current.get("settings")))
            out.append("settings changed: " + (", ".join(changed) if changed else f"hash {a} -> {b}"))
        elif key == "data_fingerprint":
            out.append(f"data changed (fingerprint {a} -> {b})")
        else:
            out.append(f"{key.replace('_', ' ')} {a} -> {b}")
    return out


def _flat(obj: Any, prefix: str = "") -> Dict[str, Any]:
    if not isinstance(obj, Mapping):
        return {prefix.rstrip("."): obj} if prefix else {}
    out: Dict[str, Any] = {}
    for k, v in obj.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, Mapping) else {f"{prefix}{k}": v})
    return out


def _changed(a: Dict[str, Any], b: Dict[str, Any], most: int = 6) -> List[str]:
    keys = [k for k in sorted(set(a) | set(b)) if a.get(k, "<unset>") != b.get(k, "<unset>")]
    out = [f"{k} {a.get(k, '<unset>')!r} -> {b.get(k, '<unset>')!r}" for k in keys[:most]]
    return out + ([f"... {len(keys) - most} more"] if len(keys) > most else [])
