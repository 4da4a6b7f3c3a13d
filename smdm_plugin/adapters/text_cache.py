"""Opt-in text-embedding cache: encode each caption once, not on every training step."""
from __future__ import annotations

import hashlib
import warnings
from collections import OrderedDict
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch
import torch.nn as nn

DEFAULT_CAPACITY = 131072

Key = Tuple[str, str]


def _check_capacity(capacity: Any, fn: str) -> None:
    """A cache capacity is an int >= 1 (captions), not a bool."""
    if not isinstance(capacity, int) or isinstance(capacity, bool) or capacity < 1:
        raise ValueError(f"{fn}: capacity must be an int >= 1 (captions), got {capacity!r}")


class TextEmbeddingCache:
    """LRU map ``(encoder identity, caption) -> tensor`` bounded to ``capacity`` entries.

    ``copy.deepcopy`` returns the cache itself: a model and its EMA copy share one cache (their
    frozen encoders are equal; entries are keyed by the encoder's identity anyway)."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        _check_capacity(capacity, "TextEmbeddingCache")
        self.capacity = capacity
        self._entries: "OrderedDict[Key, torch.Tensor]" = OrderedDict()
        self.hits = 0
        self.misses = 0
        self.evictions = 0

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: Key) -> bool:
        return key in self._entries

    def __deepcopy__(self, memo: Dict[int, Any]) -> "TextEmbeddingCache":
        return self

    @property
    def nbytes(self) -> int:
        """Bytes held by the cached tensors."""
        return sum(t.numel() * t.element_size() for t in self._entries.values())

    def get(self, key: Key) -> Optional[torch.Tensor]:
        value = self._entries.get(key)
        if value is None:
            self.misses += 1
            return None
        self._entries.move_to_end(key)
        self.hits += 1
        return value

    def put(self, key: Key, value: torch.Tensor) -> None:
        self._entries[key] = value
        self._entries.move_to_end(key)
        while len(self._entries) > self.capacity:
            self._entries.popitem(last=False)
            self.evictions += 1

    def clear(self) -> None:
        self._entries.clear()

    def stats(self) -> Dict[str, float]:
        looked = self.hits + self.misses
        return {"entries": len(self), "capacity": self.capacity, "hits": self.hits, "misses": self.misses,
                "hit_rate": self.hits / looked if looked else 0.0, "evictions": self.evictions,
                "mib": self.nbytes / 2 ** 20}


# --------------------------------------------------------------------------- encoder identity
def module_fingerprint(module: nn.Module) -> str:
    """A short hash of a module's tensors: names, shapes, dtypes and the first and last 4 values
    of each (weights of the hidden modules of an ``HFTextEncoder`` included)."""
    frozen = getattr(module, "frozen_modules", None)
    target = frozen() if callable(frozen) else module
    h = hashlib.sha1()
    with torch.no_grad():
        for name, t in sorted(list(target.named_parameters()) + list(target.named_buffers()),
                              key=lambda kv: kv[0]):
            flat = t.detach().reshape(-1)
            sample = torch.cat([flat[:4], flat[-4:]]).float().cpu().tolist() if flat.numel() else []
            h.update(f"{name}{tuple(t.shape)}{t.dtype}{sample}".encode())
    return h.hexdigest()[:16]


def _module_device(module: Optional[nn.Module]) -> Optional[torch.device]:
    if module is None:
        return None
    dev = getattr(module, "device", None)
    if isinstance(dev, torch.device):
        return dev
    for t in module.parameters():
        return t.device
    for t in module.buffers():
        return t.device
    return None


# --------------------------------------------------------------------------- encoder outputs
# The text-feature conventions understood (anything else is passed through uncached):
#   "lead1":  Tensor [1, B, W]                         MDM's CLIP; a swapped MDM
#   "flat":   Tensor [B, W]                            TinyMDM's text_encoder
#   "tokens": (Tensor [L, B, W], pad mask [B, L] bool) DiP's DistilBERT (True = no token)
def _layout(out: Any, batch: int) -> Optional[str]:
    if isinstance(out, torch.Tensor):
        if out.dim() == 3 and out.shape[0] == 1 and out.shape[1] == batch:
            return "lead1"
        if out.dim() == 2 and out.shape[0] == batch:
            return "flat"
        return None
    if (isinstance(out, tuple) and len(out) == 2 and all(isinstance(o, torch.Tensor) for o in out)
            and out[0].dim() == 3 and out[0].shape[1] == batch and out[1].dtype == torch.bool
            and tuple(out[1].shape) == (batch, out[0].shape[0])):
        return "tokens"
    return None


def _split(out: Any, layout: str) -> List[torch.Tensor]:
    """One tensor per caption: ``[W]`` (pooled) or ``[n_i, W]`` (its non-padding tokens)."""
    if layout == "lead1":
        rows = list(out[0].detach())
    elif layout == "flat":
        rows = list(out.detach())
    else:
        hidden, pad = out
        rows = [hidden[~pad[i], i].detach() for i in range(hidden.shape[1])]
    return [r.clone() for r in rows]


def _assemble(rows: Sequence[torch.Tensor], layout: str) -> Any:
    if layout == "lead1":
        return torch.stack(list(rows)).unsqueeze(0)
    if layout == "flat":
        return torch.stack(list(rows))
    lengths = torch.tensor([r.shape[0] for r in rows], device=rows[0].device)
    hidden = nn.utils.rnn.pad_sequence(list(rows))  # [L, B, W], zeros past each caption
    pad = torch.arange(hidden.shape[0], device=hidden.device)[None] >= lengths[:, None]
    return hidden, pad


# --------------------------------------------------------------------------- the wrapper
class CachedTextEncoder:
    """``encode(texts)`` with a per-caption cache; same inputs and outputs as ``encode``.

    Args:
        encode: the model's text encoding function (``texts [B]`` -> one of the layouts above).
        encoder: the module behind it (device, dropout / frozen checks, fingerprint); may be None
            for a plain function (then ``identity`` is required).
        identity: what the cache keys on besides the caption (None: the encoder's class, its
            ``identity`` attribute when it has one, and :func:`module_fingerprint`).
        cache: the :class:`TextEmbeddingCache` to use, or None: a new one of ``capacity`` captions
            (None: :data:`DEFAULT_CAPACITY`).
    """

    def __init__(self, encode: Callable[[Sequence[str]], Any], encoder: Optional[nn.Module] = None, *,
                 identity: Optional[str] = None, cache: Optional[TextEmbeddingCache] = None,
                 capacity: Optional[int] = None) -> None:
        if not callable(encode):
            raise TypeError(f"CachedTextEncoder: encode must be callable, got {type(encode).__name__}")
        if identity is None:
            if encoder is None:
                raise ValueError("CachedTextEncoder: give the encoder module or an identity string")
            identity = (f"{type(encoder).__name__}:{getattr(encoder, 'identity', '')}:"
                        f"{module_fingerprint(encoder)}")
        _check_cache(cache, capacity, "CachedTextEncoder")
        self.encode = encode
        self.encoder = encoder
        self.identity = identity
        if cache is None:
            cache = TextEmbeddingCache(DEFAULT_CAPACITY if capacity is None else capacity)
        self.cache = cache
        self.layout: Optional[str] = None
        self._warned = False

    # ------------------------------------------------------------------ when not to cache
    def _why_not(self, texts: Any) -> Optional[str]:
        if not isinstance(texts, (list, tuple)) or not texts or not all(isinstance(t, str) for t in texts):
            return "the captions are not a list of str"
        enc = self.encoder
        if enc is not None:
            if any(p.requires_grad for p in enc.parameters()):
                return "the text encoder is not frozen (a parameter requires grad)"
            if any(isinstance(m, nn.Dropout) and m.p > 0 and m.training for m in enc.modules()):
                return ("the text encoder runs dropout (training mode), so a caption does not always get "
                        "the same embedding")
        return None

    def _pass_through(self, texts: Any, why: str) -> Any:
        if not self._warned:
            self._warned = True
            warnings.warn(f"smdm text cache: not caching ({why}); encoding as upstream does", stacklevel=3)
        return self.encode(texts)

    # ------------------------------------------------------------------ call
    def __call__(self, texts: Sequence[str]) -> Any:
        why = self._why_not(texts)
        if why is not None:
            return self._pass_through(texts, why)
        device = _module_device(self.encoder)
        rows: Dict[str, torch.Tensor] = {}
        missing: List[str] = []
        for text in dict.fromkeys(texts):  # unique captions, in order
            row = self.cache.get((self.identity, text))
            if row is None:
                missing.append(text)
            else:
                if device is not None and row.device != device:
                    row = row.to(device)
                    self.cache.put((self.identity, text), row)
                rows[text] = row
        if missing:
            out = self.encode(missing)
            layout = _layout(out, len(missing))
            if layout is None or (self.layout is not None and layout != self.layout):
                return self._pass_through(texts, "the encoder output is not [1, B, W], [B, W] or "
                                                 "([L, B, W], pad mask [B, L])")
            self.layout = layout
            for text, row in zip(missing, _split(out, layout)):
                rows[text] = row
                self.cache.put((self.identity, text), row)
        return _assemble([rows[t] for t in texts], self.layout)


def _check_cache(cache: Any, capacity: Optional[int], fn: str) -> None:
    """``capacity`` is None or valid; ``cache`` is None or a :class:`TextEmbeddingCache`, and a
    ``capacity`` beside it is its own."""
    if capacity is not None:
        _check_capacity(capacity, fn)
    if cache is None:
        return
    if not isinstance(cache, TextEmbeddingCache):
        raise TypeError(f"{fn}: cache must be a TextEmbeddingCache or None, got {type(cache).__name__}")
    if capacity not in (None, cache.capacity):
        raise ValueError(f"{fn}: capacity={capacity!r} does not apply to the given cache (its capacity is "
                         f"{cache.capacity}); pass one of capacity or cache")


# --------------------------------------------------------------------------- on a model
def _encode_attr(model: nn.Module) -> str:
    if hasattr(model, "encode_text"):
        return "encode_text"  # MDM, DiP (and a ClassifierFreeSampleModel's copy)
    if getattr(model, "text_encoder", None) is not None:
        return "text_encoder"  # TinyMDM
    raise TypeError(f"install_text_cache: {type(model).__name__} has no encode_text (MDM, DiP) or "
                    "text_encoder (TinyMDM) to cache")


def _installed(current: Any) -> Optional[CachedTextEncoder]:
    """The :class:`CachedTextEncoder` already wrapping ``current`` (the model's encoder), else None."""
    if isinstance(current, nn.Module):
        current = current.__dict__.get("forward")
    return current if isinstance(current, CachedTextEncoder) else None


def install_text_cache(model: nn.Module, capacity: Optional[int] = None,
                       cache: Optional[TextEmbeddingCache] = None) -> CachedTextEncoder:
    """Wrap ``model.encode_text`` (MDM, DiP) or ``model.text_encoder`` (TinyMDM) in a
    :class:`CachedTextEncoder` and return it. The encoder module is ``model.clip_model`` (MDM's
    CLIP / DistilBERT, or a swapped encoder) when there is one. A ``text_encoder`` that is a
    registered submodule keeps its place (and its state-dict keys): its ``forward`` is wrapped.

    ``capacity``: captions kept (None: :data:`DEFAULT_CAPACITY`); ``cache``: a cache to share
    instead. Idempotent: a second call returns the installed wrapper; asking it for another
    capacity or cache is a ``ValueError`` (:func:`remove_text_cache` first)."""
    fn = "install_text_cache"
    _check_cache(cache, capacity, fn)
    attr = _encode_attr(model)
    current = getattr(model, attr)
    installed = _installed(current)
    if installed is not None:
        have = installed.cache
        asked = ("another cache" if cache not in (None, have) else
                 f"capacity={capacity}" if capacity not in (None, have.capacity) else None)
        if asked:
            raise ValueError(f"{fn}: a text cache of capacity {have.capacity} is already installed on "
                             f"{type(model).__name__}; for {asked}, call remove_text_cache(model) first")
        return installed
    if isinstance(current, nn.Module):
        wrapped = CachedTextEncoder(current.forward, current, identity=_identity(current, model),
                                    cache=cache, capacity=capacity)
        current.forward = wrapped
        return wrapped
    encoder = getattr(model, "clip_model", None)
    encoder = encoder if isinstance(encoder, nn.Module) else None
    identity = (_identity(encoder, model) if encoder is not None
                else f"{getattr(current, '__qualname__', type(current).__name__)}@{id(current):x}")
    wrapped = CachedTextEncoder(current, encoder, identity=identity, cache=cache, capacity=capacity)
    setattr(model, attr, wrapped)
    return wrapped


def _identity(encoder: nn.Module, model: nn.Module) -> str:
    name = getattr(encoder, "identity", None) or getattr(model, "clip_version", None) or ""
    return f"{type(encoder).__name__}:{name}:{module_fingerprint(encoder)}"


def remove_text_cache(model: nn.Module) -> nn.Module:
    """Undo :func:`install_text_cache`."""
    attr = _encode_attr(model)
    current = getattr(model, attr)
    if isinstance(current, nn.Module):
        if isinstance(current.__dict__.get("forward"), CachedTextEncoder):
            del current.forward
    elif isinstance(current, CachedTextEncoder):
        setattr(model, attr, current.encode)
    return model
