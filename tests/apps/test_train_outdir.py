"""``smdm train``'s output folder and runs under faults: one writer per folder (a live lock names its
owner, a stale one is named and taken over), ``--out`` apart from every input (``--data``, ``--init-from``),
``--overwrite`` replacing only the command's own files, OS errors as one line, the folder swapped in as one
unit; bad training data and bad option values refused before step 0, before anything is written; a folder
without a checkpoint is not a run to protect; resumable training (kill -9 or Ctrl-C, then ``--resume``:
bit-identical to an uninterrupted run). SIGTERM / SIGHUP / Ctrl-C during compilation:
tests/apps/test_stop_signals.py."""
from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from smdm_plugin.apps import cli
from smdm_plugin.apps import train as train_cli
from smdm_plugin.training import trainer as T
from smdm_plugin.io.outdir import MANIFEST, OutputDir, OutputLock, OutputLockedError, OutputOverlapError, lock_path

from helpers.commands import TINY_TRAIN as TINY
from helpers.commands import env as _env
from helpers.commands import smdm as _smdm
from helpers.commands import snapshot as _snapshot
from helpers.commands import train as _train
from helpers.synthetic_data import write_humanml3d


@pytest.fixture
def data(synthetic_hml) -> Path:
    return synthetic_hml



# ------------------------------------------------------------------------------ one writer per folder
def test_second_writer_is_refused_naming_folder_and_owner(tmp_path, data):
    out = tmp_path / "run"
    assert _train(data, out, "--steps", "2") == 0
    before = _snapshot(out)
    with OutputLock(out, "smdm test-holder"):  # a live run (this process) holds the folder
        p = _smdm("train", "--data", data, "--out", out, "--overwrite", "--steps", "1", *TINY)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    line = p.stderr.strip()
    assert len(line.splitlines()) == 1 and "is being written by smdm test-holder" in line
    assert f"pid {os.getpid()}" in line and "run" in line
    assert _snapshot(out) == before and not os.path.exists(lock_path(out))


def test_a_stale_lock_is_named_and_taken_over(tmp_path, data, capsys):
    out = tmp_path / "run"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    Path(lock_path(out)).write_text(json.dumps({"pid": dead.pid, "host": os.uname().nodename, "command": "smdm demo"}))
    assert _train(data, out, "--steps", "1") == 0  # no manual rm
    err = capsys.readouterr().err
    assert f"took over the stale lock {lock_path(out)} left by smdm demo (pid {dead.pid}, no longer running)" in err
    assert not os.path.exists(lock_path(out)) and T.load_trained(str(out))[0] is not None


# ------------------------------------------------------------------------------ outputs apart from inputs
@pytest.mark.parametrize("where", ["same", "inside", "contains"])
def test_out_overlapping_data_is_refused_before_anything_is_written(tmp_path, data, where, capsys):
    out = {"same": data, "inside": data / "run", "contains": tmp_path}[where]
    before = _snapshot(tmp_path)
    for extra in ([], ["--overwrite"]):
        assert _train(data, out, "--steps", "1", *extra) == 2
        err = capsys.readouterr().err
        assert "pick an output folder apart from the inputs" in err and "--data" in err
    assert _snapshot(tmp_path) == before and sorted(os.listdir(tmp_path)) == ["data"]


def test_overwrite_replaces_only_the_commands_own_files(tmp_path, data, capsys):
    out = tmp_path / "run"
    assert _train(data, out, "--sparse", "--steps", "2") == 0
    manifest = json.loads((out / MANIFEST).read_text())
    assert "sparse_config.json" in manifest["entries"] and "model000000002.pt" in manifest["entries"]
    (out / "notes.txt").write_text("mine")
    (out / "mine").mkdir()
    (out / "mine" / "a.bin").write_bytes(b"\x00\x01")
    assert _train(data, out, "--overwrite", "--steps", "1") == 0  # dense now
    assert (out / "notes.txt").read_text() == "mine" and (out / "mine" / "a.bin").read_bytes() == b"\x00\x01"
    assert not (out / "sparse_config.json").exists() and not (out / "model000000002.pt").exists()
    # a file the command would write, but did not write there: refused up front, nothing changes
    (out / MANIFEST).unlink()
    before = _snapshot(out)
    assert _train(data, out, "--overwrite", "--steps", "1") == 2
    assert "which this command writes but did not write there" in capsys.readouterr().err
    assert _snapshot(out) == before


