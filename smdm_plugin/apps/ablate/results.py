"""What ``smdm ablate`` and its study pass between their modules, typed: the status of a result
(:class:`Status`), what a run's folder holds (:class:`Cached`, :func:`read_cached`), what the
plan does with it (:class:`Action`, :class:`Planned`).

A *record* stays the JSON object written to disk (``result.json`` / ``failed.json``: the format a
running study resumes from and reports; its keys and their order are unchanged). ``Status`` is a
``str`` enum: ``json`` writes its value (``"ok"``), ``str()`` and f-strings give the value too, and
``Status.OK == "ok"`` holds, so records read back from disk compare equal.
"""
from __future__ import annotations

import json
import os
import traceback
from dataclasses import dataclass
from enum import Enum
from typing import Any, Dict, Optional

from ...io.files import OutputExistsError
from ..common.provenance import differences
from .report import check_record

#: a result record: the JSON object of ``result.json`` / ``failed.json`` (keys: ``name``, ``status``, ...)
Record = Dict[str, Any]

RESULT_FILE, FAILED_FILE = "result.json", "failed.json"
#: the manifest of an ablate / study results folder
MANIFEST = "ablate.json"


class _Text(str, Enum):
    """A ``str`` enum that prints as its value (``"ok"``, not ``"Status.OK"``)."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, spec: str) -> str:
        return format(str(self.value), spec)


class Status(_Text):
    """The status of a report row: a result (``ok``), a recorded failure, or why there are no numbers."""

    OK = "ok"
    FAILED = "failed"
    STALE = "stale"        # a result from another run (other settings, data, version, ...)
    CORRUPT = "corrupt"    # an unreadable result.json
    NOT_RUN = "not run"


class CacheState(_Text):
    """What a run's folder holds against the provenance of the run about to happen."""

    MISSING = "missing"
    CURRENT = "current"    # a result whose provenance matches
    STALE = "stale"
    FAILED = "failed"      # failed.json
    CORRUPT = "corrupt"


class Action(_Text):
    """What the plan does with a variant (or a study's (variant, seed))."""

    RUN = "run"
    KEEP = "keep"
    CONFLICT = "conflict"  # a stale result --resume would have to replace: the run stops before training


@dataclass(frozen=True)
class Cached:
    """What a run's folder holds: ``state``, the record read (``current`` / ``stale`` / ``failed``),
    and for ``stale`` / ``corrupt`` / ``failed`` the reason (what differs, what could not be read)."""

    state: CacheState
    record: Optional[Record] = None
    reason: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "state", CacheState(self.state))  # "current" -> CacheState.CURRENT


@dataclass(frozen=True)
class Planned:
    """One variant of an ablation run: its grid entry, folder, provenance, what the folder holds
    and what this run does with it."""

    variant: Dict[str, Any]
    vdir: str
    provenance: Dict[str, Any]
    cached: Cached
    action: Action


def status_of(record: Optional[Record]) -> Optional[Status]:
    """The :class:`Status` a record states (None: none, or not one of them)."""
    try:
        return Status((record or {}).get("status"))
    except ValueError:
        return None


def is_ok(record: Optional[Record]) -> bool:
    return status_of(record) is Status.OK


def failure_record(name: str, error: BaseException, provenance: Dict[str, Any], *, seed: Optional[int] = None,
                   wall_s: Optional[float] = None) -> Record:
    """The ``failed.json`` record of a run that raised ``error`` (call it inside the ``except``: the
    traceback is the current one). Keys in the order of the format: ``name``, [``seed``], ``status``,
    ``error``, ``traceback``, [``wall_s``], ``provenance``."""
    rec: Record = {"name": name}
    if seed is not None:
        rec["seed"] = seed
    rec.update(status=Status.FAILED, error=f"{type(error).__name__}: {error}", traceback=traceback.format_exc())
    if wall_s is not None:
        rec["wall_s"] = wall_s
    rec["provenance"] = provenance
    return rec


def read_cached(vdir: str, provenance: Dict[str, Any]) -> Cached:
    """Classify what ``vdir`` holds against the ``provenance`` of the run about to happen."""
    res_path, fail_path = os.path.join(vdir, RESULT_FILE), os.path.join(vdir, FAILED_FILE)
    if os.path.exists(res_path):
        try:
            with open(res_path) as f:
                rec = json.load(f)
            if not isinstance(rec, dict) or not is_ok(rec):
                raise ValueError("not a result record")
            bad = check_record(rec)
            if bad is not None:  # e.g. edited by hand: reported as corrupt, never a crash of the report
                raise ValueError(f"not a result record: {bad}")
        except (OSError, ValueError) as e:  # json.JSONDecodeError is a ValueError
            return Cached(CacheState.CORRUPT, None, f"unreadable {res_path} ({type(e).__name__}: {e})")
        why = differences(rec.get("provenance"), provenance)
        return Cached(CacheState.STALE, rec, "; ".join(why)) if why else Cached(CacheState.CURRENT, rec)
    if os.path.exists(fail_path):
        try:
            with open(fail_path) as f:
                rec = dict(json.load(f))
        except (OSError, ValueError, TypeError) as e:
            rec = {"error": f"unreadable {fail_path} ({type(e).__name__})"}
        return Cached(CacheState.FAILED, rec, str(rec.get("error", "")))
    return Cached(CacheState.MISSING)


def row_from_cache(name: str, cached: Cached) -> Record:
    """The report row of a variant not run now."""
    if cached.state is CacheState.CURRENT:
        return {**(cached.record or {}), "name": name, "reused": True}
    if cached.state is CacheState.FAILED:
        return {**(cached.record or {}), "name": name, "status": Status.FAILED}
    if cached.state in (CacheState.STALE, CacheState.CORRUPT):
        return {"name": name, "status": Status(cached.state.value), "reason": cached.reason}
    return {"name": name, "status": Status.NOT_RUN}


def check_out_dir(out: str, resume: bool = False, overwrite: bool = False) -> None:
    """Refuse (:class:`OutputExistsError`) a non-empty ``out`` unless ``resume`` (and it holds
    ablation results) or ``overwrite``."""
    if os.path.lexists(out) and not os.path.isdir(out):
        raise OutputExistsError(f"--out {out!r} exists and is not a folder")
    if overwrite or not os.path.isdir(out) or not os.listdir(out):
        return
    if not any(os.path.exists(os.path.join(out, f)) for f in (MANIFEST, "config.yaml")):
        raise OutputExistsError(f"--out {out!r} is a non-empty folder without smdm ablate results; pick another "
                                "--out, or pass --overwrite to write into it")
    if not resume:
        raise OutputExistsError(f"--out {out!r} already holds ablation results; pass --resume to reuse the "
                                "current ones and run the rest, or --overwrite to run the selected variants "
                                "again (or pick another --out)")
