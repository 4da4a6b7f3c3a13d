"""MDM and DiP end to end, with the real upstream code: ``patches/mdm.patch`` and the ``smdm run``
launcher (no upstream edit), on real motion (cmu-humanml3d, HumanML3D format).

Skipped unless ``SMDM_MDM_ROOT`` points at an MDM checkout (github:GuyTevet/motion-diffusion-model,
tested at d4fd88c; read-only, it is copied). The Python deps: ``pip install "smdm-plugin[mdm]"``
(docs/mdm.md). CLIP/DistilBERT have random
weights of the right architecture and SMPL/GloVe are stubbed (``mdm_harness.py``); the CLIP text
tower is 1 layer deep here for speed (``SMDM_TEST_CLIP_LAYERS``).

What is checked:
* the patch applies cleanly and only adds lines;
* sparse training (trans_enc, trans_dec, DiP) runs, the loss goes down (trans_enc, 60 steps),
  ``args.json`` carries the ``sparse_*`` options and ``sparse_config.json`` is saved; MDM's own
  ``sample.generate`` samples from the checkpoint (dynamic keyframe update at the end);
* ``sample.generate`` / ``sample.edit`` / ``eval.eval_humanml`` re-create the sparse model from
  ``args.json`` with no extra flag (``sample.edit`` is also run);
* flag off: patched and launched runs equal upstream bit for bit (same seed: checkpoint and samples);
* sparse with reduction 0 (all keyframes) equals the dense model within 1e-5 (same weights);
* a sparse checkpoint given to a dense model is a clear error (flag lost), and unpatched upstream
  refuses it too;
* ``torchrun --nproc_per_node 2`` (gloo) through ``smdm run`` (trans_enc, DiP) and through the
  patch (trans_enc): identical parameters on both ranks, only rank 0 writes in ``--save_dir``,
  disjoint per-rank halves of every epoch, the same all-rank loss logged by both ranks.
The launcher and DDP-hook tests at the end need no checkout (a fake MDM layout) and always run.
"""
from __future__ import annotations

import glob
import json
import os
import re
import shutil
import sys

import numpy as np
import pytest

from _upstream import PATCHES, git_apply, plugin_env, run_logged

ROOT = os.environ.get("SMDM_MDM_ROOT")
HERE = os.path.dirname(os.path.abspath(__file__))
HARNESS = os.path.join(HERE, "mdm_harness.py")
PATCH = os.path.join(PATCHES, "mdm.patch")

