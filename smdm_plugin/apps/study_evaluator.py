"""The text-motion evaluator the quality-versus-compute study scores with, behind one small interface.

:class:`MotionTextEvaluator` is what :mod:`smdm_plugin.apps.study` needs: ``embed_motion`` (raw
HumanML3D features ``[B, N, 263]`` + ``lengths [B]`` -> ``[B, D]``) and ``embed_text`` (captions ->
``[B, D]``); FID, diversity, R-precision and matching score are computed on those embeddings with
:mod:`smdm_plugin.metrics.t2m`. Providers are registered in :data:`EVALUATORS` by name and
trained once per (data fingerprint, settings), cached in the study's output folder.

``t2m`` (default of the shipped configs): the T2M architecture of :mod:`smdm_plugin.metrics.evaluator`
(movement encoder, motion and text BiGRUs, word/POS inputs, words learned from the captions) trained
as ``smdm evaluator train`` trains it. ``pooled`` (a lighter stand-in, written before that landed): a small contrastive pair of encoders trained on the train split —
motion: normalised features -> two strided 1-D convolutions (×4 temporal downsampling, as T2M's
movement encoder) -> masked mean and max pooling -> linear; text: word embeddings learned from the
train captions (words as :func:`smdm_plugin.reference.text.words` splits them; unknown words map to
one "unknown" vector) -> mean pooling -> linear; both L2-normalised, trained with a symmetric
InfoNCE loss (temperature 0.1) on random crops (≥ 70% of each motion) and a random caption per
motion. It is NOT the T2M evaluator (no BiGRU, no GloVe), so its numbers are comparable only
within this study.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass
from typing import Any, Callable, Dict, List, Protocol, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..io.files import atomic_write_json
from ..reference.text import words


class MotionTextEvaluator(Protocol):
    """Embeddings for the T2M metrics: motions and captions into one space ``[B, D]``."""

    dim: int

    def embed_motion(self, motion: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """``motion [B, N, 263]`` raw (un-normalised) features, ``lengths [B]`` -> ``[B, D]``."""

    def embed_text(self, captions: Sequence[Any]) -> torch.Tensor:
        """``captions [B]`` (:class:`~smdm_plugin.metrics.evaluator.vocab.Caption`: ``text``,
        ``tokens``) -> ``[B, D]``."""

    def save(self, folder: str) -> None:
        """Write it to ``folder`` (``evaluator.json`` + weights)."""


@dataclass(frozen=True)
class PooledSettings:
    """Settings of the ``pooled`` evaluator: embedding ``dim``, conv ``hidden`` width, optimiser
    ``steps`` × ``batch``, ``lr``, ``seed``."""

    dim: int = 128
    hidden: int = 128
    steps: int = 600
    batch: int = 32
    lr: float = 1e-3
    seed: int = 0


class _PooledNet(nn.Module):
    def __init__(self, feats: int, vocab: int, s: PooledSettings) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.Conv1d(feats, s.hidden, 4, 2, 1), nn.LeakyReLU(0.2),
                                  nn.Conv1d(s.hidden, s.hidden, 4, 2, 1), nn.LeakyReLU(0.2))
        self.motion_out = nn.Linear(2 * s.hidden, s.dim)
        self.word = nn.Embedding(vocab, s.hidden)
        self.text_out = nn.Sequential(nn.Linear(s.hidden, s.hidden), nn.LeakyReLU(0.2), nn.Linear(s.hidden, s.dim))

    def motion(self, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """``x [B, N, F]`` normalised -> ``[B, dim]`` unit vectors."""
        h = self.conv(x.transpose(1, 2))  # [B, H, ~N/4]
        n = h.shape[-1]
        valid = torch.arange(n)[None] < ((lengths + 3) // 4).clamp(1, n)[:, None]  # [B, n]
        v = valid[:, None].to(h.dtype)
        mean = (h * v).sum(-1) / v.sum(-1)
        mx = h.masked_fill(~valid[:, None], float("-inf")).amax(-1)
        return F.normalize(self.motion_out(torch.cat([mean, mx], 1)), dim=-1)

    def text(self, ids: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
        """``ids [B, W]`` word indices (0 = padding), ``counts [B]`` -> ``[B, dim]`` unit vectors."""
        e = self.word(ids) * (ids > 0)[..., None].to(torch.float32)
        return F.normalize(self.text_out(e.sum(1) / counts.clamp_min(1)[:, None]), dim=-1)


class PooledEvaluator:
    """The trained ``pooled`` evaluator (module docstring): ``embed_motion`` / ``embed_text``."""

    name = "pooled"

    def __init__(self, net: _PooledNet, vocab: Dict[str, int], mean: np.ndarray, std: np.ndarray,
                 settings: PooledSettings, report: Dict[str, Any]) -> None:
        self.net, self.vocab, self.settings, self.report = net.eval(), vocab, settings, report
        self.mean, self.std = torch.as_tensor(mean, dtype=torch.float32), torch.as_tensor(std, dtype=torch.float32)
        self.dim = settings.dim

    def _ids(self, captions: Sequence[str]):
        toks = [[self.vocab.get(w, 1) for w in words(c)] or [1] for c in captions]
        W = max(len(t) for t in toks)
        ids = torch.zeros(len(toks), W, dtype=torch.long)
        for i, t in enumerate(toks):
            ids[i, :len(t)] = torch.tensor(t)
        return ids, torch.tensor([len(t) for t in toks], dtype=torch.float32)

    @torch.no_grad()
    def embed_motion(self, motion: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        x = (torch.as_tensor(motion, dtype=torch.float32) - self.mean) / self.std
        L = torch.as_tensor(lengths).long()
        x = x * (torch.arange(x.shape[1])[None, :, None] < L[:, None, None]).to(x.dtype)
        return self.net.motion(x, L)

    @torch.no_grad()
    def embed_text(self, captions: Sequence[Any]) -> torch.Tensor:
        return self.net.text(*self._ids([c if isinstance(c, str) else c.text for c in captions]))

    def save(self, folder: str) -> None:
        torch.save(self.net.state_dict(), os.path.join(folder, "evaluator.pt"))
        np.save(os.path.join(folder, "Mean.npy"), self.mean.numpy())
        np.save(os.path.join(folder, "Std.npy"), self.std.numpy())
        atomic_write_json(os.path.join(folder, "evaluator.json"),
                          {"kind": self.name, "settings": asdict(self.settings), "vocab": self.vocab,
                           "report": self.report})

    @classmethod
    def load(cls, folder: str) -> "PooledEvaluator":
        with open(os.path.join(folder, "evaluator.json"), encoding="utf-8") as f:
            meta = json.load(f)
        if meta.get("kind") != cls.name:
            raise ValueError(f"{folder}/evaluator.json: kind {meta.get('kind')!r}, expected {cls.name!r}")
        s = PooledSettings(**meta["settings"])
        mean, std = np.load(os.path.join(folder, "Mean.npy")), np.load(os.path.join(folder, "Std.npy"))
        net = _PooledNet(mean.shape[0], max(meta["vocab"].values()) + 1, s)
        net.load_state_dict(torch.load(os.path.join(folder, "evaluator.pt"), weights_only=True))
        return cls(net, meta["vocab"], mean, std, s, meta.get("report", {}))


def train_pooled(data: Any, settings: PooledSettings, log: Callable[[str], Any] = print) -> PooledEvaluator:
    """Train the ``pooled`` evaluator on the train split of a :class:`~smdm_plugin.apps.study.StudyData`
    (raw motions and their captions); its retrieval accuracy on the evaluation split (first caption,
    one pool of all) goes into ``report``."""
    from ..metrics.t2m import retrieval

    train_motions, train_captions, mean, std = data.train_raw, data.train.captions, data.mean, data.std
    held_out = ([data.raw[i, :int(data.lengths[i])].numpy() for i in range(len(data.ids))],
                [[c] for c in data.captions])

    g = torch.Generator().manual_seed(settings.seed)
    torch.manual_seed(settings.seed)
    vocab: Dict[str, int] = {}
    for caps in train_captions:
        for c in caps:
            for w in words(c):
                vocab.setdefault(w, len(vocab) + 2)  # 0 padding, 1 unknown
    net = _PooledNet(mean.shape[0], len(vocab) + 2, settings)
    ev = PooledEvaluator(net, vocab, mean, std, settings, {})
    opt = torch.optim.Adam(net.parameters(), lr=settings.lr)
    M = len(train_motions)
    N = max(len(m) for m in train_motions)
    norm = [torch.from_numpy(((m - mean) / std).astype(np.float32)) for m in train_motions]
    net.train()
    for step in range(settings.steps):
        idx = torch.randperm(M, generator=g)[: min(settings.batch, M)].tolist()
        x = torch.zeros(len(idx), N, mean.shape[0])
        lengths = torch.zeros(len(idx), dtype=torch.long)
        caps = []
        for r, i in enumerate(idx):
            L = len(norm[i])
            crop = int(torch.randint(max(4, int(0.7 * L)), L + 1, (1,), generator=g))
            s0 = int(torch.randint(0, L - crop + 1, (1,), generator=g))
            x[r, :crop] = norm[i][s0:s0 + crop]
            lengths[r] = crop
            caps.append(train_captions[i][int(torch.randint(0, len(train_captions[i]), (1,), generator=g))])
        m, t = net.motion(x, lengths), net.text(*ev._ids(caps))
        logits = m @ t.T / 0.1
        target = torch.arange(len(idx))
        loss = 0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target))
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    report: Dict[str, Any] = {"train_loss_last": float(loss.detach()), "train_motions": M, "vocab": len(vocab)}
    if held_out is not None:
        hm, hc = held_out
        L = torch.tensor([len(m) for m in hm])
        x = torch.zeros(len(hm), int(L.max()), mean.shape[0])
        for i, m in enumerate(hm):
            x[i, :len(m)] = torch.from_numpy(np.asarray(m, np.float32))
        r = retrieval(ev.embed_text([c[0] for c in hc]).numpy(), ev.embed_motion(x, L).numpy(),
                      pool=len(hm), shuffle=False)
        report.update(held_out_top1=r.top1, held_out_top3=r.top3, held_out_pool=r.pool_size)
        log(f"  evaluator (pooled): held-out retrieval top-1 {r.top1:.3f}, top-3 {r.top3:.3f} "
            f"(pool {r.pool_size}; chance top-1 {1 / r.pool_size:.3f})")
    ev.report = report
    return ev


def cached_evaluator(folder: str, build: Callable[[], PooledEvaluator], load: Callable[[str], PooledEvaluator]
                     ) -> PooledEvaluator:
    """``load(folder)`` when it holds a finished evaluator, else ``build()`` and save it there as one
    unit (written to a temporary sibling folder, then renamed)."""
    if os.path.exists(os.path.join(folder, "evaluator.json")):
        return load(folder)
    ev = build()
    parent = os.path.dirname(os.path.abspath(folder))
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".evaluator-", dir=parent)
    try:
        ev.save(tmp)
        os.replace(tmp, folder)
    finally:
        if os.path.isdir(tmp):
            shutil.rmtree(tmp, ignore_errors=True)
    return ev


# ----------------------------------------------------------------------------------------- T2M (branch eval)
@dataclass(frozen=True)
class T2MSettings:
    """Training of the T2M-architecture evaluator (:mod:`smdm_plugin.metrics.evaluator`, as
    ``smdm evaluator train`` does it): ``epochs``, ``batch``, ``lr``, ``temperature``, ``seed``."""

    epochs: int = 60
    batch: int = 32
    lr: float = 1e-3
    temperature: float = 0.1
    seed: int = 0


class T2MEvaluator:
    """The T2M evaluator (movement encoder + motion BiGRU + text BiGRU with word/POS inputs, Guo et
    al. 2022) trained on the study's train split, behind :class:`MotionTextEvaluator`."""

    name = "t2m"

    def __init__(self, ev: Any, report: Dict[str, Any]) -> None:
        self.ev, self.report = ev.eval(), report
        self.dim = int(ev.config.dim_coemb)

    @torch.no_grad()
    def embed_motion(self, motion: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        return self.ev.encode_motion(torch.as_tensor(motion, dtype=torch.float32), torch.as_tensor(lengths).long())

    @torch.no_grad()
    def embed_text(self, captions: Sequence[Any]) -> torch.Tensor:
        return self.ev.encode_text([c.tokens for c in captions])

    def save(self, folder: str) -> None:
        from ..metrics.evaluator import save_evaluator

        save_evaluator(self.ev, folder, extra={"kind": self.name, "report": self.report})

    @classmethod
    def load(cls, folder: str) -> "T2MEvaluator":
        from ..metrics.evaluator import load_evaluator

        with open(os.path.join(folder, "evaluator.json"), encoding="utf-8") as f:
            meta = json.load(f)
        if meta.get("kind") != cls.name:
            raise ValueError(f"{folder}/evaluator.json: kind {meta.get('kind')!r}, expected {cls.name!r}")
        return cls(load_evaluator(folder), meta.get("report", {}))


def train_t2m(data: Any, settings: T2MSettings, log: Callable[[str], Any] = print) -> T2MEvaluator:
    """Train the T2M evaluator on ``data.root``'s train split (weights chosen on val when it exists),
    with :mod:`smdm_plugin.metrics.evaluator.train`; held-out accuracy on the evaluation split in
    ``report``."""
    from ..metrics.evaluator.data import load_captioned
    from ..metrics.evaluator.train import TrainSettings, build_evaluator, held_out_accuracy, train_evaluator

    ts = TrainSettings(epochs=settings.epochs, batch=settings.batch, lr=settings.lr,
                       temperature=settings.temperature, seed=settings.seed)
    train = load_captioned(data.root, "train")
    val = load_captioned(data.root, "val") if os.path.exists(os.path.join(data.root, "val.txt")) else None
    ev = build_evaluator(train, ts)
    st = train_evaluator(ev, train, val, ts)
    acc = held_out_accuracy(ev, load_captioned(data.root, data.split), seed=settings.seed)
    report = {"kept_epoch": st["best"]["epoch"], "train_seconds": st["seconds"], "held_out": acc,
              "train_motions": len(train)}
    log(f"  evaluator (t2m): held-out {data.split} top-1 {acc['top1']:.3f}, top-3 {acc['top3']:.3f} (pool "
        f"{acc['pool_size']}; chance top-1 {acc['chance_top1']:.3f}), kept epoch {st['best']['epoch']}")
    return T2MEvaluator(ev, report)


#: evaluator providers: name -> (settings type, trainer ``(StudyData, settings, log)``, loader ``(folder)``)
EVALUATORS: Dict[str, Any] = {"pooled": (PooledSettings, train_pooled, PooledEvaluator.load),
                              "t2m": (T2MSettings, train_t2m, T2MEvaluator.load)}
