"""The evaluator's sensitivity table (``smdm evaluator check``) and the evaluation protocol draws:
each degradation against a slow reference, upstream's crops and drop-last draws, the table's file
validated on load, the CLI writing it and ``smdm eval`` showing it."""
import json
import os

import numpy as np
import pytest
import torch

from smdm_plugin.apps.cli import main as smdm
from smdm_plugin.io.captions import Caption
from smdm_plugin.metrics.evaluator import Evaluator, EvaluatorConfig
from smdm_plugin.metrics.evaluator.check import (CHECK_FILENAME, CONDITIONS, load_check, save_check, sensitivity,
                                                 weights_fingerprint)
from smdm_plugin.metrics.evaluator.data import CaptionedMotions
from smdm_plugin.metrics.evaluator.protocol import replication, upstream_crop

SMALL = dict(dim_word=8, dim_movement_hidden=16, dim_movement_latent=16, dim_motion_hidden=16, dim_text_hidden=16,
             dim_coemb=8)


def _data(n=40, D=263, seed=0):
    rng = np.random.default_rng(seed)
    motions = [rng.normal(size=(int(rng.integers(40, 240)), D)).astype(np.float32) for _ in range(n)]
    words = ["walk", "run", "jump", "wave", "sit", "turn"]
    caps = [[Caption(f"a person {words[i % 6]}s", ["a/DET", "person/NOUN", f"{words[i % 6]}/VERB"])
             for _ in range(1 + i % 3)] for i in range(n)]
    return CaptionedMotions([f"m{i}" for i in range(n)], motions, caps, np.zeros(D, np.float32),
                            (0.5 + rng.random(D)).astype(np.float32))


def _evaluator(D=263, seed=0):
    torch.manual_seed(seed)
    vocab = {w: i for i, w in enumerate(["unk", "sos", "eos", "a", "person", "walk", "run", "jump", "wave", "sit",
                                         "turn"])}
    rep = "humanml3d" if D == 263 else "joints66"
    return Evaluator(EvaluatorConfig(**SMALL, dim_pose=D, drop_tail=4 if D == 263 else 0, vocab_size=len(vocab),
                                     learned_words=True, source="own", representation=rep),
                     vocab, np.zeros(D), np.ones(D)).eval()


# ----------------------------------------------------------------------------------------- degradations
def test_degradations_against_slow_references():
    rng = np.random.default_rng(1)
    m = rng.normal(size=(30, 263)).astype(np.float32)
    std = (0.5 + rng.random(263)).astype(np.float32)
    smooth = CONDITIONS["smooth_9"].perturb([m], std, "humanml3d", rng)[0]
    padded = np.concatenate([np.repeat(m[:1], 4, 0), m, np.repeat(m[-1:], 4, 0)])
    ref = np.stack([padded[t:t + 9].mean(0) for t in range(30)])
    np.testing.assert_allclose(smooth, ref, atol=1e-5)
    np.testing.assert_array_equal(CONDITIONS["reversed"].perturb([m], std, "humanml3d", rng)[0],
                                  np.stack([m[29 - t] for t in range(30)]))
    big = np.zeros((4000, 263), np.float32)
    noisy = CONDITIONS["noise_0.3"].perturb([big], std, "humanml3d", np.random.default_rng(2))[0]
    np.testing.assert_allclose(noisy.std(0) / std, 0.3, rtol=0.1)
    slid = CONDITIONS["foot_sliding"].perturb([m], std, "humanml3d", rng)[0]
    diff = slid - m
    assert np.allclose(diff[:, 2], 0.025) and np.count_nonzero(np.delete(diff, 2, axis=1)) == 0
    j = rng.normal(size=(30, 66)).astype(np.float32)
    dj = CONDITIONS["foot_sliding"].perturb([j], std[:66], "joints66", rng)[0] - j
    np.testing.assert_allclose(dj[:, 65], 0.025 * np.arange(30), atol=1e-5)
    assert np.count_nonzero(dj[:, :65]) == 0


