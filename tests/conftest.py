"""Shared fixtures of every test folder (tests are organised by the package's layers: core/, io/,
reference/, adapters/, integrations_unit/, metrics/, training/, apps/, plus package/, docs/, scripts/;
upstream checkouts: integration/). Data in ../shared (tests that need it skip when it is absent).

Shared builders that are not fixtures live in the ``helpers`` package (tests/helpers/); this file puts
tests/ on ``sys.path`` so that every test module, in any folder, imports them as ``helpers.<module>``.
Test modules never import each other.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

TESTS = os.path.dirname(os.path.abspath(__file__))
if TESTS not in sys.path:
    sys.path.insert(0, TESTS)

from helpers.paths import HML, MOCAP, SHARED  # noqa: E402,F401
from helpers.synthetic_data import write_humanml3d  # noqa: E402


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)


@pytest.fixture
def one_thread():
    """Torch on one thread for the test (tiny models run faster on one thread than on two on a shared,
    busy CPU, and deterministically); modules opt in with ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def synthetic_hml(tmp_path) -> Path:
    """A small synthetic HumanML3D-format folder (``tmp_path / "data"``, helpers.synthetic_data)."""
    return write_humanml3d(tmp_path / "data")


@pytest.fixture(scope="session")
def hml_dir() -> Path:
    if not (HML / "Mean.npy").exists():
        pytest.skip("../shared/data/cmu-humanml3d not available")
    return HML


@pytest.fixture(scope="session")
def mocap_files() -> list:
    """The CMU BVH files of ../shared/data/cmu-mocap (sorted paths; skip when absent)."""
    files = sorted(str(p) for p in MOCAP.glob("*.bvh")) if MOCAP.is_dir() else []
    if not files:
        pytest.skip("../shared/data/cmu-mocap not available")
    return files


@pytest.fixture(scope="session")
def hml_batch(hml_dir):
    """Real HumanML3D-format motions: normalised ``x [B, 263, 1, N]``, ``lengths [B]``, mean, std."""
    mean = np.load(hml_dir / "Mean.npy")
    std = np.load(hml_dir / "Std.npy")
    ids = sorted((hml_dir / "train.txt").read_text().split())[:16]
    motions = [np.load(hml_dir / "new_joint_vecs" / f"{i}.npy") for i in ids]
    N = 196
    x = np.zeros((len(motions), N, 263), np.float32)
    lengths = []
    for b, m in enumerate(motions):
        L = min(len(m), N)
        x[b, :L] = (m[:L] - mean) / std
        lengths.append(L)
    x = torch.from_numpy(x).permute(0, 2, 1).unsqueeze(2).contiguous()
    return x, torch.tensor(lengths), mean, std


@pytest.fixture(scope="session")
def triton_interpreter():
    """``run(code) -> stdout``: Python ``code`` in a fresh interpreter with Triton's interpreter on
    (``TRITON_INTERPRET=1``: a CUDA kernel's code runs on the CPU), failing the test on a non-zero
    exit; the test is skipped where ``triton`` is not installed."""
    import importlib.util
    import os
    import subprocess
    import sys

    if importlib.util.find_spec("triton") is None:
        pytest.skip("triton is not installed")

    def run(code: str, timeout: float = 900) -> str:
        env = {**os.environ, "TRITON_INTERPRET": "1"}
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=timeout)
        assert res.returncode == 0, res.stderr[-2000:]
        return res.stdout
    return run


@pytest.fixture
def fresh_dynamo():
    """Dynamo reset and its counters cleared before and after the test (compiled frames of earlier
    tests neither count against the recompile limit nor in ``counters['stats']['unique_graphs']``);
    modules opt in with ``pytestmark = pytest.mark.usefixtures("fresh_dynamo")``."""
    from torch._dynamo.utils import counters

    torch._dynamo.reset()
    counters.clear()
    yield
    torch._dynamo.reset()
