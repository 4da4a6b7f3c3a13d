"""io.files / core.atomic: atomic writes (never a half-written file, the old one kept on failure,
the usual permissions) and the refusal to overwrite without being asked."""
import json
import os
import stat
import subprocess
import sys
import textwrap

import pytest

from smdm_plugin.io.files import (OutputExistsError, atomic_open, atomic_write_json, atomic_write_text,
                                  check_new_dir, check_new_file)


def test_atomic_write_replaces_in_one_step(tmp_path):
    p = tmp_path / "r.json"
    atomic_write_json(p, {"a": 1})
    assert json.loads(p.read_text()) == {"a": 1}
    atomic_write_text(p, "héllo\n")
    assert p.read_text(encoding="utf-8") == "héllo\n" and os.listdir(tmp_path) == ["r.json"]
    with atomic_open(tmp_path / "b.bin", "wb") as f:
        f.write(b"\x00\x01")
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
    atomic_write_text(tmp_path / "new" / "deep" / "x.txt", "x")  # folders are created
    assert (tmp_path / "new" / "deep" / "x.txt").read_text() == "x"
    with pytest.raises(ValueError, match="mode must be"):
        with atomic_open(p, "a"):
            pass


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "r.txt"
    p.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_open(p) as f:
            f.write("new, half")
            assert p.read_text() == "old"  # readers see the old file while it is written
            raise RuntimeError("killed")
    assert p.read_text() == "old" and os.listdir(tmp_path) == ["r.txt"]
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C too
        with atomic_open(p) as f:
            f.write("new")
            raise KeyboardInterrupt
    assert p.read_text() == "old" and os.listdir(tmp_path) == ["r.txt"]
    with pytest.raises(TypeError):  # an object json cannot write: nothing half-written either
        atomic_write_json(p, {"a": object()})
    assert p.read_text() == "old" and os.listdir(tmp_path) == ["r.txt"]


def test_a_killed_process_leaves_the_old_file(tmp_path):
    """A process killed (SIGKILL) in the middle of writing: the target is the old file, whole."""
    p = tmp_path / "r.txt"
    p.write_text("old")
    code = textwrap.dedent(f"""
        import os, signal
        from smdm_plugin.io.files import atomic_open
        with atomic_open({str(p)!r}) as f:
            f.write("new" * 1000)
            f.flush()
            os.kill(os.getpid(), signal.SIGKILL)
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True)
    assert r.returncode != 0 and p.read_text() == "old"


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_permissions_are_those_of_a_plain_open(tmp_path):
    old = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
        with open(tmp_path / "b.txt", "w") as f:
            f.write("x")
    finally:
        os.umask(old)
    mode = lambda n: stat.S_IMODE(os.stat(tmp_path / n).st_mode)  # noqa: E731
    assert mode("a.txt") == mode("b.txt") == 0o644
    os.chmod(tmp_path / "a.txt", 0o600)
    atomic_write_text(tmp_path / "a.txt", "y")  # replacing keeps the file's own permissions
    assert mode("a.txt") == 0o600


def test_check_new_file(tmp_path):
    p = tmp_path / "out.json"
    assert check_new_file(p) == str(p)
    p.write_text("mine")
    with pytest.raises(OutputExistsError, match=r"--out '.*out.json' exists; pass --overwrite"):
        check_new_file(p, what="--out")
    assert isinstance(OutputExistsError("x"), FileExistsError)
    assert check_new_file(p, overwrite=True) == str(p) and p.read_text() == "mine"
    with pytest.raises(OutputExistsError, match="is a folder, expected a file path"):
        check_new_file(tmp_path, overwrite=True)
    os.symlink(tmp_path / "nowhere", tmp_path / "dangling")
    with pytest.raises(OutputExistsError):  # a dangling link is something the user made too
        check_new_file(tmp_path / "dangling")


def test_check_new_dir(tmp_path):
    d = tmp_path / "results"
    assert check_new_dir(d) == str(d) and d.is_dir()
    assert check_new_dir(d) == str(d)  # empty: fine
    (d / "keep.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match="exists and is not empty; pass --overwrite"):
        check_new_dir(d)
    assert check_new_dir(d, overwrite=True) == str(d) and (d / "keep.txt").read_text() == "mine"
    with pytest.raises(OutputExistsError, match="exists and is not a folder"):
        check_new_dir(d / "keep.txt", overwrite=True)
