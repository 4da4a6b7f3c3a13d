"""Writing files safely: atomically (a temporary file in the same folder, then ``os.replace``), and
never over something that exists unless asked (``overwrite=True``; the CLI's ``--overwrite``), and
never after a run whose output cannot be written (:func:`check_writable`, before the run).

``atomic_open`` / ``atomic_write_text`` / ``atomic_write_json`` are implemented in
:mod:`smdm_plugin.support.atomic` (``SparseConfig.save`` needs them, and ``core`` imports nothing
else of the package); import them from here. :func:`fingerprint_files`: a hash of files' names,
sizes and contents (the data fingerprint of a cached result).
"""
from __future__ import annotations

import hashlib
import os
import secrets
from typing import Dict, Iterable, List, Mapping

from ..support.atomic import PathLike, atomic_open, atomic_write_json, atomic_write_text

__all__ = ["OutputExistsError", "OutputUnwritableError", "check_writable", "check_new_file", "check_new_dir",
           "atomic_open", "atomic_write_text", "atomic_write_json", "fingerprint_files", "file_digests",
           "digests_fingerprint", "describe_changes"]


class OutputExistsError(FileExistsError):
    """An output file or non-empty folder exists and ``overwrite`` was not given."""


class OutputUnwritableError(OutputExistsError):
    """An output path this process cannot create or write: refused before anything is written, and
    reported as the other refusals (one line; the CLI exits 2)."""


def check_writable(path: PathLike, what: str = "output", inside: bool = False) -> None:
    """Raise :class:`OutputUnwritableError` unless a file can be created in ``path``'s folder (``inside``:
    in the folder ``path`` itself) or, where that folder does not exist yet, in the nearest folder above
    it (where the missing ones would be made): probed by creating and removing a temporary file there
    (a run killed in between leaves a ``.smdm-probe.*.tmp`` that listings ignore). ``what`` names
    ``path`` in the message."""
    shown = os.fspath(path)
    folder = os.path.abspath(shown) if inside else os.path.dirname(os.path.abspath(shown))
    while not os.path.isdir(folder):
        if os.path.lexists(folder):
            raise OutputUnwritableError(f"{what} {shown!r} cannot be created: {folder!r} is a file, not a folder")
        parent = os.path.dirname(folder)
        if parent == folder:                        # a root that is no folder (a Windows drive that is not there)
            raise OutputUnwritableError(f"{what} {shown!r} cannot be created: {folder!r} does not exist")
        folder = parent
    probe = os.path.join(folder, f".smdm-probe.{secrets.token_hex(4)}.tmp")
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as e:
        raise OutputUnwritableError(f"{what} {shown!r} cannot be written: {folder!r} takes no new file "
                                    f"({e.strerror or e})") from None
    os.close(fd)
    try:
        os.unlink(probe)
    except OSError:
        pass


def check_new_file(path: PathLike, overwrite: bool = False, what: str = "output") -> str:
    """``path`` as str; raise :class:`OutputExistsError` when it exists (and not ``overwrite``) or
    is a folder, :class:`OutputUnwritableError` when it cannot be written (:func:`check_writable`).
    ``what`` names it in the message (e.g. ``"--out"``)."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise OutputExistsError(f"{what} {path!r} is a folder, expected a file path")
    if os.path.lexists(path) and not overwrite:
        raise OutputExistsError(f"{what} {path!r} exists; pass --overwrite (overwrite=True) to replace it")
    check_writable(path, what)
    return path


def check_new_dir(path: PathLike, overwrite: bool = False, what: str = "output folder") -> str:
    """Create folder ``path`` if needed; raise :class:`OutputExistsError` when it exists, is not
    empty and not ``overwrite`` (as MDM does for ``--save_dir``), or when it is a file."""
    path = os.fspath(path)
    if os.path.lexists(path) and not os.path.isdir(path):
        raise OutputExistsError(f"{what} {path!r} exists and is not a folder")
    if os.path.isdir(path) and os.listdir(path) and not overwrite:
        raise OutputExistsError(f"{what} {path!r} exists and is not empty; pass --overwrite "
                                "(overwrite=True) to write into it")
    os.makedirs(path, exist_ok=True)
    return path


def fingerprint_files(root: str, paths: Iterable[str]) -> str:
    """sha256 (first 16 hex digits) over the relative names, sizes and contents of ``paths``
    (files below ``root``), in sorted order: equal iff the same data, wherever it was copied to."""
    h = hashlib.sha256()
    for p in sorted(set(os.path.abspath(p) for p in paths)):
        rel = os.path.relpath(p, root)
        h.update(f"{rel}\0{os.path.getsize(p)}\0".encode())
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()[:16]


def file_digests(root: str, paths: Iterable[str]) -> Dict[str, str]:
    """Relative name (``/``-separated, below ``root``) -> sha256 of the content (first 16 hex
    digits) of each of ``paths``: what :func:`describe_changes` compares."""
    out: Dict[str, str] = {}
    for p in sorted(set(os.path.abspath(p) for p in paths)):
        h = hashlib.sha256()
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        out[os.path.relpath(p, root).replace(os.sep, "/")] = h.hexdigest()[:16]
    return out


def digests_fingerprint(digests: Mapping[str, str]) -> str:
    """One hash (16 hex digits) of a :func:`file_digests` map: equal iff the same files with the
    same contents, wherever the folder was copied to."""
    h = hashlib.sha256()
    for name in sorted(digests):
        h.update(f"{name}\0{digests[name]}\0".encode())
    return h.hexdigest()[:16]


def describe_changes(saved: Mapping[str, str], now: Mapping[str, str], limit: int = 5) -> str:
    """What differs between two :func:`file_digests` maps, in words: ``changed: a.npy, b.npy;
    added: c.npy; removed: d.npy`` (at most ``limit`` names each, then a count)."""
    groups = (("changed", sorted(n for n in saved if n in now and saved[n] != now[n])),
              ("added", sorted(n for n in now if n not in saved)),
              ("removed", sorted(n for n in saved if n not in now)))
    parts: List[str] = []
    for what, names in groups:
        if names:
            more = f" and {len(names) - limit} more" if len(names) > limit else ""
            parts.append(f"{what}: {', '.join(names[:limit])}{more}")
    return "; ".join(parts) or "no file differs"
