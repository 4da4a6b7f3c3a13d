"""The CPU thread default of every command (apps/common/threads.py, docs/threads.md): busy cores left
alone, ``--threads`` before ``OMP_NUM_THREADS`` before the automatic choice, and OpenMP's passive wait
policy set before torch loads."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

from helpers.paths import ROOT


# ----------------------------------------------------------------------------------------- threads
def test_default_threads_leaves_busy_cores_alone():
    from smdm_plugin.apps.common.threads import default_threads

    assert default_threads(cores=2, load=0.0, local_processes=1) == 2      # idle: every core
    assert default_threads(cores=2, load=2.0, local_processes=1) == 1      # two busy neighbours: one
    assert default_threads(cores=2, load=7.5, local_processes=1) == 1      # never below one
    assert default_threads(cores=16, load=4.2, local_processes=1) == 12    # round(16 - 4.2)
    assert default_threads(cores=16, load=0.0, local_processes=4) == 4     # torchrun: cores shared
    # the slow obvious reference: count the cores one by one while load remains
    for cores in range(1, 9):
        for load in np.arange(0, 10, 0.25):
            free = sum(1 for c in range(cores) if c + 0.5 <= cores - load)  # cores at least half idle
            assert default_threads(cores, float(load), 1) == max(1, free), (cores, load)


def test_choose_threads_order(monkeypatch):
    from smdm_plugin.apps.common.threads import choose_threads

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert choose_threads(5) == (5, "--threads")
    assert choose_threads(None) == (3, "OMP_NUM_THREADS")
    monkeypatch.delenv("OMP_NUM_THREADS")
    n, why = choose_threads(None)
    assert n >= 1 and why.startswith("auto")


def test_more_threads_than_cores_is_said(monkeypatch, capsys):
    """0.10.5 took `--threads 1000` on 2 cores silently (oversubscribed threads wait for each other)."""
    import torch

    from smdm_plugin.apps.common import threads

    before = torch.get_num_threads()
    monkeypatch.setattr(threads, "usable_cores", lambda: 2)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    try:
        assert threads.apply_threads(2).startswith("2 CPU threads") and capsys.readouterr().err == ""
        threads.apply_threads(8)
        assert ("smdm: warning: 8 CPU threads (--threads) on the 2 cores this process can use"
                in capsys.readouterr().err) and torch.get_num_threads() == 8      # asked: warned, not changed
        monkeypatch.setenv("OMP_NUM_THREADS", "3")
        threads.apply_threads(None)
        assert "3 CPU threads (OMP_NUM_THREADS) on the 2 cores" in capsys.readouterr().err
    finally:
        torch.set_num_threads(before)


def test_cli_sets_passive_wait_policy_before_torch_loads(tmp_path):
    """In a fresh process, `smdm <cmd>` puts OMP_WAIT_POLICY=PASSIVE into the environment before
    torch is imported (and keeps a value the user set)."""
    code = ("import os, sys; from smdm_plugin.apps import cli; "
            "cli.COMMANDS['probe'] = ('probe_mod', ''); "
            "import types; m = types.ModuleType('probe_mod'); "
            "m.main = lambda argv: print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules) or 0; "
            "sys.modules['probe_mod'] = m; sys.exit(cli.main(['probe']))")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("OMP_WAIT_POLICY", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["PASSIVE", "False"], out.stderr
    env["OMP_WAIT_POLICY"] = "ACTIVE"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.split()[0] == "ACTIVE"
