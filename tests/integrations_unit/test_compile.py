"""Graph capture with one flag (runtime/compile.py, docs/compile.md), on the CPU.

The compiled model is captured once per phase (training; sampling in eval mode without grad; the
phase's first call runs eagerly) and never again: across steps, motion lengths, timesteps, both classifier-free guidance passes and the
late-step keyframe switch; compiled equals eager; checkpoints keep plain names; a partial batch
runs eagerly; ``reduce-overhead`` without CUDA is a warning. The backend is ``aot_eager`` (Dynamo +
AOTAutograd, no code generation: quick; inductor compiles the same graphs to kernels).
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch

pytest.importorskip("torch._dynamo")
from torch._dynamo.utils import counters  # noqa: E402

from smdm_plugin import SimpleDiffusion, SparseConfig, TinyMDM, load_checkpoint, sparsify  # noqa: E402
from smdm_plugin.runtime import compile as C
from smdm_plugin.families.mdm import prepare as P
from smdm_plugin.reference.simple_diffusion import ClassifierFreeGuidance  # noqa: E402
from smdm_plugin.reference.text import TextConfig, sample_with_text  # noqa: E402
from smdm_plugin.training import trainer as T  # noqa: E402
from smdm_plugin.training.data import MotionSet  # noqa: E402

pytestmark = pytest.mark.usefixtures("fresh_dynamo")
BACKEND = "aot_eager"
TINY = {"latent_dim": 32, "num_layers": 2, "num_heads": 4, "ff_size": 64, "dropout": 0.0}
N, D = 40, 12
from helpers.paths import ROOT as REPO


def graphs() -> int:
    return counters["stats"]["unique_graphs"]


def motion_set(n=10, captions=True, seed=0) -> MotionSet:
    rng = np.random.default_rng(seed)
    motions = [np.cumsum(rng.normal(size=(int(L), D)), 0).astype(np.float32) for L in rng.integers(12, N + 1, n)]
    data = MotionSet.from_motions(motions, np.zeros(D, np.float32), np.ones(D, np.float32), max_frames=N)
    if captions:
        words = ["walk", "run", "jump", "turn", "wave", "kick"]
        data = dataclasses.replace(data, captions=[[f"a person {words[i % 6]}s", f"someone {words[(i + 1) % 6]}s"]
                                                   for i in range(n)])
    return data


def train_config(mode: str, sparse=True, steps=6, **kw) -> T.TrainConfig:
    return T.TrainConfig(steps=steps, batch=4, diffusion_steps=20, model=dict(TINY), compile=mode,
                         compile_backend=BACKEND, text=TextConfig(cond_mask_prob=0.0, guidance_scale=2.5),
                         sparse=SparseConfig(mask_noise=0.0, feature="raw") if sparse else None, **kw)


def sample(model, data, seed=1):
    lengths = torch.tensor([N, 31, 17, 25])
    return sample_with_text(model, SimpleDiffusion(20), TextConfig(guidance_scale=2.5),
                            ["a person walks", "someone jumps", "a man turns", "wave"], lengths, N,
                            generator=torch.Generator().manual_seed(seed))


# ----------------------------------------------------------------------------- no recompilation
@pytest.mark.parametrize("sparse", [True, False], ids=["sparse", "dense"])
def test_one_graph_per_phase_through_training_and_guided_sampling(sparse):
    """Training: the whole step (loss forward and backward) is one graph for every step (other
    timesteps, lengths, captions); the first step runs eagerly (it fills the caches the graph
    reads). Sampling with classifier-free guidance (two calls per step, the second with
    ``uncond``) over all 20 steps, the late-step switch of the sparse schedule included (last
    round(0.1 * 20) = 2 steps on VW): one more graph (the model call), and none after it."""
    data = motion_set()
    tr = T.Trainer(train_config("default", sparse), data, device="cpu")
    step = tr.compile_setting
    assert step.mode == "default" and step.captures == C.CAPTURES_TRAIN
    assert C.compile_setting(tr.model).mode == "default"          # the model's own calls (sampling)
    tr.train(2)
    after_warmup = graphs()
    assert after_warmup == 1
    tr.train(4)
    assert graphs() == after_warmup and step.recompiles == 0       # no recompile in training
    assert (step.warm_calls, step.compiled_calls, step.eager_calls) == (1, 5, 0)
    tr.model.eval()
    out = sample(tr.model, data)
    assert graphs() == after_warmup + 1                            # both guidance passes, every t: one graph
    sample(tr.model, data, seed=2)                                 # other noise, so other keyframes
    assert graphs() == after_warmup + 1
    call = C.compile_setting(tr.model)           # warm: sampling's first (in the eager training step: eager)
    assert (call.warm_calls, call.compiled_calls, call.eager_calls, call.recompiles) == (1, 2 * 2 * 20 - 1, 0, 0)
    assert torch.isfinite(out).all()


def test_compiled_training_and_sampling_equal_eager():
    data = motion_set()
    runs = {}
    for mode in ("none", "default"):
        tr = T.Trainer(train_config(mode), data, device="cpu")
        losses = tr.train().losses
        tr.model.eval()
        runs[mode] = (losses, sample(tr.model, data))
    assert runs["default"][0] == pytest.approx(runs["none"][0], rel=1e-5, abs=1e-6)
    assert torch.allclose(runs["default"][1], runs["none"][1], atol=1e-4)


# ----------------------------------------------------------------------------- checkpoints
def test_checkpoints_keep_plain_names_and_load_both_ways(tmp_path):
    data = motion_set(captions=False)
    cfg = dataclasses.replace(train_config("default"), text=None, steps=2)
    tr = T.Trainer(cfg, data, device="cpu")
    tr.train()
    plain = TinyMDM(njoints=D, nfeats=1, cond_mode="no_cond", **TINY)
    sparsify(plain, cfg.sparse)
    sd = tr.model.state_dict()
    assert not [k for k in sd if "_orig_mod" in k]
    assert set(sd) == set(plain.state_dict())                     # the uncompiled model's names
    tr.save(str(tmp_path))
    loaded = load_checkpoint(str(tmp_path / tr.checkpoint_name()))
    loaded = loaded[0] if isinstance(loaded, tuple) else loaded
    loaded.load_state_dict(sd)                                     # compiled -> uncompiled
    C.compile_model(loaded, "default", backend=BACKEND)
    tr.model.load_state_dict(loaded.state_dict())                  # and back
    assert C.compile_setting(loaded) is not None and not [k for k in loaded.state_dict() if "_orig_mod" in k]
    x = torch.randn(4, D, 1, N)
    y = {"mask": torch.ones(4, 1, 1, N, dtype=torch.bool), "lengths": torch.full((4,), N)}
    tr.model.eval(), loaded.eval()
    with torch.no_grad():
        assert torch.allclose(loaded(x, torch.full((4,), 3), dict(y)), tr.model(x, torch.full((4,), 3), dict(y)),
                              atol=1e-5)


def test_deepcopy_runs_its_own_weights():
    """MDM's EMA model is ``copy.deepcopy(model)``: the copy is uncompiled (torch drops the compiled
    call) and says so; compiled again, it runs its own weights."""
    model = TinyMDM(njoints=D, cond_mode="no_cond", **TINY).eval()
    C.compile_model(model, "default", backend=BACKEND)
    twin = copy.deepcopy(model)
    assert C.compile_setting(twin) is None and C.compile_setting(model) is not None
    C.compile_model(twin, "default", backend=BACKEND)
    with torch.no_grad():
        for p in twin.parameters():
            p.add_(0.1)
    x, t = torch.randn(2, D, 1, N), torch.tensor([3, 7])
    y = {"mask": torch.ones(2, 1, 1, N, dtype=torch.bool), "lengths": torch.full((2,), N)}
    eager_twin = C.uncompile(copy.deepcopy(twin))
    with torch.no_grad():
        for _ in range(2):                                         # the first call eager, then compiled
            assert torch.allclose(twin(x, t, dict(y)), eager_twin(x, t, dict(y)), atol=1e-5)
        assert not torch.allclose(twin(x, t, dict(y)), model(x, t, dict(y)), atol=1e-3)
    assert (C.compile_setting(twin).warm_calls, C.compile_setting(twin).compiled_calls) == (1, 2)


# ----------------------------------------------------------------------------- static batch, guidance
def test_a_partial_batch_runs_eagerly_without_a_new_graph():
    model, diffusion = TinyMDM(njoints=D, cond_mode="no_cond", **TINY), SimpleDiffusion(20)
    sparsify(model, SparseConfig(mask_noise=0.0, feature="raw"), diffusion=diffusion)
    ref = copy.deepcopy(model)
    C.compile_model(model, "default", backend=BACKEND)
    g = torch.Generator().manual_seed(0)

    def loss(m, B):
        x = torch.randn(B, D, 1, N, generator=g)
        L = torch.randint(12, N + 1, (B,), generator=g)
        y = {"mask": (torch.arange(N) < L[:, None]).view(B, 1, 1, N), "lengths": L}
        t = torch.randint(0, 20, (B,), generator=g)
        return diffusion.training_losses(m, x, t, {"y": y}, noise=torch.ones_like(x))["loss"]

    g.manual_seed(0)
    full, part = loss(model, 4), None
    n = graphs()
    with pytest.warns(UserWarning, match="runs eagerly"):
        part = loss(model, 3)                                      # the epoch's last batch
    assert graphs() == n and C.compile_setting(model).eager_calls == 1
    g.manual_seed(0)
    assert torch.allclose(full, loss(ref, 4), atol=1e-5) and torch.allclose(part, loss(ref, 3), atol=1e-5)


def test_guidance_uncond_folds_into_zeroed_text_exactly():
    """In eval mode ``y['uncond']`` is the text features zeroed (MDM's ``mask_cond``): the prepared
    call carries zeros and no ``uncond`` key, so both guidance passes share a graph; in training
    nothing is folded (condition dropout draws random numbers there)."""
    torch.manual_seed(0)
    model = TinyMDM(njoints=D, clip_dim=16, cond_mask_prob=0.0, **TINY).eval()
    x, t = torch.randn(2, D, 1, N), torch.tensor([3, 7])
    y = {"mask": torch.ones(2, 1, 1, N, dtype=torch.bool), "lengths": torch.full((2,), N),
         "text_embed": torch.randn(1, 2, 16), "tokens": ["a", "b"], "uncond": True}
    args, kwargs = P.prepare_mdm(model, (x, t, y), {})
    py = args[2]
    assert "uncond" not in py and "tokens" not in py and torch.equal(py["text_embed"], torch.zeros(1, 2, 16))
    assert "uncond" in y and "tokens" in y                          # the caller's dict untouched
    with torch.no_grad():
        assert torch.equal(model(*args), model(x, t, y))
    model.train()
    assert P.prepare_mdm(model, (x, t, y), {})[0][2]["uncond"] is True
    cfg_model = copy.deepcopy(model).eval()
    C.compile_model(cfg_model, "default", backend=BACKEND)
    with torch.no_grad():
        guided = ClassifierFreeGuidance(cfg_model, 2.5)(x, t, {k: v for k, v in y.items() if k != "uncond"})
        ref = ClassifierFreeGuidance(model.eval(), 2.5)(x, t, {k: v for k, v in y.items() if k != "uncond"})
    assert torch.allclose(guided, ref, atol=1e-5) and graphs() == 1


class _DeepCopyGuidance(torch.nn.Module):
    """A guidance wrapper built as upstream MDM's ``ClassifierFreeSampleModel`` is: ``deepcopy(y)``
    with ``uncond`` per call, two model calls, ``out_uncond + scale * (out - out_uncond)``."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, x, timesteps, y=None):
        y_uncond = copy.deepcopy(y)
        y_uncond["uncond"] = True
        out = self.model(x, timesteps, y)
        out_uncond = self.model(x, timesteps, y_uncond)
        return out_uncond + (y["scale"].view(-1, 1, 1, 1) * (out - out_uncond))


@pytest.mark.parametrize("registered", [True, False], ids=["submodule", "vars"])
def test_an_upstream_guidance_wrapper_is_one_graph_equal_to_eager(registered):
    """``--sparse_compile`` in MDM's / priorMDM's sampling scripts: the guidance wrapper built
    around a compiled model (its ``__init__`` hooked: ``patch_cfg_sampler``) runs both passes and
    their combination as one graph over steps and timesteps (text given as strings, encoded
    once per call), equal to the eager wrapper; the model's own compiled call is never entered
    on its own; around an uncompiled model the wrapper stays upstream's. MDM registers the model
    as a submodule, priorMDM keeps it in ``vars``."""
    import types

    from smdm_plugin.families.mdm.upstream_guidance import patch_cfg_sampler

    class Wrapper(_DeepCopyGuidance):
        def __init__(self, model):
            super().__init__(model)
            if not registered:
                del self._modules["model"]
                vars(self)["model"] = model

    module = types.SimpleNamespace(ClassifierFreeSampleModel=Wrapper)
    patch_cfg_sampler(module)
    patch_cfg_sampler(module)                                     # idempotent
    enc = TextConfig(dim=16).build()
    torch.manual_seed(0)
    model = TinyMDM(njoints=D, clip_dim=16, cond_mask_prob=0.1, text_encoder=enc, **TINY).eval()
    ref = _DeepCopyGuidance(copy.deepcopy(model)).eval()
    assert module.ClassifierFreeSampleModel(model)._compiled_call_impl is None     # not compiled: upstream's
    C.compile_model(model, "default", backend=BACKEND)
    wrapper = module.ClassifierFreeSampleModel(model).eval()
    s = C.compile_setting(model)
    guided = wrapper._compiled_call_impl
    assert guided.setting.captures == C.CAPTURES_GUIDED and guided.setting.fullgraph == s.fullgraph
    x = torch.randn(2, D, 1, N)
    with torch.no_grad():
        for i, t in enumerate((19, 11, 3, 0)):
            texts = [["a person walks", "jump"], ["someone waves", "kick"]][i % 2]
            y = {"mask": torch.ones(2, 1, 1, N, dtype=torch.bool), "lengths": torch.tensor([N, 30]),
                 "text": texts, "scale": torch.full((2,), 2.5)}
            tt = torch.full((2,), t)
            got, want = wrapper(x + i, tt, dict(y)), ref(x + i, tt, dict(y))
            assert torch.allclose(got, want, atol=1e-5), t
            assert "uncond" not in y                               # the caller's y untouched
    g = guided.setting
    assert (g.warm_calls, g.compiled_calls, g.recompiles) == (1, 3, 0) and graphs() == 1
    from smdm_plugin.families.mdm.upstream_guidance import compile_guidance
    assert compile_guidance(wrapper) is g and wrapper._compiled_call_impl is guided   # patch + hook: once
    assert s.compiled_calls == 0                                  # the model: only traced inside


def test_text_given_as_strings_is_encoded_before_the_graph():
    """TinyMDM with its own text encoder gets ``y['text']`` (strings): encoded eagerly, so new
    captions never change the graph."""
    enc = TextConfig(dim=16).build()
    model = TinyMDM(njoints=D, clip_dim=16, cond_mask_prob=0.0, text_encoder=enc, **TINY).eval()
    ref = copy.deepcopy(model)
    C.compile_model(model, "default", backend=BACKEND)
    x, t = torch.randn(2, D, 1, N), torch.tensor([3, 7])
    with torch.no_grad():
        for texts in (["a person walks", "jump"], ["someone waves slowly", "kick"], ["run", "turn left"]):
            y = {"mask": torch.ones(2, 1, 1, N, dtype=torch.bool), "lengths": torch.full((2,), N), "text": texts}
            assert torch.allclose(model(x, t, dict(y)), ref(x, t, dict(y)), atol=1e-5)
    assert graphs() == 1


# ----------------------------------------------------------------------------- settings
def test_reduce_overhead_without_cuda_is_a_warning_and_runs_default():
    model = TinyMDM(njoints=D, cond_mode="no_cond", **TINY)
    with pytest.warns(UserWarning, match="reduce-overhead needs CUDA"):
        s = C.compile_model(model, "reduce-overhead", device="cpu")
    assert (s.requested, s.mode) == ("reduce-overhead", "default") and "CUDA" in s.note
    assert "reduce-overhead" in json.dumps(s.to_dict())


def test_none_leaves_the_model_untouched_and_bad_modes_name_the_flag():
    model = TinyMDM(njoints=D, cond_mode="no_cond", **TINY)
    s = C.compile_model(model, "none")
    assert s.mode == "none" and model._compiled_call_impl is None and C.compile_setting(model) is None
    with pytest.raises(ValueError, match="--sparse_compile must be one of none, default, reduce-overhead"):
        C.compile_model(model, "max")
    with pytest.raises(ValueError, match="TrainConfig.compile"):
        T.TrainConfig(compile="fast")
    assert T.TrainConfig(compile=True).compile == "default" and T.TrainConfig(compile=False).compile == "none"


def test_flag_parses_and_the_setting_is_returned():
    p = argparse.ArgumentParser()
    C.add_compile_options(C.add_compile_options(p))               # idempotent
    assert p.parse_args([]).sparse_compile == "none"
    with pytest.raises(SystemExit):
        p.parse_args(["--sparse_compile", "max"])
    args = p.parse_args(["--sparse_compile", "default"])
    model = TinyMDM(njoints=D, cond_mode="no_cond", **TINY)
    assert C.compile_from_args(model, p.parse_args([])) is None and model._compiled_call_impl is None
    s = C.compile_from_args(model, args)
    assert s.mode == "default" and s.describe().startswith("torch.compile default")
    assert not hasattr(args, "sparse_compile_applied")         # returned, not written on the args


def test_smdm_train_compile_flag_is_written_with_the_run(tmp_path, hml_dir):
    from smdm_plugin.apps import train as train_cli

    out = tmp_path / "run"
    rc = train_cli.main(["--data", str(hml_dir), "--out", str(out), "--steps", "2", "--batch", "2",
                         "--latent-dim", "32", "--layers", "1", "--ff-size", "64", "--diffusion-steps", "10",
                         "--no-progress", "--sparse", "--compile", "--compile-backend", BACKEND])
    assert rc == 0
    cfg = json.loads((out / "train_config.json").read_text())
    result = json.loads((out / "result.json").read_text())
    assert cfg["compile"] == "default" and cfg["compile_applied"]["mode"] == "default"
    assert cfg["compile_applied"]["captures"] == C.CAPTURES_TRAIN            # the whole training step
    assert result["compile"]["backend"] == BACKEND


def test_ddp_with_compile_keeps_ranks_in_sync(tmp_path, hml_dir):
    """``torchrun`` x 2 (gloo): the model compiled inside DDP; gradients still all-reduced."""
    if not torch.distributed.is_available() or not torch.distributed.is_gloo_available():
        pytest.skip("torch.distributed with gloo is not available")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    args = ["--data", str(hml_dir), "--steps", "3", "--batch", "2", "--latent-dim", "32", "--layers", "1",
            "--ff-size", "64", "--diffusion-steps", "10", "--dropout", "0", "--no-progress", "--sparse",
            "--sparse_mask_noise", "0", "--compile-backend", BACKEND]
    results = {}
    for mode in ("none", "default"):
        out = tmp_path / mode
        proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                               "-m", "smdm_plugin", "train", "--out", str(out), "--compile", mode, *args],
                              cwd=str(REPO), env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
        results[mode] = json.loads((out / "result.json").read_text())
    assert results["default"]["max_divergence"] == 0.0 and results["default"]["world_size"] == 2
    assert results["default"]["losses"] == pytest.approx(results["none"]["losses"], rel=1e-5, abs=1e-6)