@pytest.mark.parametrize("form", ["folder", "file"])
def test_init_from_is_an_input_never_deleted(tmp_path, data, capsys, form):
    """0.7.0: `--out X --init-from X --overwrite` deleted X's files, then found no model*.pt in X."""
    dense = tmp_path / "dense"
    assert _train(data, dense, "--steps", "2") == 0
    before = _snapshot(dense)
    init = dense if form == "folder" else dense / "model000000002.pt"
    for extra in ([], ["--overwrite"]):
        assert _train(data, dense, "--sparse", "--init-from", str(init), "--steps", "1", *extra) == 2
        err = capsys.readouterr().err
        assert "the input --init-from" in err and "pick an output folder apart from the inputs" in err, err
    assert _snapshot(dense) == before and not os.path.exists(lock_path(dense))


# ------------------------------------------------------------------------------ one unit; OS errors
def test_failed_overwrite_is_one_line_and_blocks_nothing(tmp_path, data, monkeypatch, capsys):
    """smdm train writes in --out itself (each file atomic; docs/reliability.md): a failed write is one
    line naming the file, leaves no lock, and the next run goes ahead."""
    out = tmp_path / "run"
    assert _train(data, out, "--sparse", "--steps", "2") == 0
    real_save = np.save

    def full_disk(f, *a, **k):  # the disk fills while the new model folder is written (a write names no file)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(np, "save", full_disk)
    rc = cli.main(["train", "--data", str(data), "--out", str(out), "--overwrite", "--steps", "1", "--min-frames",
                   "20", *TINY])
    monkeypatch.setattr(np, "save", real_save)
    err = capsys.readouterr().err
    assert rc == 1 and "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("smdm train: error: ") and last.endswith("Mean.npy: No space left on device")
    assert str(out / "Mean.npy") in last  # the path written
    assert not os.path.exists(lock_path(out)) and not [n for n in os.listdir(out) if n.endswith(".tmp")]
    assert _train(data, out, "--overwrite", "--sparse", "--steps", "2") == 0
    model, config = T.load_trained(str(out))
    assert config is not None


def test_permission_denied_on_the_output_is_one_line(tmp_path, data, monkeypatch, capsys):
    """Tests run as root (chmod does not stop root): the refusal is injected where the folder is made."""
    real = os.makedirs

    def denied(path, *a, **k):
        if os.path.basename(str(path)) == "run":
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(os, "makedirs", denied)
    rc = cli.main(["train", "--data", str(data), "--out", str(tmp_path / "run"), "--steps", "1", "--min-frames", "20",
                   *TINY])
    err = capsys.readouterr().err
    assert rc == 2 and "Permission denied" in err and str(tmp_path / "run") in err and "Traceback" not in err
    assert not (tmp_path / "run").exists() and not os.path.exists(lock_path(tmp_path / "run"))


def test_output_dir_swaps_in_one_unit(tmp_path):
    out = tmp_path / "res"
    with OutputDir(out, command="t") as od:
        Path(od.path, "a.txt").write_text("1")
        assert not out.exists()  # nothing visible until the block ends
    assert (out / "a.txt").read_text() == "1"
    with pytest.raises(RuntimeError):
        with OutputDir(out, overwrite=True, command="t") as od:
            Path(od.path, "a.txt").write_text("2")
            Path(od.path, "b.txt").write_text("2")
            raise RuntimeError("killed half-way")
    assert sorted(os.listdir(out)) == [MANIFEST, "a.txt"] and (out / "a.txt").read_text() == "1"
    assert sorted(os.listdir(tmp_path)) == ["res"]  # no partial folder, no lock left


