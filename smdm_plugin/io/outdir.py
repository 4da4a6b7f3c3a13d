"""One output folder, written safely: :class:`OutputDir`, used by every command that writes a folder.

    with OutputDir(args.out, overwrite=args.overwrite, inputs={"--data": args.data}, command="smdm train") as od:
        write_everything_into(od.path)        # a temporary sibling folder
    # here args.out holds the new content, swapped in as one unit

What it guarantees:

* **Outputs never overlap inputs**: ``out`` equal to, inside or containing an input path is refused
  (:class:`OutputOverlapError`) before anything is written, with or without ``overwrite``.
* **One writer per folder**: a lock file ``.<name>.lock`` beside ``out`` (it holds the owner's pid,
  host and command; it appears whole or not at all: written to a temporary file, then hard-linked,
  which fails when the lock exists, as ``O_EXCL`` does). A second writer gets :class:`OutputLockedError`
  naming the folder and the owner. A lock left by a process that no longer runs (same host) is
  reported as stale, never taken over: the user removes it.
* **Replaced as one unit**: the content is written in ``.<name>.partial`` beside ``out`` and
  swapped in by rename when the block ends without an error (on Linux one atomic
  ``renameat2(RENAME_EXCHANGE)``; elsewhere two renames). A reader sees the old folder or the
  new one, never a mix. On an error the partial folder is removed and ``out`` is untouched.
* **Or written as it goes** (``live``, the default of ``resumable`` commands: ``smdm train``,
  ``smdm evaluator train``): the content is written in ``out`` itself, each file atomically, so that
  a long run's checkpoints are visible, loadable and resumable while it runs and after a crash.
* **--overwrite replaces only the command's own files**: each committed folder holds a manifest
  (``.smdm-manifest.json``) of what the command wrote. Other entries of an overwritten folder are
  moved into the new one unchanged; one whose name the command would write itself is refused up
  front (:class:`OutputExistsError`).
* **OS errors name the path**: :func:`describe_os_error` turns an ``OSError`` into one line
  (``smdm``'s top level uses it for every command).
"""
from __future__ import annotations

import ctypes
import errno
import fnmatch
import json
import os
import re
import secrets
import shutil
import socket
import sys
import time
from typing import Any, Callable, List, Mapping, Optional, Sequence

from ..core.atomic import _fsync_dir, write_error
from .files import OutputExistsError, PathLike, atomic_write_json

__all__ = ["OutputDir", "OutputLock", "run_in_output_dir", "OutputLockedError", "OutputOverlapError", "MANIFEST", "check_no_overlap",
           "describe_os_error", "partial_path", "lock_path"]

MANIFEST = ".smdm-manifest.json"


class OutputLockedError(OutputExistsError):
    """Another run holds (or a dead run left) the lock of an output folder."""


class OutputOverlapError(OutputExistsError):
    """An output path is, contains or lies inside an input path."""


def _sibling(out: str, suffix: str) -> str:
    out = os.path.abspath(out)
    return os.path.join(os.path.dirname(out), f".{os.path.basename(out)}.{suffix}")


def lock_path(out: PathLike) -> str:
    """The lock file of output folder ``out`` (beside it: it survives the swap)."""
    return _sibling(os.fspath(out), "lock")


def partial_path(out: PathLike) -> str:
    """The temporary folder where ``out``'s new content is written."""
    return _sibling(os.fspath(out), "partial")


def _within(inner: str, outer: str) -> bool:
    return inner == outer or inner.startswith(outer.rstrip(os.sep) + os.sep)


def check_no_overlap(out: PathLike, inputs: Mapping[str, Optional[PathLike]], what: str = "--out") -> None:
    """Raise :class:`OutputOverlapError` when ``out`` equals, lies inside or contains any input
    path (``{"--data": path, ...}``; None values are skipped). Symlinks are resolved."""
    o = os.path.realpath(os.fspath(out))
    for name, p in inputs.items():
        if p is None:
            continue
        i = os.path.realpath(os.fspath(p))
        if _within(o, i) or _within(i, o):
            rel = "is" if o == i else ("lies inside" if _within(o, i) else "contains")
            raise OutputOverlapError(f"{what} {os.fspath(out)!r} {rel} the input {name} {os.fspath(p)!r}; "
                                     f"pick an output folder apart from the inputs")


