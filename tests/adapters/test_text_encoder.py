"""sMDM-stella text-encoder swap (smdm_plugin.adapters.text_encoder) on tiny random transformers
encoders built offline (tests/helpers/text_encoder.py), TinyMDM and SimpleDiffusion."""
import argparse
import copy
import json
import os
import sys
import warnings

import pytest
import torch
import torch.nn as nn

pytest.importorskip("transformers")

from smdm_plugin import SimpleDiffusion, SparseConfig, TinyMDM, sparsify  # noqa: E402
from smdm_plugin.adapters.text_encoder import (EncodeText, HFTextEncoder, pool_hidden, read_layout,  # noqa: E402
                                               swap_text_encoder, swapped_text_encoder, text_encoder_of)
from smdm_plugin.families.mdm import upstream_text as mdm_text
from smdm_plugin.families.mdm.upstream import sparsify_mdm, warn_if_upstream_steps  # noqa: E402

from helpers.text_encoder import dense_head, make_tiny_encoder

pytestmark = pytest.mark.usefixtures("one_thread")

CAPTIONS = ["a person walks forward and then turns left", "jumps", "a person sits on the ground slowly",
            "waves with hand"]


@pytest.fixture(scope="module")
def bert_dir(tmp_path_factory):
    return make_tiny_encoder(str(tmp_path_factory.mktemp("enc") / "bert"))


@pytest.fixture(scope="module")
def st_dir(tmp_path_factory):
    """A stella-like layout: Pooling (cls here, to see it is read), Dense head with tanh, Normalize."""
    return make_tiny_encoder(str(tmp_path_factory.mktemp("enc") / "st"), seed=3,
                             st=dict(pooling="cls", dense=24, activation="Tanh", normalize=True, prompt="motion "))


def reference_embedding(path, text, pooling="mean", prompt="", head=None, normalize=False):
    """One caption alone (no padding anywhere), pooled by hand with a Python loop over tokens."""
    from transformers import AutoModel, AutoTokenizer

    tok = AutoTokenizer.from_pretrained(path)
    model = AutoModel.from_pretrained(path).eval()
    ids = tok([prompt + text], return_tensors="pt")
    with torch.no_grad():
        h = model(**ids).last_hidden_state[0]  # [L, H]
        if pooling == "mean":
            v = sum(h[i] for i in range(h.shape[0])) / h.shape[0]
        elif pooling == "cls":
            v = h[0]
        else:
            raise ValueError(pooling)
        if head is not None:
            v = torch.tanh(head(v))
        if normalize:
            v = v / v.norm()
    return v


# --------------------------------------------------------------------------- pooling
@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("mode", ["mean", "cls", "last", "max"])
def test_pool_hidden_matches_a_loop_over_tokens(mode, side):
    g = torch.Generator().manual_seed(1)
    B, L, H = 4, 7, 5
    hidden = torch.randn(B, L, H, generator=g)
    counts = [7, 1, 4, 3]
    mask = torch.zeros(B, L, dtype=torch.long)
    for b, n in enumerate(counts):
        if side == "right":
            mask[b, :n] = 1
        else:
            mask[b, L - n:] = 1
    got = pool_hidden(hidden, mask, mode)
    for b in range(B):
        toks = [hidden[b, i] for i in range(L) if mask[b, i]]
        want = {"mean": sum(toks) / len(toks), "cls": hidden[b, 0], "last": toks[-1],
                "max": torch.stack(toks).max(0).values}[mode]
        torch.testing.assert_close(got[b], want)


def test_pool_hidden_rejects_bad_input():
    with pytest.raises(ValueError, match="mode must be one of"):
        pool_hidden(torch.zeros(1, 2, 3), torch.ones(1, 2), "avg")
    with pytest.raises(ValueError, match=r"hidden \[B, L, H\] and attention_mask \[B, L\]"):
        pool_hidden(torch.zeros(1, 2, 3), torch.ones(1, 3), "mean")


