"""Upstream's diffusion tables on the device (``integrations/tables.py``): MDM's
``_extract_into_tensor`` copies a numpy table to the device at every call, which puts a CPU tensor
into a compiled training step's graph; the hook reads a table made once per device, with the same
values. Checked on the ``meta`` device (a stand-in for CUDA: any CPU tensor in the graph shows)."""
from __future__ import annotations

import sys
import types

import numpy as np
import pytest
import torch

pytest.importorskip("torch._dynamo")

from smdm_plugin.integrations.tables import extract_from_device_table, tables_on_device  # noqa: E402

pytestmark = pytest.mark.usefixtures("fresh_dynamo")


def per_call_copy(arr, timesteps, broadcast_shape):
    """A numpy table read the way upstream's diffusion reads it: copied to ``timesteps``' device at
    every call, indexed, float32, broadcast over the trailing dimensions."""
    res = torch.from_numpy(arr).to(timesteps.device)[timesteps].float()
    return res.view(-1, *([1] * (len(broadcast_shape) - 1))).expand(broadcast_shape)


def numpy_reference(arr, index, shape):
    return torch.from_numpy(np.broadcast_to(arr[index].astype(np.float32).reshape(-1, *([1] * (len(shape) - 1))),
                                            shape).copy())


def graph_devices(fn, *args) -> set:
    """The devices of the graph inputs ``torch.compile(fn, fullgraph=True)`` captures."""
    devices = set()

    def backend(gm, example_inputs):
        devices.update(str(t.device) for t in example_inputs if isinstance(t, torch.Tensor))
        return gm.forward

    torch.compile(fn, fullgraph=True, backend=backend)(*args)
    return devices


def test_the_hook_equals_upstream_and_a_graph_reads_only_device_tables():
    table = np.linspace(0.1, 0.9, 20)                       # float64, as upstream's schedules
    other = np.cumprod(np.full(20, 0.99))
    hooked = extract_from_device_table(per_call_copy)
    t = torch.tensor([0, 7, 19])
    for shape in ((3,), (3, 4), (3, 5, 1, 6)):
        want = numpy_reference(table, [0, 7, 19], shape)
        assert torch.equal(hooked(table, t, shape), want) and torch.equal(per_call_copy(table, t, shape), want), shape
    assert hooked(table, t, (3, 2)).dtype == torch.float32

    def step(extract, t):
        return extract(table, t, (3, 2, 4)) * 2 + extract(other, t, (3, 2, 4))

    meta_t = t.to("meta")
    assert "cpu" in graph_devices(lambda u: step(per_call_copy, u), meta_t)     # upstream: a CPU table inside
    torch._dynamo.reset()
    step(hooked, meta_t)                                    # an eager call makes the device tables
    assert graph_devices(lambda u: step(hooked, u), meta_t) == {"meta"}


def test_tables_on_device_hooks_the_modules_of_the_diffusion_classes_once():
    module = types.ModuleType("smdm_test_gaussian_diffusion")
    module._extract_into_tensor = per_call_copy
    sys.modules[module.__name__] = module
    try:
        base = type("GaussianDiffusion", (), {"__module__": module.__name__})
        spaced = type("SpacedDiffusion", (base,), {"__module__": __name__})
        assert tables_on_device(spaced()) == 1 and module._extract_into_tensor is not per_call_copy
        first = module._extract_into_tensor
        assert tables_on_device(spaced()) == 1 and module._extract_into_tensor is first     # not wrapped twice
        assert torch.equal(first(np.arange(5.0), torch.tensor([4, 1]), (2,)), torch.tensor([4.0, 1.0]))
    finally:
        del sys.modules[module.__name__]


def test_arrays_made_anew_at_every_call_are_not_kept_for_ever():
    """Upstream's ``FIXED_LARGE`` variances are an array made at every call: past ``MAX_TABLES``
    kept tables the hook copies as upstream does (the same values) instead of keeping each one."""
    from smdm_plugin.integrations import tables as T

    copies = []

    def counting(arr, timesteps, broadcast_shape):
        copies.append(id(arr))
        return per_call_copy(arr, timesteps, broadcast_shape)

    extract = extract_from_device_table(counting)
    t, shape = torch.tensor([3, 0, 7]), (3, 2, 1, 4)
    base = np.linspace(0.1, 0.9, 10)
    for i in range(T.MAX_TABLES + 20):
        arr = np.append(base[1:2], base[1:]) * (1 + i)                 # a new array per call
        assert torch.equal(extract(arr, t, shape), numpy_reference(arr, t.numpy(), shape))
    assert len(copies) == 20                     # the calls past the bound ran upstream's copy
    keep = base.copy()
    assert torch.equal(extract(keep, t, shape), numpy_reference(keep, t.numpy(), shape))
    assert len(copies) == 21                     # full: a new table is not kept either
