"""``--sparse_compile`` on the real upstream code (CPU; docs/compile.md).

Each run compiles with ``SMDM_COMPILE_BACKEND=aot_eager`` (Dynamo + AOTAutograd, no code
generation: quick on 2 cores; inductor compiles the same graphs) and writes the compile
statistics at exit (``SMDM_COMPILE_STATS``): per model, the phases it ran in (train / eval, grad,
motion shape; each phase's first call runs eagerly: ``warm_calls``), its compiled calls and
``recompiles`` (calls after the first compiled call of their phase that made Dynamo capture a new
graph).

* MDM (``smdm run``): a sparse trans_enc trains 20 steps compiled, the whole loss step
  (``diffusion.training_losses``, forward and backward, the model's call inside): one graph, zero recompiles,
  the same weights as an eager run on the static-shape path (``static_mode``: what runs on a GPU;
  the CPU's eager default packs keyframes differently, so its dropout draws differ), the setting
  in ``args.json``, no ``_orig_mod.`` key in the checkpoint; ``sample.generate`` from it: the
  guidance wrapper's call whole (both passes and their combination, one call per step): one
  graph, zero recompiles, samples equal to eager; ``sample.edit`` (in-betweening: forced
  keyframes, a graph break at their host count): zero recompiles, equal to eager. DiP: training
  (the whole loss step) and autoregressive guided sampling (whole), zero recompiles. Under
  ``torchrun`` (2 ranks): the model call, compiled inside DDP. A dense MDM: its whole loss step,
  zero recompiles.
* MDM through the patch: training and ``eval.eval_humanml`` (guided calls whole), zero
  recompiles, finite FID.
* priorMDM (patch): training compiled, the whole loss step (zero recompiles, ``args.json``);
  DoubleTake, both takes, guided calls whole: zero recompiles after each take's first call, the
  unfolded sample equal to eager.
* MotionDiffuse (patch): a sparse MotionTransformer trains compiled: zero recompiles, ``opt.txt``
  states the setting, losses equal to eager within float tolerance (dropout 0 there).
"""
from __future__ import annotations

import json
import os
import re
import sys

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _upstream import fused_policy_path  # noqa: E402

COMPILE_ENV = {"SMDM_COMPILE_BACKEND": "aot_eager"}


def stats(path: str) -> dict:
    with open(path) as f:
        data = json.load(f)
    assert len(data["models"]) >= 1, data
    return data


def ran(data: dict) -> list:
    """The compiled functions that ran (a training run also builds upstream's guidance wrapper for
    its evaluations: compiled, not called; a whole step's model runs only inside it)."""
    return [m for m in data["models"] if m["warm_calls"] + m["compiled_calls"] + m["eager_calls"] > 0]


def entry(data: dict, name: str) -> dict:
    found = [m for m in data["models"] if m["name"] == name]
    assert len(found) == 1, data
    return found[0]


def model_call(data: dict) -> dict:
    found = [m for m in data["models"] if m["captures"] == "model call"]
    assert len(found) == 1, data
    return found[0]


def assert_no_recompiles(data: dict, phases: int) -> None:
    m = ran(data)[-1]
    assert m["recompiles"] == 0 and m["eager_calls"] == 0, data
    assert m["phases"] == phases and m["warm_calls"] == phases, data        # each phase's first call: eager
    if m["fullgraph"]:
        assert data["graphs"] == phases, data                     # one graph per phase, none after


def assert_whole_training_step(data: dict, steps: int = None) -> None:
    """A one-process training run captured its loss step whole: the last compiled function is
    ``diffusion.training_losses`` (one graph, the model's call traced inside it, and run eagerly
    inside the step's first, eager call: never a call of its own), ``steps`` loss calls when given."""
    step, model = entry(data, "training_losses"), model_call(data)
    assert ran(data) == [step] and step["captures"] == "training step: loss forward and backward", data
    assert model["compiled_calls"] == model["warm_calls"] == model["phases"] == 0, data
    if steps is not None:
        assert step["warm_calls"] + step["compiled_calls"] == steps, step


def assert_guided_whole(data: dict, calls: int = None) -> dict:
    """A sampling run captured its guided calls whole: the last compiled function is upstream's
    ``ClassifierFreeSampleModel`` (both passes and their combination, one graph per phase; the
    model's call traced inside it, never a call of its own), zero recompiles, ``calls`` calls when
    given. Returns its counters."""
    guided, model = entry(data, "ClassifierFreeSampleModel"), model_call(data)
    assert ran(data) == [guided], data
    assert guided["captures"] == "guided sampling call: every guidance pass", data
    assert guided["recompiles"] == 0 and guided["eager_calls"] == 0, data
    assert model["compiled_calls"] == model["warm_calls"] == 0, data
    if calls is not None:
        assert guided["warm_calls"] + guided["compiled_calls"] == calls, guided
    return guided


