"""Training an evaluator on your own captioned motion: the T2M architecture
(:mod:`~smdm_plugin.metrics.evaluator.networks`) on the train split, with GloVe word vectors when
given and otherwise word embeddings learned from the captions, by one of two recipes (:data:`RECIPES`:
``t2m``, two stages and a margin loss, or ``contrastive``)."""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional

import numpy as np
import torch
import torch.nn.functional as F

from ..t2m import retrieval
from .data import CaptionedMotions
from .model import Evaluator, EvaluatorConfig
from .score import embed_captions, embed_motions
from .vocab import build_vocabulary, load_glove

#: the sizes of the earlier one-stage recipe (``recipe="contrastive"``)
OWN_SIZES: Dict[str, int] = {"dim_word": 64, "dim_movement_hidden": 128, "dim_movement_latent": 128,
                             "dim_motion_hidden": 128, "dim_text_hidden": 128, "dim_coemb": 64}
#: T2M's sizes (the published HumanML3D evaluator's), the default of ``recipe="t2m"``; words are 300-D
#: as GloVe's (learned unless GloVe is given)
T2M_SIZES: Dict[str, int] = {"dim_word": 300, "dim_movement_hidden": 512, "dim_movement_latent": 512,
                             "dim_motion_hidden": 1024, "dim_text_hidden": 512, "dim_coemb": 512}
#: the training recipes: ``t2m`` (two stages, margin loss) and ``contrastive`` (one stage, cross-entropy)
RECIPES = ("t2m", "contrastive")
#: the recipe ``smdm evaluator train`` uses by default
DEFAULT_RECIPE = "t2m"
#: how the kept weights are chosen among the matching epochs, when there is a validation split:
#: ``val_loss`` (T2M's: the lowest :func:`validation_loss`), ``val_rprec`` (the highest mean of validation
#: R-precision top-1 and top-3)
SELECTIONS = ("val_loss", "val_rprec")


@dataclass
class TrainSettings:
    """``recipe`` (:data:`RECIPES`; ``smdm evaluator train`` uses ``t2m``, the dataclass keeps 0.4's
    ``contrastive`` for library callers), ``epochs`` (matching epochs, after ``ae_epochs`` of movement
    auto-encoder pretraining for ``t2m``; default 60 for both), ``batch`` (motions per step), ``lr``
    (Adam; default 1e-4 for ``t2m`` as T2M, 1e-3 for ``contrastive``; ``ae_lr`` for the auto-encoder),
    ``margin`` (``t2m``: negatives pushed beyond this distance), ``temperature`` (``contrastive``:
    distance scale of the logits), ``ae_window`` (frames per auto-encoder crop), ``seed``,
    ``eval_draws`` (caption draws averaged in held-out accuracy and the validation loss), ``sizes``,
    ``select`` (:data:`SELECTIONS`; default ``val_loss`` for ``t2m``, ``val_rprec`` for
    ``contrastive``), ``reversed_negatives`` (``t2m``: each caption is also pushed beyond ``margin``
    from its own motion played backwards; default on for ``t2m``)."""

    recipe: str = "contrastive"
    epochs: Optional[int] = None
    batch: int = 32
    lr: Optional[float] = None
    ae_epochs: int = 50
    ae_lr: float = 1e-4
    ae_window: int = 64
    margin: float = 10.0
    temperature: float = 0.1
    seed: int = 0
    eval_draws: int = 5
    sizes: Optional[Dict[str, int]] = None
    select: Optional[str] = None
    reversed_negatives: Optional[bool] = None

    def __post_init__(self) -> None:
        if self.recipe not in RECIPES:
            raise ValueError(f"TrainSettings: recipe must be one of {RECIPES}, got {self.recipe!r}")
        t2m = self.recipe == "t2m"
        if self.select is None:
            self.select = "val_loss" if t2m else "val_rprec"
        if self.select not in SELECTIONS:
            raise ValueError(f"TrainSettings: select must be one of {SELECTIONS}, got {self.select!r}")
        if self.reversed_negatives is None:
            self.reversed_negatives = t2m
        if self.reversed_negatives and not t2m:
            raise ValueError("TrainSettings: reversed_negatives is part of the t2m recipe's margin loss")
        if self.sizes is None:
            self.sizes = dict(T2M_SIZES if t2m else OWN_SIZES)
        if self.epochs is None:
            self.epochs = 60
        if self.lr is None:
            self.lr = 1e-4 if t2m else 1e-3
        if (self.epochs < 1 or self.batch < 2 or not self.lr > 0 or not self.temperature > 0 or self.eval_draws < 1
                or self.ae_epochs < 0 or not self.ae_lr > 0 or not self.margin > 0 or self.ae_window < 8
                or self.ae_window % 4):
            raise ValueError(f"TrainSettings: need epochs >= 1, batch >= 2, lr > 0, temperature > 0, eval_draws >= 1, "
                             f"ae_epochs >= 0, ae_lr > 0, margin > 0, ae_window a multiple of 4 >= 8; got "
                             f"{self.epochs}, {self.batch}, {self.lr}, {self.temperature}, {self.eval_draws}, "
                             f"{self.ae_epochs}, {self.ae_lr}, {self.margin}, {self.ae_window}")

    @property
    def pretrain_epochs(self) -> int:
        """Auto-encoder epochs that run before the matching epochs (0 for ``contrastive``)."""
        return self.ae_epochs if self.recipe == "t2m" else 0

    def to_dict(self) -> Dict[str, Any]:
        return dataclasses.asdict(self)


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


