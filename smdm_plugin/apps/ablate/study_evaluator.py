"""The text-motion evaluator the quality-versus-compute study scores with, behind one small interface.

:class:`MotionTextEvaluator` is what :mod:`smdm_plugin.apps.ablate.study` needs: ``embed_motion`` (raw
HumanML3D features ``[B, N, 263]`` + ``lengths [B]`` -> ``[B, D]``) and ``embed_text`` (captions ->
``[B, D]``); FID, diversity, R-precision and matching score are computed on those embeddings with
:mod:`smdm_plugin.metrics.t2m`. Providers are registered in :data:`EVALUATORS` by name and
trained once per (data fingerprint, settings), cached in the study's output folder.

``t2m``: the T2M architecture of :mod:`smdm_plugin.metrics.evaluator` (movement encoder, motion
and text BiGRUs, word/POS inputs, words learned from the captions) trained as ``smdm evaluator
train`` trains it. Another provider is one entry of :data:`EVALUATORS`.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from typing import Any, Callable, Dict, Protocol, Sequence

import torch


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


def cached_evaluator(folder: str, build: Callable[[], MotionTextEvaluator],
                     load: Callable[[str], MotionTextEvaluator]) -> MotionTextEvaluator:
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
    """Training of the T2M-architecture evaluator (:mod:`smdm_plugin.metrics.evaluator.train`):
    ``recipe`` (``contrastive``: 0.4's one stage, the default of configs written before it;
    ``t2m``: T2M's two stages, ``smdm evaluator train``'s default), ``epochs`` (matching epochs),
    ``ae_epochs``, ``margin`` and ``reversed_negatives`` (``t2m`` only), ``batch``, ``lr``, ``temperature``
    (``contrastive`` only), ``seed``, ``select`` (how the weights are chosen on val). A config's evaluator key is its ``evaluator`` mapping as written, so the fields
    added later leave earlier caches and results valid."""

    epochs: int = 60
    batch: int = 32
    lr: float = 1e-3
    temperature: float = 0.1
    seed: int = 0
    recipe: str = "contrastive"
    ae_epochs: int = 50
    margin: float = 10.0
    select: str = "val_rprec"
    reversed_negatives: bool = False

    def __post_init__(self) -> None:
        from ...metrics.evaluator.train import RECIPES, SELECTIONS

        if self.recipe not in RECIPES:
            raise TypeError(f"recipe={self.recipe!r}: expected one of {RECIPES}")
        if self.select not in SELECTIONS:
            raise TypeError(f"select={self.select!r}: expected one of {SELECTIONS}")


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
        from ...metrics.evaluator import save_evaluator

        save_evaluator(self.ev, folder, extra={"kind": self.name, "report": self.report})

    @classmethod
    def load(cls, folder: str) -> "T2MEvaluator":
        from ...metrics.evaluator import load_evaluator

        with open(os.path.join(folder, "evaluator.json"), encoding="utf-8") as f:
            meta = json.load(f)
        if meta.get("kind") != cls.name:
            raise ValueError(f"{folder}/evaluator.json: kind {meta.get('kind')!r}, expected {cls.name!r}")
        return cls(load_evaluator(folder), meta.get("report", {}))


def train_t2m(data: Any, settings: T2MSettings, log: Callable[[str], Any] = print) -> T2MEvaluator:
    """Train the T2M evaluator on ``data.root``'s train split (weights chosen on val when it exists),
    with :mod:`smdm_plugin.metrics.evaluator.train`; held-out accuracy on the evaluation split in
    ``report``."""
    from ...metrics.evaluator.data import load_captioned
    from ...metrics.evaluator.check import retrieval_check
    from ...metrics.evaluator.train import TrainSettings, build_evaluator, held_out_accuracy, train_evaluator

    ts = TrainSettings(recipe=settings.recipe, epochs=settings.epochs, batch=settings.batch, lr=settings.lr,
                       temperature=settings.temperature, seed=settings.seed, ae_epochs=settings.ae_epochs,
                       margin=settings.margin, select=settings.select, reversed_negatives=settings.reversed_negatives)
    train = load_captioned(data.root, "train")
    val = load_captioned(data.root, "val") if os.path.exists(os.path.join(data.root, "val.txt")) else None
    ev = build_evaluator(train, ts)
    st = train_evaluator(ev, train, val, ts)
    held = load_captioned(data.root, data.split)
    acc = held_out_accuracy(ev, held, seed=settings.seed)
    check = retrieval_check(ev, held, replications=20, seed=settings.seed)
    report = {"kept_epoch": st["best"]["epoch"] - ts.pretrain_epochs, "recipe": ts.recipe, "train_seconds": st["seconds"], "held_out": acc,
              "train_motions": len(train), "retrieval_check": check.to_dict()}
    log(f"  evaluator (t2m): held-out {data.split} top-1 {acc['top1']:.3f}, top-3 {acc['top3']:.3f} (pool "
        f"{acc['pool_size']}; chance top-1 {acc['chance_top1']:.3f}), {ts.recipe} recipe, kept matching epoch "
        f"{st['best']['epoch'] - ts.pretrain_epochs}; {check.line()}")
    return T2MEvaluator(ev, report)


#: evaluator providers: name -> (settings type, trainer ``(StudyData, settings, log)``, loader ``(folder)``)
EVALUATORS: Dict[str, Any] = {"t2m": (T2MSettings, train_t2m, T2MEvaluator.load)}
