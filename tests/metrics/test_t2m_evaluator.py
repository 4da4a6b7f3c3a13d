"""The T2M evaluator: upstream's checkpoint layout round trip (random networks saved as
``finest.tar`` + GloVe files, loaded through load_evaluator, same embeddings as a direct forward),
caption reading, the safe pickle reader, and — with SMDM_MDM_ROOT pointing at an MDM checkout —
the same embeddings as upstream's own modules and word vectorizer on the same input."""
import importlib.util
import os
import pickle

import numpy as np
import pytest
import torch

from smdm_plugin.metrics.evaluator import (Evaluator, EvaluatorConfig, MotionEncoderBiGRUCo, MovementConvEncoder,
                                           TextEncoderBiGRUCo, evaluator_layout, load_evaluator, save_evaluator)
from smdm_plugin.io.captions import parse_caption_line
from smdm_plugin.metrics.evaluator.vocab import POS_CATEGORIES, encode_tokens, safe_pickle_load

SMALL = dict(dim_pose=263, dim_word=12, dim_movement_hidden=16, dim_movement_latent=8, dim_motion_hidden=10,
             dim_text_hidden=9, dim_coemb=6)
WORDS = ["unk", "sos", "eos", "a", "person", "walk", "forward", "turn", "left", "jump", "slowly", "arm", "the"]
CAPTIONS = ["a person walk forward and turn left#a/DET person/NOUN walk/VERB forward/ADV and/CCONJ turn/VERB "
            "left/ADV#0.0#0.0",
            "the person jump slowly#the/DET person/NOUN jump/VERB slowly/ADV#0#0",
            "wave arm#wave/VERB arm/NOUN#0.0#0.0"]


def _upstream_files(tmp_path, nets, sizes, seed=0):
    """Write ``nets`` (movement, motion, text) in upstream's layout: t2m/text_mot_match/model/finest.tar,
    glove/our_vab_*, dataset-style t2m_mean.npy / t2m_std.npy."""
    rng = np.random.default_rng(seed)
    root = tmp_path / "checkpoints"
    ck = root / "t2m" / "text_mot_match" / "model"
    ck.mkdir(parents=True)
    movement, motion, text = nets
    torch.save({"movement_encoder": movement.state_dict(), "motion_encoder": motion.state_dict(),
                "text_encoder": text.state_dict(), "epoch": 7}, ck / "finest.tar")
    glove = root / "glove"
    glove.mkdir()
    vectors = rng.normal(size=(len(WORDS) + 2, sizes["dim_word"])).astype(np.float32)
    rows = rng.permutation(len(WORDS) + 2)[:len(WORDS)]
    np.save(glove / "our_vab_data.npy", vectors)
    with open(glove / "our_vab_words.pkl", "wb") as f:
        pickle.dump(list(WORDS), f)
    with open(glove / "our_vab_idx.pkl", "wb") as f:
        pickle.dump({w: int(r) for w, r in zip(WORDS, rows)}, f)
    mean = rng.normal(size=263).astype(np.float32)
    std = (0.5 + rng.random(263)).astype(np.float32)
    np.save(root / "t2m_mean.npy", mean)
    np.save(root / "t2m_std.npy", std)
    return root, vectors, {w: int(r) for w, r in zip(WORDS, rows)}, mean, std


def _motions(seed=1, B=5, N=60):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, N, 263, generator=g)
    lengths = torch.tensor([60, 41, 57, 16, 33])[:B]
    return x, lengths


def _tokens(line):
    return parse_caption_line(line).tokens


