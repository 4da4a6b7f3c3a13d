"""The T2M evaluator as one module (:class:`Evaluator`), from either of two sources, one interface:
upstream's published evaluator (``finest.tar`` + GloVe) or one trained here (``smdm evaluator train``)."""
from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.nn as nn

from .networks import MotionEncoderBiGRUCo, MovementConvEncoder, TextEncoderBiGRUCo
from .vocab import MAX_TEXT_LEN, POS_CATEGORIES, encode_tokens, load_glove

CONFIG_FILENAME = "evaluator.json"
WEIGHTS_FILENAME = "evaluator.pt"
UPSTREAM_CHECKPOINT = "finest.tar"


@dataclass
class EvaluatorConfig:
    """Sizes and reading conventions of an evaluator. Upstream's (T2M) sizes: word 300 (GloVe),
    movement 512/512, motion 1024, text 512, co-embedding 512, unit length 4, 20 caption tokens."""

    dim_pose: int = 263
    drop_tail: int = 4
    dim_word: int = 300
    dim_movement_hidden: int = 512
    dim_movement_latent: int = 512
    dim_motion_hidden: int = 1024
    dim_text_hidden: int = 512
    dim_coemb: int = 512
    unit_length: int = 4
    max_text_len: int = MAX_TEXT_LEN
    max_motion_length: int = 196
    vocab_size: int = 1
    learned_words: bool = False
    source: str = "upstream"
    representation: str = "humanml3d"

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.type in ("int", int) and (isinstance(v, bool) or not isinstance(v, int)):
                raise TypeError(f"EvaluatorConfig: {f.name} must be an int, got {v!r}")
        if not 0 <= self.drop_tail < self.dim_pose:
            raise ValueError(f"EvaluatorConfig: drop_tail must be in [0, dim_pose={self.dim_pose}), got {self.drop_tail}")
        if self.max_motion_length < 4 or self.max_motion_length % 4:
            raise ValueError(f"EvaluatorConfig: max_motion_length must be a multiple of 4 (frames), got "
                             f"{self.max_motion_length}")
        if self.unit_length != 4:
            raise ValueError(f"EvaluatorConfig: unit_length must be 4 (the movement encoder's stride), got "
                             f"{self.unit_length}")

    def to_dict(self) -> Dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "EvaluatorConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"EvaluatorConfig: unknown field(s) {', '.join(unknown)}")
        return cls(**d)


