"""Text conditioning for the in-package backbone without CLIP weights."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
from dataclasses import dataclass
from typing import Any, Dict, List, Sequence, Union

import numpy as np
import torch

TEXT_CONFIG_FILENAME = "text_encoder.json"
_WORD = re.compile(r"[a-z0-9']+")


@dataclass(frozen=True)
class TextConfig:
    """Text conditioning of the in-package trainer. ``encoder``: a name of :data:`TEXT_ENCODERS`;
    ``dim``: embedding width (TinyMDM's ``clip_dim``); ``seed``: the encoder's hash seed;
    ``cond_mask_prob``: fraction of training samples whose condition is dropped (classifier-free
    guidance; MDM 0.1); ``guidance_scale``: ``uncond + s * (cond - uncond)`` at sampling (MDM 2.5;
    1.0 = no guidance)."""

    encoder: str = "hashed_bow"
    dim: int = 512
    seed: int = 0
    cond_mask_prob: float = 0.1
    guidance_scale: float = 2.5

    def __post_init__(self) -> None:
        if self.encoder not in TEXT_ENCODERS:
            raise ValueError(f"TextConfig.encoder={self.encoder!r}: expected one of {sorted(TEXT_ENCODERS)}")
        checks = (("dim", isinstance(self.dim, int) and not isinstance(self.dim, bool) and self.dim >= 1, "an int >= 1"),
                  ("seed", isinstance(self.seed, int) and not isinstance(self.seed, bool) and self.seed >= 0,
                   "an int >= 0"),
                  ("cond_mask_prob", _real(self.cond_mask_prob) and 0.0 <= self.cond_mask_prob < 1.0,
                   "a float in [0, 1)"),
                  ("guidance_scale", _real(self.guidance_scale) and self.guidance_scale >= 0.0, "a float >= 0"))
        for name, ok, what in checks:
            if not ok:
                raise ValueError(f"TextConfig.{name}={getattr(self, name)!r}: expected {what}")

    def to_dict(self) -> Dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "TextConfig":
        if not isinstance(d, dict):
            raise TypeError(f"TextConfig.from_dict: expected a mapping, got {type(d).__name__}")
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise ValueError(f"TextConfig: unknown field(s) {unknown} (known: {', '.join(known)})")
        return cls(**d)

    def build(self) -> "HashedBagOfWords":
        """The encoder these settings describe."""
        return TEXT_ENCODERS[self.encoder](self.dim, self.seed)


def _real(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def words(caption: str) -> List[str]:
    """The lower-cased words of ``caption`` (runs of letters, digits and apostrophes)."""
    return _WORD.findall(caption.lower())


class HashedBagOfWords:
    """``texts [B]`` (str) -> ``[B, dim]`` float32, L2-normalised (module docstring). Frozen: no
    parameters; word vectors are cached per word."""

    def __init__(self, dim: int = 512, seed: int = 0) -> None:
        self.dim, self.seed = int(dim), int(seed)
        self._cache: Dict[str, np.ndarray] = {}

    def word_vector(self, word: str) -> np.ndarray:
        """The fixed ``±1/sqrt(dim)`` vector ``[dim]`` of one word."""
        v = self._cache.get(word)
        if v is None:
            need, chunks, k = (self.dim + 7) // 8, [], 0
            while sum(len(c) for c in chunks) < need:
                chunks.append(hashlib.blake2b(f"{self.seed}\x00{k}\x00{word}".encode(), digest_size=64).digest())
                k += 1
            bits = np.unpackbits(np.frombuffer(b"".join(chunks)[:need], np.uint8))[: self.dim]
            v = (bits.astype(np.float32) * 2.0 - 1.0) / np.float32(math.sqrt(self.dim))
            self._cache[word] = v
        return v

    def encode(self, texts: Union[str, Sequence[str]]) -> np.ndarray:
        """``[B, dim]`` float32 (a caption without words gives zeros)."""
        texts = [texts] if isinstance(texts, str) else list(texts)
        if not all(isinstance(t, str) for t in texts):
            raise TypeError(f"HashedBagOfWords: texts must be strings, got {[type(t).__name__ for t in texts][:4]}")
        out = np.zeros((len(texts), self.dim), np.float32)
        for i, t in enumerate(texts):
            for w in words(t):
                out[i] += self.word_vector(w)
            n = float(np.linalg.norm(out[i]))
            if n > 0:
                out[i] /= n
        return out

    def __call__(self, texts: Union[str, Sequence[str]]) -> torch.Tensor:
        return torch.from_numpy(self.encode(texts))


#: registry of the in-package text encoders: name -> ``(dim, seed) -> encoder``
TEXT_ENCODERS = {"hashed_bow": HashedBagOfWords}


def save_text_config(folder: str, config: TextConfig) -> str:
    """Write ``<folder>/text_encoder.json`` atomically; returns its path."""
    from ..support.atomic import atomic_write_json

    path = os.path.join(folder, TEXT_CONFIG_FILENAME)
    atomic_write_json(path, config.to_dict())
    return path


def load_text_config(folder: str) -> "TextConfig | None":
    """The :class:`TextConfig` saved in ``folder`` (None when the model is unconditional); a
    malformed file is a ``ValueError`` naming it."""
    path = os.path.join(folder, TEXT_CONFIG_FILENAME)
    if not os.path.exists(path):
        return None
    try:
        with open(path, encoding="utf-8") as f:
            return TextConfig.from_dict(json.load(f))
    except (ValueError, TypeError) as e:
        raise ValueError(f"{path}: not a valid text encoder config ({e})") from None


def text_condition(config: TextConfig, texts: Sequence[str], device: Any = "cpu") -> Dict[str, torch.Tensor]:
    """The model's text conditioning of one caption per sample: ``{"text_embed": [1, B, dim]}``."""
    return {"text_embed": config.build()(list(texts)).unsqueeze(0).to(device)}


def guided(model: torch.nn.Module, config: TextConfig) -> torch.nn.Module:
    """What sampling calls: ``model`` wrapped in classifier-free guidance at ``config.guidance_scale``
    (``model`` itself at scale 1)."""
    from .simple_diffusion import ClassifierFreeGuidance

    return model if config.guidance_scale == 1.0 else ClassifierFreeGuidance(model, config.guidance_scale)


@torch.no_grad()
def sample_with_text(model: torch.nn.Module, diffusion: Any, config: TextConfig, texts: Sequence[str],
                     lengths: torch.Tensor, frames: int, device: Any = "cpu",
                     generator: "torch.Generator | None" = None) -> torch.Tensor:
    """Generate one motion per caption: ``[B, J, 1, frames]`` (normalised features; frames past
    ``lengths [B]`` are padding), text-conditioned with classifier-free guidance at
    ``config.guidance_scale`` (two model calls per step; scale 1: the conditional model alone).
    ``model`` must be in eval mode (no condition dropout)."""
    B = len(texts)
    if tuple(lengths.shape) != (B,):
        raise ValueError(f"sample_with_text: lengths must be [B]=[{B}], got {tuple(lengths.shape)}")
    L = lengths.to(device)
    y = {"mask": (torch.arange(frames, device=device) < L[:, None]).view(B, 1, 1, frames), "lengths": L,
         **text_condition(config, texts, device)}
    J = getattr(model, "njoints", 263)
    return diffusion.p_sample_loop(guided(model, config), (B, J, 1, frames), {"y": y}, device=device,
                                   generator=generator)
