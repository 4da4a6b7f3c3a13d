"""Atomic file replacement: write a temporary file beside the target, then ``os.replace`` it.

Readers never see a half-written file, and an interrupted write (an error, Ctrl-C, a killed
process before the rename) leaves the previous file as it was. The rest of the package uses these
through :mod:`smdm_plugin.io.files`; they live in ``core`` because ``SparseConfig.save`` needs them
and ``core`` imports nothing else of the package.
"""
from __future__ import annotations

import errno
import json
import os
import secrets
import shutil
from contextlib import contextmanager
from typing import IO, Any, Iterator, Optional, Union

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
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), perms)
    except OSError as e:  # the folder takes no new file
        raise for_target(e, tmp, path) or e from None
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
        named = write_error(e, path)
        if named is not None:  # a failed write (a full disk): one OSError naming the file it was for
            raise named from None
        raise
    _fsync_dir(folder)


def for_target(e: BaseException, tmp: str, path: str) -> Optional[OSError]:
    """``e`` naming ``path``, the file a temporary ``tmp`` was for, when it is an ``OSError`` that names
    ``tmp`` (it could not be created: the user never gave that name); None for anything else."""
    if isinstance(e, OSError) and e.filename == tmp:
        return OSError(e.errno, e.strerror, path)
    return None


#: how torch's zip writer reports a failed write (``torch.save``): a RuntimeError, not an OSError
_TORCH_WRITE_FAILURES = ("inline_container", "PytorchStreamWriter", "unexpected pos")
#: below this many free bytes a failed write is reported as a full disk
_NEARLY_FULL = 1 << 20


def _free_bytes(folder: str) -> Optional[int]:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def write_error(e: BaseException, path: PathLike) -> Optional[OSError]:
    """The ``OSError`` naming ``path`` that a failed write of ``path`` is, or None when ``e`` is not a
    failed write (a bug, Ctrl-C, an OSError that already names its file).

    Writers report a full disk in several ways: ``OSError(ENOSPC)`` without the file name (Python's
    ``write``), an ``OSError`` without an errno (numpy: ``problem writing element 0``, ``0 requested
    and 8 written``) or a ``RuntimeError`` from torch's zip writer (``[enforce fail at
    inline_container.cc:...] unexpected pos ...``). Each becomes ``OSError(errno, reason, path)``;
    the reason is ``No space left on device`` when the errno says so or the disk has less than 1 MiB
    free, else the writer's message.
    """
    path = os.fspath(path)
    if isinstance(e, OSError):
        if e.filename is not None:
            return None
        msg, code = (e.strerror or str(e)), e.errno
    elif isinstance(e, RuntimeError) and any(m in str(e) for m in _TORCH_WRITE_FAILURES):
        msg, code = " ".join(str(e).split()), None
    else:
        return None
    if code is None or code == errno.EIO:
        free = _free_bytes(os.path.dirname(os.path.abspath(path)))
        if free is not None and free < _NEARLY_FULL:
            code = errno.ENOSPC
    if code == errno.ENOSPC:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), path)
    return OSError(code if code is not None else errno.EIO, f"write failed: {msg}", path)


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
