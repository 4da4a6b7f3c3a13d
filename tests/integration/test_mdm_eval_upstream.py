"""MDM's own ``eval.eval_humanml`` on a sparse checkpoint, through ``patches/mdm.patch`` and through
``smdm run`` (unpatched MDM), with T2M evaluator weights written by smdm-plugin in upstream's layout
(random networks of upstream's sizes saved as ``t2m/text_mot_match/model/finest.tar``, random GloVe
files over the data's words): upstream's evaluator wrapper loads them, evaluates the sparse model
and writes its log with finite FID / R-precision / diversity.

Skipped unless ``SMDM_MDM_ROOT`` points at an MDM checkout (and the ``[mdm]`` extra is installed,
see docs/mdm.md). Needs a test split of >= 32 motions (upstream drops an incomplete batch of 32):
``../shared/data/cmu-humanml3d-large`` (40 test motions), or ``SMDM_HUMANML3D_LARGE_DIR``.
Upstream's debug mode asks for 300 diversity pairs (it asserts more than 300 motions), so the run
clamps ``calculate_diversity``'s pair count to the motions there are; nothing else is changed.
"""
from __future__ import annotations

import glob
import os
import pickle
import re
import sys

import numpy as np
import pytest

from _upstream import PATCHES, copy_checkout, git_apply, link_humanml3d, plugin_env, run_logged

ROOT = os.environ.get("SMDM_MDM_ROOT")
HERE = os.path.dirname(os.path.abspath(__file__))
HARNESS = os.path.join(HERE, "mdm_harness.py")
REPO = os.path.dirname(os.path.dirname(HERE))
LARGE = os.environ.get("SMDM_HUMANML3D_LARGE_DIR") or os.path.join(os.path.dirname(REPO), "shared", "data",
                                                                    "cmu-humanml3d-large")
ENV = {"SMDM_TEST_CLIP_LAYERS": "1", "SMDM_TEST_NUM_WORKERS": "0", "SMDM_TEST_NO_RENDER": "1"}
TINY = ["--dataset", "humanml", "--latent_dim", "64", "--layers", "2", "--batch_size", "8",
        "--save_interval", "1000000", "--seed", "10", "--diffusion_steps", "10"]

pytestmark = pytest.mark.skipif(not ROOT or not os.path.isfile(os.path.join(LARGE, "test.txt")),
                                reason="SMDM_MDM_ROOT not set, or no cmu-humanml3d-large data")

# eval_humanml with diversity pairs clamped to the motions there are (upstream asserts N > 300)
EVAL = """
import runpy, sys
import data_loaders.humanml.utils.metrics as m
_div = m.calculate_diversity
m.calculate_diversity = lambda a, t: _div(a, min(t, a.shape[0] - 1))
sys.argv = ["eval_humanml"] + sys.argv[1:]
g = runpy.run_module("eval.eval_humanml", run_name="__main__", alter_sys=True)
from smdm_plugin import is_sparse
model = getattr(g["model"], "model", g["model"])  # inside ClassifierFreeSampleModel
print("EVAL_MODEL_SPARSE=%s" % is_sparse(model))
"""


def write_evaluator(repo: str, data: str) -> None:
    """Random T2M evaluator networks of upstream's sizes, in upstream's layout, in ``repo``."""
    import torch

    from smdm_plugin.metrics.evaluator import MotionEncoderBiGRUCo, MovementConvEncoder, TextEncoderBiGRUCo

    torch.manual_seed(0)
    ck = os.path.join(repo, "t2m", "text_mot_match", "model")
    os.makedirs(ck, exist_ok=True)
    torch.save({"movement_encoder": MovementConvEncoder(259, 512, 512).state_dict(),
                "motion_encoder": MotionEncoderBiGRUCo(512, 1024, 512).state_dict(),
                "text_encoder": TextEncoderBiGRUCo(300, 15, 512, 512).state_dict(), "epoch": 0},
               os.path.join(ck, "finest.tar"))
    words = {"unk", "sos", "eos"}
    for f in glob.glob(os.path.join(data, "texts", "*.txt")):
        for line in open(f, encoding="utf-8"):
            parts = line.strip().split("#")
            if len(parts) > 1:
                words.update(t.split("/")[0] for t in parts[1].split())
    words = sorted(words)
    g = os.path.join(repo, "glove")
    os.makedirs(g, exist_ok=True)
    np.save(os.path.join(g, "our_vab_data.npy"),
            np.random.default_rng(0).normal(size=(len(words), 300)).astype(np.float32))
    with open(os.path.join(g, "our_vab_words.pkl"), "wb") as f:
        pickle.dump(words, f)
    with open(os.path.join(g, "our_vab_idx.pkl"), "wb") as f:
        pickle.dump({w: i for i, w in enumerate(words)}, f)


@pytest.fixture(scope="module")
def repos(tmp_path_factory):
    """A patched and a pristine copy of MDM on the large CMU set, with the evaluator files."""
    out = {}
    for name, patch in (("patched", os.path.join(PATCHES, "mdm.patch")), ("pristine", None)):
        dst = str(tmp_path_factory.mktemp(f"mdm_eval_{name}"))
        copy_checkout(ROOT, dst)
        link_humanml3d(dst, os.path.abspath(LARGE))
        if patch:
            res = git_apply(patch, dst)
            assert res.returncode == 0, res.stderr
        write_evaluator(dst, LARGE)
        out[name] = dst
    return out


def harness(repo, args, launcher=False, code=None, timeout=1200):
    cmd = [sys.executable, HARNESS] + (["-c", code] if code else []) + list(args)
    if launcher:
        cmd = [sys.executable, "-m", "smdm_plugin.integrations.launcher", "--repo", repo, "--"] + cmd
    return run_logged(cmd, cwd=repo, env=plugin_env(ENV), timeout=timeout, check=True)


@pytest.mark.parametrize("launcher", [False, True], ids=["patch", "smdm-run"])
def test_eval_humanml_on_a_sparse_checkpoint(repos, launcher, tmp_path):
    repo = repos["pristine" if launcher else "patched"]
    save = str(tmp_path / "sparse")
    harness(repo, ["train.train_mdm", "--save_dir", save, "--num_steps", "10", *TINY, "--sparse"], launcher=launcher)
    ckpt = sorted(glob.glob(os.path.join(save, "model*.pt")))[-1]
    proc = harness(repo, ["--model_path", ckpt, "--eval_mode", "debug"], launcher=launcher, code=EVAL)
    out = proc.stdout + proc.stderr
    assert "Loading Evaluation Model Wrapper (Epoch 0) Completed" in out
    logs = glob.glob(os.path.join(save, "eval_humanml_*_debug.log"))
    assert logs, os.listdir(save)
    text = open(logs[0]).read()
    for metric in ("FID", "Diversity", "Matching Score", "R_precision"):
        assert metric in text, text[-2000:]
    fids = [float(v) for v in re.findall(r"\[vald\] FID: ([-0-9.eE+naninf]+)", text)]
    assert fids and all(np.isfinite(fids)), text[-2000:]
    assert "EVAL_MODEL_SPARSE=True" in out, "the sparse model was not restored from args.json"
