"""Writing files safely: atomically (a temporary file in the same folder, then ``os.replace``), and
never over something that exists unless asked (``overwrite=True``; the CLI's ``--overwrite``).

``atomic_open`` / ``atomic_write_text`` / ``atomic_write_json`` are implemented in
:mod:`smdm_plugin.core.atomic` (``SparseConfig.save`` needs them, and ``core`` imports nothing
else of the package); import them from here. :func:`fingerprint_files`: a hash of files' names,
sizes and contents (the data fingerprint of a cached result).
"""
from __future__ import annotations

import hashlib
import os
from typing import Iterable

from ..core.atomic import PathLike, atomic_open, atomic_write_json, atomic_write_text

__all__ = ["OutputExistsError", "check_new_file", "check_new_dir", "atomic_open", "atomic_write_text",
           "atomic_write_json", "fingerprint_files"]


class OutputExistsError(FileExistsError):
    """An output file or non-empty folder exists and ``overwrite`` was not given."""


def check_new_file(path: PathLike, overwrite: bool = False, what: str = "output") -> str:
    """``path`` as str; raise :class:`OutputExistsError` when it exists (and not ``overwrite``) or
    is a folder. ``what`` names it in the message (e.g. ``"--out"``)."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise OutputExistsError(f"{what} {path!r} is a folder, expected a file path")
    if os.path.lexists(path) and not overwrite:
        raise OutputExistsError(f"{what} {path!r} exists; pass --overwrite (overwrite=True) to replace it")
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
