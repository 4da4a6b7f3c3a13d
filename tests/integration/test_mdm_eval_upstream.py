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


# ----------------------------------------------------------------------------------------- sensitivity
def train_reference_evaluator(mdm_root: str, data: str, out: str, ae_steps: int = 200, steps: int = 150,
                              seed: int = 0) -> str:
    """T2M's evaluator trained with upstream's own code on ``data``'s train split, saved in upstream's
    layout in ``out``: MDM's ``modules.py`` networks at upstream's sizes, the decomposition stage with
    ``DecompTrainerV3`` (movement auto-encoder, windows of 24 frames, batch 32, Adam 1e-4 as T2M's
    ``train_decomp_v3``), then ``TextMotionMatchTrainer`` (margin 10, Adam 1e-4, batch 32 sorted by
    caption length, the movement encoder frozen) for ``steps`` steps; captions through upstream's
    ``WordVectorizer`` over random GloVe vectors (the published ones are not here), motions cropped as
    ``Text2MotionDatasetV2`` does."""
    import random
    import types

    import torch

    from smdm_plugin.metrics.evaluator.data import load_split
    from smdm_plugin.metrics.evaluator.protocol import upstream_crop

    sys.path.insert(0, mdm_root)
    from data_loaders.humanml.networks import modules, trainers
    from data_loaders.humanml.utils.word_vectorizer import POS_enumerator, WordVectorizer

    torch.manual_seed(seed)
    random.seed(seed)
    np.random.seed(seed)
    rng = np.random.default_rng(seed)
    write_evaluator(out, data)  # random GloVe files over the data's words (+ networks, replaced below)
    vec = WordVectorizer(os.path.join(out, "glove"), "our_vab")
    train = load_split(data, "train")
    mean, std = train.mean, train.std
    opt = types.SimpleNamespace(device="cpu", is_train=False, lambda_sparsity=0.001, lambda_smooth=0.1,
                                negative_margin=10.0, unit_length=4, lr=1e-4)
    enc = modules.MovementConvEncoder(259, 512, 512)
    dec = modules.MovementConvDecoder(512, 512, 263)
    decomp = trainers.DecompTrainerV3(opt, enc, dec)
    decomp.l1_criterion = torch.nn.L1Loss()
    decomp.opt_movement_enc = torch.optim.Adam(enc.parameters(), lr=1e-4)
    decomp.opt_movement_dec = torch.optim.Adam(dec.parameters(), lr=1e-4)
    for _ in range(ae_steps):
        idx = rng.choice(len(train), 32)
        win = []
        for i in idx:
            s = int(rng.integers(0, len(train.motions[i]) - 24 + 1))
            win.append((train.motions[i][s:s + 24] - mean) / std)
        decomp.forward(torch.tensor(np.stack(win)).float())
        decomp.update()
    text = modules.TextEncoderBiGRUCo(300, len(POS_enumerator), 512, 512, "cpu")
    motion = modules.MotionEncoderBiGRUCo(512, 1024, 512, "cpu")
    tm = trainers.TextMotionMatchTrainer(opt, text, motion, enc)
    tm.contrastive_loss = modules.ContrastiveLoss(10.0)
    tm.opt_text_encoder = torch.optim.Adam(text.parameters(), lr=1e-4)
    tm.opt_motion_encoder = torch.optim.Adam(motion.parameters(), lr=1e-4)
    for _ in range(steps):
        items = []
        for i in rng.choice(len(train), 32, replace=False):
            cap = train.captions[i][int(rng.integers(len(train.captions[i])))].tokens[:20]
            toks = ["sos/OTHER"] + cap + ["eos/OTHER"]
            n_tok = len(toks)
            toks += ["unk/OTHER"] * (22 - n_tok)
            s, n = upstream_crop(len(train.motions[i]), rng)
            m = np.zeros((196, 263), np.float32)
            m[:n] = (train.motions[i][s:s + n] - mean) / std
            items.append((np.stack([vec[t][0] for t in toks]), np.stack([vec[t][1] for t in toks]), n_tok, m, n))
        items.sort(key=lambda it: it[2], reverse=True)
        batch = (torch.tensor(np.stack([it[0] for it in items])).float(),
                 torch.tensor(np.stack([it[1] for it in items])).float(), None,
                 torch.tensor([it[2] for it in items]), torch.tensor(np.stack([it[3] for it in items])),
                 torch.tensor([it[4] for it in items]), None)
        tm.train_mode()
        tm.forward(batch)
        tm.update()
    ck = os.path.join(out, "t2m", "text_mot_match", "model", "finest.tar")
    torch.save({"movement_encoder": enc.state_dict(), "motion_encoder": motion.state_dict(),
                "text_encoder": text.state_dict(), "epoch": steps}, ck)
    np.save(os.path.join(out, "mean.npy"), mean)
    np.save(os.path.join(out, "std.npy"), std)
    return out


def test_default_evaluator_is_as_sensitive_as_t2m_reference(tmp_path):
    """`smdm evaluator train` (defaults) against T2M's evaluator trained with upstream's code on the same
    data (:func:`train_reference_evaluator`): paired FID / diversity² of noise 0.3 and 1.0 Std, the
    9-frame moving average and time reversal at least half the reference's (a seed's spread), and
    R-precision that falls for time-reversed and caption-swapped motion. About 10 minutes on one thread."""
    from smdm_plugin.apps.cli import main as smdm
    from smdm_plugin.metrics.evaluator import load_evaluator
    from smdm_plugin.metrics.evaluator.check import sensitivity
    from smdm_plugin.metrics.evaluator.data import load_split

    test = load_split(LARGE, "test")
    ref = load_evaluator(train_reference_evaluator(ROOT, LARGE, str(tmp_path / "ref")))
    ours = tmp_path / "ours"
    assert smdm(["evaluator", "train", "--data", LARGE, "--out", str(ours), "--no-progress", "--threads", "1"]) == 0
    tables = {k: sensitivity(ev, test, replications=10, seed=0) for k, ev in (("ref", ref),
                                                                               ("ours", load_evaluator(str(ours))))}
    for k, t in tables.items():
        print(f"\n{k}\n{t.markdown()}")
    for name in ("noise_0.3", "noise_1.0", "smooth_9", "reversed"):
        assert tables["ours"].row(name).paired >= 0.5 * tables["ref"].row(name).paired, name
    o = tables["ours"]
    assert o.row("reversed").top3[0] < o.row("real").top3[0]
    assert o.row("caption_swap").resolved and o.row("reversed").resolved and o.row("noise_1.0").resolved