needs_mdm = pytest.mark.skipif(not ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")

TINY = ["--dataset", "humanml", "--latent_dim", "64", "--layers", "2", "--batch_size", "8",
        "--save_interval", "1000000", "--seed", "10"]
ARCH = {
    "trans_enc": ["--diffusion_steps", "20"],
    "trans_dec": ["--arch", "trans_dec", "--diffusion_steps", "20"],
    "dip": ["--arch", "trans_dec", "--text_encoder_type", "bert", "--context_len", "20",
            "--pred_len", "40", "--mask_frames", "--diffusion_steps", "10"],
}
GEN = {"trans_enc": ["--motion_length", "2"], "trans_dec": ["--motion_length", "2"],
       "dip": ["--motion_length", "4", "--autoregressive"]}
ENV = {"SMDM_TEST_CLIP_LAYERS": "1", "SMDM_TEST_NUM_WORKERS": "0", "SMDM_TEST_NO_RENDER": "1"}


# --------------------------------------------------------------------------- helpers
def mdm(repo, module, args, launcher=False, check=True, timeout=600):
    """Run an MDM entry point (``train.train_mdm``, ``sample.generate``...) in ``repo`` through
    the offline harness; ``launcher`` wraps it in ``smdm run`` (no patch needed)."""
    cmd = [sys.executable, HARNESS, module, *args]
    if launcher:
        cmd = [sys.executable, "-m", "smdm_plugin.integrations.launcher", "--repo", repo, "--"] + cmd
    return run_logged(cmd, cwd=repo, env=plugin_env(ENV), timeout=timeout, check=check)


def harness_code(repo, code, launcher=False, check=True):
    cmd = [sys.executable, HARNESS, "-c", code]
    if launcher:
        cmd = [sys.executable, "-m", "smdm_plugin.integrations.launcher", "--repo", repo, "--"] + cmd
    return run_logged(cmd, cwd=repo, env=plugin_env(ENV), check=check)


def latest_checkpoint(save_dir):
    ckpts = sorted(glob.glob(os.path.join(save_dir, "model*.pt")))
    assert ckpts, f"no checkpoint in {save_dir}: {os.listdir(save_dir)}"
    return ckpts[-1]


def logged_losses(output):
    return [(int(s), float(v)) for s, v in re.findall(r"step\[(\d+)\]: loss\[([0-9.eE+-]+)\]", output)]


def train(repo, save_dir, arch, steps, extra=(), launcher=False):
    proc = mdm(repo, "train.train_mdm", ["--save_dir", save_dir, "--num_steps", str(steps),
                                         *TINY, *ARCH[arch], *extra], launcher=launcher)
    return proc, latest_checkpoint(save_dir)


def generate(repo, ckpt, out_dir, arch, extra=(), launcher=False, check=True):
    proc = mdm(repo, "sample.generate", ["--model_path", ckpt, "--output_dir", out_dir,
                                         "--num_samples", "2", "--num_repetitions", "1",
                                         "--seed", "3", *GEN[arch], *extra],
               launcher=launcher, check=check)
    if not check:
        return proc, None
    return proc, np.load(os.path.join(out_dir, "results.npy"), allow_pickle=True).item()


def load_sd(path):
    import torch

    sd = torch.load(path, map_location="cpu", weights_only=True)
    return sd.get("model", sd) if isinstance(sd.get("model", None), dict) else sd


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def pristine(upstream_copy):
    return upstream_copy(ROOT, "mdm_pristine")


@pytest.fixture(scope="module")
def patched(upstream_copy):
    return upstream_copy(ROOT, "mdm_patched", patch=PATCH)


@pytest.fixture(scope="module")
def sparse_run(patched, tmp_path_factory):
    """A sparse trans_enc trained through the patch: 60 steps, enough to see the loss fall."""
    save = str(tmp_path_factory.mktemp("runs") / "sparse_enc")
    proc, ckpt = train(patched, save, "trans_enc", 60, ["--log_interval", "10", "--lr", "5e-4",
                                                       "--sparse"])
    return {"save": save, "ckpt": ckpt, "out": proc.stdout + proc.stderr}


# --------------------------------------------------------------------------- tests
@needs_mdm
def test_patch_applies_cleanly_and_only_adds(pristine, tmp_path):
    res = git_apply(PATCH, pristine, check_only=True)
    assert res.returncode == 0, res.stderr
    with open(PATCH) as f:
        removed = [ln for ln in f if ln.startswith("-") and not ln.startswith("---")]
    assert removed == [], f"mdm.patch must only add lines, removes: {removed}"


@needs_mdm
def test_sparse_trans_enc_trains_and_samples(sparse_run, patched):
    losses = logged_losses(sparse_run["out"])
    assert len(losses) >= 6, sparse_run["out"][-3000:]
    windows = [v for s, v in losses if s > 0]  # step 0 is a single-batch average
    print("sparse trans_enc loss per 10 steps:", windows)
    assert all(np.isfinite(windows))
    assert np.mean(windows[-2:]) < 0.95 * windows[0], f"loss did not go down: {windows}"
    args = json.load(open(os.path.join(sparse_run["save"], "args.json")))
    assert args["sparse"] is True and args["sparse_reduction"] == pytest.approx(0.8)
    cfg = json.load(open(os.path.join(sparse_run["save"], "sparse_config.json")))
    assert cfg["enabled"] is True and cfg["version"] >= 1
    sd = load_sd(sparse_run["ckpt"])
    assert "smdm_sparse_version" in sd

    out = os.path.join(sparse_run["save"], "gen")
    proc, res = generate(patched, sparse_run["ckpt"], out, "trans_enc")
    assert res["motion"].shape == (2, 22, 3, 40)
    assert np.isfinite(res["motion"]).all()


@needs_mdm
@pytest.mark.parametrize("arch,launcher", [("trans_dec", True), ("dip", False), ("dip", True)],
                         ids=["trans_dec-launcher", "dip-patch", "dip-launcher"])
def test_sparse_trains_and_samples(arch, launcher, pristine, patched, tmp_path):
    repo = pristine if launcher else patched
    save = str(tmp_path / f"sparse_{arch}")
    proc, ckpt = train(repo, save, arch, 8, ["--log_interval", "4", "--sparse"], launcher=launcher)
    losses = [v for _, v in logged_losses(proc.stdout + proc.stderr)]
    assert losses and all(np.isfinite(losses))
    args = json.load(open(os.path.join(save, "args.json")))
    assert args["sparse"] is True
    cfg = json.load(open(os.path.join(save, "sparse_config.json")))
    if arch == "dip":
        assert cfg["prefix_frames"] == 20
    # the two files state the same settings, the ones resolved when the model was built included
    # (DiP's prefix, the diffusion steps): args.json is brought to what ran
    assert args["sparse_prefix_frames"] == cfg["prefix_frames"], (args, cfg)
    assert args["sparse_diffusion_steps"] == cfg["diffusion_steps"] == args["diffusion_steps"], (args, cfg)
    from smdm_plugin import SparseConfig
    from smdm_plugin.core.agreement import disagreement

    assert disagreement(SparseConfig.from_dict(cfg), args, "sparse_config.json", "args.json",
                        ignore=("version",)) is None
    assert "smdm_sparse_version" in load_sd(ckpt)
    proc, res = generate(repo, ckpt, str(tmp_path / "gen"), arch, launcher=launcher)
    n_frames = 80 if arch == "dip" else 40
    assert res["motion"].shape == (2, 22, 3, n_frames)
    assert np.isfinite(res["motion"]).all()
    # the samples say how they were made: the checkpoint's config beside results.npy
    assert json.load(open(os.path.join(str(tmp_path / "gen"), "sparse_config.json"))) == cfg


RESTORE = r"""
import sys, json
from utils import parser_util
from utils.model_util import create_model_and_diffusion, load_saved_model
from data_loaders.get_data import get_dataset_loader
from smdm_plugin import is_sparse
ckpt = sys.argv[1]
out = {}
for name, fn in [("generate", parser_util.generate_args), ("edit", parser_util.edit_args),
                 ("eval", parser_util.evaluation_parser)]:
    sys.argv = [name, "--model_path", ckpt]
    args = fn()
    out[name] = {"sparse": bool(args.sparse), "reduction": args.sparse_reduction}
data = get_dataset_loader(name="humanml", batch_size=2, num_frames=None, split="test", hml_mode="eval")
model, diffusion = create_model_and_diffusion(args, data)
load_saved_model(model, ckpt)
out["eval_model_sparse"] = is_sparse(model)
print("RESTORE=" + json.dumps(out))
"""


@needs_mdm
def test_generate_edit_eval_restore_sparse_from_args_json(sparse_run, patched, tmp_path):
    proc = harness_code(patched, RESTORE.replace("sys.argv[1]", repr(sparse_run["ckpt"])))
    out = json.loads(re.search(r"RESTORE=(.*)", proc.stdout).group(1))
    for name in ("generate", "edit", "eval"):
        assert out[name] == {"sparse": True, "reduction": pytest.approx(0.8)}, out
    assert out["eval_model_sparse"] is True
    # sample.edit end to end (in-betweening on 196 frames), sparse restored from args.json
    edit_out = str(tmp_path / "edit")
    mdm(patched, "sample.edit", ["--model_path", sparse_run["ckpt"], "--output_dir", edit_out,
                                 "--num_samples", "2", "--num_repetitions", "1",
                                 "--text_condition", "a person walks forward"])
    res = np.load(os.path.join(edit_out, "results.npy"), allow_pickle=True).item()
    assert res["motion"].shape[0] == 2 and np.isfinite(res["motion"]).all()


@needs_mdm
def test_flag_off_equals_upstream_bit_for_bit(pristine, patched, tmp_path):
    runs = {}
    for name, repo, launcher in (("upstream", pristine, False), ("patched", patched, False),
                                 ("launcher", pristine, True)):
        save = str(tmp_path / name)
        _, ckpt = train(repo, save, "trans_enc", 3, launcher=launcher)
        _, res = generate(repo, ckpt, str(tmp_path / f"gen_{name}"), "trans_enc", launcher=launcher)
        runs[name] = (load_sd(ckpt), res["motion"])
        assert not os.path.exists(os.path.join(save, "sparse_config.json"))
    ref_sd, ref_motion = runs["upstream"]
    for name in ("patched", "launcher"):
        sd, motion = runs[name]
        assert sorted(sd) == sorted(ref_sd), name
        for k in ref_sd:
            assert ref_sd[k].dtype == sd[k].dtype and bool((ref_sd[k] == sd[k]).all()), (name, k)
        assert np.array_equal(motion, ref_motion), f"{name}: samples differ from upstream"


@needs_mdm
@pytest.mark.parametrize("launcher", [False, True], ids=["patch", "launcher"])
def test_the_plugins_warnings_reach_the_log_despite_moviepy(launcher, pristine, patched, tmp_path):
    """MDM's training imports moviepy 1.0.3 (train.training_loop -> sample.generate), which calls
    ``logging.captureWarnings(True)``: 0.7.0's warnings vanished there. Sparse training at
    upstream's 1000 diffusion steps (a deviation from the paper) says so in one ``smdm:`` line,
    beside the ON line that states both phases."""
    repo = pristine if launcher else patched
    proc = mdm(repo, "train.train_mdm", ["--save_dir", str(tmp_path / "run"), "--num_steps", "2", *TINY,
                                         "--diffusion_steps", "1000", "--sparse"], launcher=launcher)
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("smdm: ")]
    assert sum("sparse training at 1000 diffusion steps" in ln for ln in lines) == 1, proc.stderr[-3000:]
    on = [ln for ln in lines if "sparse keyframe mode ON (MDM/DiP, training)" in ln]
    assert len(on) == 1 and "training: vw keyframes from x0, mask noise 0.1" in on[0], lines