# --------------------------------------------------------------------------- MDM (smdm run)
MDM_ROOT = os.environ.get("SMDM_MDM_ROOT")


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_mdm_trains_20_steps_and_samples_compiled(upstream_copy, tmp_path, monkeypatch):
    import torch

    import test_mdm_upstream as M

    repo = upstream_copy(MDM_ROOT, "mdm_compile")
    runs = {}
    for mode in ("none", "default"):
        for k, v in COMPILE_ENV.items():
            monkeypatch.setenv(k, v)
        st = str(tmp_path / f"train_{mode}.json")
        monkeypatch.setenv("SMDM_COMPILE_STATS", st)
        save = str(tmp_path / f"save_{mode}")
        if mode == "none":   # eager on the static-shape path (a GPU's path; same dropout draws)
            args = ["--save_dir", save, "--num_steps", "20", *M.TINY, *M.ARCH["trans_enc"], "--sparse"]
            code = ("import runpy, sys; from smdm_plugin.core.checks import static_mode\n"
                    f"sys.argv = ['train_mdm'] + {args!r}\n"
                    "with static_mode():\n    runpy.run_module('train.train_mdm', run_name='__main__')")
            M.harness_code(repo, code, launcher=True)
            ckpt = M.latest_checkpoint(save)
        else:
            proc, ckpt = M.train(repo, save, "trans_enc", 20, extra=["--sparse", "--sparse_compile", mode],
                                 launcher=True)
            data = stats(st)
            assert_no_recompiles(data, phases=1)          # the whole step: one graph, the model's call inside
            assert_whole_training_step(data, steps=21)    # --num_steps 20: 21 steps (MDM's loop)
            args = json.load(open(os.path.join(save, "args.json")))
            assert args["sparse_compile"] == "default"
            assert args["sparse_compile_applied"].startswith(
                "torch.compile default (aot_eager, fullgraph=True; training step: loss forward and backward)")
        runs[mode] = M.load_sd(ckpt)
    assert not [k for k in runs["default"] if "_orig_mod" in k] and runs["default"].keys() == runs["none"].keys()
    for k, v in runs["none"].items():
        assert torch.allclose(runs["default"][k].float(), v.float(), atol=1e-4), k

    samples = {}
    for mode in ("none", "default"):
        st = str(tmp_path / f"gen_{mode}.json")
        monkeypatch.setenv("SMDM_COMPILE_STATS", st)
        _, res = M.generate(repo, ckpt, str(tmp_path / f"gen_{mode}"), "trans_enc",
                            extra=["--sparse_compile", mode], launcher=True)
        samples[mode] = res["motion"]
        if mode == "default":
            data = stats(st)
            assert_no_recompiles(data, phases=1)
            assert_guided_whole(data, calls=20)                  # 20 steps, both guidance passes in each
    assert np.allclose(samples["default"], samples["none"], atol=1e-4)

    edits = {}                       # sample.edit in_between: the kept frames are forced keyframes
    for mode in ("none", "default"):
        st = str(tmp_path / f"edit_{mode}.json")
        monkeypatch.setenv("SMDM_COMPILE_STATS", st)
        out = str(tmp_path / f"edit_{mode}")
        M.mdm(repo, "sample.edit", ["--model_path", ckpt, "--output_dir", out, "--num_samples", "2",
                                    "--num_repetitions", "1", "--edit_mode", "in_between", "--text_condition",
                                    "a person walks", "--sparse_compile", mode], launcher=True)
        edits[mode] = np.load(os.path.join(out, "results.npy"), allow_pickle=True).item()["motion"]
    assert_guided_whole(stats(st), calls=20)
    assert np.allclose(edits["default"], edits["none"], atol=1e-4)


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_mdm_dense_trains_its_whole_step_compiled(upstream_copy, tmp_path, monkeypatch):
    """The A/B's other side: a dense MDM (no ``--sparse``) with ``--sparse_compile`` captures its
    whole loss step too (``fullgraph=False`` for dense models): zero recompiles, ``args.json``
    states it, the checkpoint loads into upstream's dense model (no ``_orig_mod.`` keys)."""
    import test_mdm_upstream as M

    repo = upstream_copy(MDM_ROOT, "mdm_compile_dense")
    for k, v in COMPILE_ENV.items():
        monkeypatch.setenv(k, v)
    st = str(tmp_path / "train.json")
    monkeypatch.setenv("SMDM_COMPILE_STATS", st)
    save = str(tmp_path / "dense")
    _, ckpt = M.train(repo, save, "trans_enc", 6, extra=["--sparse_compile", "default"], launcher=True)
    data = stats(st)
    assert_no_recompiles(data, phases=1)
    assert_whole_training_step(data, steps=7)                     # --num_steps 6: 7 steps (MDM's loop)
    assert entry(data, "training_losses")["fullgraph"] is False
    applied = json.load(open(os.path.join(save, "args.json")))["sparse_compile_applied"]
    assert applied == "torch.compile default (aot_eager, fullgraph=False; training step: loss forward and backward)"
    sd = M.load_sd(ckpt)
    assert not [k for k in sd if "_orig_mod" in k or k.startswith("smdm")], sorted(sd)[:5]


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_mdm_compiled_run_steps_a_fused_optimizer_across_a_resume(upstream_copy, tmp_path, monkeypatch):
    """Where the fused optimizer applies (CUDA; here the policy stands in for it on the CPU), a
    compiled MDM run's ``AdamW`` is fused (its norms and ``--use_ema``'s average hooked too),
    ``args.json`` says so, the optimizer checkpoint is fused, a resume (upstream's
    ``--resume_checkpoint``: it loads the state and sets ``capturable``) steps on fused from the
    saved counters, and the weights and their average equal a run with upstream's optimizer step
    (same compiled loss step) to float rounding."""
    import torch

    import test_mdm_upstream as M
    from smdm_plugin.families.mdm.upstream_optim import OPTIMIZER_NOTE

    repo = upstream_copy(MDM_ROOT, "mdm_compile_fused")
    for k, v in COMPILE_ENV.items():
        monkeypatch.setenv(k, v)
    common = [*M.TINY, *M.ARCH["trans_enc"], "--sparse", "--sparse_compile", "default", "--use_ema"]
    plain_path, site = os.environ.get("PYTHONPATH", ""), fused_policy_path(str(tmp_path / "site"))
    saves = {}
    for name, fused in (("fused", True), ("foreach", False)):
        monkeypatch.setenv("PYTHONPATH", site + os.pathsep + plain_path if fused else plain_path)
        saves[name] = str(tmp_path / name)
        M.mdm(repo, "train.train_mdm", ["--save_dir", saves[name], "--num_steps", "3", *common], launcher=True)
        applied = json.load(open(os.path.join(saves[name], "args.json")))["sparse_compile_applied"]
        assert applied.endswith("; " + OPTIMIZER_NOTE) == fused, applied
    ckpt = M.latest_checkpoint(saves["fused"])
    opt_file = os.path.join(saves["fused"], "opt" + os.path.basename(ckpt)[len("model"):])
    groups = torch.load(opt_file, map_location="cpu", weights_only=False)["param_groups"]
    assert groups[0]["fused"] is True
    a = torch.load(ckpt, map_location="cpu", weights_only=True)
    b = torch.load(M.latest_checkpoint(saves["foreach"]), map_location="cpu", weights_only=True)
    assert a.keys() == b.keys() == {"model", "model_avg"}                     # --use_ema: both saved
    for part in a:
        assert a[part].keys() == b[part].keys()
        for k in a[part]:
            assert torch.allclose(a[part][k].float(), b[part][k].float(), atol=1e-5), (part, k)

    resumed = str(tmp_path / "resumed")
    monkeypatch.setenv("PYTHONPATH", site + os.pathsep + plain_path)
    proc = M.mdm(repo, "train.train_mdm", ["--save_dir", resumed, "--num_steps", "6", "--resume_checkpoint", ckpt,
                                           *common], launcher=True)
    assert "loading optimizer state from checkpoint" in proc.stdout + proc.stderr
    last = M.latest_checkpoint(resumed)
    state = torch.load(os.path.join(resumed, "opt" + os.path.basename(last)[len("model"):]),
                       map_location="cpu", weights_only=False)
    assert state["param_groups"][0]["fused"] is True and state["param_groups"][0]["capturable"] is True
    first = torch.load(opt_file, map_location="cpu", weights_only=False)["state"][0]["step"]
    steps = {float(s["step"]) for s in state["state"].values()}
    assert len(steps) == 1 and steps.pop() > float(first) > 0, (float(first), steps)   # on from the saved counters