def test_motiondiffuse_interface_encodes_text_before_the_graph():
    """MotionDiffuse's ``forward(x, t, length=, text=)`` (the in-package denoiser with its
    interface), sparse: captions (strings) and lengths (a Python list) change every call, no
    recompile, equal to eager on the static path."""
    from smdm_plugin.core.checks import static_mode
    from smdm_plugin.reference.motiondiffuse_denoiser import MotionDiffuseDenoiser

    torch.manual_seed(0)
    model = MotionDiffuseDenoiser(input_feats=D, num_frames=N, latent_dim=32, ff_size=64, num_layers=2,
                                  num_heads=4, text_latent_dim=16)
    diffusion = SimpleDiffusion(20)
    sparsify(model, SparseConfig(mask_noise=0.0, feature="raw", fsq=False), diffusion=diffusion,
             family="motiondiffuse")
    ref = copy.deepcopy(model)
    C.compile_model(model, "default", backend=BACKEND)
    assert C.compile_setting(model).fullgraph
    g = torch.Generator().manual_seed(0)
    for step, texts in enumerate((["walk", "run", "jump", "wave"], ["a kick", "turn", "sit", "crawl"],
                                  ["spin", "hop", "bow", "clap"])):
        x = torch.randn(4, N, D, generator=g)
        lengths = torch.randint(12, N + 1, (4,), generator=g).tolist()
        with torch.no_grad():
            out = model(x, torch.tensor([1, 5, 9, 13]), length=lengths, text=texts)
            with static_mode():
                want = ref(x, torch.tensor([1, 5, 9, 13]), length=torch.tensor(lengths), text=texts)
        assert torch.allclose(out, want, atol=1e-5), step
    assert C.compile_setting(model).recompiles == 0 and graphs() == 1