def validation_loss(ev: Evaluator, data: CaptionedMotions, settings: "TrainSettings", draws: int = 5,
                    seed: int = 0) -> float:
    """T2M's matching loss on held-out ``data`` (the criterion T2M keeps its weights by), without its
    randomness: every motion whole (first ``max_motion_length`` frames), one caption drawn per motion
    and draw (``draws`` draws, seeded), squared distance of the true pairs plus the squared shortfall
    below ``settings.margin`` of **every** mismatched pair (T2M: one random shift of the batch).
    Mean over the draws (a float; lower is better)."""
    was = ev.training
    ev.eval()
    x, L = _padded([m[:ev.config.max_motion_length] for m in data.motions])
    with torch.no_grad():
        m_emb = ev.encode_motion(x.to(ev.mean.device), L)
        out = []
        for d in range(draws):
            t_emb = ev.encode_text(data.first_captions(seed=seed + d))
            dist = torch.cdist(t_emb.double(), m_emb.double())                       # [N, N]
            off = ~torch.eye(len(dist), dtype=torch.bool, device=dist.device)
            out.append(float((dist.diagonal() ** 2).mean() + (torch.clamp(settings.margin - dist[off], min=0) ** 2).mean()))
    ev.train(was)
    return float(np.mean(out))


def _padded(motions: List[np.ndarray]) -> tuple:
    x = np.zeros((len(motions), max(len(m) for m in motions), motions[0].shape[1]), np.float32)
    for r, m in enumerate(motions):
        x[r, :len(m)] = m
    return torch.from_numpy(x), torch.tensor([len(m) for m in motions])


