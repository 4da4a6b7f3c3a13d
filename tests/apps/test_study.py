"""Text conditioning of the in-package trainer and the quality-versus-compute study (smdm ablate
--config quality_compute --quick)."""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from smdm_plugin.apps import ablate
from smdm_plugin.apps.ablate import grid, study
from smdm_plugin.training.data import MotionSet
from smdm_plugin.training.trainer import TrainConfig, Trainer, caption_draws
from smdm_plugin.runtime.distributed import DistContext
from smdm_plugin.reference.simple_diffusion import SimpleDiffusion
from smdm_plugin.reference.text import (HashedBagOfWords, TextConfig, load_text_config, sample_with_text,
                                        words)

from helpers.paths import HML_LARGE as LARGE


@pytest.fixture(scope="module")
def large_dir() -> Path:
    if not (LARGE / "Mean.npy").exists() or not (LARGE / "texts").is_dir():
        pytest.skip("../shared/data/cmu-humanml3d-large not available")
    return LARGE


# ----------------------------------------------------------------------------------------- text encoder
def _reference_word_vector(word: str, dim: int, seed: int) -> np.ndarray:
    """Bit i of the BLAKE2b stream (most significant bit first) -> +1 / -1, over sqrt(dim)."""
    stream, k = b"", 0
    while len(stream) * 8 < dim:
        stream += hashlib.blake2b(f"{seed}\x00{k}\x00{word}".encode(), digest_size=64).digest()
        k += 1
    bits = [(stream[i // 8] >> (7 - i % 8)) & 1 for i in range(dim)]
    return np.array([1.0 if b else -1.0 for b in bits]) / math.sqrt(dim)


@pytest.mark.parametrize("dim", [7, 512, 600])
def test_hashed_bag_of_words_matches_a_slow_reference(dim):
    enc = HashedBagOfWords(dim, seed=3)
    cap = "A person walks, then walks back!"
    ref = sum(_reference_word_vector(w, dim, 3) for w in ["a", "person", "walks", "then", "walks", "back"])
    ref = ref / np.linalg.norm(ref)
    out = enc([cap, "", "back walks then person a walks"]).numpy()
    assert out.shape == (3, dim) and out.dtype == np.float32
    np.testing.assert_allclose(out[0], ref, atol=1e-6)
    assert np.all(out[1] == 0)                        # no words: zeros
    np.testing.assert_allclose(out[2], out[0], atol=1e-6)  # a bag: order does not matter


def test_text_encoder_is_deterministic_seeded_and_saved_with_the_model(tmp_path):
    cfg = TextConfig(dim=32, seed=5)
    a, b = cfg.build()(["a man jumps"]), TextConfig(dim=32, seed=5).build()(["a man jumps"])
    assert torch.equal(a, b)
    assert not torch.allclose(a, TextConfig(dim=32, seed=6).build()(["a man jumps"]))
    assert not torch.allclose(a, cfg.build()(["a man runs"]))
    # saved beside the model by Trainer.save, restored by load_text_config
    data = _toy_set(6)
    tr = Trainer(TrainConfig(steps=1, batch=2, diffusion_steps=4, text=cfg, model=_TINY), data,
                 dist=DistContext(device=torch.device("cpu")))
    tr.train(1)
    tr.save(str(tmp_path))
    back = load_text_config(str(tmp_path))
    assert back == cfg and torch.equal(back.build()(["a man jumps"]), a)
    bb = json.loads((tmp_path / "backbone.json").read_text())
    assert bb["cond_mode"] == "text" and bb["clip_dim"] == 32 and bb["cond_mask_prob"] == cfg.cond_mask_prob
    saved = json.loads((tmp_path / "train_config.json").read_text())
    saved = {k: v for k, v in saved.items() if k not in ("world_size", "global_batch", "step")}
    assert TrainConfig.from_dict(saved).text == cfg
    assert load_text_config(str(tmp_path / "nowhere")) is None
    (tmp_path / "text_encoder.json").write_text('{"dim": 0}')
    with pytest.raises(ValueError, match="text_encoder.json"):
        load_text_config(str(tmp_path))


@pytest.mark.parametrize("bad, match", [({"dim": 0}, "dim"), ({"cond_mask_prob": 1.0}, "cond_mask_prob"),
                                        ({"encoder": "clip"}, "encoder"), ({"guidance_scale": -1}, "guidance")])
def test_text_config_rejects_bad_values(bad, match):
    with pytest.raises(ValueError, match=match):
        TextConfig(**bad)


# ----------------------------------------------------------------------------------------- trainer
_TINY = {"latent_dim": 16, "num_layers": 1, "num_heads": 2, "ff_size": 32, "dropout": 0.0}


def _toy_set(M: int = 6, N: int = 24, D: int = 263) -> MotionSet:
    g = torch.Generator().manual_seed(0)
    lengths = torch.randint(12, N + 1, (M,), generator=g)
    frames = torch.randn(int(lengths.sum()), D, generator=g)
    caps = [[f"motion {i} walks", f"motion {i} turns", "a person moves"][: 1 + i % 3] for i in range(M)]
    return MotionSet(frames, lengths, [str(i) for i in range(M)], np.zeros(D, np.float32), np.ones(D, np.float32),
                     N, captions=caps)


def test_caption_draws_depend_on_seed_step_and_sample_only():
    a = caption_draws(0, 3, range(8, 16), [3] * 8)
    assert a == caption_draws(0, 3, range(8, 16), [3] * 8)
    assert a[4:] == caption_draws(0, 3, range(12, 16), [3] * 4)  # a shard of the batch draws the same
    assert all(0 <= k < 3 for k in a) and len(set(a)) > 1
    assert caption_draws(0, 4, range(8, 16), [3] * 8) != a
    assert caption_draws(0, 3, range(8, 16), [1] * 8) == [0] * 8


def test_text_conditioned_training_feeds_the_drawn_caption(monkeypatch):
    data = _toy_set()
    cfg = TextConfig(dim=16, cond_mask_prob=0.0)
    tr = Trainer(TrainConfig(steps=2, batch=3, diffusion_steps=4, text=cfg, model=_TINY), data,
                 dist=DistContext(device=torch.device("cpu")))
    seen = []
    orig = tr.model.forward

    def spy(x, t, y=None):
        seen.append(y["text_embed"].clone())
        return orig(x, t, y)

    monkeypatch.setattr(tr.model, "forward", spy)
    tr.step()
    ids = tr.batch_indices(0).tolist()
    pick = caption_draws(0, 0, range(0, 3), [len(data.captions[i]) for i in ids])
    expected = cfg.build()([data.captions[i][k] for i, k in zip(ids, pick)])
    assert seen[0].shape == (1, 3, 16) and torch.allclose(seen[0][0], expected)
    assert tr.model.embed_text.weight.grad is not None and tr.model.embed_text.weight.grad.abs().sum() > 0


def test_training_stays_unconditional_by_default():
    tr = Trainer(TrainConfig(steps=1, batch=2, diffusion_steps=4, model=_TINY), _toy_set(),
                 dist=DistContext(device=torch.device("cpu")))
    assert tr.backbone_args["cond_mode"] == "no_cond" and not hasattr(tr.model, "embed_text")
    with pytest.raises(ValueError, match="captions"):
        Trainer(TrainConfig(steps=1, batch=2, diffusion_steps=4, model=_TINY, text=TextConfig(dim=8)),
                MotionSet(torch.zeros(20, 263), torch.tensor([20]), ["a"], np.zeros(263, np.float32),
                          np.ones(263, np.float32), 24), dist=DistContext(device=torch.device("cpu")))


# ----------------------------------------------------------------------------------------- CFG
def _text_model(dim: int = 16):
    from smdm_plugin.reference.backbone import TinyMDM

    torch.manual_seed(0)
    return TinyMDM(njoints=263, nfeats=1, cond_mode="text", clip_dim=dim, **_TINY).eval()


def test_sampling_with_guidance_matches_the_formula():
    model, diff = _text_model(), SimpleDiffusion(3)
    texts, L = ["a man walks", "someone jumps"], torch.tensor([10, 7])
    for scale in (2.5, 1.0, 0.0):
        cfg = TextConfig(dim=16, guidance_scale=scale)
        out = sample_with_text(model, diff, cfg, texts, L, 10, generator=torch.Generator().manual_seed(1))
        emb = cfg.build()(texts).unsqueeze(0)
        y = {"mask": (torch.arange(10) < L[:, None]).view(2, 1, 1, 10), "lengths": L, "text_embed": emb}

        def guided(x, t, y):  # the formula, written out
            c = model(x, t, y)
            u = model(x, t, {**y, "text_embed": torch.zeros_like(emb)})
            return u + scale * (c - u)

        ref = diff.p_sample_loop(guided, (2, 263, 1, 10), {"y": y}, generator=torch.Generator().manual_seed(1))
        torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)
    # scale 0 is the unconditional model: the captions do not matter
    c0 = TextConfig(dim=16, guidance_scale=0.0)
    a = sample_with_text(model, diff, c0, texts, L, 10, generator=torch.Generator().manual_seed(1))
    b = sample_with_text(model, diff, c0, ["x", "y"], L, 10, generator=torch.Generator().manual_seed(1))
    c = sample_with_text(model, diff, TextConfig(dim=16), ["x", "y"], L, 10, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(a, b)
    assert not torch.allclose(b, c)


# ----------------------------------------------------------------------------------------- statistics
def test_t_interval_against_scipy():
    stats = pytest.importorskip("scipy.stats")
    for n in (2, 3, 5, 31):
        v = np.random.default_rng(n).normal(size=n)
        mean, hw, k = study.t_interval(list(v))
        ref = stats.t.ppf(0.975, n - 1) * v.std(ddof=1) / math.sqrt(n)
        assert k == n and mean == pytest.approx(v.mean()) and hw == pytest.approx(ref, rel=1e-3)
    assert math.isnan(study.t_interval([1.0])[1]) and study.t_interval([1.0, float("nan"), 3.0])[2] == 2


def test_speed_normalised_jitter_against_a_loop():
    from smdm_plugin.metrics import jitter, to_joint_positions
    from smdm_plugin.metrics.feature_measures import per_motion_quality

    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 30, 263, generator=g) * 0.3
    L = torch.tensor([30, 20, 12])
    mean, std = np.zeros(263, np.float32), np.ones(263, np.float32)
    q = per_motion_quality(x, L, mean, std)
    j = to_joint_positions(x, mean, std)
    for b in range(3):
        p = j[b, : int(L[b])].double()
        speed = np.mean([float((p[k + 1] - p[k]).norm(dim=-1).mean()) * 20 for k in range(len(p) - 1)])
        jit = float(jitter(p, fps=20))
        assert q["speed"][b] == pytest.approx(speed, rel=1e-4)
        assert q["jitter_per_speed"][b] == pytest.approx(jit / speed, rel=1e-4)


# ----------------------------------------------------------------------------------------- the study
def test_study_config_is_validated():
    cfg = study.load_study("quality_compute")
    assert {v["name"] for v in cfg["variants"]} >= {"dense", "sparse (VW)", "sparse uniform",
                                                    "sparse w/o interpolation", "sparse FSQ off"}
    assert len(cfg["seeds"]) >= 3 and cfg["snapshots"]["steps"] and cfg["snapshots"]["seconds"]
    assert study.is_study_config("quality_compute") and not study.is_study_config("table1")
    for bad, match in (({"clock": "sun"}, "clock"), ({"snapshots": {"steps": [], "seconds": []}}, "snapshots"),
                       ({"bogus": 1}, "unknown key"), ({"seeds": [0, 0]}, "seeds"),
                       ({"text": {"dim": 0}}, "text"), ({"evaluator": {"kind": "nope"}}, "evaluator.kind"),
                       # the grid's variant checks (0.10.5 took these): a bool dense, no sparse settings on a dense one
                       ({"variants": [{"name": "d", "dense": "yes"}]}, r"variants\[0\].dense='yes'"),
                       ({"variants": [{"name": "d", "dense": True, "sparse": {"fsq": False}}]},
                        "do not apply to a dense variant"),
                       ({"variants": [{"name": "a"}, {"name": "A"}]}, "have the same folder name 'a'")):
        raw = {**{k: v for k, v in cfg.items() if k != "data"}, **bad}
        with pytest.raises(ValueError, match=match):
            study.resolve_study(raw)


def test_quick_study_end_to_end(large_dir, tmp_path, capsys, monkeypatch):
    out = tmp_path / "qc"
    args = ["--config", "quality_compute", "--quick", "--out", str(out), "--data", str(large_dir)]
    assert ablate.main(args) == 0
    res = json.loads((out / "results.json").read_text())
    cfg = res["config"]
    assert (out / "fid_vs_time.png").stat().st_size > 1000 and (out / "results.csv").exists()
    md = (out / "results.md").read_text()
    assert "## Equal optimiser steps" in md and "## Equal training time" in md
    names = [v["name"] for v in cfg["variants"]]
    for row in res["rows"]:
        assert row["seeds"] == len(cfg["seeds"]) and row["variant"] in names
        if row["kind"] == "steps":  # the equal-step snapshot has exactly that many steps, every variant and seed
            assert row["step"]["values"] == [row["at"]] * len(cfg["seeds"])
        else:  # a time snapshot is taken at the first step past the budget
            assert all(t >= row["at"] for t in row["train_s"]["values"])
        for k in study.METRICS:
            assert math.isfinite(row[k]["mean"]) and math.isfinite(row[k]["ci95"]) and row[k]["ci95"] >= 0
        assert 0 <= row["r_precision_top1"]["mean"] <= row["r_precision_top3"]["mean"] <= 1
    ref = res["reference"]
    assert ref["fid"] == pytest.approx(0.0, abs=1e-6) and ref["fid_train_vs_eval"] > 0
    # every (variant, seed) folder has its result with provenance; the evaluator is cached
    for v in names:
        for s in cfg["seeds"]:
            r = json.loads((out / grid.slug(v) / f"seed{s}" / "result.json").read_text())
            assert r["status"] == "ok" and r["provenance"]["seed"] == s and len(r["snapshots"]) == 4
    assert len(list((out / "evaluator").iterdir())) == 1
    # resumable per (variant, seed): nothing retrains; without a flag the folder is refused
    calls = []
    monkeypatch.setattr(study, "run_seed", lambda *a, **k: calls.append(a[1]["name"]))
    assert ablate.main(args + ["--resume"]) == 0 and calls == []
    # a report rebuilt from part of the runs: the missing ones are not trained, their rows count fewer seeds
    (out / "dense" / "seed1" / "result.json").unlink()
    assert ablate.main(args + ["--resume", "--report-only"]) == 0 and calls == []
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert {r["seeds"] for r in rows if r["variant"] == "dense"} == {1}
    capsys.readouterr()
    assert ablate.main(args) == 2 and "--resume" in capsys.readouterr().err


def test_smdm_train_text_flag(large_dir, tmp_path, capsys):
    from smdm_plugin.apps import train as trainer

    out = tmp_path / "m"
    base = ["--data", str(large_dir), "--steps", "2", "--batch", "2", "--max-frames", "48", "--diffusion-steps", "4",
            "--latent-dim", "16", "--layers", "1", "--heads", "2", "--ff-size", "32", "--no-progress", "--threads", "1"]
    assert trainer.main(base + ["--out", str(out), "--text", "--guidance-scale", "3"]) == 0
    assert load_text_config(str(out)) == TextConfig(guidance_scale=3.0)
    assert json.loads((out / "backbone.json").read_text())["cond_mode"] == "text"
    with pytest.raises(SystemExit) as e:
        trainer.main(base + ["--out", str(tmp_path / "n"), "--guidance-scale", "3"])
    assert e.value.code == 2 and "only with --text" in capsys.readouterr().err
    assert trainer.main(base + ["--out", str(tmp_path / "u")]) == 0  # default: unconditional
    assert load_text_config(str(tmp_path / "u")) is None
    assert json.loads((tmp_path / "u" / "backbone.json").read_text())["cond_mode"] == "no_cond"


@pytest.mark.parametrize("kind, settings", [("t2m", {"epochs": 1})])
def test_evaluator_is_cached_and_reloads_to_the_same_embeddings(large_dir, tmp_path, kind, settings):
    cfg = study.load_study("quality_compute_quick")
    cfg["evaluator"] = {"kind": kind, **settings}
    data = study.StudyData(str(large_dir), cfg)
    logs = []
    ev, key, folder = study.build_evaluator(cfg, data, str(tmp_path), logs.append)
    again, key2, _ = study.build_evaluator(cfg, data, str(tmp_path), logs.append)
    assert key == key2 and sum("training the" in m for m in logs) == 1  # trained once, then loaded
    assert type(again) is type(ev) and Path(folder).is_dir()
    m1, m2 = ev.embed_motion(data.raw, data.lengths), again.embed_motion(data.raw, data.lengths)
    t1, t2 = ev.embed_text(data.caption_objs), again.embed_text(data.caption_objs)
    assert m1.shape == (len(data.ids), ev.dim) and t1.shape == m1.shape
    torch.testing.assert_close(m1, m2)
    torch.testing.assert_close(t1, t2)
    cfg["evaluator"] = {"kind": kind, **settings, "seed": 1}  # other settings: another cache entry
    assert study.build_evaluator(cfg, data, str(tmp_path), logs.append)[1] != key


def test_an_interrupted_run_continues_from_its_last_snapshot(large_dir, tmp_path, monkeypatch):
    """run_seed with a checkpoint folder: interrupted right after its first snapshot's checkpoint, a
    second call continues from that step (not from 0) and gives the uninterrupted run's snapshots;
    the anchors and the FID interval are in every record."""
    cfg = study.load_study("quality_compute_quick")
    cfg["snapshots"] = {"steps": [2, 4], "seconds": []}      # steps only: the same snapshots every time
    data = study.StudyData(str(large_dir), cfg)
    ref = study._reference(cfg, data, str(tmp_path / "out"), lambda *_: None)
    for k in ("fid_floor", "fid_train_matched", "fid_train_vs_eval", "fid_train_sample"):
        lo, hi = ref.scores[f"{k}_interval"]
        assert lo <= ref.scores[k] <= hi, k
    variant = {"name": "sparse (VW)"}
    args = (cfg, variant, 0, data, ref.evaluator, ref.text_emb, ref.real_emb, torch.device("cpu"))
    whole = study.run_seed(*args, log=lambda *_: None)
    real_checkpoint = study._checkpoint

    def stop_after(trainer, folder, progress):
        real_checkpoint(trainer, folder, progress)
        raise KeyboardInterrupt

    ckpt = str(tmp_path / "ckpt")
    monkeypatch.setattr(study, "_checkpoint", stop_after)
    with pytest.raises(KeyboardInterrupt):
        study.run_seed(*args, log=lambda *_: None, checkpoint_dir=ckpt)
    monkeypatch.setattr(study, "_checkpoint", real_checkpoint)
    logs = []
    again = study.run_seed(*args, log=logs.append, checkpoint_dir=ckpt)
    assert any("continuing from step 2" in m for m in logs)
    keys = ("kind", "at", "step", "fid", "fid_low", "fid_high", "r_precision_top3", "jitter", "speed")
    assert [{k: s[k] for k in keys} for s in again["snapshots"]] == [{k: s[k] for k in keys} for s in whole["snapshots"]]
    assert again["losses"] == whole["losses"]
    assert all(s["fid_low"] <= s["fid"] <= s["fid_high"] for s in whole["snapshots"])