FLAG_OFF_IMPORTS = r"""
import json, sys
def plugin():
    return sorted(m for m in sys.modules if m == "smdm_plugin" or m.startswith("smdm_plugin."))
seen = {}
import train.train_mdm                      # the patch's DDP hooks, at import
seen["import"] = plugin()
from utils.parser_util import train_args
sys.argv = ["train_mdm", "--save_dir", sys.argv[1], "--dataset", "humanml"]
args = train_args()                         # every option group, the flag off
seen["parse"] = plugin()
print("SEEN=" + json.dumps(seen))
"""


@needs_mdm
def test_a_flag_off_run_loads_only_the_plugins_options(patched, tmp_path):
    """The patched MDM with the flag off: at import the hooks' module and its family's registration
    (8 small modules, no torch; 0.7.0: 5), and after parsing only the option modules and the config
    they describe (0.7.0: 18, the integration, its start options, presets and registry among them)."""
    proc = harness_code(patched, FLAG_OFF_IMPORTS.replace("sys.argv[1]", repr(str(tmp_path / "x"))))
    seen = json.loads(proc.stdout.split("SEEN=")[1].splitlines()[0])
    # the hooks' module, its family's package and the family's one registration (names, no torch)
    assert seen["import"] == ["smdm_plugin", "smdm_plugin.adapters", "smdm_plugin.adapters.families", "smdm_plugin.core",
                              "smdm_plugin.core.registry", "smdm_plugin.families", "smdm_plugin.families.mdm",
                              "smdm_plugin.families.mdm.upstream_train"]
    extra = [m for m in seen["parse"] if m not in seen["import"] and not m.startswith(("smdm_plugin.core",
                                                                                      "smdm_plugin.support"))]
    assert extra == ["smdm_plugin.integrations", "smdm_plugin.integrations.options", "smdm_plugin.runtime",
                     "smdm_plugin.runtime.compile"], seen["parse"]
    assert "smdm_plugin.core.presets" not in seen["parse"] and len(seen["parse"]) <= 19, seen["parse"]


