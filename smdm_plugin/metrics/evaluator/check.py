"""What an evaluator can resolve: its **sensitivity table** on a split of real captioned motion."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..t2m import diversity, frechet_distance, mean_interval, retrieval
from .data import CaptionedMotions
from .model import Evaluator
from .protocol import replication
from .score import embed_captions, embed_motions

CHECK_FILENAME = "sensitivity.json"
CHECK_FORMAT = "smdm-evaluator-check/1"
Perturb = Callable[[List[np.ndarray], np.ndarray, str, np.random.Generator], List[np.ndarray]]


def _noise(scale: float) -> Perturb:
    def f(motions, std, rep, rng):
        return [(m + scale * std * rng.standard_normal(m.shape)).astype(np.float32) for m in motions]
    return f


def _smooth(motions, std, rep, rng, k: int = 9):
    out = []
    for m in motions:
        pad = np.concatenate([np.repeat(m[:1], k // 2, 0), m, np.repeat(m[-1:], k // 2, 0)])
        c = np.cumsum(np.concatenate([np.zeros((1, m.shape[1])), pad]), 0)
        out.append(((c[k:] - c[:-k]) / k).astype(np.float32))
    return out


def _reverse(motions, std, rep, rng):
    return [np.ascontiguousarray(m[::-1]) for m in motions]


def _slide(motions, std, rep, rng, step: float = 0.025):
    out = []
    for m in motions:
        m = m.astype(np.float32).copy()
        if rep == "humanml3d":
            m[:, 2] += step
        elif rep == "joints66":
            m[:, 65] += step * np.arange(len(m), dtype=np.float32)
        else:
            raise ValueError(f"foot_sliding: no root channels known for representation {rep!r}")
        out.append(m)
    return out


def _same(motions, std, rep, rng):
    return list(motions)


@dataclass(frozen=True)
class Condition:
    """One row: ``name``, ``label`` (for tables), ``perturb`` (motions, Std, representation, rng -> motions),
    ``swap`` (captions deranged)."""

    name: str
    label: str
    perturb: Perturb
    swap: bool = False


#: the rows of the table, in order (registry: name -> condition)
CONDITIONS: Dict[str, Condition] = {c.name: c for c in (
    Condition("real", "real (floor)", _same),
    Condition("noise_0.1", "noise 0.1·Std", _noise(0.1)),
    Condition("noise_0.3", "noise 0.3·Std", _noise(0.3)),
    Condition("noise_1.0", "noise 1.0·Std", _noise(1.0)),
    Condition("smooth_9", "9-frame moving average", _smooth),
    Condition("reversed", "time reversal", _reverse),
    Condition("foot_sliding", "foot sliding (root +0.5 m/s)", _slide),
    Condition("caption_swap", "caption swap", _same, swap=True),
)}
_METRICS = ("fid", "fid_over_div2", "top1", "top3", "matching_score")


@dataclass
class CheckRow:
    """One condition: per-metric ``(mean, 95% interval)`` over replications, and ``paired`` FID ÷ div²."""

    name: str
    label: str
    fid: List[float]
    fid_over_div2: List[float]
    top1: List[float]
    top3: List[float]
    matching_score: List[float]
    paired: float
    resolved: bool

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "CheckRow":
        names = [f.name for f in dataclasses.fields(cls)]
        if not isinstance(d, dict) or sorted(d) != sorted(names):
            raise ValueError(f"row needs exactly the fields {names}")
        for k in _METRICS:
            v = d[k]
            if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v)):
                raise ValueError(f"row {d.get('name')!r}: {k} must be [mean, interval]")
        if not isinstance(d["paired"], (int, float)) or not isinstance(d["resolved"], bool):
            raise ValueError(f"row {d.get('name')!r}: paired must be a number and resolved a bool")
        return cls(**d)


@dataclass
class SensitivityTable:
    """The check of one evaluator on one split: ``rows`` (one per :data:`CONDITIONS`), ``protocol``,
    ``replications``, ``pool`` (motions per draw), ``n_motions``, ``data``, ``split``, ``seed``,
    ``weights`` (fingerprint of the evaluator's weights)."""

    rows: List[CheckRow]
    protocol: str
    replications: int
    pool: int
    n_motions: int
    data: str
    split: str
    seed: int
    weights: str

    def to_dict(self) -> Dict[str, Any]:
        return {"format": CHECK_FORMAT, **dataclasses.asdict(self)}

    def row(self, name: str) -> CheckRow:
        for r in self.rows:
            if r.name == name:
                return r
        raise KeyError(name)

    def markdown(self) -> str:
        """The table (and how to read it) as Markdown."""
        lines = ["| condition | FID | FID ÷ div² | paired FID ÷ div² | R-prec. top-1 | top-3 | matching score | "
                 "resolved |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | :---: |"]
        for r in self.rows:
            pm = lambda v, f: f"{v[0]:{f}} ± {v[1]:{f}}"  # noqa: E731
            lines.append(f"| {r.label} | {pm(r.fid, '.3g')} | {pm(r.fid_over_div2, '.2e')} | {r.paired:.2e} | "
                         f"{pm(r.top1, '.3f')} | {pm(r.top3, '.3f')} | {pm(r.matching_score, '.3g')} | "
                         f"{'—' if r.name == 'real' else ('yes' if r.resolved else 'no')} |")
        return "\n".join(lines) + (
            f"\n\n* {self.replications} replications of the {self.protocol} protocol (draws of {self.pool} of "
            f"{self.n_motions} {self.split} motions, seed {self.seed}); mean ± 1.96·std/√R. Chance R-precision top-1 "
            f"/ top-3: {1 / self.pool:.3f} / {min(1.0, 3 / self.pool):.3f}.\n"
            "* resolved: FID (or, for caption swap, R-precision top-3) separated from the real floor by more than "
            "both intervals.\n")


def weights_fingerprint(ev: Evaluator) -> str:
    """SHA-256 (first 16 hex digits) of the evaluator's parameters and buffers, in state-dict order."""
    h = hashlib.sha256()
    for k, v in ev.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().float().numpy().tobytes())
    return h.hexdigest()[:16]


