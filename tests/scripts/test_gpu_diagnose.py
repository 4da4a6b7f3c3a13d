"""scripts/gpu_diagnose.py: its parts switch off what they name (the H200 run's "no FSQ" rows ran
with FSQ on), and its sections run on a CPU (``--dry-run``)."""
import importlib.util
import sys

import pytest
import torch

from helpers.paths import ROOT

pytest.importorskip("torch._dynamo")


def _script():
    sys.path.insert(0, str(ROOT / "scripts"))
    spec = importlib.util.spec_from_file_location("gpu_diagnose", ROOT / "scripts" / "gpu_diagnose.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_each_part_switches_off_what_it_names():
    from smdm_plugin.core.fsq import FSQMultiheadAttention
    from smdm_plugin.core.lipschitz import LipschitzMLP
    from smdm_plugin.training import workloads

    gd = _script()
    seen = {}
    for label, config in gd.PARTS.items():
        model, _ = workloads.build("trans_enc", 0.8, torch.device("cpu"), True, 10, frames=40, **config)
        seen[label] = (any(isinstance(m, FSQMultiheadAttention) for m in model.modules()),
                       any(isinstance(m, LipschitzMLP) for m in model.modules()))
    assert seen == {"recipe": (True, True), "no FSQ": (False, True), "no Lipschitz": (True, False),
                    "neither": (False, False)}


def test_dry_run_prints_every_model_and_part(tmp_path, capsys, monkeypatch):
    gd = _script()
    monkeypatch.setattr(sys, "argv", ["gpu_diagnose.py", "--dry-run", "--sections", "syncs", "parts",
                                      "--out", str(tmp_path)])
    assert gd.main() == 0
    out = capsys.readouterr().out
    for _, _, name in gd.gcheck.MODELS:
        assert f"{name} train: 0 syncs" in out and f"{name} sample: 0 syncs" in out
    for amp in ("bf16", "fp32"):
        for call in ("train", "sample"):
            line = next(ln for ln in out.splitlines() if ln.startswith(f"{amp} {call}: "))
            assert all(f"{k} " in line for k in ["dense", *gd.PARTS]), line
    assert "Traceback" not in out


def test_kernels_section_switches_each_group_the_other_way_and_restores(tmp_path, capsys, monkeypatch):
    """``--sections kernels``: each timed case runs with exactly its group of Triton kernels switched
    away from the default (the others at theirs), and the defaults are back afterwards."""
    from smdm_plugin.core.kernels import TRITON_KERNELS

    gd = _script()
    states = []
    real = gd.event_times

    def recording(fn, device, repeats, warmup):
        states.append({n: k.enabled for n, k in TRITON_KERNELS.items()})
        return real(fn, device, repeats, warmup)

    monkeypatch.setattr(gd, "event_times", recording)
    monkeypatch.setattr(sys, "argv", ["gpu_diagnose.py", "--dry-run", "--sections", "kernels", "--out", str(tmp_path)])
    assert gd.main() == 0
    out = capsys.readouterr().out
    defaults = {n: k.default for n, k in TRITON_KERNELS.items()}
    assert {n: k.enabled for n, k in TRITON_KERNELS.items()} == defaults
    flipped = {frozenset(n for n in s if s[n] != defaults[n]) for s in states}
    assert flipped == {frozenset()} | {frozenset(g) for g in gd.KERNEL_GROUPS.values()}
    for arch in ("trans_enc", "trans_dec"):
        for amp in ("bf16", "fp32"):
            for call in ("train", "sample"):
                line = next(ln for ln in out.splitlines() if ln.startswith(f"{arch} {amp} {call}: "))
                assert all(f"{g} " in line for g in gd.KERNEL_GROUPS), line
    assert "Traceback" not in out


def test_optimizer_section_runs_and_agrees_on_a_cpu(tmp_path, capsys, monkeypatch):
    """``--sections optimizer`` (0.9.7's upstream-run checks for the next GPU session): on a CPU's dry
    run the fused AdamW resumed from a foreach state stays fused and agrees with foreach, a fused
    state loads into torch's AdamW, the one-sync norms and the device tables equal upstream's, and
    so do 0.9.8's timesteps made on the device, pinned timestep draws and losses read at a dump, and
    0.9.9's MotionDiffuse padding mask and printed loss."""
    gd = _script()
    monkeypatch.setattr(sys, "argv", ["gpu_diagnose.py", "--dry-run", "--sections", "optimizer", "--out", str(tmp_path)])
    assert gd.main() == 0
    out = capsys.readouterr().out
    assert "Traceback" not in out
    resumed = next(ln for ln in out.splitlines() if ln.startswith("AdamW resumed from a foreach state: fused True"))
    assert float(resumed.split("after 2 steps ")[1].split(";")[0]) < 1e-5, resumed
    assert "a fused state in torch's AdamW: fused True" in out
    norms = next(ln for ln in out.splitlines() if ln.startswith("norms of 40 tensors"))
    assert "max relative difference 0.00e+00" in norms, norms       # bit for bit on the CPU
    assert "6 schedule reads (a p_sample step): equal True" in out
    for line in ("50 steps of timesteps and timestep_map: equal True", "10 timestep draws: equal True",
                 "5 batches to the loop: equal True",
                 "50 steps of a logged loss: equal True",
                 "MotionDiffuse padding mask, B=32: equal True", "MotionDiffuse, 50 steps of the loss printed: equal True"):
        assert line in out, out
