"""One output folder, written safely: :class:`OutputDir`, used by every command that writes a folder."""
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

from ..support.atomic import _fsync_dir, for_target, write_error
from .files import OutputExistsError, OutputUnwritableError, PathLike, atomic_write_json, check_writable

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
    """Whether process ``pid`` (> 0) exists; True when that cannot be told (another user's process)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (OSError, OverflowError):  # PermissionError: another user's; a pid no system has: not judged
        return True
    return True


def process_start(pid: int) -> Optional[str]:
    """When process ``pid`` started, as a token that differs for a reused pid: Linux
    ``/proc/<pid>/stat``'s starttime (clock ticks since boot) with the boot id; None where unknown
    (no ``/proc``: liveness alone decides, which never mistakes a live owner for a dead one)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
        start = int(stat[stat.rindex(b")") + 2:].split()[19])  # field 22; fields after comm start at 3
    except (OSError, ValueError, IndexError):
        return None
    try:
        with open("/proc/sys/kernel/random/boot_id", encoding="ascii") as f:
            boot = f.read().strip()
    except OSError:
        boot = ""
    return f"{boot}:{start}"


def owner_gone(owner: Mapping[str, Any]) -> Optional[str]:
    """Why the run that wrote lock content ``owner`` (pid, host, start) is certainly gone, or None
    when it may still run (another host, or its pid alive with the same or an unknown start)."""
    pid, host = int(owner["pid"]), str(owner["host"])
    if host != socket.gethostname() or pid <= 0:  # pid 0 / -n: a process group, not an owner
        return None
    if not _pid_alive(pid):
        return "no longer running"
    saved, now = owner.get("start"), process_start(pid)
    if saved is not None and now is not None and str(saved) != now:
        return "no longer running; its pid now belongs to another process"
    return None