# --------------------------------------------------------------------------- the encoder
def test_mean_pooled_encoder_matches_per_caption_reference(bert_dir):
    enc = HFTextEncoder(bert_dir)
    from transformers import AutoConfig

    assert enc.width == AutoConfig.from_pretrained(bert_dir).hidden_size == 32
    assert enc.pooling == "mean" and not enc.layout.sentence_transformers
    out = enc(CAPTIONS)  # one padded batch
    assert out.shape == (len(CAPTIONS), 32) and out.dtype == torch.float32
    for i, text in enumerate(CAPTIONS):
        torch.testing.assert_close(out[i], reference_embedding(bert_dir, text), atol=1e-5, rtol=1e-5)


def test_sentence_transformers_layout_is_followed(st_dir):
    layout = read_layout(st_dir)
    assert (layout.pooling, layout.head, layout.normalize, layout.prompt) == ("cls", "2_Dense", True, "motion ")
    enc = HFTextEncoder(st_dir)
    assert enc.width == 24  # the Dense head's out_features, not the hidden size
    out = enc(CAPTIONS)
    head = dense_head(st_dir)
    for i, text in enumerate(CAPTIONS):
        want = reference_embedding(st_dir, text, "cls", "motion ", head, normalize=True)
        torch.testing.assert_close(out[i], want, atol=1e-5, rtol=1e-5)
    # an explicit pooling overrides the layout's
    assert HFTextEncoder(st_dir, pooling="mean").pooling == "mean"


def test_layout_of_a_hub_id_is_read_through_hf_hub_download(monkeypatch, st_dir):
    """A hub id (not a folder): the layout files are fetched one by one; absent ones are absent."""
    import huggingface_hub
    from huggingface_hub.errors import EntryNotFoundError

    asked = []

    def fake_download(repo_id, filename, **kw):
        asked.append((repo_id, filename))
        path = os.path.join(st_dir, filename)
        if not os.path.isfile(path):
            raise EntryNotFoundError(f"{filename} not in {repo_id}")
        return path

    monkeypatch.setattr(huggingface_hub, "hf_hub_download", fake_download)
    layout = read_layout("someone/stella-like")
    assert (layout.pooling, layout.head, layout.normalize, layout.prompt) == ("cls", "2_Dense", True, "motion ")
    assert ("someone/stella-like", "modules.json") in asked
    assert ("someone/stella-like", "1_Pooling/config.json") in asked


def test_unsupported_sentence_transformers_module_is_a_clear_error(tmp_path, bert_dir):
    import shutil

    d = str(tmp_path / "odd")
    shutil.copytree(bert_dir, d)
    with open(os.path.join(d, "modules.json"), "w") as f:
        json.dump([{"idx": 0, "path": "", "type": "sentence_transformers.models.Transformer"},
                   {"idx": 1, "path": "1_X", "type": "sentence_transformers.models.WeightedLayerPooling"}], f)
    with pytest.raises(ValueError, match="'WeightedLayerPooling' is not supported"):
        HFTextEncoder(d)
    with pytest.raises(ValueError, match="pooling must be None or one of"):
        HFTextEncoder(bert_dir, pooling="avg")


def test_encoder_is_frozen_hidden_and_shared_by_deepcopy(bert_dir):
    enc = HFTextEncoder(bert_dir)
    assert list(enc.parameters()) == [] and enc.state_dict() == {}
    assert all(not p.requires_grad for p in enc.transformer.parameters())
    enc.train()
    assert not enc.training and not enc.transformer.training  # dropout never on
    twin = copy.deepcopy(enc)
    assert twin is not enc and twin.transformer is enc.transformer
    torch.testing.assert_close(twin(CAPTIONS), enc(CAPTIONS))
    enc.to(torch.float64)  # .to() reaches the hidden model
    assert next(enc.transformer.parameters()).dtype == torch.float64
    assert enc(CAPTIONS).dtype == torch.float32
    with pytest.raises(TypeError, match="non-empty list of str"):
        enc([1, 2])