@needs_mdm
def test_patched_checkout_without_the_plugin_runs_as_upstream(pristine, patched, tmp_path):
    """A colleague without smdm-plugin (``import smdm_plugin`` fails) runs the patched checkout as
    upstream: training and sampling work, bit for bit upstream's; ``--sparse`` is then an unknown
    argument (argparse), not a traceback from the plugin's imports."""
    blocker = tmp_path / "no_plugin" / "smdm_plugin"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text('raise ImportError("smdm-plugin is not installed (test)")\n')
    env = plugin_env(ENV)
    env["PYTHONPATH"] = str(blocker.parent) + os.pathsep + env["PYTHONPATH"]

    def run(repo, module, args, check=True):
        return run_logged([sys.executable, HARNESS, module, *args], cwd=repo, env=env, check=check)

    runs = {}
    for name, repo in (("upstream", pristine), ("patched", patched)):
        save = str(tmp_path / name)
        run(repo, "train.train_mdm", ["--save_dir", save, "--num_steps", "3", *TINY, *ARCH["trans_enc"]])
        ckpt = latest_checkpoint(save)
        out = str(tmp_path / f"gen_{name}")
        run(repo, "sample.generate", ["--model_path", ckpt, "--output_dir", out, "--num_samples", "2",
                                      "--num_repetitions", "1", "--seed", "3", *GEN["trans_enc"]])
        runs[name] = (load_sd(ckpt), np.load(os.path.join(out, "results.npy"), allow_pickle=True).item()["motion"])
        assert not os.path.exists(os.path.join(save, "sparse_config.json"))
        assert "sparse" not in json.load(open(os.path.join(save, "args.json")))
    (ref_sd, ref_motion), (sd, motion) = runs["upstream"], runs["patched"]
    assert sorted(sd) == sorted(ref_sd) and all(bool((ref_sd[k] == sd[k]).all()) for k in ref_sd)
    assert np.array_equal(motion, ref_motion)
    proc = run(patched, "train.train_mdm", ["--save_dir", str(tmp_path / "flag"), "--num_steps", "1", *TINY,
                                            *ARCH["trans_enc"], "--sparse"], check=False)
    assert proc.returncode == 2 and "unrecognized arguments: --sparse" in proc.stderr, proc.stderr[-800:]