def _separated(a: Sequence[float], b: Sequence[float], higher: bool) -> bool:
    return (a[0] - a[1] > b[0] + b[1]) if higher else (a[0] + a[1] < b[0] - b[1])


def _replicate(ev: Evaluator, data: CaptionedMotions, names: Sequence[str], replications: int, seed: int,
               protocol: str, pool: int) -> Tuple[Dict[str, Dict[str, List[float]]], int]:
    """Per condition of ``names`` and metric of :data:`_METRICS`, the value of every replication (the
    same draws, captions and caption embeddings for every condition), and the motions per draw."""
    if replications < 1:
        raise ValueError(f"sensitivity: replications must be >= 1, got {replications}")
    unknown = [n for n in names if n not in CONDITIONS]
    if unknown or "real" not in names:
        raise ValueError(f"sensitivity: conditions must include 'real' and come from {list(CONDITIONS)}, got {names}")
    names = ["real", *[n for n in names if n != "real"]]  # the real row first: its diversity scales the others
    std = np.asarray(data.std, np.float32)
    lengths = [len(m) for m in data.motions]
    ncap = [len(c) for c in data.captions]
    vals: Dict[str, Dict[str, List[float]]] = {n: {k: [] for k in _METRICS} for n in names}
    P = 0
    for r in range(replications):
        rep = replication(protocol, lengths, ncap, seed=seed * 100003 + r, pool=pool)
        ref = embed_motions(ev, rep.reference.motions(data.motions))
        scored = rep.scored.motions(data.motions)
        caps = [c.tokens for c in rep.scored.captions(data.captions)]
        P = len(scored)
        text = embed_captions(ev, caps)
        rng = np.random.default_rng([seed, r, 1])
        real_emb = None
        for n in names:
            cond = CONDITIONS[n]
            emb = embed_motions(ev, cond.perturb(scored, std, data.representation, rng))
            if n == "real":
                real_emb = emb
            t = text
            if cond.swap:
                perm = (np.arange(P) + int(rng.integers(1, P))) % P  # a derangement: each caption moves
                t = text[perm]
            div = diversity(real_emb, P, seed=rng)[0]
            fid = frechet_distance(ref, emb)
            ret = retrieval(t, emb, pool=pool, seed=rng)
            v = vals[n]
            v["fid"].append(fid)
            v["fid_over_div2"].append(fid / div ** 2)
            v["top1"].append(ret.top1)
            v["top3"].append(ret.top3)
            v["matching_score"].append(ret.matching_score)
    return vals, P