def test_mdm_integration_compiles_dense_models_and_records_the_setting(tmp_path, capsys):
    """What the MDM patch / ``smdm run`` call after ``create_model_and_diffusion``: a dense model
    is compiled too (the A/B's other side), ``args.json`` of a training run gets what applied;
    ``--sparse_compile none`` leaves the model untouched. The option joins MDM's ``base`` group
    (never overwritten from ``args.json`` at sampling)."""
    import types

    from smdm_plugin.families.mdm.upstream import patch_base_options, sparsify_mdm

    (tmp_path / "args.json").write_text(json.dumps({"seed": 10, "sparse_compile": "reduce-overhead"}))
    args = argparse.Namespace(sparse=False, sparse_compile="reduce-overhead", save_dir=str(tmp_path),
                              model_path=None, overwrite=False)
    model = TinyMDM(njoints=D, cond_mode="no_cond", **TINY)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sparsify_mdm(model, args)
    s = C.compile_setting(model)
    assert s is not None and s.requested == "reduce-overhead"
    saved = json.loads((tmp_path / "args.json").read_text())
    assert saved["seed"] == 10 and saved["sparse_compile"] == "reduce-overhead"
    assert saved["sparse_compile_applied"] == s.describe() and "runs torch.compile" in capsys.readouterr().err
    plain = TinyMDM(njoints=D, cond_mode="no_cond", **TINY)
    sparsify_mdm(plain, argparse.Namespace(sparse=False, sparse_compile="none", save_dir=None, model_path="m.pt"))
    assert plain._compiled_call_impl is None

    parser_util = types.SimpleNamespace(add_base_options=lambda parser: parser.add_argument_group("base"))
    patch_base_options(parser_util)
    patch_base_options(parser_util)                               # idempotent
    p = argparse.ArgumentParser()
    parser_util.add_base_options(p)
    base = next(g for g in p._action_groups if g.title == "base")
    assert [a.dest for a in base._group_actions] == ["sparse_compile"]
    assert p.parse_args(["--sparse_compile", "default"]).sparse_compile == "default"