#: a ``sitecustomize`` line that holds each FSQ layer's key maps apart, as 0.9 did (0.10: one bank per stack)
PER_LAYER_KEY_MAPS = ("import smdm_plugin.core.fsq as F, smdm_plugin.families.mdm.model as M\n"
                      "_quantize = F.quantize_attention_keys\n"
                      "M.quantize_attention_keys = lambda module, levels, bank=True: _quantize(module, levels, bank=False)\n")


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_mdm_run_of_per_layer_key_maps_resumes_with_its_optimizer_state(upstream_copy, tmp_path, monkeypatch):
    """A sparse run that 0.9 wrote (each FSQ layer's key maps apart: 4 tensors per layer for
    ``AdamW``) resumes today (one bank: 4 tensors): upstream's ``_load_optimizer_state`` is handed the
    state in today's layout, and the Adam counters go on from the saved ones. (Upstream's resume sets
    ``capturable``, which torch's AdamW refuses on the CPU: the fused policy stands in for CUDA's.)"""
    import torch

    import test_mdm_upstream as M
    from _upstream import FUSED_POLICY

    repo = upstream_copy(MDM_ROOT, "mdm_resume_0_9")
    for k, v in COMPILE_ENV.items():
        monkeypatch.setenv(k, v)
    common = [*M.TINY, *M.ARCH["trans_enc"], "--sparse", "--sparse_compile", "default"]
    plain = os.environ.get("PYTHONPATH", "")
    old_site, site = str(tmp_path / "old_site"), fused_policy_path(str(tmp_path / "site"))
    os.makedirs(old_site)
    with open(os.path.join(old_site, "sitecustomize.py"), "w") as f:
        f.write(FUSED_POLICY + PER_LAYER_KEY_MAPS)
    monkeypatch.setenv("PYTHONPATH", old_site + os.pathsep + plain)
    old = str(tmp_path / "old")
    M.mdm(repo, "train.train_mdm", ["--save_dir", old, "--num_steps", "3", *common], launcher=True)
    ckpt = M.latest_checkpoint(old)
    saved = torch.load(os.path.join(old, "opt" + os.path.basename(ckpt)[len("model"):]), map_location="cpu",
                       weights_only=False)
    monkeypatch.setenv("PYTHONPATH", site + os.pathsep + plain)
    new = str(tmp_path / "new")
    proc = M.mdm(repo, "train.train_mdm", ["--save_dir", new, "--num_steps", "6", "--resume_checkpoint", ckpt,
                                           *common], launcher=True)
    assert "loading optimizer state from checkpoint" in proc.stdout + proc.stderr
    last = M.latest_checkpoint(new)
    state = torch.load(os.path.join(new, "opt" + os.path.basename(last)[len("model"):]), map_location="cpu",
                       weights_only=False)
    n_old, n_new = (len(s["param_groups"][0]["params"]) for s in (saved, state))
    assert n_old - n_new == 4 * 2 - 4                              # --layers 2
    first = float(saved["state"][0]["step"])
    steps = {float(s["step"]) for s in state["state"].values()}
    assert len(steps) == 1 and steps.pop() > first > 0, (first, steps)