class Evaluator(nn.Module):
    """Movement, motion and text encoders plus the word table (``words``: GloVe, frozen, or learned),
    the vocabulary (word -> row) and the motion normalisation (buffers ``mean``/``std`` ``[D]``)."""

    def __init__(self, config: EvaluatorConfig, vocab: Dict[str, int], mean: np.ndarray, std: np.ndarray) -> None:
        super().__init__()
        self.config = config
        D = config.dim_pose
        mean, std = np.asarray(mean, np.float32).reshape(-1), np.asarray(std, np.float32).reshape(-1)
        if mean.shape != (D,) or std.shape != (D,):
            raise ValueError(f"Evaluator: mean and std must be [{D}], got {mean.shape} and {std.shape}")
        if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std > 0).all()):
            raise ValueError("Evaluator: mean must be finite and std finite and > 0")
        if "unk" not in vocab or len(vocab) == 0 or max(vocab.values()) >= config.vocab_size:
            raise ValueError(f"Evaluator: the vocabulary needs 'unk' and rows < vocab_size={config.vocab_size}")
        self.vocab = dict(vocab)
        self.register_buffer("mean", torch.from_numpy(mean))
        self.register_buffer("std", torch.from_numpy(std))
        self.words = nn.Embedding(config.vocab_size, config.dim_word)
        self.words.weight.requires_grad_(config.learned_words)
        self.movement_encoder = MovementConvEncoder(D - config.drop_tail, config.dim_movement_hidden,
                                                    config.dim_movement_latent)
        self.motion_encoder = MotionEncoderBiGRUCo(config.dim_movement_latent, config.dim_motion_hidden,
                                                   config.dim_coemb)
        self.text_encoder = TextEncoderBiGRUCo(config.dim_word, len(POS_CATEGORIES), config.dim_text_hidden,
                                               config.dim_coemb)

    # ------------------------------------------------------------------------------ motion
    def prepare_motion(self, features: torch.Tensor, lengths: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Normalised motion ``[B, M, D - drop_tail]`` and movement lengths ``[B]`` (steps) from raw
        features ``[B, N, D]`` with ``lengths [B]`` (frames), read as upstream's evaluation reads a
        real motion: the first ``min(length, M)`` frames (M = ``max_motion_length``, 196) rounded down
        to a multiple of 4, normalised, zero-padded to M frames (the padding enters the last
        movement steps through the convolutions, so the buffer length is part of the protocol)."""
        D, M = self.config.dim_pose, self.config.max_motion_length
        if features.dim() != 3 or features.shape[-1] != D:
            raise ValueError(f"Evaluator: motions must be raw features [B, N, {D}], got {tuple(features.shape)}")
        lengths = torch.as_tensor(lengths, device=features.device).long().reshape(-1)
        B, N, _ = features.shape
        if lengths.shape[0] != B or bool((lengths < self.config.unit_length).any()) or bool((lengths > N).any()):
            raise ValueError(f"Evaluator: lengths must be [B]=[{B}] in [{self.config.unit_length}, N={N}] frames, "
                             f"got {lengths.tolist()}")
        lengths = lengths.clamp(max=M) // self.config.unit_length * self.config.unit_length
        x = features[:, :M].to(self.mean)
        if x.shape[1] < M:
            x = torch.cat([x, x.new_zeros(B, M - x.shape[1], D)], dim=1)
        x = (x - self.mean) / self.std
        valid = torch.arange(M, device=x.device)[None, :] < lengths[:, None]
        x = torch.where(valid[..., None], x, torch.zeros((), dtype=x.dtype, device=x.device))
        return x[..., :D - self.config.drop_tail], lengths // self.config.unit_length

    def encode_motion(self, features: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """Co-embeddings ``[B, C]`` of raw motions ``features [B, N, D]`` with ``lengths [B]`` (frames)."""
        x, steps = self.prepare_motion(features, lengths)
        return self.motion_encoder(self.movement_encoder(x), steps)

    # ------------------------------------------------------------------------------ text
    def prepare_text(self, captions: Sequence[Sequence[str]]) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(word rows [B, T] long, part of speech [B, T, 15] one-hot, token counts [B])`` of captions
        given as ``word/POS`` token lists (``sos`` + at most 20 tokens + ``eos``; padding: ``unk``)."""
        rows = [encode_tokens(c, self.vocab, self.config.max_text_len) for c in captions]
        if not rows:
            raise ValueError("Evaluator: no captions given")
        T = max(len(w) for w, _ in rows)
        unk = self.vocab["unk"]
        words = torch.full((len(rows), T), unk, dtype=torch.long)
        pos = torch.zeros(len(rows), T, len(POS_CATEGORIES))
        pos[:, :, POS_CATEGORIES.index("OTHER")] = 1.0
        for i, (w, p) in enumerate(rows):
            words[i, :len(w)] = torch.tensor(w)
            pos[i, :len(p)] = 0.0
            pos[i, torch.arange(len(p)), torch.tensor(p)] = 1.0
        lengths = torch.tensor([len(w) for w, _ in rows])
        dev = self.mean.device
        return words.to(dev), pos.to(dev), lengths

    def encode_text(self, captions: Sequence[Sequence[str]]) -> torch.Tensor:
        """Co-embeddings ``[B, C]`` of captions (``word/POS`` token lists)."""
        words, pos, lengths = self.prepare_text(captions)
        return self.text_encoder(self.words(words), pos.to(self.words.weight.dtype), lengths)


# ----------------------------------------------------------------------------------------- files
def save_evaluator(evaluator: Evaluator, folder: str, extra: Optional[Dict[str, Any]] = None) -> None:
    """Write ``evaluator.pt`` (state dict) and ``evaluator.json`` (config, vocabulary, ``extra``),
    each atomically (the caller checks that ``folder`` may be written)."""
    from ...io.files import atomic_open, atomic_write_json

    os.makedirs(folder, exist_ok=True)
    with atomic_open(os.path.join(folder, WEIGHTS_FILENAME), "wb") as f:
        torch.save({k: v.detach().cpu() for k, v in evaluator.state_dict().items()}, f)
    words = sorted(evaluator.vocab, key=evaluator.vocab.get)
    atomic_write_json(os.path.join(folder, CONFIG_FILENAME),
                      {"format": "smdm-evaluator/1", "config": evaluator.config.to_dict(),
                       "vocab": {w: evaluator.vocab[w] for w in words}, **(extra or {})})


def _load_own(folder: str, device: Any) -> Evaluator:
    path = os.path.join(folder, CONFIG_FILENAME)
    try:
        with open(path) as f:
            meta = json.load(f)
        config = EvaluatorConfig.from_dict(meta["config"])
        vocab = {str(k): int(v) for k, v in meta["vocab"].items()}
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"{path}: not a valid evaluator config ({e})") from None
    state = torch.load(os.path.join(folder, WEIGHTS_FILENAME), map_location="cpu", weights_only=True)
    ev = Evaluator(config, vocab, np.zeros(config.dim_pose), np.ones(config.dim_pose))
    _load_state(ev, state, path)
    return ev.to(device).eval()


