"""Atomic file replacement: write a temporary file beside the target, then ``os.replace`` it.

Readers never see a half-written file, and an interrupted write (an error, Ctrl-C, a killed
process before the rename) leaves the previous file as it was. The rest of the package uses these
through :mod:`smdm_plugin.io.files`; they live in ``core`` because ``SparseConfig.save`` needs them
and ``core`` imports nothing else of the package.
"""
from __future__ import annotations

import json
import os
import secrets
from contextlib import contextmanager
from typing import IO, Any, Iterator, Union

PathLike = Union[str, "os.PathLike[str]"]


@contextmanager
def atomic_open(path: PathLike, mode: str = "w", **kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing (``mode`` ``"w"`` or ``"wb"``); when the
    block ends without an error it replaces ``path`` in one step, otherwise it is removed.

    The new file gets the permissions a plain ``open(path, "w")`` would give it (``0o666`` minus
    the umask), or those of the file it replaces.
    """
    if mode not in ("w", "wb", "wt"):
        raise ValueError(f"atomic_open: mode must be 'w', 'wt' or 'wb', got {mode!r}")
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{secrets.token_hex(4)}.tmp")
    try:
        perms = os.stat(path).st_mode & 0o7777
    except OSError:
        perms = 0o666  # os.open applies the umask
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), perms)
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(e, OSError) and e.filename is None and e.errno is not None:
            # a failed write (a full disk): name the file it was for
            raise type(e)(e.errno, e.strerror, path) from None
        raise
    _fsync_dir(folder)


def _fsync_dir(folder: str) -> None:
    """Make the rename itself durable where the platform allows it (POSIX); best effort."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_text(path: PathLike, text: str) -> str:
    """Write ``text`` to ``path`` atomically (UTF-8); returns the path."""
    with atomic_open(path, "w", encoding="utf-8") as f:
        f.write(text)
    return os.fspath(path)


def atomic_write_json(path: PathLike, obj: Any, **dump_kwargs: Any) -> str:
    """``json.dump(obj)`` to ``path`` atomically (``indent=2`` unless given, trailing newline)."""
    dump_kwargs.setdefault("indent", 2)
    return atomic_write_text(path, json.dumps(obj, **dump_kwargs) + "\n")
