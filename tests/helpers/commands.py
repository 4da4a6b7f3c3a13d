"""Running the package's commands as a user does (a subprocess on this checkout), and what several
command tests share: the tiny ``smdm train`` model options, a folder's content snapshot, the error a
full disk gives ``torch.save``."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

from helpers.paths import ROOT

#: ``smdm train``'s smallest useful model (seconds per run on one thread)
TINY_TRAIN = ["--latent-dim", "16", "--layers", "1", "--heads", "2", "--ff-size", "32", "--batch", "2",
              "--diffusion-steps", "10", "--no-progress", "--threads", "1"]

#: the RuntimeError torch.save's zip writer raises on a full disk
TORCH_FULL_DISK = "[enforce fail at inline_container.cc:672] . unexpected pos 19776 vs 19728"


def env() -> dict:
    """The environment of a subprocess that imports this checkout's smdm_plugin, on one thread."""
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
            "OMP_NUM_THREADS": "1"}


def smdm(*args, **kw) -> subprocess.CompletedProcess:
    """``python -m smdm_plugin <args>`` in a subprocess (output captured as text)."""
    return subprocess.run([sys.executable, "-m", "smdm_plugin", *map(str, args)], capture_output=True, text=True,
                          env=env(), timeout=300, **kw)


def torchrun(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc_per_node 2 <args>`` from the repository root; fails the test on a
    non-zero exit."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", *args]
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    e["OMP_NUM_THREADS"] = "1"
    proc = subprocess.run(cmd, cwd=str(ROOT), env=e, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    return proc


def snapshot(folder: Path) -> dict:
    """Every file under ``folder`` -> sha256 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def train(data: Path, out: Path, *extra) -> int:
    """``smdm train`` in this process (its exit status) on ``data`` with the tiny model, into ``out``."""
    from smdm_plugin.apps import train as train_cli

    return train_cli.main(["--data", str(data), "--out", str(out), "--min-frames", "20", *TINY_TRAIN, *extra])
