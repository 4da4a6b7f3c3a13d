"""``smdm::vw_keyframes``: every implementation equals the heap reference (random, ties, constant
motion, every length 2..N, forced frames, inactive rows), the op is registered properly, and
``torch.compile`` sees one op. The Triton kernel runs under ``TRITON_INTERPRET=1`` on the CPU when
triton is installed (the GPU itself is not needed)."""
import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from smdm_plugin.core.kernels.vw import vw_keyframes
from smdm_plugin.core.kernels.vw_numpy import vw_numpy
from smdm_plugin.core.kernels.vw_torch import vw_torch
from smdm_plugin.core.selection import keyframe_count

from helpers.vw import cases, reference_mask

HAS_TRITON = importlib.util.find_spec("triton") is not None


def every_length(N=14, F=3):
    X = np.random.default_rng(1).standard_normal((N - 1, N, F)).cumsum(1).astype(np.float32)
    lengths = np.arange(2, N + 1)
    return X, lengths, np.array([keyframe_count(int(L), 0.7) for L in lengths]), None, None


IMPLS = {
    "numpy (cpu kernel)": lambda X, L, K, f, a: vw_numpy(X, L, K, f, a),
    "portable torch": lambda X, L, K, f, a: vw_torch(torch.from_numpy(X), torch.from_numpy(L), torch.from_numpy(K),
                                                     None if f is None else torch.from_numpy(f),
                                                     None if a is None else torch.from_numpy(a)).numpy(),
    "registered op": lambda X, L, K, f, a: vw_keyframes(torch.from_numpy(X), torch.from_numpy(L), torch.from_numpy(K),
                                                        None if f is None else torch.from_numpy(f),
                                                        None if a is None else torch.from_numpy(a)).numpy(),
}


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("seed", range(24))
def test_implementation_equals_heap_reference(impl, seed):
    X, L, K, f, a = cases(seed)
    assert np.array_equal(IMPLS[impl](X, L, K, f, a), reference_mask(X, L, K, f, a))


@pytest.mark.parametrize("impl", IMPLS)
def test_every_length_from_2_to_N(impl):
    X, L, K, f, a = every_length()
    assert np.array_equal(IMPLS[impl](X, L, K, f, a), reference_mask(X, L, K, f, a))


def test_forced_frames_count_inside_the_budget_and_inactive_rows_are_empty():
    X, L, K, _, _ = cases(0)
    forced = np.zeros(X.shape[:2], dtype=bool)
    forced[:, 1] = True
    active = np.array([True, False, True, True, False, True])
    m = vw_numpy(X, L, K, forced, active)
    assert not m[~active].any()
    for b in np.flatnonzero(active):
        protected = len({0, 1, int(L[b]) - 1})
        assert m[b].sum() == max(K[b], protected) and m[b, 1] and m[b, 0] and m[b, L[b] - 1]


def test_op_registration_and_one_node_under_compile():
    X, L, K, f, _ = cases(3)
    args = (torch.from_numpy(X), torch.from_numpy(L), torch.from_numpy(K), torch.from_numpy(f), None)
    op = torch.ops.smdm.vw_keyframes.default          # registered for tracing only (eager: a plain call)
    torch.library.opcheck(op, args)
    nodes = []

    def backend(gm, inputs):
        nodes.extend(n.target for n in gm.graph.nodes if n.op == "call_function")
        return gm.forward

    fn = torch.compile(lambda *a: vw_keyframes(*a), fullgraph=True, backend=backend)
    assert torch.equal(fn(*args), vw_keyframes(*args))
    assert nodes.count(op) == 1


def test_triton_kernel_equals_reference_in_interpreter_mode(tmp_path, triton_interpreter):
    """The CUDA kernel's code, run by Triton's interpreter on the CPU, on a few of the cases."""
    data = []
    for seed in (0, 1, 2, 3, 5):
        X, L, K, f, a = cases(seed)
        data.append({"X": X.tolist(), "L": L.tolist(), "K": K.tolist(),
                     "f": None if f is None else f.tolist(), "a": None if a is None else a.tolist(),
                     "ref": reference_mask(X, L, K, f, a).tolist()})
    path = tmp_path / "cases.json"
    path.write_text(json.dumps(data))
    code = (
        "import json, sys, torch\n"
        "from smdm_plugin.core.kernels.vw_triton import vw_triton\n"
        "bad = 0\n"
        f"for c in json.load(open({str(path)!r})):\n"
        "    T = lambda v, dt: None if v is None else torch.tensor(v, dtype=dt)\n"
        "    m = vw_triton(T(c['X'], torch.float32), T(c['L'], torch.long), T(c['K'], torch.long),\n"
        "                  T(c['f'], torch.bool), T(c['a'], torch.bool))\n"
        "    bad += int(not torch.equal(m, torch.tensor(c['ref'])))\n"
        "print('mismatches', bad)\n")
    out = triton_interpreter(code)
    assert "mismatches 0" in out, out