def test_mdm_integration_captures_a_training_runs_whole_loss_step(tmp_path, capsys):
    """With the diffusion that ``create_model_and_diffusion`` built, a training run (one process)
    also compiles ``diffusion.training_losses`` whole, in place, and ``args.json`` states that
    setting (``...; training step: loss forward and backward``); a sampling run (``model_path``)
    leaves the diffusion as it is."""
    from smdm_plugin.families.mdm.upstream import sparsify_mdm

    (tmp_path / "args.json").write_text(json.dumps({"seed": 10}))
    args = argparse.Namespace(sparse=False, sparse_compile="default", save_dir=str(tmp_path), model_path=None,
                              overwrite=False)
    model, diffusion = TinyMDM(njoints=D, cond_mode="no_cond", **TINY), SimpleDiffusion(20)
    sparsify_mdm(model, args, None, diffusion)
    step = C.compile_setting(diffusion.training_losses)
    assert step is not None and step.captures == C.CAPTURES_TRAIN and C.compile_setting(model).captures == C.CAPTURES_MODEL
    assert json.loads((tmp_path / "args.json").read_text())["sparse_compile_applied"] == step.describe()
    assert "the training step runs torch.compile" in capsys.readouterr().err
    x, t = torch.randn(4, D, 1, N), torch.tensor([3, 7, 11, 19])
    y = {"mask": torch.ones(4, 1, 1, N, dtype=torch.bool), "lengths": torch.full((4,), N)}
    for _ in range(3):
        torch.manual_seed(0)
        got = diffusion.training_losses(model, x, t, model_kwargs={"y": y})["loss"]
        torch.manual_seed(0)
        want = SimpleDiffusion.training_losses(diffusion, model, x, t, {"y": y})["loss"]
        assert torch.allclose(got, want, atol=1e-6)
    assert (step.warm_calls, step.compiled_calls, step.recompiles) == (1, 2, 0)

    sampling = SimpleDiffusion(20)
    sparsify_mdm(TinyMDM(njoints=D, cond_mode="no_cond", **TINY), argparse.Namespace(
        sparse=False, sparse_compile="default", save_dir=None, model_path="m.pt"), None, sampling)
    assert "training_losses" not in vars(sampling)


