"""Training an evaluator on your own captioned motion: the T2M architecture
(:mod:`~smdm_plugin.metrics.evaluator.networks`) trained end to end, contrastively, on the train
split, with GloVe word vectors when given and otherwise word embeddings learned from the captions.

Differences from upstream's recipe (Guo et al. pre-train the movement encoder as an auto-encoder,
then train the BiGRUs with a margin loss on shifted negative pairs): one stage, a symmetric
cross-entropy over the batch on negative Euclidean distances (every other motion/caption of the
batch is a negative; the distance is what R-precision ranks by), the smaller default sizes of
:data:`OWN_SIZES` (fast on a CPU, and a 64-D embedding keeps the FID covariance estimable on a few
hundred motions). Every epoch draws one caption per motion and a random crop (length rounded down
to a multiple of 4, a third of the time 4 frames shorter, random offset), as upstream's loader does.

The weights kept are those of the epoch with the best mean validation R-precision (top-1 and top-3)
when there is a validation split, else the last; each epoch's numbers are in the history.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional

import numpy as np
import torch
import torch.nn.functional as F

from ..t2m import retrieval
from .data import CaptionedMotions
from .model import Evaluator, EvaluatorConfig
from .score import embed_captions, embed_motions
from .vocab import build_vocabulary, load_glove

#: sizes of an evaluator trained here (upstream's are EvaluatorConfig's defaults)
OWN_SIZES: Dict[str, int] = {"dim_word": 64, "dim_movement_hidden": 128, "dim_movement_latent": 128,
                             "dim_motion_hidden": 128, "dim_text_hidden": 128, "dim_coemb": 64}


@dataclass
class TrainSettings:
    """``epochs``, ``batch`` (motions per step), ``lr`` (Adam), ``temperature`` (distance scale of the
    contrastive logits), ``seed``, ``eval_draws`` (caption draws averaged in held-out accuracy)."""

    epochs: int = 60
    batch: int = 32
    lr: float = 1e-3
    temperature: float = 0.1
    seed: int = 0
    eval_draws: int = 5
    sizes: Dict[str, int] = field(default_factory=lambda: dict(OWN_SIZES))

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch < 2 or not self.lr > 0 or not self.temperature > 0 or self.eval_draws < 1:
            raise ValueError(f"TrainSettings: need epochs >= 1, batch >= 2, lr > 0, temperature > 0, eval_draws >= 1; "
                             f"got {self.epochs}, {self.batch}, {self.lr}, {self.temperature}, {self.eval_draws}")


def build_evaluator(train: CaptionedMotions, settings: TrainSettings, glove: Optional[str] = None) -> Evaluator:
    """A fresh evaluator for ``train``'s features: GloVe vectors (frozen) from ``glove``, else a word
    table learned over the training captions' vocabulary."""
    torch.manual_seed(settings.seed)
    sizes = dict(settings.sizes)
    D = train.motions[0].shape[1]
    drop = 4 if train.representation == "humanml3d" else 0
    if glove is not None:
        vectors, vocab = load_glove(glove)
        sizes["dim_word"] = int(vectors.shape[1])
    else:
        vocab = build_vocabulary([c.tokens for caps in train.captions for c in caps])
        vectors = None
    config = EvaluatorConfig(dim_pose=D, drop_tail=drop, vocab_size=len(vectors) if vectors is not None else len(vocab),
                             learned_words=vectors is None, source="own", representation=train.representation,
                             **sizes)
    ev = Evaluator(config, vocab, train.mean, train.std)
    if vectors is not None:
        with torch.no_grad():
            ev.words.weight.copy_(torch.from_numpy(vectors))
    else:
        torch.nn.init.normal_(ev.words.weight, std=1.0 / math.sqrt(config.dim_word))
    return ev


def _crop(motion: np.ndarray, rng: np.random.Generator, max_len: int) -> np.ndarray:
    L = min(len(motion), max_len)
    L = L // 4 * 4 - (4 if rng.random() < 1 / 3 and L >= 48 else 0)
    start = int(rng.integers(0, len(motion) - L + 1))
    return motion[start:start + L]