#: harness code: ``sample.generate`` with ``ARGS``, counting what upstream's diffusion copies from the
#: host to the device (on CUDA a blocking copy, after which PyTorch synchronizes the stream): the
#: numpy tables inside ``p_sample`` (``torch.from_numpy``: one per ``_extract_into_tensor`` call
#: upstream) and the tensors the sampling loop makes from host data (``torch.tensor`` called by
#: upstream's diffusion modules or the hook's ``th``: upstream's ``th.tensor([i] * B,
#: device=device)``, one per step)
COUNT_TABLE_COPIES = """
import atexit, sys, torch
import diffusion.gaussian_diffusion as G
import sample.generate as generate         # the harness's no-render stubs are on this module
n = {"copies": 0, "steps": 0, "inside": 0, "tensors": 0, "in_loop": 0}
_from_numpy, _tensor, _p_sample = torch.from_numpy, torch.tensor, G.GaussianDiffusion.p_sample
_loop = G.GaussianDiffusion.p_sample_loop_progressive
def from_numpy(a):
    n["copies"] += bool(n["inside"])
    return _from_numpy(a)
def tensor(*a, **k):
    caller = sys._getframe(1).f_code.co_filename
    n["tensors"] += bool(n["in_loop"]) and caller.endswith(("gaussian_diffusion.py", "respace.py", "timesteps.py"))
    return _tensor(*a, **k)
def p_sample(self, *a, **k):
    n["steps"] += 1
    n["inside"] += 1
    try:
        return _p_sample(self, *a, **k)
    finally:
        n["inside"] -= 1
def loop(self, *a, **k):
    steps = _loop(self, *a, **k)
    while True:
        n["in_loop"] += 1
        try:
            out = next(steps)
        except StopIteration:
            return
        finally:
            n["in_loop"] -= 1
        yield out
torch.from_numpy, torch.tensor, G.GaussianDiffusion.p_sample = from_numpy, tensor, p_sample
G.GaussianDiffusion.p_sample_loop_progressive = loop
atexit.register(lambda: print("TABLE_COPIES", n["copies"], n["steps"], n["tensors"], flush=True))
sys.argv = ["generate"] + ARGS
generate.main()
"""


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_mdm_compiled_sampling_copies_no_table_per_step(upstream_copy, tmp_path, monkeypatch):
    """``--sparse_compile`` sampling reads upstream's schedules from device tables and fills each
    step's timesteps on the device: upstream's ``p_sample`` copies six numpy tables to the device
    per step, its loop a list of timesteps and ``respace``'s model wrapper its ``timestep_map``
    (each a blocking copy and a stream synchronization on CUDA); with the flag, each table and the
    map once per run, no timesteps; the same samples."""
    import test_mdm_upstream as M

    repo = upstream_copy(MDM_ROOT, "mdm_tables")
    for k, v in COMPILE_ENV.items():
        monkeypatch.setenv(k, v)
    _, ckpt = M.train(repo, str(tmp_path / "save"), "trans_enc", 1, extra=["--sparse"], launcher=True)
    counts = {}
    for mode in ("none", "default"):
        args = ["--model_path", ckpt, "--output_dir", str(tmp_path / f"gen_{mode}"), "--num_samples", "2",
                "--num_repetitions", "1", "--seed", "3", *M.GEN["trans_enc"], "--sparse_compile", mode]
        proc = M.mdm(repo, "-c", [COUNT_TABLE_COPIES.replace("ARGS", repr(args))], launcher=True)
        line = [ln for ln in proc.stdout.splitlines() if ln.startswith("TABLE_COPIES ")]
        assert len(line) == 1, proc.stdout[-3000:]
        counts[mode] = tuple(int(v) for v in line[0].split()[1:])
    print("table copies, steps, timestep copies (upstream, --sparse_compile):", counts["none"], counts["default"])
    (upstream, steps, upstream_t), (hooked, steps_hooked, hooked_t) = counts["none"], counts["default"]
    assert steps == steps_hooked == 20, counts                   # --diffusion_steps 20
    assert upstream == 6 * steps and upstream_t == 2 * steps, counts   # six tables, two int lists per step
    assert hooked <= 6 and hooked_t == 1, counts                 # each table once (4 distinct ones); the map once
    a, b = (np.load(str(tmp_path / f"gen_{mode}" / "results.npy"), allow_pickle=True).item()["motion"]
            for mode in ("none", "default"))
    assert a.shape == b.shape and np.allclose(a, b, atol=1e-4), np.abs(a - b).max()


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_mdm_step_after_the_loss_host_work(upstream_copy, tmp_path):
    """Upstream's step after the loss (the logged norms, AdamW, ``--use_ema``'s average) on its
    own ``TrainLoop``, counted (``optimizer_step_work.py``): what a compiled run on CUDA runs
    instead reads nothing back per tensor (0 ``.item()``; upstream: one per norm), runs a handful
    of aten ops (upstream: thousands, a few per tensor) and logs the same norms."""
    import test_mdm_upstream as M

    repo = upstream_copy(MDM_ROOT, "mdm_step_work")
    code = f"exec(open({os.path.join(HERE, 'optimizer_step_work.py')!r}).read())"
    proc = M.mdm(repo, "-c", [code, "--save_dir", str(tmp_path / "save"), "--num_steps", "1", *M.TINY,
                              *M.ARCH["trans_enc"], "--use_ema"])
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("OPTIMIZER_STEP_WORK ")]
    assert len(line) == 1, proc.stdout[-3000:]
    row = json.loads(line[0].split(" ", 1)[1])
    up, hooked = row["upstream"], row["hooked"]
    assert row["same_norms"] and row["use_ema"], row
    assert up["reads"] >= row["params"] + row["with_grad"] and hooked["reads"] == 0, row
    assert hooked["ops"] <= 16 and up["ops"] >= 4 * row["params"], row
    assert hooked["calls"] < up["calls"] / 4, row


