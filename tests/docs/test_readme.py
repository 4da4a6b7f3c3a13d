"""Every command the README shows runs as written, in order, in a fresh folder (so the README cannot drift).

What runs: each line of the README's ```` ```bash ```` blocks, split at ``&&``, whose command is
``smdm ...`` (run as ``python -m smdm_plugin ...`` on this checkout) or ``python -c ...`` (a
one-line helper the README uses to make an input file). Comments after ``#`` are dropped.

Skipped, by these explicit rules (:data:`SKIP`), each with its reason:

* ``smdm run`` — needs an upstream checkout (``--repo PATH``) and its weights/data;
* a command naming an argument the user must replace (``...``, ``PATH``, ``dataset/HumanML3D``);
* anything that is not ``smdm``/``python -c`` (``pip``, ``git``, ``cd``, ``torchrun``, ``python -m``
  upstream scripts): installs, upstream code, or launchers tested elsewhere (tests/apps/test_ddp_apps.py).

Small-size flags (:data:`SMALL`) are appended where a command has them, to keep the whole run
within about a minute on 2 cores; they change sizes and speed, never which files are written or read:

* ``smdm demo``: ``--quick --no-gif`` (``--quick`` keeps 120 frames, so the later in-betweening
  examples, with keyframes up to frame 119, run on its models as on the full-size demo's);
* ``smdm inbetween``: ``--no-gif --quiet`` (the GIF is the renderer's, tested in test_render.py);
* ``smdm render``: ``--stride 10 --quiet`` (every 10th frame);
* ``smdm bench``: ``--quick``; ``smdm ablate``: ``--steps 2``; ``smdm train``: ``--steps 2``;
  ``smdm evaluator train``: ``--epochs 2 --ae-epochs 2``; ``smdm evaluator check``: ``--replications 2``;
  ``smdm eval``: ``--replications 1 --mm-repeats 0``;
  every command: ``--threads 1`` where it has the option.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path
from typing import List, Optional, Tuple

import pytest

from helpers.paths import ROOT
README = ROOT / "README.md"

#: extra flags per command (added when the command does not already give them)
SMALL = {
    "demo": ["--quick", "--no-gif", "--threads", "1"],
    "inbetween": ["--no-gif", "--quiet", "--threads", "1"],
    "render": ["--stride", "10", "--quiet"],
    "bench": ["--quick", "--threads", "1"],
    "ablate": ["--steps", "2", "--threads", "1", "--no-progress"],
    "train": ["--steps", "2", "--threads", "1", "--no-progress"],
    "evaluator train": ["--epochs", "2", "--ae-epochs", "2", "--threads", "1", "--no-progress"],
    "evaluator check": ["--replications", "2", "--threads", "1"],
    "eval": ["--replications", "1", "--mm-repeats", "0", "--threads", "1", "--no-progress"],
}

#: (rule, reason): a command matching the regular expression is not run
SKIP = [
    (r"^smdm run\b", "needs an upstream checkout (--repo PATH)"),
    (r"\.\.\.|\bPATH\b|dataset/HumanML3D", "an argument the user replaces with their own"),
]


def bash_blocks(text: str) -> List[str]:
    return re.findall(r"^```bash\n(.*?)^```", text, flags=re.S | re.M)


def readme_commands(text: str) -> List[Tuple[str, Optional[str]]]:
    """``[(command, reason it is skipped or None)]`` in README order, ``smdm`` and ``python -c`` only."""
    out = []
    for block in bash_blocks(text):
        for line in block.splitlines():
            for part in line.split("&&"):
                words = shlex.split(part, comments=True)
                if not words or not (words[0] == "smdm" or words[:2] == ["python", "-c"]):
                    continue
                cmd = shlex.join(words)
                reason = next((why for rule, why in SKIP if re.search(rule, cmd)), None)
                out.append((cmd, reason))
    return out


def with_small_flags(words: List[str]) -> List[str]:
    """``words`` plus the small-size flags of its command (``SMALL[sub]`` or ``SMALL["sub subsub"]``)."""
    key = " ".join(words[1:3]) if " ".join(words[1:3]) in SMALL else words[1]
    extra, given = SMALL.get(key, []), set(words)
    add, i = [], 0
    while i < len(extra):  # a flag and its values, unless the command gives the flag itself
        j = i + 1
        while j < len(extra) and not extra[j].startswith("--"):
            j += 1
        if extra[i] not in given:
            add += extra[i:j]
        i = j
    return words + add


def test_readme_lists_commands_and_skips_only_by_rule() -> None:
    cmds = readme_commands(README.read_text())
    run = [c for c, why in cmds if why is None]
    assert any(c == "smdm demo" for c in run), "the first screen's `smdm demo` must be among the commands run"
    assert len(run) >= 8, run
    for c, why in cmds:
        assert why is None or c.startswith("smdm run") or re.search(r"\.\.\.|\bPATH\b|dataset/HumanML3D", c), (c, why)


def test_every_readme_command_runs_in_order(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    env.pop("SMDM_MOCAP", None)
    ran = []
    for cmd, why in readme_commands(README.read_text()):
        if why:
            continue
        words = shlex.split(cmd)
        if words[0] == "smdm":
            argv = [sys.executable, "-m", "smdm_plugin", *with_small_flags(words)[1:]]
        else:
            argv = [sys.executable, *words[1:]]
        r = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, f"README command failed ({r.returncode}): {cmd}\n{r.stdout[-1500:]}\n{r.stderr[-1500:]}"
        ran.append(cmd)
    assert (tmp_path / "smdm_out" / "demo" / "sparse").is_dir() and (tmp_path / "dance.npy").exists(), ran