EQUIV = r"""
import argparse, numpy as np, torch
from utils import parser_util
from utils.model_util import create_model_and_diffusion
from smdm_plugin import is_sparse

mean = np.load("dataset/HumanML3D/Mean.npy"); std = np.load("dataset/HumanML3D/Std.npy")
class _DS: pass
ds = _DS(); ds.mean, ds.std = mean, std
data = argparse.Namespace(dataset=ds)
ARCH = {ARCH}
worst = {{}}
for arch, extra in ARCH.items():
    def build(flags):
        p = argparse.ArgumentParser()
        parser_util.add_base_options(p); parser_util.add_data_options(p)
        parser_util.add_model_options(p); parser_util.add_diffusion_options(p)
        args = parser_util.apply_rules(p.parse_args(["--dataset", "humanml", "--latent_dim", "64",
                                                     "--layers", "2"] + extra + flags))
        torch.manual_seed(0)
        model = create_model_and_diffusion(args, data)[0]
        model.eval()  # (MDM.train returns None, so model.eval() does too)
        return model
    dense = build([])
    sparse = build(["--sparse", "--sparse_reduction", "0.0", "--sparse_lipschitz", "false",
                    "--sparse_fsq", "false", "--sparse_mask_noise", "0.0"])
    assert is_sparse(sparse) and not is_sparse(dense)
    missing, unexpected = sparse.load_state_dict(dense.state_dict(), strict=False)
    assert unexpected == [] and set(missing) <= {{"smdm_sparse_version"}}, (missing, unexpected)
    g = torch.Generator().manual_seed(1)
    B, N = 3, 40
    x = torch.randn(B, 263, 1, N, generator=g)
    lengths = torch.tensor([40, 31, 22])
    mask = (torch.arange(N)[None] < lengths[:, None]).view(B, 1, 1, N)
    texts = ["a person walks", "a person jumps", "someone dances"]
    with torch.no_grad():
        emb = dense.encode_text(texts)
    valid = mask.view(B, 1, 1, N).float()  # frames at or past a sample's length are not compared
    diffs = []
    for t in (0, 5, 19):
        ts = torch.full((B,), t, dtype=torch.long)
        def y():
            d = {{"mask": mask.clone(), "lengths": lengths.clone(), "text": texts, "text_embed": emb}}
            if "--context_len" in extra:
                d["prefix"] = torch.randn(B, 263, 1, 20, generator=torch.Generator().manual_seed(2))
            return d
        with torch.no_grad():
            a = dense(x, ts, y()); b = sparse(x, ts, y())
        diffs.append(float(((a - b).abs() * valid).max()))
    worst[arch] = max(diffs)
print("EQUIV=" + repr(worst))
"""


@needs_mdm
@pytest.mark.parametrize("launcher", [False, True], ids=["patch", "launcher"])
def test_reduction_zero_equals_dense(launcher, pristine, patched):
    arch = {k: ARCH[k] + (["--mask_frames"] if k != "dip" else []) for k in ARCH}
    code = EQUIV.replace("{ARCH}", repr(arch)).replace("{{", "{").replace("}}", "}")
    proc = harness_code(pristine if launcher else patched, code, launcher=launcher)
    worst = eval(re.search(r"EQUIV=(.*)", proc.stdout).group(1))
    print("max |dense - sparse(reduction=0)|:", worst)
    assert set(worst) == set(ARCH)
    for arch_name, d in worst.items():
        assert d < 1e-5, (arch_name, d)


@needs_mdm
def test_sparse_checkpoint_into_dense_model_is_a_clear_error(sparse_run, pristine, patched, tmp_path):
    # --sparse lost: args.json without the sparse keys (e.g. copied from a dense run)
    lost = str(tmp_path / "flag_lost")
    shutil.copytree(sparse_run["save"], lost, ignore=shutil.ignore_patterns("gen*", "edit*"))
    args = json.load(open(os.path.join(lost, "args.json")))
    for k in [k for k in args if k == "sparse" or k.startswith("sparse_")]:
        del args[k]
    json.dump(args, open(os.path.join(lost, "args.json"), "w"))
    ckpt = os.path.join(lost, os.path.basename(sparse_run["ckpt"]))
    proc, _ = generate(patched, ckpt, str(tmp_path / "g1"), "trans_enc", check=False)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "SPARSE" in text and "dense" in text, text[-2000:]
    # the launcher path gives the same error
    proc, _ = generate(pristine, ckpt, str(tmp_path / "g2"), "trans_enc", launcher=True, check=False)
    assert proc.returncode != 0 and "SPARSE" in proc.stdout + proc.stderr
    # unpatched upstream does not load it silently either (unexpected state-dict keys)
    proc, _ = generate(pristine, sparse_run["ckpt"], str(tmp_path / "g3"), "trans_enc", check=False)
    assert proc.returncode != 0
    assert not os.path.exists(os.path.join(tmp_path, "g3", "results.npy"))


