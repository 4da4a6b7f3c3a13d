"""sMDM-stella's text-encoder swap and the text-embedding cache on the real MDM / DiP code.

Skipped unless ``SMDM_MDM_ROOT`` points at an MDM checkout (see test_mdm_upstream.py; same harness:
random-weight CLIP with a 1-layer text tower, DistilBERT stub, SMPL/GloVe stubs). The encoder is a
tiny random BERT saved offline with ``save_pretrained`` (tests/helpers/text_encoder.py).

* ``--sparse_text_encoder DIR`` trains (MDM trans_enc through the patch, DiP through ``smdm run``):
  ``embed_text`` takes the encoder's width, the encoder's weights stay out of the checkpoint,
  ``args.json`` / ``sparse_config.json`` name it, and ``sample.generate`` with only
  ``--model_path`` rebuilds the same encoder (same embeddings as a fresh ``HFTextEncoder(DIR)``);
* ``SMDM_TEXT_CACHE``: training steps of the real MDM (dense and sparse; CLIP) give the same losses
  with and without the cache while the encoder runs only on new captions; DiP's DistilBERT (dropout
  on under ``model.train()``) is not cached; DiP with the swapped encoder is; unset, nothing changes
  (``encode_text`` is upstream's own method).
"""
from __future__ import annotations

import json
import os
import re
import sys

import numpy as np
import pytest

from _upstream import PATCHES
from test_mdm_upstream import generate, harness_code, load_sd, needs_mdm, train

ROOT = os.environ.get("SMDM_MDM_ROOT")
PATCH = os.path.join(PATCHES, "mdm.patch")
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # tests/: the helpers package


@pytest.fixture(scope="module")
def encoder_dir(tmp_path_factory):
    pytest.importorskip("transformers")
    from helpers.text_encoder import make_tiny_encoder

    return make_tiny_encoder(str(tmp_path_factory.mktemp("text_encoder") / "tiny_bert"), hidden=32)


@pytest.fixture(scope="module")
def repos(upstream_copy):
    return {"patch": upstream_copy(ROOT, "mdm_text_patched", patch=PATCH),
            "launcher": upstream_copy(ROOT, "mdm_text_pristine")}


PROBE = r"""
import sys, json, torch
from utils import parser_util
from utils.model_util import create_model_and_diffusion, load_saved_model
from data_loaders.get_data import get_dataset_loader
from smdm_plugin.adapters.text_encoder import HFTextEncoder
ckpt, enc_dir = sys.argv[1], sys.argv[2]
sys.argv = ["generate", "--model_path", ckpt]
args = parser_util.generate_args()
data = get_dataset_loader(name="humanml", batch_size=2, num_frames=None, split="test", hml_mode="text_only")
model, diffusion = create_model_and_diffusion(args, data)
load_saved_model(model, ckpt)
texts = ["a person walks forward", "jumps"]
out = model.encode_text(texts)
emb = out[0] if isinstance(out, tuple) else out
ref = HFTextEncoder(enc_dir)(texts)
print("PROBE=" + json.dumps({"text_encoder": args.sparse_text_encoder, "encoder": type(model.clip_model).__name__,
      "width": model.embed_text.in_features, "tuple": isinstance(out, tuple), "shape": list(emb.shape),
      "max_diff": float((emb[0] - ref).abs().max())}))
"""


@needs_mdm
@pytest.mark.parametrize("arch,route", [("trans_enc", "patch"), ("dip", "launcher")])
def test_text_encoder_swap_trains_saves_and_restores(arch, route, repos, encoder_dir, tmp_path):
    repo, launcher = repos[route], route == "launcher"
    save = str(tmp_path / f"stella_{arch}")
    proc, ckpt = train(repo, save, arch, 6, ["--log_interval", "3", "--sparse",
                                             "--sparse_text_encoder", encoder_dir], launcher=launcher)
    losses = [float(v) for v in re.findall(r"loss\[([0-9.eE+-]+)\]", proc.stdout + proc.stderr)]
    assert losses and np.isfinite(losses).all()
    args = json.load(open(os.path.join(save, "args.json")))
    assert args["sparse"] is True and args["sparse_text_encoder"] == encoder_dir
    assert json.load(open(os.path.join(save, "sparse_config.json")))["text_encoder"] == encoder_dir
    sd = load_sd(ckpt)
    assert tuple(sd["embed_text.weight"].shape) == (64, 32)  # latent 64 <- the encoder's width 32
    assert not [k for k in sd if k.startswith("clip_model.")]  # the encoder is not saved
    # sample.generate: only --model_path; the encoder comes back from args.json
    _, res = generate(repo, ckpt, str(tmp_path / "gen"), arch, launcher=launcher)
    assert res["motion"].shape == (2, 22, 3, 80 if arch == "dip" else 40)
    assert np.isfinite(res["motion"]).all()
    proc = harness_code(repo, PROBE.replace("sys.argv[1], sys.argv[2]", f"{ckpt!r}, {encoder_dir!r}"),
                        launcher=launcher)
    out = json.loads(re.search(r"PROBE=(.*)", proc.stdout).group(1))
    assert out["text_encoder"] == encoder_dir and out["encoder"] == "HFTextEncoder" and out["width"] == 32
    assert out["tuple"] is (arch == "dip") and out["shape"] == [1, 2, 32]
    assert out["max_diff"] < 1e-5