def held_out_accuracy(ev: Evaluator, data: CaptionedMotions, draws: int = 5, seed: int = 0) -> Dict[str, float]:
    """R-precision top-1/2/3 and matching score of ``data`` (real motion against its own captions),
    averaged over ``draws`` random caption choices; with the pool size and the chance top-1/top-3."""
    was = ev.training
    ev.eval()
    motion = embed_motions(ev, data.motions)
    rows = []
    for d in range(draws):
        text = embed_captions(ev, data.first_captions(seed=seed + d))
        rows.append(retrieval(text, motion, seed=seed + d))
    ev.train(was)
    pool = rows[0].pool_size
    return {"top1": float(np.mean([r.top1 for r in rows])), "top2": float(np.mean([r.top2 for r in rows])),
            "top3": float(np.mean([r.top3 for r in rows])),
            "matching_score": float(np.mean([r.matching_score for r in rows])),
            "pool_size": pool, "n_scored": rows[0].n_scored, "n_motions": len(data),
            "chance_top1": 1.0 / pool, "chance_top3": min(1.0, 3.0 / pool), "caption_draws": draws}


def train_evaluator(ev: Evaluator, train: CaptionedMotions, val: Optional[CaptionedMotions], settings: TrainSettings,
                    state: Optional[Dict[str, Any]] = None, progress: bool = False,
                    on_epoch: Optional[Callable[[Dict[str, Any]], None]] = None) -> Dict[str, Any]:
    """Train ``ev`` in place for ``settings.epochs`` (from ``state``, a dict :func:`train_evaluator`
    passed to ``on_epoch``, to resume). Every epoch ends with ``on_epoch(state)``; ``state`` holds
    ``epoch``, ``model``, ``optimizer``, ``best`` (state dict + epoch + score), ``history``, ``seconds``.
    Returns the final state (``ev`` then holds the best weights)."""
    params = [p for p in ev.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=settings.lr)
    st: Dict[str, Any] = {"epoch": 0, "history": [], "best": None, "seconds": 0.0}
    if state is not None:
        ev.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        st = {k: state[k] for k in ("epoch", "history", "best", "seconds")}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=settings.epochs, initial=st["epoch"], desc="evaluator", unit="epoch", mininterval=0.5)
    n = len(train)
    for epoch in range(st["epoch"], settings.epochs):
        t0 = time.perf_counter()
        rng = np.random.default_rng([settings.seed, epoch])  # a function of (seed, epoch): resumes exactly
        torch.manual_seed(int(rng.integers(2 ** 62)))
        ev.train()
        order = rng.permutation(n)
        losses = []
        for s in range(0, n - 1, settings.batch):
            idx = order[s:s + settings.batch]
            if len(idx) < 2:
                break
            motions = [_crop(train.motions[i], rng, ev.config.max_motion_length) for i in idx]
            caps = [train.captions[i][int(rng.integers(len(train.captions[i])))].tokens for i in idx]
            x = np.zeros((len(idx), max(len(m) for m in motions), motions[0].shape[1]), np.float32)
            for r, m in enumerate(motions):
                x[r, :len(m)] = m
            m_emb = ev.encode_motion(torch.from_numpy(x).to(ev.mean.device), torch.tensor([len(m) for m in motions]))
            t_emb = ev.encode_text(caps)
            logits = -torch.cdist(t_emb, m_emb) * (1.0 / settings.temperature) / math.sqrt(ev.config.dim_coemb)
            target = torch.arange(len(idx), device=logits.device)
            loss = 0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 1.0)
            opt.step()
            losses.append(float(loss.detach()))
        st["seconds"] += time.perf_counter() - t0
        row: Dict[str, Any] = {"epoch": epoch + 1, "loss": float(np.mean(losses)), "seconds": st["seconds"]}
        score = None
        if val is not None:
            acc = held_out_accuracy(ev, val, draws=settings.eval_draws, seed=settings.seed)
            row.update(val_top1=acc["top1"], val_top3=acc["top3"])
            score = 0.5 * (acc["top1"] + acc["top3"])
        st["history"].append(row)
        if st["best"] is None or score is None or score > st["best"]["score"]:
            st["best"] = {"epoch": epoch + 1, "score": score,
                          "model": {k: v.detach().cpu().clone() for k, v in ev.state_dict().items()}}
        st["epoch"] = epoch + 1
        st["model"] = {k: v.detach().cpu().clone() for k, v in ev.state_dict().items()}
        st["optimizer"] = opt.state_dict()
        if bar is not None:
            bar.set_postfix_str(f"loss {row['loss']:.3f}" + (f" val top-3 {row['val_top3']:.2f}" if val else ""))
            bar.update(1)
        if on_epoch is not None:
            on_epoch(st)
    if bar is not None:
        bar.close()
    ev.load_state_dict(st["best"]["model"])
    ev.eval()
    return st