def describe_os_error(e: OSError) -> str:
    """One line: the path(s) and the reason (``strerror``), e.g. ``/x/model.pt: No space left on
    device``."""
    reason = e.strerror or (str(e.args[-1]) if e.args else type(e).__name__)
    paths = [p for p in (e.filename, e.filename2) if p is not None]
    where = " -> ".join(p.decode(errors="replace") if isinstance(p, bytes) else
                        os.fspath(p) if isinstance(p, (str, os.PathLike)) else str(p) for p in paths)
    return f"{where}: {reason}" if where else f"{reason} ({type(e).__name__})"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return True
    return True


def _own_entries(folder: str) -> Optional[List[str]]:
    """The top-level names listed in ``folder``'s manifest, or None when it has none (or it is
    unreadable). The manifest of a folder written in place (``live``) also holds the command's name
    ``patterns``: every entry matching one is the command's too (written since the manifest was)."""
    try:
        with open(os.path.join(folder, MANIFEST), encoding="utf-8") as f:
            data = json.load(f)
        names = data["entries"]
        patterns = data.get("patterns", [])
        if (isinstance(names, list) and all(isinstance(n, str) for n in names) and isinstance(patterns, list)
                and all(isinstance(n, str) for n in patterns)):
            if patterns:
                present = [n for n in os.listdir(folder) if any(fnmatch.fnmatchcase(n, p) for p in patterns)]
                names = sorted(set(names) | set(present))
            return names
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return None


_TMP_NAME = re.compile(r"\..+\.[0-9a-f]{8}\.tmp")


def _listing(folder: str) -> List[str]:
    """``folder``'s entries but the manifest and temporary files an interrupted atomic write left."""
    return [n for n in os.listdir(folder) if n != MANIFEST and not _TMP_NAME.fullmatch(n)]


_RENAME_EXCHANGE = 2