def _autoencoder_step(ev: Evaluator, decoder: torch.nn.Module, motions: List[np.ndarray], rng: np.random.Generator,
                      window: int) -> torch.Tensor:
    """T2M's decomposition loss on one batch: windows of ``window`` frames (at most the shortest motion,
    a multiple of 4) at random offsets, normalised; L1 reconstruction of all features from the movement
    code of all but the last ``drop_tail`` + 0.001 L1 sparsity + 0.1 L1 smoothness of the code."""
    w = min(window, min(len(m) for m in motions) // 4 * 4)
    crops = []
    for m in motions:
        s = int(rng.integers(0, len(m) - w + 1))
        crops.append(m[s:s + w])
    x = (torch.from_numpy(np.stack(crops)).to(ev.mean) - ev.mean) / ev.std
    z = ev.movement_encoder(x[..., :ev.config.dim_pose - ev.config.drop_tail])
    rec = decoder(z)
    return (F.l1_loss(rec, x) + 0.001 * z.abs().mean() + 0.1 * F.l1_loss(z[:, 1:], z[:, :-1]))


def _matching_loss(ev: Evaluator, settings: TrainSettings, motions: List[np.ndarray], caps: List[List[str]],
                   rng: np.random.Generator) -> torch.Tensor:
    """``t2m``: T2M's margin loss (positives: squared distance; negatives, the batch shifted by a random
    1..B-1: squared shortfall below ``margin``), the movement encoder frozen; ``contrastive``: symmetric
    cross-entropy over the batch on negative distances, everything trained."""
    x, L = _padded(motions)
    x = x.to(ev.mean.device)
    t_emb = ev.encode_text(caps)
    if settings.recipe == "t2m":
        xin, steps = ev.prepare_motion(x, L)
        with torch.no_grad():
            mov = ev.movement_encoder(xin)
        m_emb = ev.motion_encoder(mov, steps)
        B = len(motions)
        shift = int(rng.integers(1, B))
        neg = m_emb[(torch.arange(B) + shift) % B]
        d_pos = F.pairwise_distance(t_emb, m_emb)
        d_neg = F.pairwise_distance(t_emb, neg)
        loss = (d_pos ** 2).mean() + (torch.clamp(settings.margin - d_neg, min=0.0) ** 2).mean()
        if settings.reversed_negatives:  # each caption against its own motion played backwards
            rev = torch.stack([torch.cat([x[b, :int(n)].flip(0), x[b, int(n):]]) for b, n in enumerate(L)])
            xr, _ = ev.prepare_motion(rev, L)
            with torch.no_grad():
                mov_r = ev.movement_encoder(xr)
            d_rev = F.pairwise_distance(t_emb, ev.motion_encoder(mov_r, steps))
            loss = loss + (torch.clamp(settings.margin - d_rev, min=0.0) ** 2).mean()
        return loss
    m_emb = ev.encode_motion(x, L)
    logits = -torch.cdist(t_emb, m_emb) * (1.0 / settings.temperature) / math.sqrt(ev.config.dim_coemb)
    target = torch.arange(len(motions), device=logits.device)
    return 0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target))


def _snapshot(module: torch.nn.Module) -> Dict[str, torch.Tensor]:
    return {k: v.detach().cpu().clone() for k, v in module.state_dict().items()}