def test_bert_text_tokens_padded_to_a_bucket_change_nothing():
    """DiP's ``(features [L, B, d], mask [B, L])`` padded with masked tokens: the decoder's
    cross-attention gives the same output (masked keys weigh 0), and every L <= 64 has one shape."""
    torch.manual_seed(0)
    layer = torch.nn.TransformerDecoderLayer(16, 4, 32, dropout=0.0)
    dec = torch.nn.TransformerDecoder(layer, 2).eval()
    tgt = torch.randn(10, 3, 16)
    for L in (5, 17, 64):
        feats, mask = torch.randn(L, 3, 16), torch.zeros(3, L, dtype=torch.bool)
        mask[0, L // 2:] = True                                    # a shorter caption in the batch
        pf, pm = P.pad_text_tokens((feats, mask))
        assert pf.shape == (64, 3, 16) and pm.shape == (3, 64) and pm[:, L:].all()
        with torch.no_grad():
            want = dec(tgt, feats, memory_key_padding_mask=mask)
            got = dec(tgt, pf, memory_key_padding_mask=pm)
        assert torch.allclose(got, want, atol=1e-5), L
    assert P.pad_text_tokens((torch.randn(70, 3, 16), torch.zeros(3, 70, dtype=torch.bool)))[0].shape[0] == 128


def test_forced_keyframes_with_a_bound_trace_whole():
    """``with_forced(y, forced, bound)``: the plan is sized from the bound, nothing is read on the
    host, so the call traces whole (``fullgraph=True``: a graph break would raise), in the same
    phase as calls without forced frames; equal to eager, no recompile across steps. Without the
    bound the same call would need its own phase with a break (the test below)."""
    from smdm_plugin import with_forced

    model, diffusion = TinyMDM(njoints=D, cond_mode="no_cond", **TINY), SimpleDiffusion(20)
    sparsify(model, SparseConfig(mask_noise=0.0, feature="raw"), diffusion=diffusion)
    model.eval()
    ref = copy.deepcopy(model)
    C.compile_model(model, "default", backend=BACKEND)
    assert C.compile_setting(model).fullgraph
    x = torch.randn(2, D, 1, N)
    y = {"mask": torch.ones(2, 1, 1, N, dtype=torch.bool), "lengths": torch.tensor([N, 30])}
    forced = torch.zeros(2, N, dtype=torch.bool)
    forced[:, 10] = True
    forced[1, 20] = True
    with torch.no_grad():
        for step in (19, 12, 5, 1, 0):
            t = torch.full((2,), step)
            yf = with_forced(y, forced, 2)
            assert torch.allclose(model(x, t, dict(yf)), ref(x, t, dict(yf)), atol=1e-5), step
    s = C.compile_setting(model)
    call = model._compiled_call_impl
    assert s.recompiles == 0 and s.compiled_calls == 4 and len(call._static) == 1
    assert all(fullgraph for fullgraph in call._compiled), "the bounded calls traced with a break"


def test_forced_keyframes_trace_with_a_break_and_never_recompile():
    """In-betweening / ``sample.edit``: forced keyframes are counted on the host once per call (as
    in eager), so those calls compile without fullgraph: no error, no recompile across steps and
    other forced frames of the same count pattern, equal to eager."""
    from smdm_plugin import with_forced

    model, diffusion = TinyMDM(njoints=D, cond_mode="no_cond", **TINY), SimpleDiffusion(20)
    sparsify(model, SparseConfig(mask_noise=0.0, feature="raw"), diffusion=diffusion)
    model.eval()
    ref = copy.deepcopy(model)
    C.compile_model(model, "default", backend=BACKEND)
    x = torch.randn(2, D, 1, N)
    y = {"mask": torch.ones(2, 1, 1, N, dtype=torch.bool), "lengths": torch.tensor([N, 30])}
    forced = torch.zeros(2, N, dtype=torch.bool)
    forced[:, 10] = True
    with torch.no_grad():
        for step in (19, 12, 5, 1, 0):
            t = torch.full((2,), step)
            yf = with_forced(y, forced)
            assert torch.allclose(model(x, t, dict(yf)), ref(x, t, dict(yf)), atol=1e-5), step
            assert torch.allclose(model(x, t, dict(y)), ref(x, t, dict(y)), atol=1e-5), step
    s = C.compile_setting(model)
    assert s.recompiles == 0 and (s.warm_calls, s.compiled_calls) == (2, 8) and len(model._compiled_call_impl._static) == 2