def test_auto_map_without_trust_remote_code_warns(tmp_path, bert_dir):
    import shutil

    d = str(tmp_path / "remote")
    shutil.copytree(bert_dir, d)
    cfg_path = os.path.join(d, "config.json")
    with open(cfg_path) as f:
        cfg = json.load(f)
    cfg["auto_map"] = {"AutoModel": "modeling_custom.CustomModel"}
    with open(cfg_path, "w") as f:
        json.dump(cfg, f)
    with pytest.warns(UserWarning, match="ships its own modelling code"):
        enc = HFTextEncoder(d)
    assert enc.width == 32


def test_missing_transformers_names_the_extra(monkeypatch, bert_dir):
    monkeypatch.setitem(sys.modules, "transformers", None)
    with pytest.raises(ImportError, match=r'pip install "smdm-plugin\[hf\]"'):
        HFTextEncoder(bert_dir)


# --------------------------------------------------------------------------- model surgery
def tiny_model(**kw):
    torch.manual_seed(0)
    return TinyMDM(latent_dim=64, ff_size=128, num_layers=2, cond_mask_prob=0.0, **kw)


def motion_batch(B=4, N=40, seed=0):
    """Each caption has its own motion (a per-caption pose held over the frames, plus a slow wave):
    only the text tells the samples apart."""
    g = torch.Generator().manual_seed(seed)
    pose = torch.randn(B, 263, 1, 1, generator=g)
    wave = torch.sin(torch.linspace(0, 3.0, N)).view(1, 1, 1, N) * torch.randn(1, 263, 1, 1, generator=g)
    x = pose + 0.5 * wave
    lengths = torch.tensor([N, N - 5, N - 10, N][:B])
    y = {"mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N), "lengths": lengths,
         "text": CAPTIONS[:B]}
    return x, y


def test_swap_on_tinymdm_sets_width_and_keeps_encoder_out_of_the_state_dict(bert_dir):
    model = tiny_model()
    before = {k for k in model.state_dict()}
    swap_text_encoder(model, bert_dir)
    assert model.clip_dim == 32 and model.embed_text.in_features == 32 and model.embed_text.out_features == 64
    assert isinstance(text_encoder_of(model), HFTextEncoder) and swapped_text_encoder(model) == bert_dir
    assert not [k for k in vars(model) if k.startswith("_smdm")]     # the id lives on our EncodeText
    assert swapped_text_encoder(tiny_model()) is None and text_encoder_of(tiny_model()) is None
    assert {k for k in model.state_dict()} == before  # no encoder weights saved
    x, y = motion_batch()
    model.eval()
    out = model(x, torch.tensor([3, 3, 3, 3]), y)
    other = model(x, torch.tensor([3, 3, 3, 3]), {**y, "text": list(reversed(y["text"]))})
    assert out.shape == x.shape
    assert not torch.allclose(out, other)  # the captions reach the model through the new encoder
    # the text path equals: encoder -> pooled [B, W] -> embed_text
    enc = model.text_encoder(y["text"])
    torch.testing.assert_close(enc, text_encoder_of(model)(y["text"]))
    from smdm_plugin.adapters.text_cache import install_text_cache

    install_text_cache(model)
    assert swapped_text_encoder(model) == bert_dir                   # read through the cache