def _load_state(module: nn.Module, state: Any, where: str) -> None:
    if not isinstance(state, dict):
        raise ValueError(f"{where}: expected a state dict, got {type(state).__name__}")
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = str(e).strip().splitlines()
        raise ValueError(f"{where}: weights do not fit the evaluator ({' '.join(l.strip() for l in first[:3])})") from None


def find_upstream_checkpoint(folder: str) -> Optional[str]:
    """Path of ``finest.tar`` in the places :mod:`this module <smdm_plugin.metrics.evaluator.model>` names."""
    for rel in ("", "text_mot_match/model", "t2m/text_mot_match/model", "kit/text_mot_match/model"):
        p = os.path.join(folder, rel, UPSTREAM_CHECKPOINT)
        if os.path.isfile(p):
            return p
    return None


def _find_stats(folder: str, checkpoint: str) -> Optional[Tuple[str, str]]:
    ckdir = os.path.dirname(checkpoint)
    bases = [folder, os.path.join(folder, "meta"), os.path.join(folder, "dataset"), ckdir,
             os.path.join(ckdir, "..", "..", "Comp_v6_KLD01", "meta")]
    for base in bases:
        for m, s in (("t2m_mean.npy", "t2m_std.npy"), ("kit_mean.npy", "kit_std.npy"), ("mean.npy", "std.npy"),
                     ("Mean.npy", "Std.npy")):
            if os.path.isfile(os.path.join(base, m)) and os.path.isfile(os.path.join(base, s)):
                return os.path.join(base, m), os.path.join(base, s)
    return None


