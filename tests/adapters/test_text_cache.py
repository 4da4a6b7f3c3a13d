"""Text-embedding cache (smdm_plugin.adapters.text_cache): LRU bound, exact results against the
uncached encoder in every output convention, only new captions encoded, safety bypasses."""
import copy
import warnings

import pytest
import torch
import torch.nn as nn

from smdm_plugin import SimpleDiffusion, SparseConfig, TinyMDM, sparsify
from smdm_plugin.adapters.text_cache import (CachedTextEncoder, TextEmbeddingCache, install_text_cache,
                                             module_fingerprint, remove_text_cache)

from helpers.text_encoder import make_tiny_encoder

pytestmark = pytest.mark.usefixtures("one_thread")

CAPTIONS = ["a person walks forward", "jumps", "a person sits down", "waves with hand", "jumps"]


class ToyEncoder(nn.Module):
    """A deterministic text encoder: bag of character embeddings through a linear layer, in one
    of the three conventions; counts the captions it encodes."""

    def __init__(self, style: str = "lead1", width: int = 8, seed: int = 0, dropout: float = 0.0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.chars = nn.Parameter(torch.randn(128, width, generator=g), requires_grad=False)
        self.proj = nn.Linear(width, width)
        with torch.no_grad():  # weights from the seed only (not from the global RNG)
            self.proj.weight.copy_(torch.randn(width, width, generator=g) / width ** 0.5)
            self.proj.bias.copy_(torch.randn(width, generator=g))
        self.proj.requires_grad_(False)
        self.drop = nn.Dropout(dropout)
        self.style = style
        self.seen = []

    def tokens(self, text):
        return torch.stack([self.chars[ord(c) % 128] for c in text])  # [n_chars, W]

    def forward(self, texts):
        self.seen.append(list(texts))
        toks = [self.drop(self.proj(self.tokens(t))) for t in texts]
        if self.style == "tokens":  # DiP-like: ([L, B, W], pad mask [B, L]), right padding
            L = max(len(t) for t in toks)
            hidden = torch.full((L, len(texts), toks[0].shape[-1]), 7.0)  # junk at padding
            pad = torch.ones(len(texts), L, dtype=torch.bool)
            for b, t in enumerate(toks):
                hidden[: len(t), b] = t
                pad[b, : len(t)] = False
            return hidden, pad
        pooled = torch.stack([t.mean(0) for t in toks])
        return pooled.unsqueeze(0) if self.style == "lead1" else pooled


# --------------------------------------------------------------------------- the LRU
def test_lru_bound_and_order():
    cache = TextEmbeddingCache(capacity=2)
    a, b, c = torch.zeros(3), torch.ones(3), torch.full((3,), 2.0)
    cache.put(("e", "a"), a)
    cache.put(("e", "b"), b)
    assert cache.get(("e", "a")) is a  # a is now the most recent
    cache.put(("e", "c"), c)  # evicts b, the least recently used
    assert ("e", "b") not in cache and ("e", "a") in cache and ("e", "c") in cache
    assert cache.get(("e", "b")) is None
    st = cache.stats()
    assert (st["entries"], st["hits"], st["misses"], st["evictions"]) == (2, 1, 1, 1)
    assert cache.nbytes == 2 * 3 * 4
    assert copy.deepcopy(cache) is cache  # shared by EMA copies
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="capacity must be an int >= 1"):
            TextEmbeddingCache(bad)


# --------------------------------------------------------------------------- exactness, misses only
@pytest.mark.parametrize("style", ["lead1", "flat", "tokens"])
def test_cached_equals_uncached_and_encodes_only_new_captions(style):
    enc = ToyEncoder(style)
    cached = CachedTextEncoder(enc, enc)
    first = cached(CAPTIONS)
    assert enc.seen == [["a person walks forward", "jumps", "a person sits down", "waves with hand"]]  # dedup
    second = cached(["jumps", "new caption", "a person walks forward"])
    assert enc.seen[-1] == ["new caption"]  # only the unseen one
    for texts, got in ((CAPTIONS, first), (["jumps", "new caption", "a person walks forward"], second)):
        want = enc(texts)
        if style == "tokens":
            (h, pad), (wh, wpad) = got, want
            assert torch.equal(pad, wpad)
            torch.testing.assert_close(h[~pad.t()], wh[~wpad.t()])  # every real token
            assert (h[pad.t()] == 0).all()  # zeros at padding (never read by attention)
        else:
            assert got.shape == want.shape
            torch.testing.assert_close(got, want)
    assert cached.cache.stats()["hits"] == 2 and cached.layout == style