@pytest.mark.parametrize("arch", ["trans_enc", "trans_dec"])
def test_sparse_tinymdm_trains_through_the_swapped_encoder(bert_dir, arch):
    """A few sparse training steps on captions whose motions differ: the loss falls, the new
    projection learns, the encoder stays frozen."""
    model = tiny_model(arch=arch)
    swap_text_encoder(model, bert_dir)
    diffusion = SimpleDiffusion(50)
    sparsify(model, SparseConfig(reduction=0.8, lipschitz_lambda=0.0), diffusion=diffusion)
    enc_before = {k: v.clone() for k, v in text_encoder_of(model).transformer.state_dict().items()}
    proj_before = model.embed_text.weight.detach().clone()
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=2e-3)
    x, y = motion_batch()
    g = torch.Generator().manual_seed(0)
    losses = []
    model.train()
    for _ in range(30):
        t = torch.randint(0, 50, (x.shape[0],), generator=g)
        loss = diffusion.training_losses(model, x, t, {"y": dict(y)})["loss"].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert all(torch.isfinite(torch.tensor(losses)))
    assert sum(losses[-5:]) / 5 < 0.6 * sum(losses[:5]) / 5, losses
    assert not torch.equal(model.embed_text.weight, proj_before)
    for k, v in text_encoder_of(model).transformer.state_dict().items():
        assert torch.equal(v, enc_before[k]), k


def test_checkpoint_roundtrip_rebuilds_the_encoder_from_its_id(bert_dir, tmp_path):
    model = tiny_model()
    swap_text_encoder(model, bert_dir)
    sparsify(model, SparseConfig(text_encoder=bert_dir))
    torch.save(model.state_dict(), tmp_path / "model.pt")
    model._smdm_state.config.save(str(tmp_path))
    # what a loader does: the config names the encoder; rebuild, swap, then load the weights
    cfg = SparseConfig.load(str(tmp_path))
    fresh = tiny_model()
    swap_text_encoder(fresh, cfg.text_encoder)
    sparsify(fresh, cfg)
    fresh.load_state_dict(torch.load(tmp_path / "model.pt", weights_only=True), strict=True)
    x, y = motion_batch()
    model.eval()
    fresh.eval()
    with torch.no_grad():
        torch.testing.assert_close(fresh(x, torch.tensor([5] * 4), y), model(x, torch.tensor([5] * 4), y))


def test_deepcopy_of_a_swapped_model_keeps_one_encoder(bert_dir):
    model = tiny_model()
    swap_text_encoder(model, bert_dir)
    ema = copy.deepcopy(model)
    assert ema.text_encoder.encoder is ema.clip_model  # the copy's own wrapper...
    assert ema.clip_model.transformer is model.clip_model.transformer  # ...sharing the frozen weights
    x, y = motion_batch()
    model.eval()
    ema.eval()
    torch.testing.assert_close(ema(x, torch.tensor([1] * 4), y), model(x, torch.tensor([1] * 4), y))


class FakeMDM(nn.Module):
    """MDM's text interface only: encode_text, text_encoder_type, clip_model, embed_text."""

    def __init__(self, bert: bool):
        super().__init__()
        self.text_encoder_type = "bert" if bert else "clip"
        self.clip_model = nn.Linear(2, 2)
        self.embed_text = nn.Linear(768 if bert else 512, 16)
        self.encode_text = lambda texts: None


@pytest.mark.parametrize("bert", [False, True], ids=["mdm-clip", "dip-bert"])
def test_mdm_and_dip_conventions(bert_dir, bert):
    model = FakeMDM(bert)
    swap_text_encoder(model, bert_dir)
    assert model.embed_text.in_features == 32 and model.clip_dim == 32
    assert isinstance(model.clip_model, HFTextEncoder)
    out = model.encode_text(CAPTIONS)
    pooled = model.clip_model(CAPTIONS)
    if bert:  # DiP: (tokens [L=1, B, W], pad mask [B, 1], False = a token)
        emb, pad = out
        assert emb.shape == (1, 4, 32) and pad.shape == (4, 1) and pad.dtype == torch.bool and not pad.any()
        torch.testing.assert_close(emb[0], pooled)
    else:
        assert out.shape == (1, 4, 32)
        torch.testing.assert_close(out[0], pooled)


def test_swap_rejects_models_without_text_conditioning(bert_dir):
    with pytest.raises(TypeError, match="no text projection embed_text"):
        swap_text_encoder(tiny_model(cond_mode="no_cond"), bert_dir)
    with pytest.raises(TypeError, match="nn.Module with an int width"):
        swap_text_encoder(tiny_model(), nn.Linear(2, 2))
    with pytest.raises(ValueError, match="style must be one of"):
        EncodeText(nn.Identity(), "clip")


