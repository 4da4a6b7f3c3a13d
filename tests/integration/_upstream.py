"""Helpers shared by the upstream integration tests (MDM/DiP, priorMDM, MotionDiffuse);
the fixtures built on them are in ``conftest.py``.

Every upstream test is skipped unless its ``SMDM_<NAME>_ROOT`` points at a checkout (read-only:
the tests copy it into a temporary directory and patch the copy). Real motion comes from
``SMDM_HUMANML3D_DIR`` (default: ``shared/data/cmu-humanml3d`` beside this repository, or
``shared/data/cmu-humanml3d`` inside it), a small HumanML3D-format data set.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from typing import Dict, List, Optional, Sequence

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
PATCHES = os.path.join(REPO, "patches")
LAUNCHER = [sys.executable, "-m", "smdm_plugin.apps.cli", "run"]  # `smdm run`, whatever is on PATH


def find_humanml3d() -> Optional[str]:
    for cand in (os.environ.get("SMDM_HUMANML3D_DIR"),
                 os.path.join(os.path.dirname(REPO), "shared", "data", "cmu-humanml3d"),
                 os.path.join(REPO, "shared", "data", "cmu-humanml3d")):
        if cand and os.path.isdir(os.path.join(cand, "new_joint_vecs")):
            return os.path.abspath(cand)
    return None


def copy_checkout(src: str, dst: str) -> str:
    """Copy the tracked files of an upstream checkout (``git ls-tree HEAD`` when it is a repo; large
    assets skipped) into ``dst`` (``git apply`` works there without a repo)."""
    os.makedirs(dst, exist_ok=True)
    top = subprocess.run(["git", "-C", src, "rev-parse", "--show-toplevel"], capture_output=True, text=True)
    if top.returncode == 0 and os.path.samefile(top.stdout.strip(), src):
        # committed files (an index can be empty in a partial checkout)
        files = subprocess.run(["git", "-C", src, "ls-tree", "-r", "--name-only", "HEAD"], capture_output=True,
                               text=True, check=True).stdout.splitlines()
        for rel in files:
            if rel.startswith("assets/") or rel.endswith((".gif", ".mp4", ".png")):
                continue
            s = os.path.join(src, rel)
            if not os.path.isfile(s):
                continue
            d = os.path.join(dst, rel)
            os.makedirs(os.path.dirname(d), exist_ok=True)
            shutil.copy2(s, d)
    else:
        shutil.copytree(src, dst, dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("assets", "save", "*.mp4", ".git"))
    return dst


def git_apply(patch: str, repo: str, check_only: bool = False) -> subprocess.CompletedProcess:
    cmd = ["git", "apply", "--whitespace=nowarn"] + (["--check"] if check_only else []) + [patch]
    return subprocess.run(cmd, cwd=repo, capture_output=True, text=True)


def link_humanml3d(repo: str, data: str) -> None:
    """``repo/dataset/HumanML3D`` -> ``data`` (MDM/priorMDM's default data path)."""
    link = os.path.join(repo, "dataset", "HumanML3D")
    os.makedirs(os.path.dirname(link), exist_ok=True)
    if not os.path.lexists(link):
        os.symlink(data, link)


def plugin_env(extra: Optional[Dict[str, str]] = None) -> Dict[str, str]:
    """The environment for upstream subprocesses: this repository importable (``smdm_plugin``),
    upstream's own working directory first on ``sys.path`` (``python -m`` / the harnesses)."""
    env = dict(os.environ)
    old = env.get("PYTHONPATH", "")
    env["PYTHONPATH"] = REPO + (os.pathsep + old if old else "")
    env.setdefault("TOKENIZERS_PARALLELISM", "false")
    env.setdefault("WANDB_MODE", "disabled")
    env.update(extra or {})
    return env


#: a ``sitecustomize`` that stands in for CUDA's optimizer policy on the CPU (torch's fused Adam /
#: AdamW run on both): ``fused_optimizer_kwargs`` says fused wherever a run compiles
FUSED_POLICY = ("import smdm_plugin.runtime.compile as C\n"
                "C.fused_optimizer_kwargs = lambda device, mode: "
                "{'fused': True} if C.check_compile_mode(mode) != 'none' else {}\n")


def fused_policy_path(folder: str) -> str:
    """``folder`` with :data:`FUSED_POLICY` as its ``sitecustomize.py``: put first on a
    subprocess's ``PYTHONPATH``, the run takes the fused optimizer as it would on CUDA."""
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "sitecustomize.py"), "w") as f:
        f.write(FUSED_POLICY)
    return folder


def run_logged(cmd: Sequence[str], cwd: str, env: Dict[str, str], timeout: float = 600,
               check: bool = True) -> subprocess.CompletedProcess:
    """Run a subprocess; on failure (``check``) fail the test with the tail of its output."""
    proc = subprocess.run(list(cmd), cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        out = (proc.stdout + "\n" + proc.stderr)[-6000:]
        pytest.fail(f"command failed ({proc.returncode}): {' '.join(cmd)}\n--- output tail ---\n{out}")
    return proc


def python_cmd(*args: str) -> List[str]:
    return [sys.executable, *args]