def training_log(proc) -> dict:
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("TRAINING_LOG ")]
    assert len(line) == 1, proc.stdout[-3000:]
    return json.loads(line[0].split(" ", 1)[1])


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_mdm_training_log_kept_until_read(upstream_copy, tmp_path, monkeypatch):
    """Upstream's training log (``log_loss_dict``, the norms) kept until it is read
    (``training_log_reads.py``): on upstream's own ``TrainLoop`` and logger, every dump has
    upstream's keys, order, types and values, and no ``run_step`` reads a value back outside the
    optimizer (upstream: three reads per loss, one per norm). A ``--sparse_compile`` run where the
    fused optimizer applies (CUDA; the policy standing in): no read in any step at all, its batches
    handed to the loop on its device."""
    import test_mdm_upstream as M

    repo = upstream_copy(MDM_ROOT, "mdm_log_kept")
    code = f"exec(open({os.path.join(HERE, 'training_log_reads.py')!r}).read())"
    common = ["--num_steps", "5", "--log_interval", "2", *M.TINY, *M.ARCH["trans_enc"]]
    rows = {}
    for keep in ("0", "1"):
        monkeypatch.setenv("SMDM_TEST_KEEP_LOG", keep)
        rows[keep] = training_log(M.mdm(repo, "-c", [code, "--save_dir", str(tmp_path / keep), *common]))
    up, kept = rows["0"], rows["1"]
    assert len(up["dumps"]) >= 3 and up["dumps"] == kept["dumps"], (up["dumps"], kept["dumps"])
    keys = {k for dump in up["dumps"] for k, _, _ in dump}
    assert {"loss", "grad_norm", "param_norm", "step"} <= keys and any("_q" in k for k in keys), keys
    steps = len(up["reads"])
    assert steps >= 5 and kept["reads"] == [0] * steps, kept["reads"]
    assert min(up["reads"]) >= 3 * 2 + 2, up["reads"]                       # loss, rot_mse; two norms
    assert up["optimizer_reads"] == kept["optimizer_reads"]                  # a foreach AdamW's counters

    monkeypatch.delenv("SMDM_TEST_KEEP_LOG")
    for k, v in COMPILE_ENV.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setenv("PYTHONPATH", fused_policy_path(str(tmp_path / "site")) + os.pathsep
                       + os.environ.get("PYTHONPATH", ""))
    flagged = training_log(M.mdm(repo, "-c", [code, "--save_dir", str(tmp_path / "flag"), *common, "--sparse",
                                              "--sparse_compile", "default"], launcher=True))
    assert flagged["reads"] == [0] * len(flagged["reads"]) and flagged["optimizer_reads"] == flagged["reads"], flagged
    assert flagged["data"] == "DeviceBatches" and up["data"] == "DataLoader", (flagged["data"], up["data"])
    # (apart: the CPU's numpy keyframe selection reads its input; CUDA runs its own kernel)
    assert len(flagged["dumps"]) == len(up["dumps"]), flagged["dumps"]
    for dump in flagged["dumps"]:
        values = {k: v for k, _, v in dump}
        assert {"loss", "grad_norm", "step"} <= values.keys() and np.isfinite(float(values["loss"])), dump


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_mdm_torchrun_compiled_inside_ddp(upstream_copy, tmp_path, monkeypatch):
    """``smdm run -- torchrun --nproc_per_node 2`` (gloo): the model compiled inside MDM's DDP
    wrapper, the optimizer step fused with ``--use_ema`` (the CUDA policy standing in on the CPU);
    both ranks end with identical parameters, zero recompiles on each, ``args.json`` says so."""
    import torch

    import test_mdm_upstream as M
    from smdm_plugin.families.mdm.upstream_optim import OPTIMIZER_NOTE

    repo = upstream_copy(MDM_ROOT, "mdm_compile_ddp")
    for k, v in COMPILE_ENV.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setenv("PYTHONPATH", fused_policy_path(str(tmp_path / "site")) + os.pathsep
                       + os.environ.get("PYTHONPATH", ""))
    monkeypatch.setenv("SMDM_COMPILE_STATS", str(tmp_path / "rank{rank}.json"))
    probe = tmp_path / "probe"
    probe.mkdir()
    M.torchrun_train(repo, str(tmp_path / "save"), str(probe), "trans_enc",
                     ["--sparse", "--sparse_compile", "default", "--use_ema"], launcher=True)
    applied = json.load(open(tmp_path / "save" / "args.json"))["sparse_compile_applied"]
    assert applied.endswith("; model call); " + OPTIMIZER_NOTE), applied
    r0, r1 = (torch.load(probe / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    assert sorted(r0) == sorted(r1) and not [k for k in r0 if "_orig_mod" in k]
    for k in r0:
        assert torch.equal(r0[k], r1[k]), k
    for r in (0, 1):
        data = stats(str(tmp_path / f"rank{r}.json"))
        assert_no_recompiles(data, phases=1)
        assert [m["captures"] for m in ran(data)] == ["model call"], data         # DDP: the model call only


# --------------------------------------------------------------------------- priorMDM DoubleTake
PRIOR_ROOT = os.environ.get("SMDM_PRIORMDM_ROOT")


@pytest.mark.skipif(not PRIOR_ROOT, reason="SMDM_PRIORMDM_ROOT not set")
def test_doubletake_samples_compiled(tmp_path, monkeypatch):
    import shutil

    import test_priormdm_upstream as P

    if not P.DATA:
        pytest.skip("no HumanML3D-format data")
    run, save = P.prepare(str(tmp_path / "priorMDM")), str(tmp_path / "save" / "sparse")
    for k, v in COMPILE_ENV.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setenv("SMDM_COMPILE_STATS", str(tmp_path / "train.json"))
    P.harness(run, *P.train_args(save, 2), "--sparse_compile", "default")   # priorMDM's training, compiled
    assert_no_recompiles(stats(str(tmp_path / "train.json")), phases=1)
    assert_whole_training_step(stats(str(tmp_path / "train.json")))
    applied = json.load(open(os.path.join(save, "args.json")))["sparse_compile_applied"]
    assert applied.startswith("torch.compile") and "training step: loss forward and backward" in applied, applied
    ckpt = os.path.join(save, "model000000002.pt")
    motions = {}
    for mode in ("none", "default"):
        for k, v in COMPILE_ENV.items():
            monkeypatch.setenv(k, v)
        st = str(tmp_path / f"dt_{mode}.json")
        monkeypatch.setenv("SMDM_COMPILE_STATS", st)
        texts = os.path.join(run, "dt_texts.txt")
        with open(texts, "w") as f:
            f.write("a person walks forward\na person jumps up and down\na person waves\n")
        P.harness(run, "-m", "sample.double_take", "--model_path", ckpt, "--num_samples", "3",
                  "--handshake_size", str(P.H), "--blend_len", str(P.BLEND), "--skip_steps_double_take",
                  str(P.SKIP), "--input_text", texts, "--guidance_param", "2.5", "--sparse_compile", mode)
        out_dir = P.dt_out_dir(run, ckpt, input_text=texts)
        motions[mode] = np.load(os.path.join(out_dir, "results.npy"), allow_pickle=True).item()["motion"]
        shutil.rmtree(out_dir)
        if mode == "default":
            data = stats(st)
            assert_no_recompiles(data, phases=2)                  # first take, second take
            guided = assert_guided_whole(data, calls=P.DT_STEPS + (P.DT_STEPS - P.SKIP))   # both takes
            # the forcing has its bound (--handshake_size, --blend_len): nothing read on the host, so
            # every call traced whole (fullgraph=True raises at a graph break)
            assert guided["fullgraph"] is True, guided
    assert np.allclose(motions["default"], motions["none"], atol=1e-4)


# --------------------------------------------------------------------------- MotionDiffuse
MD_ROOT = os.environ.get("SMDM_MOTIONDIFFUSE_ROOT")


@pytest.mark.skipif(not MD_ROOT, reason="SMDM_MOTIONDIFFUSE_ROOT not set")
def test_motiondiffuse_trains_compiled(tmp_path, monkeypatch):
    import test_motiondiffuse_upstream as D

    if not D.DATA:
        pytest.skip("no HumanML3D-format data")
    import torch

    from smdm_plugin.families.motiondiffuse.upstream import LOSS_READ_NOTE

    losses = {}
    plain_path, site = os.environ.get("PYTHONPATH", ""), fused_policy_path(str(tmp_path / "site"))
    for name, mode in (("none", "none"), ("default", "default"), ("fused", "default")):
        for k, v in COMPILE_ENV.items():
            monkeypatch.setenv(k, v)
        st = str(tmp_path / f"md_{name}.json")
        monkeypatch.setenv("SMDM_COMPILE_STATS", st)
        # "fused": the fused Adam as on CUDA (the policy stands in for it on the CPU)
        monkeypatch.setenv("PYTHONPATH", site + os.pathsep + plain_path if name == "fused" else plain_path)
        t2m = D.prepare(str(tmp_path / f"md_{name}"))
        out = D.harness(t2m, *D.train_args(3), "--sparse_compile", mode, anomaly=False)  # 21 iterations
        losses[name] = np.array([float(v) for v in re.findall(r"loss_mot_rec: (\S+)", out)])
        if mode == "default":
            assert_no_recompiles(stats(st), phases=1)
            run = os.path.join(t2m, "checkpoints", "t2m", "sparse_ci")
            applied = [ln for ln in open(os.path.join(run, "opt.txt")).read().splitlines()
                       if ln.startswith("sparse_compile_applied: torch.compile default")]
            # the patch route: upstream's backward_G reads the loss (the note says so)
            assert len(applied) == 1 and applied[0].endswith("; " + LOSS_READ_NOTE) == (name == "fused"), applied
            groups = torch.load(os.path.join(run, "model", "latest.tar"), map_location="cpu",
                                weights_only=False)["opt_encoder"]["param_groups"]
            assert bool(groups[0]["fused"]) == (name == "fused"), groups[0]
    for name in ("default", "fused"):
        assert len(losses[name]) >= 20 and np.allclose(losses[name], losses["none"], rtol=1e-3, atol=1e-5), name


@pytest.mark.skipif(not MD_ROOT, reason="SMDM_MOTIONDIFFUSE_ROOT not set")
def test_motiondiffuse_hooks_compiled_loop_prints_the_loss_it_did_not_read(tmp_path, monkeypatch):
    """The hooks' route (what ``smdm run`` installs) with ``--sparse_compile default`` and the fused
    ``Adam`` as on CUDA (the policy standing in): ``loop_without_sync`` hooks upstream's own trainer
    and loop (``families/motiondiffuse/upstream_loop.py``): ``backward_G`` returns a ``LossValue``,
    upstream's loop sums three steps of it and ``print_current_loss`` prints their mean; the means
    equal the eager hooks' run (rtol 1e-3: the compiled step and the fused Adam), the note says
    the loss was logged without a sync."""
    import test_motiondiffuse_upstream as D

    if not D.DATA:
        pytest.skip("no HumanML3D-format data")
    from smdm_plugin.families.motiondiffuse.upstream import OPTIMIZER_NOTE

    args = D.train_args(3)                                   # 21 iterations
    args[args.index("--log_every") + 1] = "3"
    plain_path, site = os.environ.get("PYTHONPATH", ""), fused_policy_path(str(tmp_path / "site"))
    means = {}
    for name in ("eager", "fused"):
        for k, v in COMPILE_ENV.items():
            monkeypatch.setenv(k, v)
        monkeypatch.setenv("PYTHONPATH", site + os.pathsep + plain_path if name == "fused" else plain_path)
        t2m = D.prepare(str(tmp_path / f"md_{name}"), patch=False)
        extra = ["--sparse_compile", "default"] if name == "fused" else []
        out = D.harness(t2m, *args, *extra, hooks="motiondiffuse", anomaly=False)
        means[name] = np.array([float(v) for v in re.findall(r"loss_mot_rec: (\S+)", out)])
        if name == "fused":
            run = os.path.join(t2m, "checkpoints", "t2m", "sparse_ci")
            applied = [ln for ln in open(os.path.join(run, "opt.txt")).read().splitlines()
                       if ln.startswith("sparse_compile_applied: ")]
            assert len(applied) == 1 and applied[0].endswith("; " + OPTIMIZER_NOTE), applied
    assert len(means["eager"]) == 7 and np.isfinite(means["eager"]).all(), means
    assert np.allclose(means["fused"], means["eager"], rtol=1e-3, atol=1e-5), means


# --------------------------------------------------------------------------- MDM eval (patch route)
@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_mdm_patch_trains_and_evaluates_compiled(tmp_path, monkeypatch):
    """``patches/mdm.patch`` carries the flag (``base`` group): training and ``eval.eval_humanml``
    (guided sampling of the evaluation batches) compiled, zero recompiles, finite FID."""
    import glob

    import test_mdm_eval_upstream as E

    if not os.path.isfile(os.path.join(E.LARGE, "test.txt")):
        pytest.skip("no cmu-humanml3d-large data")
    import tempfile

    from _upstream import copy_checkout, git_apply, link_humanml3d

    repo = tempfile.mkdtemp(dir=str(tmp_path))
    copy_checkout(MDM_ROOT, repo)
    link_humanml3d(repo, os.path.abspath(E.LARGE))
    assert git_apply(os.path.join(E.PATCHES, "mdm.patch"), repo).returncode == 0
    E.write_evaluator(repo, E.LARGE)
    for k, v in COMPILE_ENV.items():
        monkeypatch.setenv(k, v)
    save = str(tmp_path / "sparse")
    st = str(tmp_path / "train.json")
    monkeypatch.setenv("SMDM_COMPILE_STATS", st)
    E.harness(repo, ["train.train_mdm", "--save_dir", save, "--num_steps", "10", *E.TINY, "--sparse",
                     "--sparse_compile", "default"])
    assert_no_recompiles(stats(st), phases=1)
    assert json.load(open(os.path.join(save, "args.json")))["sparse_compile"] == "default"
    ckpt = sorted(glob.glob(os.path.join(save, "model*.pt")))[-1]
    st = str(tmp_path / "eval.json")
    monkeypatch.setenv("SMDM_COMPILE_STATS", st)
    proc = E.harness(repo, ["--model_path", ckpt, "--eval_mode", "debug", "--sparse_compile", "default"], code=E.EVAL)
    assert "EVAL_MODEL_SPARSE=True" in proc.stdout + proc.stderr
    assert assert_guided_whole(stats(st))["compiled_calls"] > 0
    text = open(glob.glob(os.path.join(save, "eval_humanml_*_debug.log"))[0]).read()
    fids = [float(v) for v in re.findall(r"\[vald\] FID: ([-0-9.eE+naninf]+)", text)]
    assert fids and all(np.isfinite(fids)), text[-2000:]


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
def test_dip_trains_and_samples_autoregressively_compiled(upstream_copy, tmp_path, monkeypatch):
    """DiP (DistilBERT features of batch-dependent length, padded to a fixed bucket; the prefix is
    the previous window's tail): one graph in training, one in autoregressive guided sampling,
    zero recompiles, samples equal to eager."""
    import test_mdm_upstream as M

    repo = upstream_copy(MDM_ROOT, "mdm_compile_dip")
    for k, v in COMPILE_ENV.items():
        monkeypatch.setenv(k, v)
    st = str(tmp_path / "train.json")
    monkeypatch.setenv("SMDM_COMPILE_STATS", st)
    _, ckpt = M.train(repo, str(tmp_path / "dip"), "dip", 6, extra=["--sparse", "--sparse_compile", "default"],
                      launcher=True)
    assert_no_recompiles(stats(st), phases=1)
    assert_whole_training_step(stats(st))
    samples = {}
    for mode in ("none", "default"):
        st = str(tmp_path / f"gen_{mode}.json")
        monkeypatch.setenv("SMDM_COMPILE_STATS", st)
        _, res = M.generate(repo, ckpt, str(tmp_path / f"gen_{mode}"), "dip", extra=["--sparse_compile", mode],
                            launcher=True)
        samples[mode] = res["motion"]
    assert_no_recompiles(stats(st), phases=1)
    assert_guided_whole(stats(st))
    assert np.allclose(samples["default"], samples["none"], atol=1e-4)
