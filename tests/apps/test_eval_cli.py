"""smdm evaluator train / smdm eval: an evaluator trained quickly on real motion scores the real
test motions against themselves with FID ≈ 0, noised real motion clearly worse (higher FID, lower
R-precision); resume; bad input is one line with exit status 2."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from smdm_plugin.apps.cli import main as smdm
from smdm_plugin.metrics.evaluator import load_evaluator
from smdm_plugin.metrics.evaluator.data import load_split
from smdm_plugin.metrics.evaluator.score import score_motions

from pathlib import Path

from helpers.paths import HML_LARGE as LARGE
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _data():
    if (LARGE / "texts").is_dir():
        return str(LARGE)
    pytest.skip("../shared/data/cmu-humanml3d-large not available")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """An evaluator trained for a few epochs on the large CMU set (HumanML3D 263-D features), with 0.4's
    quick one-stage recipe (the T2M recipe's own tests: test_evaluator_check.py)."""
    data = _data()
    out = tmp_path_factory.mktemp("ev") / "ev"
    assert smdm(["evaluator", "train", "--data", data, "--out", str(out), "--epochs", "8", "--recipe", "contrastive",
                 "--no-progress", "--threads", "1"]) == 0
    return data, str(out)


def test_evaluator_folder_reports_held_out_accuracy(trained):
    _, out = trained
    meta = json.load(open(os.path.join(out, "evaluator.json")))
    m = meta["metrics"]
    assert set(m) >= {"val", "test", "train"}
    assert m["test"]["pool_size"] == 32 and m["val"]["pool_size"] == 16  # val has 16 motions: one batch of 16
    # better than chance on held-out motion (chance top-3: 3/32)
    assert m["test"]["top3"] > 2 * m["test"]["chance_top3"]


def test_real_against_itself_and_noised(trained, tmp_path):
    data, out = trained
    ev = load_evaluator(out)
    test = load_split(data, "test")
    caps = test.first_captions(seed=0)  # the caption draw smdm eval makes for --seed 0, replication 1
    same = score_motions(ev, test.motions, None, caps, test.motions, seed=0)
    assert abs(same.fid) < 1e-4
    assert same.r_precision_top3 == same.real_r_precision_top3
    rng = np.random.default_rng(0)
    # white noise of 3 std per feature and frame: the distribution moves (FID), the texts match less
    noised = [m + 3.0 * test.std * rng.normal(size=m.shape).astype(np.float32) for m in test.motions]
    worse = score_motions(ev, test.motions, None, caps, noised, seed=0)
    assert worse.fid > 1.0
    # the same motions given to the wrong captions: the same set (FID 0), R-precision down
    rolled = test.motions[1:] + test.motions[:1]
    top3 = [score_motions(ev, test.motions, None, caps, m, seed=s).r_precision_top3 for s in range(4)
            for m in (test.motions, rolled)]
    assert abs(score_motions(ev, test.motions, None, caps, rolled).fid) < 1e-4
    assert np.mean(top3[1::2]) < np.mean(top3[0::2])
    # the CLI on a folder of the noised motions writes the same numbers
    mdir = tmp_path / "m"
    mdir.mkdir()
    for i, m in zip(test.ids, noised):
        np.save(mdir / f"{i}.npy", m)
    rdir = tmp_path / "r"
    assert smdm(["eval", "--data", data, "--evaluator", out, "--motions", str(mdir), "--out", str(rdir),
                 "--protocol", "fixed", "--threads", "1"]) == 0
    res = json.load(open(rdir / "metrics.json"))
    assert res["fid"] == pytest.approx(worse.fid, rel=1e-4)
    assert res["r_precision_top3"] == pytest.approx(worse.r_precision_top3)
    assert res["protocol"]["pool_size"] == 32 and res["protocol"]["n_scored"] == 32
    assert res["real"]["fid"] == 0.0 and res["replications"] == 1
    assert res["real"]["jitter"] < res["jitter"]  # noise is jerky
    assert (rdir / "metrics.md").exists() and (rdir / "metrics.png").exists()
    # never over an existing result without --overwrite
    r = subprocess.run([sys.executable, "-m", "smdm_plugin", "eval", "--data", data, "--evaluator", out, "--motions",
                        str(mdir), "--out", str(rdir)], capture_output=True, text=True, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": REPO})
    assert r.returncode == 2 and "--overwrite" in r.stderr and "Traceback" not in r.stderr
    # upstream's protocol (the default): 20 replications of drop-last draws of 32, a real-vs-real floor > 0
    # below the noised motions' FID; the same numbers as the draws computed here
    up = tmp_path / "up"
    assert smdm(["eval", "--data", data, "--evaluator", out, "--motions", str(mdir), "--out", str(up),
                 "--threads", "1"]) == 0
    res = json.load(open(up / "metrics.json"))
    assert res["replications"] == 20 and res["protocol"]["name"] == "upstream"
    assert res["protocol"]["n_generated"] == 32 and res["protocol"]["pool_size"] == 32
    assert 0 < res["real"]["fid"] < res["fid"] and res["real"]["fid_interval"] > 0
    from smdm_plugin.metrics.evaluator.protocol import replication
    from smdm_plugin.metrics.evaluator.score import embed_captions, embed_motions, score_embeddings

    rep = replication("upstream", [len(m) for m in test.motions], [len(c) for c in test.captions], seed=1)
    by_id = dict(zip(test.ids, noised))
    r1 = score_embeddings(embed_motions(ev, rep.reference.motions(test.motions)),
                          embed_captions(ev, [c.tokens for c in rep.scored.captions(test.captions)]),
                          embed_motions(ev, [by_id[test.ids[i]][:n] for i, n in
                                                 zip(rep.scored.index, rep.scored.length)]), seed=1,
                          scored_real=embed_motions(ev, rep.scored.motions(test.motions)))
    assert res["metrics"]["fid"]["values"][1] == pytest.approx(r1.fid, rel=1e-6)
    assert res["rows"][1]["real_fid"] == pytest.approx(r1.real_fid, rel=1e-6)
    assert "real-vs-real floor" in (up / "metrics.md").read_text()


def test_eval_with_a_model_and_resume(tmp_path):
    """Embedded default data (joints66): a 2-epoch evaluator resumed to 3, and a demo-style model
    folder generating the split for 2 replications (mean ± interval, multimodality)."""
    import torch

    from smdm_plugin.core.config import SparseConfig
    from smdm_plugin.training.bundle import save_bundle
    from smdm_plugin.io.representation import Representation
    from smdm_plugin.reference.backbone import TinyMDM
    from smdm_plugin.reference.simple_diffusion import SimpleDiffusion

    ev = tmp_path / "ev"
    small = ["--hidden", "32", "--dim", "16", "--ae-epochs", "2", "--no-progress", "--threads", "1"]
    assert smdm(["evaluator", "train", "--out", str(ev), "--epochs", "2"] + small) == 0
    assert smdm(["evaluator", "train", "--out", str(ev), "--epochs", "3", "--resume"] + small) == 0
    assert json.load(open(ev / "evaluator.json"))["epochs"] == 3
    train = load_split(None, "train")
    backbone = {"njoints": 66, "nfeats": 1, "latent_dim": 32, "ff_size": 64, "num_layers": 1, "num_heads": 4,
                "dropout": 0.0, "arch": "trans_enc"}
    model = TinyMDM(**backbone)
    save_bundle(str(tmp_path / "model"), model, SimpleDiffusion(4), backbone, Representation("joints66"),
                train.mean, train.std, max_frames=196)
    rdir = tmp_path / "r"
    assert smdm(["eval", "--evaluator", str(ev), "--model", str(tmp_path / "model"), "--out", str(rdir),
                 "--replications", "2", "--mm-repeats", "3", "--mm-captions", "2", "--threads", "1"]) == 0
    res = json.load(open(rdir / "metrics.json"))
    assert len(res["metrics"]["fid"]["values"]) == 2 and res["metrics"]["fid"]["interval"] is not None
    assert res["multimodality"] is not None and res["protocol"]["multimodality_times"] == 2
    assert res["fid"] > 0
    assert res["keyframe_error"] is None
    # in-betweening through the real motions' frames 0, 10, 20, ... and the last: imposed exactly (x0 imputation)
    r2 = tmp_path / "r2"
    assert smdm(["eval", "--evaluator", str(ev), "--model", str(tmp_path / "model"), "--out", str(r2),
                 "--replications", "1", "--mm-repeats", "0", "--inbetween-every", "10", "--threads", "1"]) == 0
    res2 = json.load(open(r2 / "metrics.json"))
    assert res2["keyframe_error"] is not None and res2["keyframe_error"] < 1e-4
    assert res2["fid"] < res["metrics"]["fid"]["values"][0]  # through the real keyframes: closer to the real set


@pytest.mark.parametrize("args,needle", [
    (["eval", "--evaluator", "nowhere", "--motions", ".", "--out", "x"], "--evaluator"),
    (["eval", "--evaluator", ".", "--out", "x"], "one of the arguments --motions --model is required"),
    (["evaluator", "train", "--out", "x", "--epochs", "0"], "--epochs"),
    (["evaluator", "fit"], "unknown subcommand"),
    (["eval", "--evaluator", ".", "--motions", "docs", "--out", "x", "--inbetween-every", "5"], "needs --model"),
    # multimodality generates motions: with --motions its options cannot apply (0.10.5 ignored them)
    (["eval", "--evaluator", ".", "--motions", "docs", "--out", "x", "--mm-repeats", "5"],
     "argument --mm-repeats: needs --model"),
    (["eval", "--evaluator", ".", "--motions", "docs", "--out", "x", "--mm-captions", "3"],
     "argument --mm-captions: needs --model"),
    (["eval", "--evaluator", ".", "--motions", "docs", "--out", "x", "--protocol", "fixed", "--eval-mode", "debug"],
     "argument --eval-mode: upstream's eval modes are --protocol upstream's"),
])
def test_bad_input_is_one_line(args, needle):
    r = subprocess.run([sys.executable, "-m", "smdm_plugin"] + args, capture_output=True, text=True, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": REPO})
    assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr


def test_an_eval_mode_with_multimodality_on_motions_says_it_is_not_measured():
    r = subprocess.run([sys.executable, "-m", "smdm_plugin", "eval", "--evaluator", ".", "--motions", "docs", "--out",
                        "docs", "--eval-mode", "mm_short"], capture_output=True, text=True, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": REPO})
    assert "smdm eval: warning: --eval-mode mm_short's multimodality needs --model" in r.stderr
    assert r.returncode == 2 and "Traceback" not in r.stderr          # (then --out, inside the input, is refused)


def test_eval_missing_motions_and_wrong_evaluator(tmp_path):
    ev = tmp_path / "ev"
    assert smdm(["evaluator", "train", "--out", str(ev), "--epochs", "1", "--ae-epochs", "1", "--hidden", "16", "--dim",
                 "8", "--no-progress", "--threads", "1"]) == 0
    (tmp_path / "m").mkdir()
    r = subprocess.run([sys.executable, "-m", "smdm_plugin", "eval", "--evaluator", str(ev), "--motions",
                        str(tmp_path / "m"), "--out", str(tmp_path / "r")], capture_output=True, text=True, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": REPO})
    assert r.returncode == 2 and "missing 19 of 19 motions" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    if (LARGE / "texts").is_dir():  # a joints66 evaluator cannot read HumanML3D features
        r = subprocess.run([sys.executable, "-m", "smdm_plugin", "eval", "--data", str(LARGE), "--evaluator", str(ev),
                            "--motions", str(tmp_path / "m"), "--out", str(tmp_path / "r")], capture_output=True,
                           text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": REPO})
        assert r.returncode == 2 and "reads joints66 [66] features" in r.stderr


def test_resume_continues_exactly_and_glove(tmp_path):
    """2 auto-encoder + 3 matching epochs in one go == 2 + 2, then --resume to 3 (same weights); --glove:
    frozen GloVe words."""
    import pickle

    import torch

    a, b = tmp_path / "a", tmp_path / "b"
    common = ["--no-progress", "--threads", "1", "--hidden", "16", "--dim", "8", "--ae-epochs", "2"]
    assert smdm(["evaluator", "train", "--out", str(a), "--epochs", "3"] + common) == 0
    assert smdm(["evaluator", "train", "--out", str(b), "--epochs", "2"] + common) == 0
    assert smdm(["evaluator", "train", "--out", str(b), "--epochs", "3", "--resume"] + common) == 0
    sa = torch.load(a / "evaluator.pt", weights_only=True)
    sb = torch.load(b / "evaluator.pt", weights_only=True)
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    # other settings than the state was written with: refused
    r = subprocess.run([sys.executable, "-m", "smdm_plugin", "evaluator", "train", "--out", str(b), "--epochs", "4",
                        "--resume", "--dim", "16", "--no-progress"], capture_output=True, text=True, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": REPO})
    assert r.returncode == 2 and "other settings" in r.stderr
    glove = tmp_path / "glove"
    glove.mkdir()
    words = ["unk", "sos", "eos", "walk", "run", "jog", "jump"]
    np.save(glove / "our_vab_data.npy", np.random.default_rng(0).normal(size=(len(words), 20)).astype(np.float32))
    pickle.dump(words, open(glove / "our_vab_words.pkl", "wb"))
    pickle.dump({w: i for i, w in enumerate(words)}, open(glove / "our_vab_idx.pkl", "wb"))
    g = tmp_path / "g"
    assert smdm(["evaluator", "train", "--out", str(g), "--epochs", "1", "--glove", str(glove)] + common) == 0
    ev = load_evaluator(str(g))
    assert not ev.config.learned_words and ev.config.dim_word == 20 and ev.config.vocab_size == len(words)
    torch.testing.assert_close(ev.words.weight, torch.from_numpy(np.load(glove / "our_vab_data.npy")))
    # loading it, GloVe (upstream's evaluator's option) cannot apply: its words are its own (0.10.5 ignored it)
    with pytest.raises(ValueError, match=r"was trained here .*; glove applies to upstream's evaluator only"):
        load_evaluator(str(g), glove=str(glove))


def test_text_model_is_sampled_with_its_captions_and_guidance(tmp_path, monkeypatch):
    """`smdm eval --model` on a `smdm train --text` model: every denoiser call gets the text embedding of
    the drawn caption of its motion, half the calls unconditional (classifier-free guidance at the saved
    scale); sampling it without captions is refused. Fails if the model is sampled without its text."""
    import torch

    from smdm_plugin.apps import train as trainer
    from smdm_plugin.apps.evaluate import Generator
    from smdm_plugin.metrics.evaluator.protocol import replication
    from smdm_plugin.reference.text import HashedBagOfWords

    data = _data()
    model = tmp_path / "m"
    assert trainer.main(["--data", data, "--steps", "2", "--batch", "2", "--max-frames", "48", "--diffusion-steps", "3",
                         "--latent-dim", "16", "--layers", "1", "--heads", "2", "--ff-size", "32", "--no-progress",
                         "--threads", "1", "--out", str(model), "--text", "--guidance-scale", "3"]) == 0
    gen = Generator(str(model), "cpu")
    assert gen.text is not None and "guidance 3" in gen.conditioning
    calls = []
    inner = gen.model

    class Spy(torch.nn.Module):
        njoints = inner.njoints

        def forward(self, x, t, y):
            calls.append(dict(y))
            return inner(x, t, y)

    gen.model = Spy()
    texts = ["a person walks forward", "someone jumps twice", "a man waves"]
    out = gen.generate([40, 44, 48], seed=0, texts=texts)
    assert [len(m) for m in out] == [40, 44, 48]
    assert len(calls) == 2 * 3  # 3 diffusion steps, a conditional and an unconditional call each
    want = torch.from_numpy(HashedBagOfWords(512, 0).encode(texts)).unsqueeze(0)
    for y in calls:
        torch.testing.assert_close(y["text_embed"], want)
    assert sum(bool(y.get("uncond")) for y in calls) == 3
    with pytest.raises(ValueError, match="needs one caption per motion"):
        gen.generate([40], seed=0)
    # through the CLI: the texts encoded are the scored draw's captions, one draw per motion and replication
    seen = []
    real_encode = HashedBagOfWords.encode

    def encode(self, texts):
        seen.append(list(texts))
        return real_encode(self, texts)

    monkeypatch.setattr(HashedBagOfWords, "encode", encode)
    ev = tmp_path / "ev"
    assert smdm(["evaluator", "train", "--data", data, "--out", str(ev), "--epochs", "1", "--ae-epochs", "1",
                 "--hidden", "16", "--dim", "8", "--no-progress", "--threads", "1"]) == 0
    assert smdm(["eval", "--data", data, "--evaluator", str(ev), "--model", str(model), "--out", str(tmp_path / "r"),
                 "--replications", "2", "--threads", "1"]) == 0
    test = load_split(data, "test")
    want = []
    for r in range(2):
        rep = replication("upstream", [len(m) for m in test.motions], [len(c) for c in test.captions], seed=r)
        want.append([c.text for c in rep.scored.captions(test.captions)])
    assert seen == want
    res = json.load(open(tmp_path / "r" / "metrics.json"))
    assert res["protocol"]["sampling"].startswith("text (hashed_bow, guidance 3")


@pytest.mark.parametrize("command", ["eval", "check"])
def test_evaluator_of_other_features_is_one_line_naming_both(trained, tmp_path, capsys, command):
    """An evaluator trained on HumanML3D 263-D features given the embedded clips (joints66): refused
    before anything runs, naming the argument, what the evaluator reads and what the data has."""
    _, ev = trained
    (tmp_path / "m").mkdir()
    argv = (["eval", "--evaluator", ev, "--motions", str(tmp_path / "m"), "--out", str(tmp_path / "r")]
            if command == "eval" else ["evaluator", "check", ev])
    with pytest.raises(SystemExit) as e:
        smdm(argv + ["--threads", "1"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and "it reads humanml3d [263] features" in err and "joints66 [66]" in err, err
    assert ("--evaluator" if command == "eval" else "EDIR") in err
    assert not (tmp_path / "r").exists() and not os.path.exists(os.path.join(ev, "sensitivity.json"))