# --------------------------------------------------------------------------- MDM integration glue
def mdm_args(tmp_path, **kw):
    d = dict(sparse=True, save_dir=str(tmp_path), diffusion_steps=50, sparse_feature="raw")
    d.update(kw)
    if not d["sparse"]:                     # a dense run given a sparse setting is refused (it would drop it)
        del d["sparse_feature"]
    return argparse.Namespace(**d)


def test_sparsify_mdm_swaps_encoder_from_the_option_and_saves_it(bert_dir, tmp_path):
    model = tiny_model()
    args = mdm_args(tmp_path, sparse_text_encoder=bert_dir)
    sparsify_mdm(model, args, None, SimpleDiffusion(50))
    assert isinstance(text_encoder_of(model), HFTextEncoder)
    saved = json.load(open(tmp_path / "sparse_config.json"))
    assert saved["text_encoder"] == bert_dir  # restored on load with the rest of the config
    sparsify_mdm(model, args, None, None)  # patch + launcher both call it: idempotent
    assert isinstance(text_encoder_of(model), HFTextEncoder)


def test_text_encoder_also_applies_to_a_dense_run(bert_dir, tmp_path):
    model = tiny_model()
    sparsify_mdm(model, mdm_args(tmp_path, sparse=False, sparse_text_encoder=bert_dir))
    assert isinstance(text_encoder_of(model), HFTextEncoder)
    assert not hasattr(model, "_smdm_state")


def test_environment_options():
    assert mdm_text.cache_capacity_from_env({}) == 0
    assert mdm_text.cache_capacity_from_env({"SMDM_TEXT_CACHE": "off"}) == 0
    assert mdm_text.cache_capacity_from_env({"SMDM_TEXT_CACHE": "on"}) == 131072
    assert mdm_text.cache_capacity_from_env({"SMDM_TEXT_CACHE": "1"}) == 131072
    assert mdm_text.cache_capacity_from_env({"SMDM_TEXT_CACHE": "5000"}) == 5000
    for bad in ("-3", "lots"):
        with pytest.raises(ValueError, match="SMDM_TEXT_CACHE"):
            mdm_text.cache_capacity_from_env({"SMDM_TEXT_CACHE": bad})
    opts = mdm_text.encoder_options_from_env({"SMDM_TRUST_REMOTE_CODE": "1", "SMDM_TEXT_ENCODER_DTYPE": "bfloat16"})
    assert opts == {"trust_remote_code": True, "dtype": torch.bfloat16}
    with pytest.raises(ValueError, match="SMDM_TEXT_ENCODER_DTYPE"):
        mdm_text.encoder_options_from_env({"SMDM_TEXT_ENCODER_DTYPE": "fp8"})


# --------------------------------------------------------------------------- the 1000-step warning
@pytest.mark.parametrize("steps,sparse,training,warns", [
    (1000, True, True, True), (50, True, True, False), (1000, False, True, False), (1000, True, False, False)])
def test_sparse_training_at_1000_steps_warns_and_changes_nothing(tmp_path, steps, sparse, training, warns):
    model = tiny_model()
    args = mdm_args(tmp_path, sparse=sparse, diffusion_steps=steps)
    if not training:
        args.model_path = str(tmp_path / "model.pt")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sparsify_mdm(model, args, None, SimpleDiffusion(steps))
    hit = [w for w in caught if "1000 diffusion steps" in str(w.message)]
    assert bool(hit) == warns
    if warns:
        assert "Table 2" in str(hit[0].message) and "--diffusion_steps 50" in str(hit[0].message)
        assert model._smdm_state.config.diffusion_steps == 1000  # warned, not overridden
    with pytest.warns(UserWarning, match="1000 diffusion steps"):
        assert warn_if_upstream_steps(SparseConfig(), 1000)
    assert not warn_if_upstream_steps(SparseConfig(), 50)