# --------------------------------------------------------------------------- torchrun (DDP)
def torchrun_train(repo, save_dir, probe, arch, extra=(), launcher=True):
    """MDM's own ``train.train_mdm`` in 2 gloo processes: ``smdm run --repo REPO -- torchrun
    --nproc_per_node 2 <harness> train.train_mdm ...`` (or, patch route, torchrun alone)."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", HARNESS,
           "train.train_mdm", "--save_dir", save_dir, "--num_steps", "4", "--log_interval", "1",
           *TINY[:6], "--batch_size", "4", "--save_interval", "1000000", "--seed", "10", *ARCH[arch], *extra]
    if launcher:
        cmd = [sys.executable, "-m", "smdm_plugin", "run", "--repo", repo, "--"] + cmd
    env = plugin_env({**ENV, "SMDM_TEST_DDP_PROBE": probe, "OMP_NUM_THREADS": "1"})
    return run_logged(cmd, cwd=repo, env=env, timeout=900)


@needs_mdm
@pytest.mark.parametrize("arch,launcher", [("trans_enc", True), ("dip", True), ("trans_enc", False)],
                         ids=["trans_enc-launcher", "dip-launcher", "trans_enc-patch"])
def test_torchrun_two_processes(arch, launcher, pristine, patched, tmp_path):
    import torch

    save, probe = str(tmp_path / "save"), tmp_path / "probe"
    probe.mkdir()
    proc = torchrun_train(pristine if launcher else patched, save, str(probe), arch, ["--sparse"], launcher)
    out = proc.stdout + proc.stderr
    r0, r1 = (torch.load(probe / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    # identical parameters and buffers on both ranks after training
    assert sorted(r0) == sorted(r1) and "smdm_sparse_version" in r0
    for k in r0:
        assert torch.equal(r0[k], r1[k]), k
    # rank 0 wrote the run folder, rank 1 nothing in it (its start-up files went to a removed temp dir)
    w0, w1 = (json.load(open(probe / f"rank{r}.json")) for r in (0, 1))
    in_save = [[p for p in w["writes"] if p.startswith(save + os.sep)] for w in (w0, w1)]
    assert in_save[1] == [], in_save[1]
    names = {os.path.basename(p) for p in in_save[0]}
    assert {"args.json", "sparse_config.json"} <= names
    assert any(re.fullmatch(r"model\d{9}\.pt", n) for n in names) and any(n.startswith("opt") for n in names)
    private = {os.path.dirname(os.path.dirname(p)) for p in w1["writes"] if "smdm_rank1_" in p}
    assert private and not any(os.path.exists(d) for d in private)
    ckpt = load_sd(latest_checkpoint(save))
    assert set(ckpt) <= set(r0) and all(torch.equal(ckpt[k], r0[k]) for k in ckpt)
    # each rank drew its own half of every epoch (DistributedSampler), a new shuffle each epoch
    assert len(w0["epochs"]) == len(w1["epochs"]) >= 1
    for e0, e1 in zip(w0["epochs"], w1["epochs"]):
        assert len(e0) == len(e1) > 0 and not set(e0) & set(e1)
    # the logged loss is the mean over both ranks' samples: both ranks print the same value per step
    per_step = {}
    for step, value in logged_losses(out):
        per_step.setdefault(step, []).append(value)
    assert per_step and all(len(v) == 2 and v[0] == v[1] for v in per_step.values()), per_step
    assert all(np.isfinite(v[0]) for v in per_step.values())


@needs_mdm
def test_torchrun_one_process_equals_the_plain_run(pristine, tmp_path):
    """``torchrun --nproc_per_node 1``: DDP over one process changes nothing (same data order, same
    random stream on rank 0, gradients averaged over one rank): the checkpoint is bit for bit the
    one of the plain run (dense, through ``smdm run``)."""
    import torch

    plain, ddp = str(tmp_path / "plain"), str(tmp_path / "ddp")
    _, ckpt_plain = train(pristine, plain, "trans_enc", 3, launcher=True)
    cmd = [sys.executable, "-m", "smdm_plugin", "run", "--repo", pristine, "--", sys.executable, "-m",
           "torch.distributed.run", "--standalone", "--nproc_per_node", "1", HARNESS, "train.train_mdm",
           "--save_dir", ddp, "--num_steps", "3", *TINY, *ARCH["trans_enc"]]
    run_logged(cmd, cwd=pristine, env=plugin_env(ENV), timeout=900)  # the environment of the plain run
    a, b = load_sd(ckpt_plain), load_sd(latest_checkpoint(ddp))
    assert os.path.basename(latest_checkpoint(ddp)) == os.path.basename(ckpt_plain)
    assert sorted(a) == sorted(b)
    for k in a:
        assert torch.equal(a[k], b[k]), k


# --------------------------------------------------------------------------- launcher, no checkout
FAKE_PARSER = """
def add_model_options(parser):
    group = parser.add_argument_group('model')
    group.add_argument('--layers', default=2, type=int)