def sensitivity(ev: Evaluator, data: CaptionedMotions, replications: int = 20, seed: int = 0,
                protocol: str = "upstream", pool: int = 32, data_name: str = "", split: str = "test",
                conditions: Optional[Sequence[str]] = None) -> SensitivityTable:
    """The :class:`SensitivityTable` of ``ev`` on ``data`` (docs/modules.md)."""
    names = list(conditions) if conditions is not None else list(CONDITIONS)
    vals, P = _replicate(ev, data, names, replications, seed, protocol, pool)
    std = np.asarray(data.std, np.float32)
    # paired: every motion, first min(L, 196) frames, against itself degraded
    full = [m[:ev.config.max_motion_length] for m in data.motions]
    base = embed_motions(ev, full)
    div_full = diversity(base, len(base), seed=seed)[0]
    rows = []
    summary = {n: {k: list(mean_interval(v[k])) for k in _METRICS} for n, v in vals.items()}
    floor = summary["real"]
    for n in names:
        cond = CONDITIONS[n]
        paired = 0.0
        if n != "real" and not cond.swap:
            paired = frechet_distance(base, embed_motions(ev, cond.perturb(full, std, data.representation,
                                                                          np.random.default_rng([seed, 7])))) / div_full ** 2
        s = summary[n]
        resolved = (_separated(floor["top3"], s["top3"], True) if cond.swap
                    else _separated(s["fid"], floor["fid"], True)) if n != "real" else False
        rows.append(CheckRow(n, cond.label, paired=float(paired), resolved=bool(resolved), **s))
    return SensitivityTable(rows, protocol, replications, int(P), len(data), data_name, split, seed,
                            weights_fingerprint(ev))


@dataclass
class RetrievalCheck:
    """Whether an evaluator's R-precision reacts to order and to the caption, on a split's real motions,
    under the evaluation protocol: each ``(mean, 95% interval)`` over ``replications`` (mean ±
    1.96·std/√R). ``top1``/``top3``: the real motions against their captions; ``reversed_top3``: the
    motions reversed in time; ``swapped_top3``: each scored against another motion's caption;
    ``drop_reversed_top1``/``drop_reversed_top3``/``drop_swapped_top3``: the **paired** drops (real −
    degraded, the same draws and captions in each replication); ``fid_floor``: the real-vs-real FID."""

    top1: List[float]
    top3: List[float]
    reversed_top3: List[float]
    swapped_top3: List[float]
    drop_reversed_top1: List[float]
    drop_reversed_top3: List[float]
    drop_swapped_top3: List[float]
    fid_floor: List[float]
    replications: int
    pool: int

    def sees_order(self) -> bool:
        """R-precision top-3 falls for time-reversed motion: the paired drop's interval is above 0."""
        return self.drop_reversed_top3[0] - self.drop_reversed_top3[1] > 0

    def sees_captions(self) -> bool:
        """R-precision top-3 falls for swapped captions: the paired drop's interval is above 0."""
        return self.drop_swapped_top3[0] - self.drop_swapped_top3[1] > 0

    def to_dict(self) -> Dict[str, Any]:
        return dataclasses.asdict(self)

    def line(self) -> str:
        """One line for a summary: R@3, its drops and whether they are clear of 0."""
        pm = lambda v: f"{v[0]:.3f} ± {v[1]:.3f}"  # noqa: E731
        return (f"R-precision top-3 {pm(self.top3)} (top-1 {pm(self.top1)}); time-reversed {pm(self.reversed_top3)}, "
                f"paired drop {pm(self.drop_reversed_top3)} ({'clear of 0' if self.sees_order() else 'NOT clear of 0'});"
                f" captions swapped {pm(self.swapped_top3)}, drop {pm(self.drop_swapped_top3)} "
                f"({'clear of 0' if self.sees_captions() else 'NOT clear of 0'}); FID floor {self.fid_floor[0]:.2f}")