def _exchange(a: str, b: str) -> bool:
    """Swap two paths atomically (Linux ``renameat2(RENAME_EXCHANGE)``); False when unsupported."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    AT_FDCWD = -100
    rc = fn(AT_FDCWD, os.fsencode(a), AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP if hasattr(errno, "ENOTSUP") else errno.EINVAL):
        return False
    raise OSError(err, os.strerror(err), a, None, b)


def _create_with_content(path: str, data: bytes, exists: Callable[[], BaseException]) -> None:
    """Create ``path`` holding ``data``, atomically: it appears complete or not at all (``exists()``
    is raised when it is there already). The content is written to a temporary file first and
    hard-linked to ``path`` (``link`` fails when ``path`` exists: the same guarantee as ``O_EXCL``);
    where hard links are not supported, ``O_EXCL`` then write, and the file is removed if the write
    fails. A failed write (a full disk) is an ``OSError`` naming ``path``; nothing is left behind."""
    folder = os.path.dirname(path)
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        try:
            with open(tmp, "xb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        except BaseException as e:
            named = write_error(e, path)
            raise (named if named is not None else e) from None
        try:
            os.link(tmp, path)
            return
        except FileExistsError:
            raise exists() from None
        except OSError as e:
            if e.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.ENOSYS,
                               errno.EMLINK):
                raise
    finally:
        try:
            os.unlink(tmp)
        except OSError:
            pass
    try:  # no hard links here: O_EXCL, and the file removed if its content cannot be written
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        raise exists() from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except BaseException as e:
        try:
            os.unlink(path)
        except OSError:
            pass
        named = write_error(e, path)
        raise (named if named is not None else e) from None


class OutputLock:
    """The lock of output folder ``out`` for one run (``.<name>.lock`` beside it, ``O_EXCL``, with
    pid, host and command); a context manager. A held lock is :class:`OutputLockedError` naming
    the owner; a stale one (its process gone, same host) is reported, never taken over."""

    def __init__(self, out: PathLike, command: str = "smdm", what: str = "--out") -> None:
        self.out = os.path.abspath(os.fspath(out))
        self.path, self.command, self.what = lock_path(self.out), command, what
        self.held = False

    def _shown(self) -> str:
        rel = os.path.relpath(self.out)
        return self.out if rel.startswith("..") else rel

    def acquire(self) -> "OutputLock":
        if self.held:
            return self
        os.makedirs(os.path.dirname(self.path), exist_ok=True)
        info = {"pid": os.getpid(), "host": socket.gethostname(), "command": self.command,
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        _create_with_content(self.path, json.dumps(info).encode(), lambda: OutputLockedError(self.message()))
        self.held = True
        return self

    def message(self) -> str:
        """Why the folder cannot be locked: who holds it, or that the lock is stale."""
        shown = self._shown()
        try:
            with open(self.path, encoding="utf-8") as f:
                owner = json.load(f)
            pid, host, cmd = int(owner["pid"]), str(owner["host"]), str(owner.get("command", "?"))
        except (OSError, ValueError, KeyError, TypeError):
            return (f"{self.what} {shown!r} is locked by {self.path} (unreadable: another run may be starting, or "
                    "an older version failed to write it); if none is starting, remove that file and run again")
        if host == socket.gethostname() and not _pid_alive(pid):
            return (f"{self.what} {shown!r}: stale lock {self.path} left by {cmd} (pid {pid}, no longer running); "
                    "if no other run writes there, remove that file and run again")
        return (f"{self.what} {shown!r} is being written by {cmd} (pid {pid} on {host}); wait for it or pick "
                f"another {self.what}")

    def release(self) -> None:
        if self.held:
            try:
                os.unlink(self.path)
            except OSError:
                pass
            self.held = False

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()


class OutputDir:
    """An output folder written as one unit (or, ``live``, in place), locked for the run, apart from
    the inputs.

    Args:
        out: the folder the command writes.
        overwrite: replace an existing non-empty ``out`` (its own files only; see the module doc).
        inputs: ``{"--data": path, ...}``: paths ``out`` must not overlap.
        command: names the owner in the lock (``"smdm train"``).
        owns: glob patterns of the top-level names the command writes; with ``overwrite``, an entry
            of ``out`` matching one that the folder's manifest does not list is refused up front.
        resumable: keep the partial folder when the block fails (``--resume`` continues from it),
            and refuse to start over one left by an interrupted run unless ``resume`` or ``overwrite``.
        resume: continue: a partial folder of an interrupted run is kept and written further; else
            the new partial folder starts as a copy of ``out``'s own files (a finished run continued).
        what: the option name in messages.
        live: write in ``out`` itself instead of a partial folder (default: ``resumable``; the
            long-running commands): each file appears, atomically, as it is made (a checkpoint is
            visible, loadable and resumable during the run and after a crash). The lock, the overlap
            check and the refusals stay; ``overwrite`` removes the command's own entries of ``out``
            when the run starts (the new run replaces the old one as it goes); a failure leaves
            what was written.

    Attributes: ``path`` (where to write, inside the block), ``out``.
    """

    def __init__(self, out: PathLike, overwrite: bool = False, inputs: Optional[Mapping[str, Optional[PathLike]]] = None,
                 command: str = "smdm", owns: Sequence[str] = ("*",), resumable: bool = False, resume: bool = False,
                 what: str = "--out", live: Optional[bool] = None) -> None:
        self.out = os.path.abspath(os.fspath(out))
        self.overwrite, self.inputs, self.command = overwrite, dict(inputs or {}), command
        self.owns, self.resumable, self.resume, self.what = tuple(owns), resumable, resume, what
        self.live = resumable if live is None else bool(live)
        self.path = self.out if self.live else partial_path(self.out)
        self._created = False
        self.lock = OutputLock(self.out, command, what)
        self._abandoned = False
        self._keep = resumable
        self.resumed_from: Optional[str] = None

    # ------------------------------------------------------------------ checks (nothing written)
    def check(self) -> None:
        """Every refusal that needs no writing: overlap, a file where the folder belongs, a
        non-empty folder without ``overwrite``/``resume``, foreign files the command would replace."""
        shown = self._shown()
        check_no_overlap(self.out, self.inputs, self.what)
        if os.path.lexists(self.out) and not os.path.isdir(self.out):
            raise OutputExistsError(f"{self.what} {shown!r} exists and is not a folder")
        existing = _listing(self.out) if os.path.isdir(self.out) else []
        if existing and not (self.overwrite or self.resume):
            if self.resumable and _own_entries(self.out):
                raise OutputExistsError(f"{self.what} {shown!r} holds a run of {self.command} (interrupted or "
                                        "finished); pass --resume to continue it, --overwrite to start over")
            raise OutputExistsError(f"{self.what} {shown!r} exists and is not empty; pass --overwrite "
                                    "(overwrite=True) to write into it")
        if existing:
            own = set(_own_entries(self.out) or ())
            clash = sorted(n for n in existing if n not in own and n != MANIFEST
                           and any(fnmatch.fnmatchcase(n, p) for p in self.owns))
            if clash and self.owns != ("*",):
                raise OutputExistsError(
                    f"{self.what} {shown!r} holds {', '.join(clash[:5])}, which this command writes but did not "
                    f"write there (no {MANIFEST} lists it); move it away or pick another {self.what}")

    def _shown(self) -> str:
        return self.lock._shown()

    # ------------------------------------------------------------------ enter / exit
    def open(self) -> "OutputDir":
        """Check, lock and prepare the partial folder (``with`` does it too; call it first to
        report a refusal before the block)."""
        if self.lock.held:
            return self
        self.check()
        self.lock.acquire()
        try:
            self._prepare_live() if self.live else self._prepare_partial()
        except BaseException:
            self.lock.release()
            raise
        return self

    def __enter__(self) -> "OutputDir":
        return self.open()

    def _prepare_partial(self) -> None:
        if os.path.lexists(self.path):
            if self.resumable and self.resume:
                self.resumed_from = self.path
                return
            if self.resumable and not self.overwrite:
                raise OutputExistsError(
                    f"{self.what} {self._shown()!r}: an interrupted run left {self.path}; pass --resume to continue "
                    "it, --overwrite to start over, or remove it")
            shutil.rmtree(self.path) if os.path.isdir(self.path) else os.unlink(self.path)
        os.makedirs(self.path)
        if self.resume and os.path.isdir(self.out) and os.listdir(self.out):
            for name in _own_entries(self.out) or ():
                src = os.path.join(self.out, name)
                if os.path.isdir(src):
                    shutil.copytree(src, os.path.join(self.path, name))
                elif os.path.exists(src):
                    shutil.copy2(src, os.path.join(self.path, name))
            self.resumed_from = self.out

    def _patterns(self) -> List[str]:
        return [] if self.owns == ("*",) else list(self.owns)

    def _prepare_live(self) -> None:
        legacy = partial_path(self.out)  # an interrupted run of smdm-plugin <= 0.4 wrote there
        migrated = False
        if os.path.lexists(legacy):
            out_empty = not (os.path.isdir(self.out) and _listing(self.out))
            if self.overwrite:
                shutil.rmtree(legacy) if os.path.isdir(legacy) else os.unlink(legacy)
            elif self.resume and out_empty and os.path.isdir(legacy):
                if os.path.isdir(self.out):
                    shutil.rmtree(self.out)
                os.rename(legacy, self.out)  # continued in --out itself from now on
                migrated = True  # a partial folder holds only the command's own files (no manifest yet)
            else:
                raise OutputExistsError(
                    f"{self.what} {self._shown()!r}: an interrupted run left {legacy}; "
                    + ("pass --resume to continue it (its files move into " + self.what + "), " if out_empty else
                       f"move its files into {self.what} to continue it with --resume, ")
                    + "--overwrite to start over, or remove it")
        existed = os.path.isdir(self.out)
        own = (_listing(self.out) if migrated else (_own_entries(self.out) or [])) if existed else []
        if existed and self.overwrite and not self.resume:
            for name in own:  # the new run replaces the old one as it goes
                p = os.path.join(self.out, name)
                if os.path.isdir(p) and not os.path.islink(p):
                    shutil.rmtree(p)
                elif os.path.lexists(p):
                    os.unlink(p)
            own = []
        if existed:
            for name in os.listdir(self.out):
                if _TMP_NAME.fullmatch(name):  # left by a killed atomic write
                    os.unlink(os.path.join(self.out, name))
        os.makedirs(self.out, exist_ok=True)
        self._created = not existed
        own = [n for n in own if os.path.lexists(os.path.join(self.out, n))]
        if self.resume and own:
            self.resumed_from = self.out
        self._write_manifest(own)

    def _write_manifest(self, entries: Sequence[str]) -> None:
        data: dict = {"command": self.command, "entries": sorted(entries)}
        if self.live and self._patterns():
            data["patterns"] = self._patterns()
        atomic_write_json(os.path.join(self.path, MANIFEST), data)

    def abandon(self, keep: Optional[bool] = None) -> None:
        """Do not commit at the end of the block (the command failed without an exception): ``out``
        stays as it was; the partial folder is kept when ``keep`` (default: ``resumable``), else
        removed."""
        self._abandoned = True
        self._keep = self.resumable if keep is None else keep

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        try:
            if exc_type is None and not self._abandoned:
                self.commit()
            elif self.live:  # what was written stays (each file whole); a folder made for nothing goes
                if self._abandoned and not self._keep and self._created and not _listing(self.out):
                    shutil.rmtree(self.out, ignore_errors=True)
            elif not (self._keep if self._abandoned else self.resumable):
                shutil.rmtree(self.path, ignore_errors=True)
        finally:
            self.lock.release()

    def commit(self) -> None:
        """Write the manifest and swap the partial folder in for ``out`` (foreign entries of an
        existing ``out`` carried over); ``live``: write the manifest of what ``out`` holds now."""
        if self.live:
            self._write_manifest(_own_entries(self.out) or [])
            _fsync_dir(self.out)
            return
        new_entries = sorted(n for n in os.listdir(self.path) if n != MANIFEST)
        atomic_write_json(os.path.join(self.path, MANIFEST), {"command": self.command, "entries": new_entries})
        if os.path.isdir(self.out):
            own = set(_own_entries(self.out) or ()) | {MANIFEST}
            if _own_entries(self.out) is None:  # a folder not written by this mechanism: keep all but clashes
                own = {MANIFEST}
            for name in os.listdir(self.out):
                if name in own or name in new_entries:
                    continue
                os.rename(os.path.join(self.out, name), os.path.join(self.path, name))
            if not _exchange(self.path, self.out):
                old = _sibling(self.out, f"old-{os.getpid()}")
                os.rename(self.out, old)
                try:
                    os.rename(self.path, self.out)
                except BaseException:
                    os.rename(old, self.out)
                    raise
                shutil.rmtree(old, ignore_errors=True)
            else:
                shutil.rmtree(self.path, ignore_errors=True)  # now the old content
        else:
            os.rename(self.path, self.out)
        _fsync_dir(os.path.dirname(self.out))



def open_or_refuse(od: "OutputDir", command: str) -> bool:
    """Open ``od``; a refused output (exists, locked, overlaps an input) is one line on stderr
    (``<command>: error: ...``) and False."""
    try:
        od.open()
    except OutputExistsError as e:
        print(f"{command}: error: {e}", file=sys.stderr)
        return False
    return True


def run_in_output_dir(fn: Callable[[str], int], out: PathLike, overwrite: bool = False,
                      inputs: Optional[Mapping[str, Optional[PathLike]]] = None, command: str = "smdm",
                      **kwargs: Any) -> int:
    """``fn(folder) -> exit status`` writing into an :class:`OutputDir` of ``out``: committed when it
    returns 0, abandoned otherwise. A refused ``out`` (exists, locked, overlaps an input) is one
    line on stderr and exit status 2."""
    od = OutputDir(out, overwrite=overwrite, inputs=inputs, command=command, **kwargs)
    if not open_or_refuse(od, command):
        return 2
    with od:
        status = int(fn(od.path) or 0)
        if status != 0:
            od.abandon()
    return status