def _manifest_command(folder: str) -> Optional[str]:
    """The command named in ``folder``'s manifest (what wrote the folder), or None (no manifest,
    unreadable, or written before manifests named it)."""
    try:
        with open(os.path.join(folder, MANIFEST), encoding="utf-8") as f:
            command = json.load(f).get("command")
    except (OSError, ValueError, AttributeError):
        return None
    return command if isinstance(command, str) else None


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
            named = write_error(e, path) or for_target(e, tmp, path)
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
    """The lock of output folder ``out`` for one run (``.<name>.lock`` beside it, created atomically,
    with pid, host, start time and command); a context manager. A held lock is
    :class:`OutputLockedError` naming the owner and the lock file; a stale one (:func:`owner_gone`)
    is taken over, and the takeover is said on stderr (``took_over``: that line, else None)."""

    def __init__(self, out: PathLike, command: str = "smdm", what: str = "--out") -> None:
        self.out = os.path.abspath(os.fspath(out))
        self.path, self.command, self.what = lock_path(self.out), command, what
        self.held = False
        self.took_over: Optional[str] = None

    def _shown(self) -> str:
        rel = os.path.relpath(self.out)
        return self.out if rel.startswith("..") else rel

    def acquire(self) -> "OutputLock":
        if self.held:
            return self
        check_writable(self._shown(), self.what)    # the folder the lock goes in takes new files
        try:
            os.makedirs(os.path.dirname(self.path), exist_ok=True)
        except OSError as e:
            raise OutputUnwritableError(f"{self.what} {self._shown()!r} cannot be created: "
                                        f"{describe_os_error(e)}") from None
        info = {"pid": os.getpid(), "host": socket.gethostname(), "start": process_start(os.getpid()),
                "command": self.command, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        data = json.dumps(info).encode()
        try:
            _create_with_content(self.path, data, _LockExists)
        except _LockExists:
            stale = self.stale()
            if stale is None or not _remove_if_unchanged(self.path, stale[0]):
                raise OutputLockedError(self.message()) from None
            _create_with_content(self.path, data, lambda: OutputLockedError(self.message()))
            self.took_over = f"{self.command}: took over the {stale[1]}"
            print(self.took_over, file=sys.stderr)
        self.held = True
        _HELD.add(self)
        return self

    def _owner(self) -> "tuple[bytes, Optional[dict]]":
        """The lock file's bytes and its content (None when unreadable); ``FileNotFoundError`` when absent."""
        with open(self.path, "rb") as f:
            raw = f.read()
        try:
            owner = json.loads(raw.decode("utf-8"))
            int(owner["pid"]), str(owner["host"])
            return raw, owner
        except (ValueError, KeyError, TypeError):
            return raw, None

    def stale(self) -> "Optional[tuple[bytes, str]]":
        """``(the lock's bytes, a description naming it and its owner)`` when a lock is there and its
        owner is gone (:func:`owner_gone`); else None."""
        try:
            raw, owner = self._owner()
        except OSError:
            return None
        why = owner_gone(owner) if owner is not None else None
        if why is None:
            return None
        return raw, f"stale lock {self.path} left by {owner.get('command', '?')} (pid {owner['pid']}, {why})"

    def message(self) -> str:
        """Why the folder cannot be locked: who holds it, naming the lock file."""
        shown = self._shown()
        try:
            _, owner = self._owner()
        except OSError:
            owner = None
        if owner is None:
            return (f"{self.what} {shown!r} is locked by {self.path} (unreadable: another run may be starting, or "
                    "an older version failed to write it); if none is starting, remove that file and run again")
        pid, host, cmd = int(owner["pid"]), str(owner["host"]), str(owner.get("command", "?"))
        return (f"{self.what} {shown!r} is being written by {cmd} (pid {pid} on {host}; lock {self.path}); wait for "
                f"it or pick another {self.what}")

    def release(self) -> None:
        if self.held:
            try:
                os.unlink(self.path)
            except OSError:
                pass
            self.held = False
            _HELD.discard(self)

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()


class _LockExists(Exception):
    """The lock file is there (whose it is is decided afterwards)."""


#: the locks this process holds (released by :func:`release_held_locks` on a forced exit)
_HELD: "set[OutputLock]" = set()


def release_held_locks() -> None:
    """Release every lock this process holds (before a forced exit that skips the ``with`` blocks)."""
    for lock in list(_HELD):
        lock.release()


def _remove_if_unchanged(path: str, content: bytes) -> bool:
    """Remove the lock ``path`` if it still holds ``content`` (the stale lock that was judged), so that
    of two runs taking over the same stale lock only one removes it: the lock is renamed aside (one
    rename wins), checked, and put back when it turns out to be another run's new lock."""
    aside = f"{path}.{os.getpid()}.{secrets.token_hex(4)}.stale"
    try:
        os.rename(path, aside)
    except FileNotFoundError:
        return True  # removed meanwhile: try to create it
    try:
        with open(aside, "rb") as f:
            same = f.read() == content
        if not same:  # another run's new lock: back where it was
            try:
                os.link(aside, path)
            except FileExistsError:
                pass
            except OSError:  # no hard links here
                os.rename(aside, path)
        return same
    finally:
        try:
            os.unlink(aside)
        except OSError:
            pass


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
                 what: str = "--out", live: Optional[bool] = None, protects: Optional[Sequence[str]] = None) -> None:
        self.out = os.path.abspath(os.fspath(out))
        self.protects = None if protects is None else tuple(protects)
        self._start_over = False
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
        """Every refusal that needs no writing: overlap, a live lock, a file where the folder belongs,
        a non-empty folder without ``overwrite``/``resume`` (unless it holds only the command's own
        files and nothing ``protects`` names), foreign files the command would replace."""
        shown = self._shown()
        check_no_overlap(self.out, self.inputs, self.what)
        stale = self.lock.stale()
        if stale is None and os.path.lexists(self.lock.path) and not self.lock.held:
            raise OutputLockedError(self.lock.message())
        if os.path.lexists(self.out) and not os.path.isdir(self.out):
            raise OutputExistsError(f"{self.what} {shown!r} exists and is not a folder")
        check_writable(shown, self.what)             # beside it: the lock (and the partial folder)
        if os.path.isdir(self.out):
            check_writable(shown, self.what, inside=True)   # in it: the run's files
        existing = _listing(self.out) if os.path.isdir(self.out) else []
        own = (_own_entries(self.out) or []) if existing else []
        other = _manifest_command(self.out) if existing else None
        if other is not None and other != self.command and (self.resume or not self.overwrite):
            # another command's output (its files are not this command's to replace or continue)
            raise OutputExistsError(
                f"{self.what} {shown!r} holds the output of {other}, not " + (
                    f"a run of {self.command} to resume; pick another {self.what}" if self.resume else
                    f"of {self.command}; pass --overwrite (overwrite=True) to replace it, or pick another {self.what}"))
        if existing and not (self.overwrite or self.resume):
            if self.resumable and own and set(existing) <= set(own) and not self._protected(own):
                self._start_over = True  # a run that failed before its first checkpoint: nothing to keep
            elif self.resumable and own:
                lock = f"; either takes over the {stale[1]}" if stale else ""
                raise OutputExistsError(f"{self.what} {shown!r} holds a run of {self.command} (interrupted or "
                                        f"finished); pass --resume to continue it, --overwrite to start over{lock}")
            else:
                raise OutputExistsError(f"{self.what} {shown!r} exists and is not empty; pass --overwrite "
                                        "(overwrite=True) to write into it")
        if existing:
            clash = sorted(n for n in set(existing) - set(own) if n != MANIFEST
                           and any(fnmatch.fnmatchcase(n, p) for p in self.owns))
            if clash and self.owns != ("*",):
                raise OutputExistsError(
                    f"{self.what} {shown!r} holds {', '.join(clash[:5])}, which this command writes but did not "
                    f"write there (no {MANIFEST} lists it); move it away or pick another {self.what}")

    def _protected(self, own: Sequence[str]) -> bool:
        """Whether the own entries ``own`` hold one that makes the folder a run to protect."""
        if self.protects is None:
            return True
        return any(fnmatch.fnmatchcase(n, p) for n in own for p in self.protects)

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
        if existed and (self.overwrite or self._start_over) and not self.resume:
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