def test_upstream_layout_round_trip(tmp_path):
    torch.manual_seed(0)
    s = SMALL
    nets = (MovementConvEncoder(259, s["dim_movement_hidden"], s["dim_movement_latent"]),
            MotionEncoderBiGRUCo(s["dim_movement_latent"], s["dim_motion_hidden"], s["dim_coemb"]),
            TextEncoderBiGRUCo(s["dim_word"], 15, s["dim_text_hidden"], s["dim_coemb"]))
    for n in nets:
        n.eval()
    root, vectors, vocab, mean, std = _upstream_files(tmp_path, nets, s)
    assert evaluator_layout(str(root)) == "upstream"
    ev = load_evaluator(str(root))
    assert ev.config.dim_coemb == 6 and ev.config.dim_motion_hidden == 10 and ev.config.dim_word == 12

    # direct forward, by hand: crop to a multiple of 4, normalise, zero-pad to 196, drop contacts, lengths // 4
    x, L = _motions()
    want = []
    for b in range(len(L)):
        Lb = int(L[b]) // 4 * 4
        xb = torch.zeros(1, 196, 259)
        xb[0, :Lb] = ((x[b, :Lb] - torch.from_numpy(mean)) / torch.from_numpy(std))[:, :259]
        mov = nets[0](xb)
        want.append(nets[1](mov, torch.tensor([Lb // 4])))
    got = ev.encode_motion(x, L)
    torch.testing.assert_close(got, torch.cat(want), rtol=1e-5, atol=1e-5)

    caps = [_tokens(c) for c in CAPTIONS]
    want_t = []
    for toks in caps:
        seq = ["sos/OTHER"] + toks + ["eos/OTHER"]
        wv, pv = [], []
        for t in seq:
            w, _, p = t.partition("/")
            if w in vocab:
                wv.append(vectors[vocab[w]])
                vip = {"forward": "Loc_VIP", "left": "Loc_VIP", "walk": "Act_VIP", "turn": "Act_VIP",
                       "jump": "Act_VIP", "slowly": "Desc_VIP", "arm": "Body_VIP"}.get(w, p)
                pv.append(POS_CATEGORIES.index(vip) if vip in POS_CATEGORIES else 14)
            else:
                wv.append(vectors[vocab["unk"]])
                pv.append(14)
        oh = torch.zeros(1, len(seq), 15)
        oh[0, torch.arange(len(seq)), torch.tensor(pv)] = 1
        want_t.append(nets[2](torch.from_numpy(np.stack(wv))[None], oh, torch.tensor([len(seq)])))
    torch.testing.assert_close(ev.encode_text(caps), torch.cat(want_t), rtol=1e-5, atol=1e-5)


def test_own_layout_round_trip_and_order_independence(tmp_path):
    torch.manual_seed(0)
    vocab = {w: i for i, w in enumerate(WORDS)}
    cfg = EvaluatorConfig(**SMALL, vocab_size=len(WORDS), learned_words=True, source="own")
    ev = Evaluator(cfg, vocab, np.zeros(263), np.full(263, 2.0)).eval()
    save_evaluator(ev, str(tmp_path / "e"), {"metrics": {"test": {"top1": 0.5}}})
    assert evaluator_layout(str(tmp_path / "e")) == "own"
    back = load_evaluator(str(tmp_path / "e"))
    x, L = _motions()
    caps = [_tokens(c) for c in CAPTIONS]
    torch.testing.assert_close(back.encode_motion(x, L), ev.encode_motion(x, L))
    torch.testing.assert_close(back.encode_text(caps), ev.encode_text(caps))
    # batch order does not change a motion's embedding; padding beyond the length does not either
    perm = torch.tensor([3, 0, 4, 2, 1])
    torch.testing.assert_close(ev.encode_motion(x[perm], L[perm]), ev.encode_motion(x, L)[perm], rtol=1e-5, atol=1e-6)
    y = x.clone()
    for b in range(len(L)):
        y[b, int(L[b]):] = 99.0
    torch.testing.assert_close(ev.encode_motion(y, L), ev.encode_motion(x, L), rtol=1e-5, atol=1e-6)
    one = ev.encode_motion(x[1:2, :41], L[1:2])
    torch.testing.assert_close(one, ev.encode_motion(x, L)[1:2], rtol=1e-5, atol=1e-6)


def test_caption_reading_and_errors(tmp_path):
    c = parse_caption_line("a man runs.#a/DET man/NOUN run/VERB#1.5#3.0")
    assert c.tokens == ["a/DET", "man/NOUN", "run/VERB"] and (c.start, c.end) == (1.5, 3.0)
    vocab = {"unk": 0, "sos": 1, "eos": 2, "run": 3, "man": 4}
    words, pos = encode_tokens(c.tokens, vocab)
    assert words == [1, 0, 4, 3, 2]  # sos, a -> unk, man, run, eos
    assert pos == [14, 14, 1, POS_CATEGORIES.index("Act_VIP"), 14]
    assert len(encode_tokens(["run/VERB"] * 30, vocab)[0]) == 22  # 20 tokens + sos + eos
    evil = tmp_path / "evil.pkl"
    with open(evil, "wb") as f:
        pickle.dump(os.getcwd, f)  # a function: would be called/imported by pickle.load
    with pytest.raises(ValueError, match="not a plain pickle"):
        safe_pickle_load(str(evil))
    with pytest.raises(FileNotFoundError, match="neither an evaluator trained here"):
        load_evaluator(str(tmp_path))
    ev = Evaluator(EvaluatorConfig(**SMALL, vocab_size=3), {"unk": 0, "sos": 1, "eos": 2}, np.zeros(263), np.ones(263))
    with pytest.raises(ValueError, match=r"raw features \[B, N, 263\]"):
        ev.encode_motion(torch.zeros(2, 40, 66), torch.tensor([40, 40]))
    with pytest.raises(ValueError, match="lengths must be"):
        ev.encode_motion(torch.zeros(2, 40, 263), torch.tensor([40, 41]))


# ----------------------------------------------------------------------------------------- upstream
MDM_ROOT = os.environ.get("SMDM_MDM_ROOT")


def _import_file(name, path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT (an MDM checkout) not set")
def test_same_embeddings_as_upstream_modules(tmp_path):
    """Upstream's MovementConvEncoder / MotionEncoderBiGRUCo / TextEncoderBiGRUCo (random init, upstream's
    sizes) and WordVectorizer, driven as EvaluatorMDMWrapper.get_co_embeddings and Text2MotionDatasetV2
    do (batch sorted by length, motions[..., :-4], m_lens // 4, sos/eos/unk padding), against
    load_evaluator on the files they are saved to."""
    hml = os.path.join(MDM_ROOT, "data_loaders", "humanml")
    modules = _import_file("mdm_modules", os.path.join(hml, "networks", "modules.py"))
    wv_mod = _import_file("mdm_word_vectorizer", os.path.join(hml, "utils", "word_vectorizer.py"))
    torch.manual_seed(3)
    dev = "cpu"
    movement = modules.MovementConvEncoder(263 - 4, 512, 512).eval()
    text = modules.TextEncoderBiGRUCo(word_size=300, pos_size=len(wv_mod.POS_enumerator), hidden_size=512,
                                      output_size=512, device=dev).eval()
    motion = modules.MotionEncoderBiGRUCo(input_size=512, hidden_size=1024, output_size=512, device=dev).eval()
    sizes = dict(dim_word=300)
    root, _, _, mean, std = _upstream_files(tmp_path, (movement, motion, text), sizes, seed=4)
    ev = load_evaluator(str(root))
    vec = wv_mod.WordVectorizer(str(root / "glove"), "our_vab")

    B, N = 5, 196
    g = torch.Generator().manual_seed(5)
    raw = torch.randn(B, N, 263, generator=g).double().numpy() * std + mean
    m_lens = np.array([196, 120, 64, 180, 44])  # multiples of 4, as the dataset crops them
    caps = [_tokens(c) for c in CAPTIONS] + [_tokens(CAPTIONS[0])[:4], _tokens(CAPTIONS[1])]
    # Text2MotionDatasetV2.__getitem__ + collate (sorted by sentence length)
    items = []
    for b in range(B):
        toks = ["sos/OTHER"] + caps[b][:20] + ["eos/OTHER"]
        sent_len = len(toks)
        toks = toks + ["unk/OTHER"] * (22 - sent_len)
        wemb = np.stack([vec[t][0] for t in toks])
        pohe = np.stack([vec[t][1] for t in toks])
        m = (raw[b] - mean) / std
        m[m_lens[b]:] = 0.0
        items.append((wemb, pohe, sent_len, m, m_lens[b], b))
    items.sort(key=lambda it: it[2], reverse=True)
    word_embs = torch.tensor(np.stack([i[0] for i in items])).float()
    pos_oh = torch.tensor(np.stack([i[1] for i in items])).float()
    sent_lens = torch.tensor([i[2] for i in items])
    motions = torch.tensor(np.stack([i[3] for i in items])).float()
    lens = torch.tensor([i[4] for i in items])
    order = [i[5] for i in items]
    with torch.no_grad():  # EvaluatorMDMWrapper.get_co_embeddings
        align = np.argsort(lens.tolist())[::-1].copy()
        mov = movement(motions[align][..., :-4])
        up_motion = motion(mov, lens[align] // 4)
        up_text = text(word_embs, pos_oh, sent_lens)[align]
        ours_motion = ev.encode_motion(torch.from_numpy(raw).float()[order][align], lens[align])
        ours_text = ev.encode_text([caps[order[i]] for i in align])
    dm = float((up_motion - ours_motion).abs().max())
    dt = float((up_text - ours_text).abs().max())
    print(f"max |upstream - ours|: motion {dm:.3g}, text {dt:.3g} (embedding scale {float(up_motion.abs().max()):.3g})")
    assert dm < 1e-4 and dt < 1e-4


def test_smdm_eval_reads_upstream_layout(tmp_path):
    """`smdm eval --evaluator` detects upstream's layout (finest.tar + glove/ + t2m_mean/std) and scores
    a data set's own test motions against themselves: FID 0, R-precision as the real row."""
    import json
    from pathlib import Path

    from smdm_plugin.apps.cli import main as smdm
    from smdm_plugin.metrics.evaluator.data import load_split

    from helpers.paths import HML_LARGE as large
    if not (large / "texts").is_dir():
        pytest.skip("../shared/data/cmu-humanml3d-large not available")
    torch.manual_seed(0)
    s = SMALL
    nets = (MovementConvEncoder(259, s["dim_movement_hidden"], s["dim_movement_latent"]),
            MotionEncoderBiGRUCo(s["dim_movement_latent"], s["dim_motion_hidden"], s["dim_coemb"]),
            TextEncoderBiGRUCo(s["dim_word"], 15, s["dim_text_hidden"], s["dim_coemb"]))
    root, *_ = _upstream_files(tmp_path, nets, s)
    test = load_split(str(large), "test")
    mdir = tmp_path / "m"
    mdir.mkdir()
    for i, m in zip(test.ids, test.motions):
        np.save(mdir / f"{i}.npy", m)
    assert smdm(["eval", "--data", str(large), "--evaluator", str(root), "--motions", str(mdir), "--out",
                 str(tmp_path / "r"), "--protocol", "fixed", "--threads", "1"]) == 0
    res = json.load(open(tmp_path / "r" / "metrics.json"))
    assert res["protocol"]["evaluator"].startswith("upstream")
    assert abs(res["fid"]) < 1e-4 and res["r_precision_top3"] == res["real"]["r_precision_top3"]