"""
FAKE_MODEL_UTIL = """
def create_model_and_diffusion(args, data):
    from smdm_plugin import TinyMDM
    return TinyMDM(latent_dim=32, num_layers=args.layers, cond_mode='no_cond'), None

def load_model_wo_clip(model, state_dict):
    model.load_state_dict(state_dict, strict=False)
"""
PROBE = """
import argparse, json, os, sys
from utils.parser_util import add_model_options
from utils.model_util import create_model_and_diffusion, load_model_wo_clip
import utils.model_util as mu
p = argparse.ArgumentParser()
add_model_options(p)
args = p.parse_args()
groups = {g.title: [a.dest for a in g._group_actions] for g in p._action_groups}
model, _ = create_model_and_diffusion(args, None)
from smdm_plugin import is_sparse
err = ''
if is_sparse(model):
    from smdm_plugin import unsparsify
    sd = dict(model.state_dict())
    dense = mu.create_model_and_diffusion(argparse.Namespace(layers=args.layers, sparse=False), None)[0]
    try:
        load_model_wo_clip(dense, sd)
    except RuntimeError as e:
        err = str(e)
print('PROBE=' + json.dumps({'sparse': is_sparse(model), 'in_model_group': 'sparse' in groups['model'],
      'reduction': getattr(args, 'sparse_reduction', None), 'chained': os.environ.get('CHAINED_MARK', ''),
      'load_error': err, 'cwd': os.getcwd()}))