def retrieval_check(ev: Evaluator, data: CaptionedMotions, replications: int = 20, seed: int = 0,
                    protocol: str = "upstream", pool: int = 32) -> RetrievalCheck:
    """The :class:`RetrievalCheck` of ``ev`` on ``data`` (the conditions ``real``, ``reversed`` and
    ``caption_swap`` of :data:`CONDITIONS`)."""
    vals, P = _replicate(ev, data, ["real", "reversed", "caption_swap"], replications, seed, protocol, pool)
    real, rev, swap = vals["real"], vals["reversed"], vals["caption_swap"]
    drop = lambda a, b: list(mean_interval(np.subtract(a, b)))  # noqa: E731
    return RetrievalCheck(list(mean_interval(real["top1"])), list(mean_interval(real["top3"])),
                          list(mean_interval(rev["top3"])), list(mean_interval(swap["top3"])),
                          drop(real["top1"], rev["top1"]), drop(real["top3"], rev["top3"]),
                          drop(real["top3"], swap["top3"]), list(mean_interval(real["fid"])), replications, P)


def save_check(table: SensitivityTable, folder: str) -> str:
    """Write ``folder/sensitivity.json`` atomically; returns its path."""
    from ...io.files import atomic_write_json

    path = os.path.join(folder, CHECK_FILENAME)
    atomic_write_json(path, table.to_dict())
    return path


def load_check(folder: str, ev: Optional[Evaluator] = None) -> Optional[SensitivityTable]:
    """The table saved in ``folder`` (None when there is none); ValueError naming the file when it is
    malformed or, with ``ev``, was measured on other weights."""
    path = os.path.join(folder, CHECK_FILENAME)
    if not os.path.isfile(path):
        return None
    try:
        with open(path, encoding="utf-8") as f:
            d = json.load(f)
        if not isinstance(d, dict) or d.get("format") != CHECK_FORMAT:
            raise ValueError(f"format must be {CHECK_FORMAT!r}")
        fields = [f.name for f in dataclasses.fields(SensitivityTable)]
        missing = [k for k in fields if k not in d]
        if missing:
            raise ValueError(f"missing {missing}")
        rows = d["rows"]
        if not isinstance(rows, list) or not rows:
            raise ValueError("rows must be a non-empty list")
        table = SensitivityTable(**{k: d[k] for k in fields if k != "rows"}, rows=[CheckRow.from_dict(r) for r in rows])
        if not (isinstance(table.replications, int) and table.replications >= 1 and isinstance(table.pool, int)
                and table.pool >= 2 and isinstance(table.weights, str)):
            raise ValueError("replications and pool must be ints (>= 1, >= 2) and weights a string")
        table.row("real")
    except (OSError, ValueError, TypeError, KeyError) as e:
        raise ValueError(f"{path}: not a valid sensitivity table ({e})") from None
    if ev is not None and table.weights != weights_fingerprint(ev):
        raise ValueError(f"{path}: measured on other weights (fingerprint {table.weights}, the evaluator's is "
                         f"{weights_fingerprint(ev)}); rerun smdm evaluator check")
    return table