def train_evaluator(ev: Evaluator, train: CaptionedMotions, val: Optional[CaptionedMotions], settings: TrainSettings,
                    state: Optional[Dict[str, Any]] = None, progress: bool = False,
                    on_epoch: Optional[Callable[[Dict[str, Any]], None]] = None) -> Dict[str, Any]:
    """Train ``ev`` in place: ``settings.pretrain_epochs`` of movement auto-encoding, then
    ``settings.epochs`` of text-motion matching (from ``state``, a dict :func:`train_evaluator` passed
    to ``on_epoch``, to resume). Every epoch ends with ``on_epoch(state)``; ``state`` holds ``epoch``
    (both stages counted), ``model``, ``decoder``, ``optimizer``, ``ae_optimizer``, ``best`` (state dict
    + epoch + score, matching epochs only), ``history``, ``seconds``. Returns the final state (``ev``
    then holds the best weights)."""
    from .networks import MovementConvDecoder

    c = ev.config
    t2m = settings.recipe == "t2m"
    decoder = MovementConvDecoder(c.dim_movement_latent, c.dim_movement_hidden, c.dim_pose).to(ev.mean.device)
    ae_params = list(ev.movement_encoder.parameters()) + list(decoder.parameters())
    frozen = {id(p) for p in ev.movement_encoder.parameters()} if t2m else set()
    params = [p for p in ev.parameters() if p.requires_grad and id(p) not in frozen]
    ae_opt = torch.optim.Adam(ae_params, lr=settings.ae_lr)
    opt = torch.optim.Adam(params, lr=settings.lr)
    pre = settings.pretrain_epochs
    total = pre + settings.epochs
    st: Dict[str, Any] = {"epoch": 0, "history": [], "best": None, "seconds": 0.0}
    if state is not None:
        ev.load_state_dict(state["model"])  # (load_state_dict copies onto ev's device)
        opt.load_state_dict(state["optimizer"])
        if state.get("decoder") is not None:
            decoder.load_state_dict(state["decoder"])
            ae_opt.load_state_dict(state["ae_optimizer"])
        st = {k: state[k] for k in ("epoch", "history", "best", "seconds")}
    bar = None
    from ...support.progress import bars_on  # stderr a terminal (or --progress)

    if bars_on(progress):
        from tqdm.auto import tqdm

        bar = tqdm(total=total, initial=st["epoch"], desc="evaluator", unit="epoch", mininterval=0.5)
    n = len(train)
    for epoch in range(st["epoch"], total):
        t0 = time.perf_counter()
        rng = np.random.default_rng([settings.seed, epoch])  # a function of (seed, epoch): resumes exactly
        torch.manual_seed(int(rng.integers(2 ** 62)))
        stage = "autoencoder" if epoch < pre else "matching"
        ev.train()
        if t2m and stage == "matching":
            ev.movement_encoder.eval()  # frozen: no dropout, no gradient
        order = rng.permutation(n)
        losses = []
        for s in range(0, n - 1, settings.batch):
            idx = order[s:s + settings.batch]
            if len(idx) < 2:
                break
            if stage == "autoencoder":
                loss = _autoencoder_step(ev, decoder, [train.motions[i] for i in idx], rng, settings.ae_window)
                o, ps, clip = ae_opt, ae_params, None
            else:
                motions = [_crop(train.motions[i], rng, c.max_motion_length) for i in idx]
                caps = [train.captions[i][int(rng.integers(len(train.captions[i])))].tokens for i in idx]
                loss = _matching_loss(ev, settings, motions, caps, rng)
                o, ps, clip = opt, params, 0.5 if t2m else 1.0
            o.zero_grad(set_to_none=True)
            loss.backward()
            if clip is not None:
                torch.nn.utils.clip_grad_norm_(ps, clip)
            o.step()
            losses.append(float(loss.detach()))
        st["seconds"] += time.perf_counter() - t0
        row: Dict[str, Any] = {"epoch": epoch + 1, "stage": stage, "loss": float(np.mean(losses)),
                               "seconds": st["seconds"]}
        if stage == "matching":
            score = None
            if val is not None:
                acc = held_out_accuracy(ev, val, draws=settings.eval_draws, seed=settings.seed)
                vloss = validation_loss(ev, val, settings, draws=settings.eval_draws, seed=settings.seed)
                row.update(val_top1=acc["top1"], val_top3=acc["top3"], val_loss=vloss)
                score = -vloss if settings.select == "val_loss" else 0.5 * (acc["top1"] + acc["top3"])
            if st["best"] is None or score is None or score > st["best"]["score"]:
                st["best"] = {"epoch": epoch + 1, "score": score, "model": _snapshot(ev)}
        st["history"].append(row)
        st["epoch"] = epoch + 1
        st["model"] = _snapshot(ev)
        st["decoder"] = _snapshot(decoder) if pre else None
        st["optimizer"] = opt.state_dict()
        st["ae_optimizer"] = ae_opt.state_dict() if pre else None
        if bar is not None:
            bar.set_postfix_str(f"{stage} loss {row['loss']:.3f}" + (
                f" val top-3 {row['val_top3']:.2f}" if "val_top3" in row else ""))
            bar.update(1)
        if on_epoch is not None:
            on_epoch(st)
    if bar is not None:
        bar.close()
    ev.load_state_dict(st["best"]["model"])
    ev.eval()
    return st