def load_upstream_evaluator(folder: str, glove: Optional[str] = None, mean: Optional[np.ndarray] = None,
                            std: Optional[np.ndarray] = None, device: Any = "cpu") -> Evaluator:
    """Upstream's published evaluator (``finest.tar`` + GloVe + normalisation; see docs/modules.md)
    in upstream's sizes; ``dim_pose`` (263 HumanML3D, 251 KIT) is read from the weights."""
    ck = find_upstream_checkpoint(folder)
    if ck is None:
        raise FileNotFoundError(f"evaluator {folder!r}: no {CONFIG_FILENAME} (an evaluator trained here) and no "
                                f"{UPSTREAM_CHECKPOINT} (upstream's: <dir>/t2m/text_mot_match/model/finest.tar)")
    try:
        state = torch.load(ck, map_location="cpu", weights_only=True)
    except Exception as e:  # a pickle with objects weights_only refuses, or not a torch file
        raise ValueError(f"{ck}: cannot be read as plain tensors ({type(e).__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from None
    parts = ("movement_encoder", "motion_encoder", "text_encoder")
    if not isinstance(state, dict) or any(not isinstance(state.get(p), dict) for p in parts):
        raise ValueError(f"{ck}: expected a dict with state dicts {', '.join(parts)}")
    w = state["movement_encoder"].get("main.0.weight")
    if not isinstance(w, torch.Tensor) or w.dim() != 3:
        raise ValueError(f"{ck}: movement_encoder has no main.0.weight [hidden, D - 4, 4]")
    gdir = glove
    if gdir is None:
        for cand in (os.path.join(folder, "glove"), folder, os.path.join(folder, "..", "glove")):
            if os.path.isfile(os.path.join(cand, "our_vab_data.npy")):
                gdir = cand
                break
    if gdir is None:
        raise FileNotFoundError(f"evaluator {folder!r}: no GloVe files (our_vab_data.npy, our_vab_words.pkl, "
                                "our_vab_idx.pkl) in <dir>/glove; give the folder with glove=... / --glove")
    vectors, vocab = load_glove(gdir)
    if mean is None or std is None:
        stats = _find_stats(folder, ck)
        if stats is None:
            raise FileNotFoundError(f"evaluator {folder!r}: no normalisation of the evaluator (t2m_mean.npy and "
                                    "t2m_std.npy from MDM's dataset/ folder, or mean.npy/std.npy); give mean= and std=")
        mean, std = np.load(stats[0]), np.load(stats[1])
    text_w = state["text_encoder"]
    config = EvaluatorConfig(
        dim_pose=int(w.shape[1]) + 4, drop_tail=4, dim_word=int(vectors.shape[1]),
        dim_movement_hidden=int(w.shape[0]),
        dim_movement_latent=int(state["movement_encoder"]["out_net.weight"].shape[0]),
        dim_motion_hidden=int(state["motion_encoder"]["hidden"].shape[-1]),
        dim_text_hidden=int(text_w["hidden"].shape[-1]),
        dim_coemb=int(text_w["output_net.3.weight"].shape[0]),
        vocab_size=int(vectors.shape[0]), learned_words=False, source="upstream")
    ev = Evaluator(config, vocab, mean, std)
    with torch.no_grad():
        ev.words.weight.copy_(torch.from_numpy(vectors))
    for p in parts:
        _load_state(getattr(ev, p), state[p], f"{ck} [{p}]")
    return ev.to(device).eval()


def evaluator_layout(path: str) -> str:
    """``"own"`` (``evaluator.json``), ``"upstream"`` (a ``finest.tar`` found), else FileNotFoundError."""
    if os.path.isfile(os.path.join(path, CONFIG_FILENAME)):
        return "own"
    if os.path.isdir(path) and find_upstream_checkpoint(path) is not None:
        return "upstream"
    raise FileNotFoundError(f"evaluator {path!r}: neither an evaluator trained here ({CONFIG_FILENAME}) nor "
                            f"upstream's ({UPSTREAM_CHECKPOINT}, e.g. <dir>/t2m/text_mot_match/model/finest.tar)")


def load_evaluator(path: str, glove: Optional[str] = None, mean: Optional[np.ndarray] = None,
                   std: Optional[np.ndarray] = None, device: Any = "cpu") -> Evaluator:
    """An evaluator folder of either layout (:func:`evaluator_layout`), in ``eval`` mode on ``device``;
    ``glove``/``mean``/``std`` apply to upstream's layout (given for one trained here: a ``ValueError``,
    never ignored: it keeps its own vocabulary and statistics)."""
    if evaluator_layout(path) == "own":
        given = [name for name, v in (("glove", glove), ("mean", mean), ("std", std)) if v is not None]
        if given:
            raise ValueError(f"evaluator {path!r} was trained here ({CONFIG_FILENAME}: its own vocabulary and "
                             f"statistics); {', '.join(given)} appl{'y' if len(given) > 1 else 'ies'} to upstream's "
                             "evaluator only (--glove: leave it out)")
        return _load_own(path, device)
    return load_upstream_evaluator(path, glove=glove, mean=mean, std=std, device=device)


def feature_mismatch(evaluator: Evaluator, layout: str, representation: str, dim: int) -> Optional[str]:
    """Why ``evaluator`` (of ``layout``) cannot read ``representation [dim]`` features, or None:
    "it reads humanml3d [263] features" (the caller names its argument and the data)."""
    cfg = evaluator.config
    if cfg.dim_pose != dim or (layout == "own" and cfg.representation != representation):
        return f"it reads {cfg.representation} [{cfg.dim_pose}] features"
    return None


def evaluator_info(path: str) -> Dict[str, Any]:
    """What ``evaluator.json`` says beside the config (held-out accuracy, data, ...); ``{}`` for upstream's."""
    p = os.path.join(path, CONFIG_FILENAME)
    if not os.path.isfile(p):
        return {}
    with open(p) as f:
        meta = json.load(f)
    return {k: v for k, v in meta.items() if k not in ("config", "vocab")}
