"""Output folders and the writes into them (io/outdir.py, io/files.py): a failed write (a full disk,
however the writer reports it) is one OSError naming the file; the lock of an output folder appears
whole or not at all; long runs write in --out itself (OutputDir live), short commands swap a complete
folder in. (The readers: tests/io/test_readers.py.)"""
from __future__ import annotations

import builtins
import errno
import json
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import smdm_plugin.support.atomic as atomic
import smdm_plugin.io.outdir as outdir
from smdm_plugin.io.files import atomic_open
from smdm_plugin.io.outdir import MANIFEST, OutputDir, OutputLock, OutputLockedError, lock_path, partial_path

from helpers.commands import TORCH_FULL_DISK  # what torch.save raises when the disk fills under its zip writer


class _FullDiskFile:
    """A real file whose writes fail as on a full disk (ENOSPC, no file name: as Python reports it)."""

    def __init__(self, f):
        self._f = f

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __getattr__(self, name):
        return getattr(self._f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._f.close()


# ------------------------------------------------------------------------------ failed writes
def test_torch_save_on_a_full_disk_is_an_oserror_naming_the_file(tmp_path, monkeypatch):
    def full(obj, f, *a, **k):
        f.write(b"PK\x03\x04")
        raise RuntimeError(TORCH_FULL_DISK)

    monkeypatch.setattr(torch, "save", full)
    monkeypatch.setattr(atomic, "_free_bytes", lambda folder: 0)  # the disk is full
    target = tmp_path / "model.pt"
    with pytest.raises(OSError) as e:
        with atomic_open(target, "wb") as f:
            torch.save({"w": torch.zeros(3)}, f)
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(target)
    assert outdir.describe_os_error(e.value) == f"{target}: No space left on device"
    assert os.listdir(tmp_path) == []  # no temporary file left


def test_torch_writer_failure_with_space_left_still_names_the_file(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "_free_bytes", lambda folder: 10 << 30)
    with pytest.raises(OSError) as e:
        with atomic_open(tmp_path / "m.pt", "wb"):
            raise RuntimeError(TORCH_FULL_DISK)
    assert e.value.filename == str(tmp_path / "m.pt") and "unexpected pos" in e.value.strerror
    # any other RuntimeError inside the block is not a write failure: it passes through unchanged
    with pytest.raises(RuntimeError, match="a bug"):
        with atomic_open(tmp_path / "m.pt", "wb"):
            raise RuntimeError("a bug")


def test_numpy_errno_less_write_failure_names_the_file(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "_free_bytes", lambda folder: 0)
    with pytest.raises(OSError) as e:
        with atomic_open(tmp_path / "Mean.npy", "wb"):
            raise OSError("problem writing element 0")  # numpy's tofile: no errno, no file name
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(tmp_path / "Mean.npy")


# ------------------------------------------------------------------------------ the lock
def _full_disk_open(monkeypatch):
    """Every file opened by io/outdir.py (and os.fdopen anywhere) fails its writes as on a full disk."""
    real_open, real_fdopen = builtins.open, os.fdopen
    monkeypatch.setattr(outdir, "open", lambda *a, **k: _FullDiskFile(real_open(*a, **k)), raising=False)
    monkeypatch.setattr(os, "fdopen", lambda *a, **k: _FullDiskFile(real_fdopen(*a, **k)))


@pytest.mark.parametrize("hard_links", [True, False])
def test_a_lock_that_cannot_be_written_is_not_left_behind(tmp_path, monkeypatch, hard_links):
    """0.4.0 left a 0-byte lock on a full disk, and every later run was refused ("unreadable")."""
    if not hard_links:  # a file system without hard links: O_EXCL, the file removed when its write fails
        def no_link(*a, **k):
            raise OSError(errno.EPERM, "Operation not permitted")

        monkeypatch.setattr(os, "link", no_link)
    out = tmp_path / "run"
    _full_disk_open(monkeypatch)
    with pytest.raises(OSError) as e:
        OutputLock(out, "smdm train").acquire()
    assert e.value.errno == errno.ENOSPC and e.value.filename == lock_path(out)
    assert os.listdir(tmp_path) == []  # no lock, no temporary file
    monkeypatch.setattr(outdir, "open", builtins.open, raising=False)
    monkeypatch.undo()
    with OutputLock(out, "smdm train"):  # the next run goes ahead
        owner = json.loads(Path(lock_path(out)).read_text())
        assert owner["pid"] == os.getpid() and owner["command"] == "smdm train"


def test_the_lock_appears_with_its_content(tmp_path):
    """Created by linking a complete file: a second writer never reads an empty lock."""
    out = tmp_path / "o"
    with OutputLock(out, "a"):
        assert json.loads(Path(lock_path(out)).read_text())["command"] == "a"
        with pytest.raises(OutputLockedError, match="is being written by a"):
            OutputLock(out, "b").acquire()
    assert os.listdir(tmp_path) == []


def test_an_empty_lock_left_by_an_older_version_is_explained(tmp_path):
    out = tmp_path / "o"
    Path(lock_path(out)).write_bytes(b"")
    with pytest.raises(OutputLockedError, match="an older version failed to write it"):
        OutputLock(out, "t").acquire()


def _write_lock(out: Path, **owner) -> Path:
    path = Path(lock_path(out))
    path.write_text(json.dumps({"host": socket.gethostname(), "command": "smdm train", **owner}))
    return path


def _dead_pid() -> int:
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    return dead.pid


def test_a_lock_whose_owner_is_gone_is_named_and_taken_over(tmp_path, capsys):
    out = tmp_path / "o"
    pid = _dead_pid()
    path = _write_lock(out, pid=pid)
    with OutputLock(out, "smdm eval") as lock:
        assert json.loads(path.read_text())["pid"] == os.getpid()  # ours now
        assert lock.took_over == f"smdm eval: took over the stale lock {path} left by smdm train (pid {pid}, no longer running)"
    assert lock.took_over in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


@pytest.mark.skipif(outdir.process_start(os.getpid()) is None, reason="no /proc: a pid's start time is unknown")
def test_a_reused_pid_is_told_apart_by_its_start_time(tmp_path):
    """This process is alive: its pid with another start time is a dead owner whose pid was reused."""
    out = tmp_path / "o"
    path = _write_lock(out, pid=os.getpid(), start="another-boot:12")
    with OutputLock(out, "t") as lock:
        assert "its pid now belongs to another process" in lock.took_over and str(path) in lock.took_over
    _write_lock(out, pid=os.getpid(), start=outdir.process_start(os.getpid()))  # the owner itself: live
    with pytest.raises(OutputLockedError, match=rf"is being written by smdm train \(pid {os.getpid()} on .*; lock "
                                                rf"{re.escape(str(path))}\)"):
        OutputLock(out, "t").acquire()
    assert json.loads(path.read_text())["start"] == outdir.process_start(os.getpid())  # untouched


def test_a_lock_of_another_host_or_without_start_time_is_never_taken_over(tmp_path):
    out = tmp_path / "o"
    _write_lock(out, pid=_dead_pid(), host="elsewhere")  # its pid means nothing here
    with pytest.raises(OutputLockedError, match="is being written by smdm train .* on elsewhere"):
        OutputLock(out, "t").acquire()
    _write_lock(out, pid=os.getpid())  # an older lock without start time, its pid alive: live
    with pytest.raises(OutputLockedError, match="is being written by"):
        OutputLock(out, "t").acquire()


def test_of_two_runs_taking_over_one_stale_lock_only_one_removes_it(tmp_path):
    out = tmp_path / "o"
    stale = _write_lock(out, pid=_dead_pid()).read_bytes()
    with OutputLock(out, "first"):  # took it over; a second run that judged the old content comes late
        assert outdir._remove_if_unchanged(lock_path(out), stale) is False
        assert json.loads(Path(lock_path(out)).read_text())["command"] == "first"  # put back, still held
    assert os.listdir(tmp_path) == []


def test_a_folder_without_a_checkpoint_is_started_over(tmp_path):
    """A resumable command's folder holding only its own files and nothing ``protects`` names (a run
    that failed before its first checkpoint) is not a run to protect; with a checkpoint it is."""
    out = tmp_path / "run"
    kw = dict(command="t", owns=("model*.pt", "log.txt"), resumable=True, protects=("model*.pt",))
    with pytest.raises(RuntimeError):
        with OutputDir(out, **kw):
            (out / "log.txt").write_text("step 0 failed")
            raise RuntimeError("failed at step 0")
    with OutputDir(out, **kw):  # neither --resume nor --overwrite needed
        assert not (out / "log.txt").exists()
        (out / "model1.pt").write_text("1")
    with pytest.raises(outdir.OutputExistsError, match="pass --resume to continue it"):
        OutputDir(out, **kw).open()
    (out / "model1.pt").unlink()
    (out / "notes.txt").write_text("mine")  # not the command's own: not started over silently
    with pytest.raises(outdir.OutputExistsError):
        OutputDir(out, **kw).open()


# ------------------------------------------------------------------------------ live output folders
def test_live_output_dir_writes_in_out_as_it_goes(tmp_path):
    out = tmp_path / "run"
    od = OutputDir(out, command="t", owns=("model*.pt", "log.txt"), resumable=True)
    assert od.live and od.path == str(out)
    with pytest.raises(KeyboardInterrupt):
        with od:
            (out / "model1.pt").write_text("1")  # visible at once, in --out itself
            assert os.path.exists(lock_path(out)) and not os.path.exists(partial_path(out))
            raise KeyboardInterrupt
    # the interrupted run's files stay, listed as the command's own (the manifest's patterns)
    assert (out / "model1.pt").read_text() == "1" and not os.path.exists(lock_path(out))
    assert outdir._own_entries(str(out)) == ["model1.pt"]
    with pytest.raises(outdir.OutputExistsError, match="pass --resume to continue it"):
        OutputDir(out, command="t", owns=("model*.pt", "log.txt"), resumable=True).open()
    (out / "notes.txt").write_text("mine")  # a user's file: carried through --overwrite
    with OutputDir(out, overwrite=True, command="t", owns=("model*.pt", "log.txt"), resumable=True) as od:
        assert not (out / "model1.pt").exists()  # the new run replaces the old one as it goes
        (out / "model2.pt").write_text("2")
    assert json.loads((out / MANIFEST).read_text())["entries"] == ["model2.pt"]
    assert (out / "notes.txt").read_text() == "mine"
    with OutputDir(out, resume=True, command="t", owns=("model*.pt", "log.txt"), resumable=True) as od:
        assert od.resumed_from == str(out)
    assert sorted(os.listdir(tmp_path)) == ["run"]


def test_live_output_dir_continues_a_partial_folder_of_an_older_version(tmp_path):
    out = tmp_path / "run"
    legacy = Path(partial_path(out))
    legacy.mkdir()
    (legacy / "model1.pt").write_text("1")
    with pytest.raises(outdir.OutputExistsError, match="an interrupted run left"):
        OutputDir(out, command="t", owns=("model*.pt",), resumable=True).open()
    with OutputDir(out, resume=True, command="t", owns=("model*.pt",), resumable=True) as od:
        assert (out / "model1.pt").read_text() == "1" and od.resumed_from == str(out)
    assert sorted(os.listdir(tmp_path)) == ["run"]


def test_short_commands_keep_the_all_or_nothing_swap(tmp_path):
    out = tmp_path / "res"
    with OutputDir(out, command="t") as od:
        assert not od.live and od.path == partial_path(out)
        Path(od.path, "a.txt").write_text("1")
        assert not out.exists()
    assert (out / "a.txt").read_text() == "1"
