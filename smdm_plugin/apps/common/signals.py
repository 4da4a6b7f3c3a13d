"""How a command ends when it is told to stop: Ctrl-C (SIGINT), SIGTERM (``timeout``, a cluster's job
cancel, ``docker stop``) and SIGHUP (the terminal closed) all unwind the command as Ctrl-C does
(``with`` blocks exit: output-folder locks are released, an interrupted ``smdm train`` names the
checkpoint to resume from), and the exit status is ``128 + N`` (130, 143, 129)."""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from typing import Any, Iterator, Optional

__all__ = ["Stopped", "stop_on_signals", "check", "received", "exit_status", "GRACE_S"]

#: seconds a command has to end after a stop signal before the process exits without unwinding
GRACE_S = 5.0
_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))
_received: Optional[int] = None
_timer: Optional[threading.Timer] = None


class Stopped(KeyboardInterrupt):
    """The command was told to stop by signal ``signum`` (a ``KeyboardInterrupt``: every ``except
    KeyboardInterrupt`` that saves or reports handles SIGTERM and SIGHUP the same way)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def received() -> Optional[int]:
    """The stop signal received during the command, or None."""
    return _received


def check() -> None:
    """Raise :class:`Stopped` again when a stop signal came and its exception was swallowed."""
    if _received is not None:
        raise Stopped(_received)


def exit_status(status: int) -> int:
    """``128 + N`` when signal ``N`` stopped the command (whatever status its code returned), else ``status``."""
    return 128 + _received if _received is not None else status


def _force_exit(signum: int, why: str) -> None:
    """Release this process's output-folder locks and exit with ``128 + signum`` now."""
    from ...io.outdir import release_held_locks

    release_held_locks()
    try:
        sys.stderr.write(f"\nsmdm: {signal.Signals(signum).name}: {why}; exiting\n")
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    os._exit(128 + signum)


def _handler(signum: int, frame: Any) -> None:
    global _received, _timer
    if _received is not None:
        _force_exit(signum, "stop requested again")
    _received = signum
    _timer = threading.Timer(GRACE_S, _force_exit, (signum, f"the command did not stop within {GRACE_S:g} s"))
    _timer.daemon = True
    _timer.start()
    raise Stopped(signum)


@contextlib.contextmanager
def stop_on_signals(bound_exit: bool = False) -> Iterator[None]:
    """Within the block, SIGINT / SIGTERM / SIGHUP raise :class:`Stopped` (see the module doc), but
    those the process ignores (``nohup``); the previous handlers come back afterwards. ``bound_exit`` (the process's entry point): after a stop
    signal the grace timer keeps running, so that the interpreter's shutdown (compile workers ...)
    cannot keep the process alive either; else it is cancelled when the block ends. Outside the
    main thread: nothing changes."""
    global _received
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _received = None
    # a signal the caller ignores stays ignored (`nohup`: SIGHUP; `cmd &` in a script: SIGINT)
    previous = {s: signal.signal(s, _handler) for s in _SIGNALS if signal.getsignal(s) is not signal.SIG_IGN}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        if _timer is not None and not bound_exit:
            _timer.cancel()