"""


@pytest.fixture()
def fake_mdm(tmp_path):
    repo = tmp_path / "fake_mdm"
    (repo / "model").mkdir(parents=True)
    (repo / "utils").mkdir()
    (repo / "model" / "mdm.py").write_text("# fake\n")
    (repo / "utils" / "parser_util.py").write_text(FAKE_PARSER)
    (repo / "utils" / "model_util.py").write_text(FAKE_MODEL_UTIL)
    (repo / "probe.py").write_text(PROBE)
    # an existing sitecustomize that the generated one must still run
    other = tmp_path / "other_site"
    other.mkdir()
    (other / "sitecustomize.py").write_text("import os\nos.environ['CHAINED_MARK'] = 'yes'\n")
    return str(repo), str(other)


def _launch(repo, other, *args):
    env = plugin_env()
    env["PYTHONPATH"] = env["PYTHONPATH"] + os.pathsep + other
    cmd = [sys.executable, "-m", "smdm_plugin.integrations.launcher", "--repo", repo, "--",
           sys.executable, "probe.py", *args]
    proc = run_logged(cmd, cwd=os.path.dirname(repo), env=env, timeout=300)
    return json.loads(re.search(r"PROBE=(.*)", proc.stdout).group(1))


def test_launcher_hooks_fake_mdm(fake_mdm):
    repo, other = fake_mdm
    out = _launch(repo, other, "--sparse", "--sparse_reduction", "0.5")
    assert out["sparse"] is True and out["in_model_group"] is True
    assert out["reduction"] == 0.5
    assert out["chained"] == "yes", "the pre-existing sitecustomize was not run"
    assert os.path.realpath(out["cwd"]) == os.path.realpath(repo)
    assert "SPARSE" in out["load_error"]
    out = _launch(repo, other)  # flag off: options there, model untouched
    assert out["sparse"] is False and out["in_model_group"] is True


def test_launcher_detects_repo_kind(tmp_path):
    from smdm_plugin.integrations.launcher import detect_repo, parse_run_args

    (tmp_path / "mdm" / "model").mkdir(parents=True)
    (tmp_path / "mdm" / "utils").mkdir()
    (tmp_path / "mdm" / "model" / "mdm.py").write_text("")
    (tmp_path / "mdm" / "utils" / "model_util.py").write_text("")
    assert detect_repo(str(tmp_path / "mdm")) == "mdm"
    (tmp_path / "mdm" / "model" / "DoubleTake_MDM.py").write_text("")
    assert detect_repo(str(tmp_path / "mdm")) == "priormdm"
    (tmp_path / "md" / "text2motion").mkdir(parents=True)
    assert detect_repo(str(tmp_path / "md")) == "motiondiffuse"
    with pytest.raises(ValueError, match="model/mdm.py"):
        detect_repo(str(tmp_path))
    args, cmd = parse_run_args(["--repo", "x", "--", "python", "-m", "train.train_mdm", "--sparse"])
    assert args.repo == "x" and cmd == ["python", "-m", "train.train_mdm", "--sparse"]


# --------------------------------------------------------------------------- DDP hooks, no checkout
TORCHRUN_ENV = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def test_ddp_hooks_are_not_installed_without_torchrun(monkeypatch):
    from smdm_plugin.integrations import _hooks
    from smdm_plugin.families.mdm import upstream_train as mdm_train

    for k in TORCHRUN_ENV:
        monkeypatch.delenv(k, raising=False)
    before = {k: list(v) for k, v in _hooks._CALLBACKS.items()}
    mdm_train.install_hooks()
    assert {k: list(v) for k, v in _hooks._CALLBACKS.items()} == before
    monkeypatch.setenv("RANK", "0")  # a partial torchrun environment is not torchrun either
    assert not mdm_train.active()
    for k, v in zip(TORCHRUN_ENV, ("0", "2", "0", "127.0.0.1", "29500")):
        monkeypatch.setenv(k, v)
    assert mdm_train.active()
    monkeypatch.setenv("SMDM_DDP", "0")
    assert not mdm_train.active()


def test_ddp_training_loader_is_sharded_per_rank(monkeypatch):
    """``get_dataset_loader(split='train', hml_mode='train')`` draws from a DistributedSampler:
    the two ranks split every epoch, a new shuffle each epoch; evaluation loaders stay as they are."""
    import types

    from torch.utils.data import DataLoader, DistributedSampler

    from smdm_plugin.families.mdm import upstream_train as mdm_train

    def get_dataset_loader(name, batch_size, num_frames, split="train", hml_mode="train", fixed_len=0):
        return DataLoader(list(range(20)), batch_size=batch_size, shuffle=True, drop_last=True,
                          collate_fn=lambda b: b)

    epochs = {}
    for rank in (0, 1):
        monkeypatch.setattr(mdm_train, "_RUN", mdm_train._Run(rank=rank, world_size=2, local_rank=rank, seed=3))
        fake = types.SimpleNamespace(get_dataset_loader=get_dataset_loader)
        mdm_train._patch_get_data(fake)
        loader = fake.get_dataset_loader("humanml", 3, None)
        assert isinstance(loader.sampler, DistributedSampler)
        assert (loader.sampler.rank, loader.sampler.num_replicas, loader.batch_size) == (rank, 2, 3)
        epochs[rank] = [[i for b in loader for i in b] for _ in range(2)]
        evaluation = fake.get_dataset_loader("humanml", 3, None, split="test", hml_mode="eval")
        assert not isinstance(evaluation.sampler, DistributedSampler)
    for e in range(2):
        assert len(epochs[0][e]) == len(epochs[1][e]) == 9  # 10 per rank, 3 full batches
        assert not set(epochs[0][e]) & set(epochs[1][e])
    assert epochs[0][0] != epochs[0][1]  # reshuffled each epoch (set_epoch)


def test_ddp_wrapper_answers_the_model_attributes(tmp_path):
    import torch
    import torch.distributed as dist

    from smdm_plugin.families.mdm import upstream_train as mdm_train
    from smdm_plugin.runtime.distributed import constant_buffers_kwargs

    if not dist.is_available() or not dist.is_gloo_available() or dist.is_initialized():
        pytest.skip("needs a fresh gloo process group")
    dist.init_process_group("gloo", store=dist.FileStore(str(tmp_path / "store"), 1), rank=0, world_size=1)
    try:
        model = torch.nn.Linear(3, 2)
        model.all_goal_joint_names = ["pelvis"]
        ddp = mdm_train._ddp_class()(model, **constant_buffers_kwargs())
        assert ddp.all_goal_joint_names == ["pelvis"] and ddp.module is model
        assert torch.equal(ddp(torch.ones(1, 3)), model(torch.ones(1, 3)))
        with pytest.raises(AttributeError):
            ddp.no_such_attribute
    finally:
        dist.destroy_process_group()
