"""Writing files safely: atomically (a temporary file in the same folder, then ``os.replace``), and
never over something that exists unless asked (``overwrite=True``; the CLI's ``--overwrite``)."""
from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from typing import Any, Iterator, Union

PathLike = Union[str, "os.PathLike[str]"]


class OutputExistsError(FileExistsError):
    """An output file or non-empty folder exists and ``overwrite`` was not given."""


def check_new_file(path: PathLike, overwrite: bool = False, what: str = "output") -> str:
    """``path`` as str; raise :class:`OutputExistsError` when it exists and not ``overwrite``."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise OutputExistsError(f"{what} {path!r} is a folder, expected a file path")
    if os.path.exists(path) and not overwrite:
        raise OutputExistsError(f"{what} {path!r} exists; pass --overwrite (overwrite=True) to replace it")
    return path


def check_new_dir(path: PathLike, overwrite: bool = False, what: str = "output folder") -> str:
    """Create folder ``path`` if needed; raise :class:`OutputExistsError` when it exists, is not
    empty and not ``overwrite`` (as MDM does for ``--save_dir``)."""
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise OutputExistsError(f"{what} {path!r} exists and is not a folder")
    if os.path.isdir(path) and os.listdir(path) and not overwrite:
        raise OutputExistsError(f"{what} {path!r} exists and is not empty; pass --overwrite "
                                "(overwrite=True) to write into it")
    os.makedirs(path, exist_ok=True)
    return path


@contextmanager
def atomic_open(path: PathLike, mode: str = "w", **kwargs: Any) -> Iterator[Any]:
    """Open a temporary file beside ``path`` for writing; on success it replaces ``path`` in one
    step (readers never see a half-written file), on error it is removed."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def atomic_write_text(path: PathLike, text: str) -> str:
    with atomic_open(path, "w") as f:
        f.write(text)
    return os.fspath(path)


def atomic_write_json(path: PathLike, obj: Any, **dump_kwargs: Any) -> str:
    dump_kwargs.setdefault("indent", 2)
    with atomic_open(path, "w") as f:
        json.dump(obj, f, **dump_kwargs)
        f.write("\n")
    return os.fspath(path)
