"""Every way a run is told to stop leaves a folder the next command understands, on a real ``smdm train``
subprocess: SIGTERM (``timeout``, a job cancel, ``docker stop``) and SIGHUP end it as Ctrl-C does (exit
128 + N, the lock released, ``--resume`` continues), and Ctrl-C during ``--compile`` stops it within seconds
with exit 130, also when the compiler swallows the ``KeyboardInterrupt``. (kill -9:
tests/apps/test_train_outdir.py.)"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from smdm_plugin.apps.common.signals import GRACE_S
from smdm_plugin.io.outdir import lock_path
from smdm_plugin.training import trainer as T

from helpers.commands import TINY_TRAIN, env
from helpers.commands import train as _train

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signals")

#: ``smdm train`` as its console script runs it, after registering a torch.compile backend that
#: swallows Ctrl-C (``Exception ignored ...``, as torch's compiler sometimes does) and compiles for 2 minutes
DRIVER = '''
import sys, time
from pathlib import Path
import torch._dynamo

MARKER = Path(sys.argv[1])


@torch._dynamo.register_backend
def swallow(gm, example_inputs):
    MARKER.write_text("compiling")
    end = time.monotonic() + 120
    while time.monotonic() < end:
        try:
            time.sleep(0.05)
        except KeyboardInterrupt:
            print("Exception ignored in swallow: KeyboardInterrupt", file=sys.stderr)
    return gm.forward

from smdm_plugin.apps.cli import main
sys.argv = ["smdm", *sys.argv[2:]]
sys.exit(main())
'''


def _default_signals() -> None:
    """The stop signals at their defaults in the child, as a terminal starts a command: a test run
    started under ``nohup`` (SIGHUP ignored) or as a script's background job (SIGINT ignored) would
    hand its children ignored signals, which a command rightly leaves ignored."""
    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, signal.SIG_DFL)


def _start(*argv: str, driver: Path = None, marker: Path = None) -> subprocess.Popen:
    head = [sys.executable, str(driver), str(marker)] if driver else [sys.executable, "-m", "smdm_plugin"]
    return subprocess.Popen([*head, *argv], env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_signals)


def _wait_for(path: Path, child: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists() and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    if not path.exists():
        child.kill()
        pytest.fail(f"{path.name} never appeared: {child.communicate()[1][-2000:]}")


def _stopped(child: subprocess.Popen, sig: int, within: float) -> str:
    """Send ``sig``; the child's stderr once it ended, failing when that takes longer than ``within`` s."""
    os.kill(child.pid, sig)
    t0 = time.monotonic()
    try:
        _, err = child.communicate(timeout=within)
    except subprocess.TimeoutExpired:
        child.kill()
        pytest.fail(f"still running {within:g} s after {signal.Signals(sig).name}: {child.communicate()[1][-2000:]}")
    assert time.monotonic() - t0 < within
    return err


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP"])
def test_sigterm_and_sighup_end_a_run_as_ctrl_c_does(tmp_path, synthetic_hml, sig):
    """0.7.0: SIGTERM killed the run outright (exit 143, but its lock stayed and --resume refused)."""
    run, signum = tmp_path / "run", getattr(signal, sig)
    child = _start("train", "--data", str(synthetic_hml), "--out", str(run), "--min-frames", "20", *TINY_TRAIN,
                   "--save-every", "5", "--steps", "100000")
    _wait_for(run / T.TRAIN_STATE_FILENAME, child)
    err = _stopped(child, signum, within=60)
    assert child.returncode == 128 + signum, err
    assert f"smdm train: stopped by {sig}" in err and "rerun with --resume to continue from step" in err
    assert "Traceback" not in err and not os.path.exists(lock_path(run))
    step = torch.load(run / T.TRAIN_STATE_FILENAME, weights_only=True)["step"]
    assert _train(synthetic_hml, run, "--steps", str(step + 1), "--resume") == 0  # no lock to remove
    assert (run / f"model{step + 1:09d}.pt").exists()


@pytest.mark.parametrize("backend", ["swallow", "inductor"])
def test_ctrl_c_during_compilation_stops_within_seconds(tmp_path, synthetic_hml, backend):
    """``swallow``: a compiler that swallows the KeyboardInterrupt and compiles on (0.7.0 trained to the
    end, exit 0, minutes later); ``inductor``: torch's own compiler, interrupted once it started."""
    run, marker = tmp_path / "run", tmp_path / "compiling"
    argv = ["train", "--data", str(synthetic_hml), "--out", str(run), "--min-frames", "20", *TINY_TRAIN,
            "--steps", "50", "--compile", "--compile-backend", backend]
    if backend == "swallow":
        (tmp_path / "driver.py").write_text(DRIVER)
        child = _start(*argv, driver=tmp_path / "driver.py", marker=marker)
        _wait_for(marker, child)
    else:
        child = _start(*argv)
        assert "torch.compile" in child.stdout.readline()  # the header: the first step compiles next
        time.sleep(1.0)
    err = _stopped(child, signal.SIGINT, within=GRACE_S + 20)
    assert child.returncode == 130, err
    assert "Traceback" not in err and not os.path.exists(lock_path(run))
    # the folder holds no checkpoint: the corrected command needs neither --resume nor --overwrite
    assert _train(synthetic_hml, run, "--steps", "1") == 0


def test_a_signal_the_caller_ignores_stays_ignored():
    """`nohup smdm train ...` ignores SIGHUP: the run must go on when the terminal closes."""
    from smdm_plugin.apps.common.signals import stop_on_signals

    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with stop_on_signals():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, signal.SIG_IGN)
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, before)