# ----------------------------------------------------------------------------------------- protocol
def test_upstream_draws_are_drop_last_pools_with_upstream_crops():
    lengths = list(range(40, 240, 5))  # 40 motions
    ncap = [1 + i % 3 for i in range(40)]
    rep = replication("upstream", lengths, ncap, seed=3)
    for d in (rep.reference, rep.scored):
        assert len(d.index) == 32 and len(set(d.index.tolist())) == 32  # one drop-last batch of 32
        L = np.array(lengths)[d.index]
        assert (d.length % 4 == 0).all() and (d.length <= np.minimum(L, 196)).all()
        assert (d.length >= np.minimum(L, 196) // 4 * 4 - 4).all()
        assert (d.start >= 0).all() and (d.start + d.length <= L).all()
        assert (d.caption < np.array(ncap)[d.index]).all()
    assert not np.array_equal(rep.reference.index, rep.scored.index)  # two independent draws
    # a third of the crops 4 frames shorter, offsets spread over the motion
    rng = np.random.default_rng(0)
    crops = [upstream_crop(100, rng) for _ in range(3000)]
    short = np.mean([n == 96 for _, n in crops])
    assert abs(short - 1 / 3) < 0.03 and {n for _, n in crops} == {96, 100}
    assert max(s for s, n in crops if n == 96) == 4
    # fixed: every motion whole, the caption draw of CaptionedMotions.first_captions(seed)
    data = _data()
    fx = replication("fixed", [len(m) for m in data.motions], [len(c) for c in data.captions], seed=7)
    assert fx.reference is fx.scored and (fx.scored.start == 0).all()
    assert [c.tokens for c in fx.scored.captions(data.captions)] == data.first_captions(seed=7)
    with pytest.raises(ValueError, match="protocol"):
        replication("mine", lengths, ncap, seed=0)


# ----------------------------------------------------------------------------------------- the table
def test_sensitivity_table_rows_and_file(tmp_path):
    data, ev = _data(), _evaluator()
    table = sensitivity(ev, data, replications=3, seed=0)
    assert [r.name for r in table.rows] == list(CONDITIONS)
    real, swap = table.row("real"), table.row("caption_swap")
    assert real.paired == 0.0 and swap.fid == real.fid  # the same motions: FID as the floor
    assert table.row("noise_1.0").paired > table.row("noise_0.1").paired > 0
    assert table.row("noise_1.0").fid[0] > real.fid[0]
    assert table.pool == 32 and table.n_motions == 40
    path = save_check(table, str(tmp_path))
    again = load_check(str(tmp_path), ev)
    assert again.to_dict() == table.to_dict()
    # other weights: refused, naming the file
    with pytest.raises(ValueError, match="other weights"):
        load_check(str(tmp_path), _evaluator(seed=1))
    d = json.load(open(path))
    d["rows"][0]["fid"] = [1.0]
    json.dump(d, open(path, "w"))
    with pytest.raises(ValueError, match=CHECK_FILENAME):
        load_check(str(tmp_path))
    assert weights_fingerprint(ev) == table.weights


def test_caption_swap_and_noise_resolved_by_an_evaluator_that_can_tell():
    """An evaluator whose motion embedding is the caption's word (the motions carry it) resolves the
    caption swap (R-precision falls), and noise moves FID above the floor."""
    data, ev = _data(), _evaluator()
    words = ["walk", "run", "jump", "wave", "sit", "turn"]
    for i, m in enumerate(data.motions):
        m[:, :6] = 0.0
        m[:, i % 6] = 3.0

    def text(caps):
        return torch.stack([torch.eye(8)[words.index(c[2].split("/")[0])] for c in caps]) * 3.0

    def motion(x, lengths):
        return torch.cat([x[:, 0, :6], torch.zeros(len(x), 2)], 1)

    ev.encode_text = text
    ev.encode_motion = motion
    table = sensitivity(ev, data, replications=4, seed=0, conditions=["real", "noise_1.0", "caption_swap"])
    real, swap = table.row("real"), table.row("caption_swap")
    assert real.top1[0] > 0.15 and swap.top3[0] < real.top3[0] and swap.resolved
    assert table.row("noise_1.0").resolved


# ----------------------------------------------------------------------------------------- CLI
def test_cli_check_writes_the_table_and_eval_shows_it(tmp_path, capsys):
    ev = tmp_path / "ev"
    assert smdm(["evaluator", "train", "--out", str(ev), "--epochs", "1", "--ae-epochs", "1", "--hidden", "16",
                 "--dim", "8", "--no-progress", "--threads", "1"]) == 0
    assert smdm(["evaluator", "check", str(ev), "--replications", "2", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "time reversal" in out and "real (floor)" in out
    table = json.load(open(ev / CHECK_FILENAME))
    assert table["replications"] == 2 and len(table["rows"]) == len(CONDITIONS)
    mdir = tmp_path / "m"
    mdir.mkdir()
    from smdm_plugin.metrics.evaluator.data import load_split

    test = load_split(None, "test")
    for i, m in zip(test.ids, test.motions):
        np.save(mdir / f"{i}.npy", m)
    assert smdm(["eval", "--evaluator", str(ev), "--motions", str(mdir), "--out", str(tmp_path / "r"),
                 "--replications", "2", "--threads", "1"]) == 0
    md = (tmp_path / "r" / "metrics.md").read_text()
    assert "Evaluator sensitivity" in md and "time reversal" in md
    # a table of other weights is not shown as if it were this evaluator's
    d = json.load(open(ev / CHECK_FILENAME))
    d["weights"] = "0" * 16
    json.dump(d, open(ev / CHECK_FILENAME, "w"))
    assert smdm(["eval", "--evaluator", str(ev), "--motions", str(mdir), "--out", str(tmp_path / "r2"),
                 "--replications", "1", "--threads", "1"]) == 0
    md = (tmp_path / "r2" / "metrics.md").read_text()
    assert "other weights" in md and "time reversal" not in md


def test_cli_check_bad_input_is_one_line(tmp_path, capsys):
    assert smdm(["evaluator", "check", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "neither an evaluator trained here" in err and "Traceback" not in err


# ----------------------------------------------------------------------------------------- the T2M recipe
def test_t2m_recipe_pretrains_then_freezes_the_movement_encoder():
    """Auto-encoder epochs move only the movement encoder (its reconstruction loss falls); the matching
    epochs leave it exactly as the auto-encoder left it and train the BiGRUs with the margin loss."""
    from smdm_plugin.metrics.evaluator.train import TrainSettings, build_evaluator, train_evaluator

    data = _data(n=24, seed=3)
    s = TrainSettings(recipe="t2m", ae_epochs=6, epochs=2, batch=8, ae_lr=3e-3, sizes=dict(SMALL))
    ev = build_evaluator(data, s)
    snaps = []
    st = train_evaluator(ev, data, None, s, on_epoch=lambda st: snaps.append(
        {k: v.clone() for k, v in st["model"].items()}))
    stages = [h["stage"] for h in st["history"]]
    assert stages == ["autoencoder"] * 6 + ["matching"] * 2
    ae = [h["loss"] for h in st["history"][:6]]
    assert ae[-1] < ae[0]
    mov = [k for k in snaps[0] if k.startswith("movement_encoder.")]
    gru = [k for k in snaps[0] if k.startswith("motion_encoder.") or k.startswith("text_encoder.")]
    assert any(not torch.equal(snaps[0][k], snaps[5][k]) for k in mov)            # trained as an auto-encoder
    assert all(torch.equal(snaps[0][k], snaps[5][k]) for k in gru)                # the BiGRUs wait
    assert all(torch.equal(snaps[5][k], snaps[7][k]) for k in mov)                # then frozen
    assert any(not torch.equal(snaps[5][k], snaps[7][k]) for k in gru)
    with pytest.raises(ValueError, match="recipe"):
        TrainSettings(recipe="mine")


def test_decisive_study_configs_resolve():
    """configs/ablations/decisive_t{10,50}.yaml: dense vs sparse, >= 256-D x 4 layers, >= 3 seeds, >= 20
    CPU-minutes per run, T = 10 and 50, scored with the T2M-recipe evaluator."""
    from smdm_plugin.apps.ablate.study import load_study
    from smdm_plugin.apps.ablate.study_evaluator import T2MSettings

    Ts = set()
    for name in ("decisive_t10", "decisive_t50"):
        c = load_study(name)
        Ts.add(c["diffusion_steps"])
        assert c["model"]["latent_dim"] >= 256 and c["model"]["num_layers"] >= 4 and len(c["seeds"]) >= 3
        assert c["clock"] == "cpu" and max(c["snapshots"]["seconds"]) >= 20 * 60
        assert any(v.get("dense") for v in c["variants"]) and any(not v.get("dense") for v in c["variants"])
        s = T2MSettings(**{k: v for k, v in c["evaluator"].items() if k != "kind"})
        assert s.recipe == "t2m"
    assert Ts == {10, 50}
    with pytest.raises(TypeError, match="recipe"):
        T2MSettings(recipe="mine")