def test_two_encoders_never_share_entries():
    shared = TextEmbeddingCache()
    e1, e2 = ToyEncoder(seed=1), ToyEncoder(seed=2)
    c1, c2 = CachedTextEncoder(e1, e1, cache=shared), CachedTextEncoder(e2, e2, cache=shared)
    assert c1.identity != c2.identity and module_fingerprint(e1) != module_fingerprint(e2)
    out1, out2 = c1(CAPTIONS), c2(CAPTIONS)
    assert not torch.allclose(out1, out2)
    torch.testing.assert_close(out2, e2(CAPTIONS))
    assert len(shared) == 8  # 4 unique captions x 2 encoders
    assert module_fingerprint(ToyEncoder(seed=1)) == module_fingerprint(e1)  # same weights, same id


def test_bypass_when_dropout_or_trainable_or_odd_input():
    enc = ToyEncoder(dropout=0.5)
    cached = CachedTextEncoder(enc, enc)
    enc.train()
    with pytest.warns(UserWarning, match="runs dropout"):
        cached(CAPTIONS)
    assert len(cached.cache) == 0 and enc.seen[-1] == CAPTIONS  # encoded as upstream, nothing kept
    enc.eval()
    cached(CAPTIONS)
    assert len(cached.cache) == 4
    trainable = ToyEncoder()
    trainable.proj.weight.requires_grad_(True)
    with pytest.warns(UserWarning, match="not frozen"):
        CachedTextEncoder(trainable, trainable)(CAPTIONS)
    plain = ToyEncoder()
    with pytest.warns(UserWarning, match="not a list of str"):
        CachedTextEncoder(plain, plain)("just one string")
    with pytest.raises(ValueError, match="encoder module or an identity"):
        CachedTextEncoder(lambda t: t)


# --------------------------------------------------------------------------- on a model
def tiny(encoder):
    torch.manual_seed(0)
    return TinyMDM(latent_dim=64, ff_size=128, num_layers=2, clip_dim=8, text_encoder=encoder)


def train_losses(model, steps=6):
    diffusion = SimpleDiffusion(20)
    sparsify(model, SparseConfig(reduction=0.8), diffusion=diffusion)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-3)
    g = torch.Generator().manual_seed(0)
    out = []
    for step in range(steps):
        x = torch.randn(4, 263, 1, 30, generator=g)
        texts = [CAPTIONS[(step + i) % len(CAPTIONS)] for i in range(4)]
        y = {"mask": torch.ones(4, 1, 1, 30, dtype=torch.bool), "lengths": torch.full((4,), 30), "text": texts}
        t = torch.randint(0, 20, (4,), generator=g)
        torch.manual_seed(100 + step)  # same noise / cond dropout / mask noise in both runs
        loss = diffusion.training_losses(model, x, t, {"y": y})["loss"].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        out.append(loss.item())
    return out


def test_training_with_the_cache_equals_training_without():
    plain = train_losses(tiny(ToyEncoder("flat")))
    model = tiny(ToyEncoder("flat"))
    wrapped = install_text_cache(model, capacity=1000)
    assert model.text_encoder.forward is wrapped and install_text_cache(model) is wrapped
    assert isinstance(model.text_encoder, ToyEncoder)  # still a registered submodule
    cached = train_losses(model)
    assert cached == pytest.approx(plain, rel=1e-6, abs=1e-7)
    st = wrapped.cache.stats()
    assert st["entries"] == 4 and st["hits"] > 0
    remove_text_cache(model)
    assert "forward" not in model.text_encoder.__dict__


def test_ema_copy_shares_the_cache_but_uses_its_own_encoder():
    model = tiny(ToyEncoder("flat"))
    wrapped = install_text_cache(model)
    ema = copy.deepcopy(model)
    copied = ema.text_encoder.forward
    assert isinstance(copied, CachedTextEncoder) and copied is not wrapped and copied.cache is wrapped.cache
    assert copied.encoder is ema.text_encoder and copied.encode.__self__ is ema.text_encoder  # its own module
    ema.text_encoder(CAPTIONS)
    assert len(wrapped.cache) == 4


def test_cache_on_a_swapped_hf_encoder_matches_uncached(tmp_path):
    pytest.importorskip("transformers")
    from smdm_plugin.adapters.text_encoder import swap_text_encoder

    path = make_tiny_encoder(str(tmp_path / "enc"))
    model = TinyMDM(latent_dim=32, ff_size=64, num_layers=1)
    swap_text_encoder(model, path)
    direct = model.text_encoder(CAPTIONS)
    wrapped = install_text_cache(model)
    assert wrapped.identity.startswith("HFTextEncoder:hf:" + path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # frozen, eval: no bypass warning
        torch.testing.assert_close(model.text_encoder(CAPTIONS), direct, atol=1e-6, rtol=1e-6)
        torch.testing.assert_close(model.text_encoder(list(reversed(CAPTIONS))), direct.flip(0),
                                   atol=1e-6, rtol=1e-6)