CACHE = r"""
import json, os, sys, tempfile, types, warnings, numpy as np, torch
from utils import parser_util
from utils.model_util import create_model_and_diffusion
from smdm_plugin.adapters.text_cache import CachedTextEncoder

stats = types.SimpleNamespace(mean=np.load("dataset/HumanML3D/Mean.npy"), std=np.load("dataset/HumanML3D/Std.npy"))
data = types.SimpleNamespace(dataset=stats)  # what sparsify_mdm reads Mean/Std from
ENC = {ENC}
CAPS = ["a person walks forward", "a person jumps", "someone dances", "a person sits down", "jumps",
        "a person walks forward"]

def build(flags, cache):
    os.environ.pop("SMDM_TEXT_CACHE", None)
    if cache:
        os.environ["SMDM_TEXT_CACHE"] = "on"
    sys.argv = ["train", "--dataset", "humanml", "--latent_dim", "64", "--layers", "2", "--diffusion_steps", "20",
                "--save_dir", tempfile.mkdtemp()] + flags
    args = parser_util.train_args()
    torch.manual_seed(0)
    model, diffusion = create_model_and_diffusion(args, data)
    model.train()
    return model, diffusion

def steps(model, diffusion, n=4):
    opt = torch.optim.AdamW([q for q in model.parameters() if q.requires_grad], lr=1e-3)
    g = torch.Generator().manual_seed(1)
    losses = []
    for i in range(n):
        B = 4
        N = 40 if model.is_prefix_comp else 60
        x = torch.randn(B, 263, 1, N, generator=g)
        y = {"mask": torch.ones(B, 1, 1, N, dtype=torch.bool), "lengths": torch.full((B,), N),
             "text": [CAPS[(i + k) % len(CAPS)] for k in range(B)]}
        if model.is_prefix_comp:
            y["prefix"] = torch.randn(B, 263, 1, 20, generator=g)
        t = torch.randint(0, 20, (B,), generator=g)
        torch.manual_seed(100 + i)
        loss = diffusion.training_losses(model, x, t, model_kwargs={"y": y})["loss"].mean()
        opt.zero_grad(); loss.backward(); opt.step()
        losses.append(loss.item())
    return losses

out = {}
for name, flags in {
        "dense": [],
        "sparse": ["--sparse"],
        "dip_bert": ["--arch", "trans_dec", "--text_encoder_type", "bert", "--context_len", "20",
                     "--pred_len", "40", "--sparse"],
        "dip_swapped": ["--arch", "trans_dec", "--text_encoder_type", "bert", "--context_len", "20",
                        "--pred_len", "40", "--sparse", "--sparse_text_encoder", ENC]}.items():
    plain_model, d1 = build(flags, False)
    upstream_method = getattr(plain_model.encode_text, "__func__", None) is not None
    plain = steps(plain_model, d1)
    model, d2 = build(flags, True)
    wrapped = model.encode_text
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cached = steps(model, d2)
    st = wrapped.cache.stats()
    out[name] = {"plain": plain, "cached": cached, "wrapped": isinstance(wrapped, CachedTextEncoder),
                 "upstream_method_when_off": upstream_method, "entries": st["entries"], "hits": st["hits"],
                 "bypassed": any("not caching" in str(w.message) for w in caught)}
print("CACHE=" + json.dumps(out))
"""


@needs_mdm
def test_text_cache_gives_upstream_losses(repos, encoder_dir):
    code = CACHE.replace("{ENC}", repr(encoder_dir))
    proc = harness_code(repos["patch"], code)
    out = json.loads(re.search(r"CACHE=(.*)", proc.stdout).group(1))
    print({k: (v["plain"], v["cached"], v["hits"]) for k, v in out.items()})
    for name in ("dense", "sparse", "dip_bert", "dip_swapped"):
        r = out[name]
        assert r["wrapped"], name
        assert r["cached"] == pytest.approx(r["plain"], rel=1e-5, abs=1e-6), name
    for name in ("dense", "sparse"):  # CLIP: model.encode_text is upstream's method when the cache is off
        assert out[name]["upstream_method_when_off"]
    for name in ("dense", "sparse", "dip_swapped"):
        assert not out[name]["bypassed"] and out[name]["entries"] == 5 and out[name]["hits"] > 0, name
    # DistilBERT runs dropout in model.train(): never cached, encoded as upstream
    assert out["dip_bert"]["bypassed"] and out["dip_bert"]["entries"] == 0