# ------------------------------------------------------------------------------ resumable training
def test_resume_after_kill_9_is_bit_identical(tmp_path, data, capsys):
    ref, run = tmp_path / "ref", tmp_path / "run"
    steps = 120
    common = ["--data", data, "--min-frames", "20", "--save-every", "20", "--sparse", *TINY]

    def train(*args) -> int:  # in this process (fast); the run to kill is a child process
        return train_cli.main([*map(str, common), *map(str, args)])

    assert train("--out", ref, "--steps", steps) == 0
    # the same run, killed with SIGKILL once a checkpoint is there, then resumed to the same step
    child = subprocess.Popen([sys.executable, "-m", "smdm_plugin", "train", *map(str, common), "--out", str(run),
                              "--steps", "100000"], env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    state = run / T.TRAIN_STATE_FILENAME  # written in --out as training goes
    deadline = time.time() + 120
    while not state.exists() and child.poll() is None and time.time() < deadline:
        time.sleep(0.002)
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    assert state.exists()
    killed_at = torch.load(state, weights_only=True)["step"]
    assert 20 <= killed_at < steps
    T.load_trained(str(run), step=killed_at)  # the killed run's checkpoint: visible and loadable
    capsys.readouterr()
    # without --resume: refused, nothing lost, and the message names the killed run's lock
    assert train("--out", run, "--steps", steps) == 2
    err = capsys.readouterr().err
    assert "pass --resume to continue it" in err and state.exists()
    assert f"takes over the stale lock {lock_path(run)} left by smdm train (pid {child.pid}, no longer running" in err
    # --resume takes the stale lock over: no manual rm
    assert train("--out", run, "--steps", steps, "--resume") == 0
    out = capsys.readouterr()
    assert f"resumed at step {killed_at}" in out.out and f"took over the stale lock {lock_path(run)}" in out.err
    a = torch.load(ref / f"model{steps:09d}.pt", weights_only=True)
    b = torch.load(run / f"model{steps:09d}.pt", weights_only=True)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (ref / "losses.csv").read_text() == (run / "losses.csv").read_text()
    # a finished run continues to more steps the same way; its earlier checkpoints stay
    assert train("--out", run, "--steps", steps + 20, "--resume") == 0
    assert (run / f"model{steps + 20:09d}.pt").exists() and (run / f"model{steps:09d}.pt").exists()
    # other settings: refused, naming what differs, the folder unchanged
    before = _snapshot(run)
    assert train("--out", run, "--steps", steps + 40, "--resume", "--lr", "0.001") == 2
    assert "lr: saved 0.0002, now 0.001" in capsys.readouterr().err and _snapshot(run) == before
    assert sorted(os.listdir(tmp_path)) == ["data", "ref", "run"]  # no partial folder, no lock left


# ------------------------------------------------------------------------------ input data before step 0
@pytest.mark.parametrize("edit,match", [
    (lambda d: np.save(d / "new_joint_vecs" / "train001.npy", np.full((52, 263), np.nan, np.float32)),
     r"train001.npy: motion holds a non-finite value"),
    (lambda d: np.save(d / "new_joint_vecs" / "train001.npy", np.zeros((52, 250), np.float32)),
     r"train001.npy: motion must have shape \[\*, 263\], got \[52, 250\]"),
    (lambda d: np.save(d / "new_joint_vecs" / "train001.npy", np.zeros((52, 263), np.complex64)),
     r"train001.npy: motion must be real numbers"),
    (lambda d: ((d / "new_joint_vecs" / "train001.npy").unlink(), (d / "new_joint_vecs" / "train001.npy").mkdir()),
     r"train001.npy: is a folder, expected a .npy file"),
    (lambda d: np.save(d / "Std.npy", np.ones(200, np.float32)), r"Std.npy: std must have shape \[263\]"),
    (lambda d: np.save(d / "Std.npy", np.r_[0.0, np.ones(262)].astype(np.float32)), r"Std.npy: std must be > 0"),
    (lambda d: np.save(d / "Mean.npy", np.r_[np.inf, np.ones(262)].astype(np.float32)), r"Mean.npy: mean holds a non-finite"),
    (lambda d: (d / "train.txt").write_bytes(b"\xff\xfe\x00"), r"train.txt: not UTF-8"),
])
def test_bad_training_data_is_one_line_before_step_0(tmp_path, data, edit, match, capsys):
    edit(data)
    assert _train(data, tmp_path / "run", "--steps", "1") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("smdm train: data: ")
    import re

    assert re.search(match, err), err
    assert not (tmp_path / "run").exists()


def test_clips_too_short_for_the_reduction(tmp_path, capsys):
    data = write_humanml3d(tmp_path / "d", train=(6, 40), val=(40,))
    assert _train(data, tmp_path / "run", "--min-frames", "2", "--sparse", "--steps", "1") == 2
    err = capsys.readouterr().err
    assert "train000.npy has 6 frames: at reduction 0.8 it would keep 2" in err and "--min-frames 8" in err
    assert _train(data, tmp_path / "run", "--min-frames", "8", "--sparse", "--steps", "1") == 0


def test_resume_without_a_run_is_refused_and_leaves_nothing(tmp_path, data, capsys):
    assert _train(data, tmp_path / "o", "--steps", "1", "--resume") == 2
    assert "holds no run to continue" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ["data"]


def test_ctrl_c_keeps_the_checkpoint_for_resume(tmp_path, data, monkeypatch, capsys):
    real_step = T.Trainer.step

    def step(self):
        if self.step_count == 3:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(T.Trainer, "step", step)
    rc = cli.main(["train", "--data", str(data), "--out", str(tmp_path / "o"), "--steps", "9", "--save-every", "2",
                   "--min-frames", "20", *TINY])
    assert rc == 130 and "rerun with --resume to continue from step 2" in capsys.readouterr().err
    assert (tmp_path / "o" / "model000000002.pt").exists() and not (tmp_path / ".o.partial").exists()
    assert not os.path.exists(lock_path(tmp_path / "o"))
    monkeypatch.setattr(T.Trainer, "step", real_step)
    assert _train(data, tmp_path / "o", "--steps", "9", "--save-every", "2", "--resume") == 0
    assert (tmp_path / "o" / "model000000009.pt").exists() and not (tmp_path / ".o.partial").exists()


# ------------------------------------------------------------------------------ bad options; failed starts
@pytest.mark.parametrize("value,needle", [("nope", "unknown torch.compile backend 'nope'"),
                                          ("indcutor", "did you mean 'inductor'?")])
def test_an_unknown_compile_backend_is_refused_before_anything_is_written(tmp_path, data, capsys, value, needle):
    """0.7.0: an InvalidBackend traceback at step 0, leaving files that refused the corrected command."""
    with pytest.raises(SystemExit) as e:
        _train(data, tmp_path / "run", "--compile", "--compile-backend", value, "--steps", "1")
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and err.startswith("smdm train: error: argument --compile-backend: ") and needle in err
    assert sorted(os.listdir(tmp_path)) == ["data"]


def test_a_run_that_failed_before_its_first_checkpoint_does_not_block_the_next(tmp_path, data, monkeypatch, capsys):
    out = tmp_path / "run"

    def fails(self):
        raise RuntimeError("the compiler failed at step 0")

    monkeypatch.setattr(T.Trainer, "step", fails)
    with pytest.raises(RuntimeError, match="at step 0"):
        _train(data, out, "--steps", "3", "--save-every", "1")
    assert MANIFEST in os.listdir(out) and "data_files.json" in os.listdir(out)  # what such a run leaves
    assert not os.path.exists(lock_path(out))
    monkeypatch.undo()
    assert _train(data, out, "--steps", "2") == 0  # the corrected command, neither --resume nor --overwrite
    assert sorted(n for n in os.listdir(out) if n.startswith("model")) == ["model000000002.pt"]
    assert _train(data, out, "--steps", "2") == 2  # a folder with a checkpoint is protected as before
    assert "pass --resume to continue it" in capsys.readouterr().err


def test_a_batch_that_cannot_fit_is_refused_at_once(tmp_path, data):
    """0.7.0: `--batch 100000000` printed nothing for a minute while memory climbed."""
    t0 = time.monotonic()
    p = _smdm("train", "--data", data, "--out", tmp_path / "run", "--min-frames", "20", *TINY, "--batch", "100000000")
    assert p.returncode == 2 and "Traceback" not in p.stderr and time.monotonic() - t0 < 60
    line = p.stderr.strip()
    assert len(line.splitlines()) == 1 and line.startswith("smdm train: error: argument --batch: 100000000 samples")
    assert "GiB free on cpu" in line and sorted(os.listdir(tmp_path)) == ["data"]


def test_the_batch_bound_is_a_lower_bound_of_a_step(monkeypatch):
    """What check_batch_fits refuses cannot fit; the largest size it names is accepted, one more is not."""
    import re

    from smdm_plugin.core.config import SparseConfig
    from smdm_plugin.training.memory import check_batch_fits, step_bytes

    model = dict(T.DEFAULT_MODEL)
    dev = torch.device("cpu")
    with pytest.raises(ValueError, match=r"argument --batch: 4096 samples .* more than the 0.1 GiB free on cpu; "
                                         r"at most about (\d+) can fit") as e:
        check_batch_fits(4096, 196, 263, model, None, dev, available=100 << 20)
    most = int(re.search(r"at most about (\d+)", str(e.value)).group(1))
    check_batch_fits(most, 196, 263, model, None, dev, available=100 << 20)
    with pytest.raises(ValueError):
        check_batch_fits(most + 1, 196, 263, model, None, dev, available=100 << 20)
    # at least the four [N, D] tensors of every sample; the sparse transformer runs on fewer tokens
    assert step_bytes(16, 196, 263, model) - step_bytes(0, 196, 263, model) >= 16 * 4 * 4 * 196 * 263
    assert step_bytes(16, 196, 263, model, SparseConfig()) < step_bytes(16, 196, 263, model)
    with pytest.raises(ValueError, match="shared by 2 processes"):
        check_batch_fits(most, 196, 263, model, None, dev, processes=2, available=100 << 20)
