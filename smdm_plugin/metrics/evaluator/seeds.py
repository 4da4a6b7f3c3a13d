"""How an evaluator recipe varies over training seeds: one row per seed (held-out R-precision, its
paired drops for time-reversed motion and for swapped captions, the real-vs-real FID floor), what
``scripts/evaluator_seeds.py`` measures and ``smdm evaluator train`` prints beside its own numbers.

The table measured for ``smdm evaluator train``'s default recipe on ``cmu-humanml3d-large`` is packaged
as :data:`SEEDS_FILE` (``smdm_plugin/data/evaluator_seeds.json``) and shown in docs/evaluation.md
(``tests/metrics/test_evaluator_order.py`` checks that the page shows this file's table).
"""
from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass
from typing import Any, Dict, List, Optional

SEEDS_FILE = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "data",
                          "evaluator_seeds.json")
SEEDS_FORMAT = "smdm-evaluator-seeds/1"


@dataclass
class SeedRow:
    """One training seed: ``top1``/``top3`` (held-out test R-precision, all motions, averaged over caption
    draws, as ``evaluator.json`` reports it), ``check`` (a
    :class:`~smdm_plugin.metrics.evaluator.check.RetrievalCheck` as a dict: the protocol's R-precision,
    time-reversed, caption-swapped, the paired drops, the FID floor), ``kept_epoch``, ``train_seconds``."""

    seed: int
    top1: float
    top3: float
    check: Dict[str, Any]
    kept_epoch: int
    train_seconds: float

    def sees_order(self) -> bool:
        d = self.check["drop_reversed_top3"]
        return d[0] - d[1] > 0

    def sees_captions(self) -> bool:
        d = self.check["drop_swapped_top3"]
        return d[0] - d[1] > 0


@dataclass
class SeedTable:
    """``rows`` of one recipe (``settings``: :class:`~smdm_plugin.metrics.evaluator.train.TrainSettings`
    as a dict without ``seed`` and ``eval_draws``) on ``data`` (its name), ``replications`` of the check."""

    data: str
    settings: Dict[str, Any]
    replications: int
    rows: List[SeedRow]

    @property
    def seeds(self) -> List[int]:
        return [r.seed for r in self.rows]

    def to_dict(self) -> Dict[str, Any]:
        return {"format": SEEDS_FORMAT, **dataclasses.asdict(self)}

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "SeedTable":
        if not isinstance(d, dict) or d.get("format") != SEEDS_FORMAT:
            raise ValueError(f"format must be {SEEDS_FORMAT!r}")
        return cls(d["data"], d["settings"], int(d["replications"]), [SeedRow(**r) for r in d["rows"]])

    def markdown(self) -> str:
        """One row per seed: R@1, R@3 (held-out test), R@3 under the protocol, time-reversed and caption-
        swapped with their paired drops, the FID floor, the kept epoch."""
        pm = lambda v, f=".3f": f"{v[0]:{f}} ± {v[1]:{f}}"  # noqa: E731
        lines = ["| seed | R@1 | R@3 | R@3, protocol | R@3 reversed (drop) | R@3 caption-swapped (drop) | FID floor | "
                 "kept epoch |", "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for r in self.rows:
            c = r.check
            lines.append(f"| {r.seed} | {r.top1:.3f} | {r.top3:.3f} | {pm(c['top3'])} | {c['reversed_top3'][0]:.3f} "
                         f"({pm(c['drop_reversed_top3'])}) | {c['swapped_top3'][0]:.3f} ({pm(c['drop_swapped_top3'])}) | "
                         f"{pm(c['fid_floor'], '.2f')} | {r.kept_epoch} |")
        return "\n".join(lines)

    def spread_markdown(self) -> str:
        """Each column's mean and range over the seeds, and on how many seeds R-precision falls."""
        def col(get) -> str:
            v = [get(r) for r in self.rows]
            return f"{sum(v) / len(v):.3f} ({min(v):.3f}–{max(v):.3f})"
        n = len(self.rows)
        return "\n".join([
            "| over seeds: mean (min–max) | R@1 | R@3 | R@3 reversed, drop | R@3 caption-swapped, drop | FID floor |",
            "| --- | ---: | ---: | ---: | ---: | ---: |",
            f"| {n} seeds | {col(lambda r: r.top1)} | {col(lambda r: r.top3)} | "
            f"{col(lambda r: r.check['drop_reversed_top3'][0])} | {col(lambda r: r.check['drop_swapped_top3'][0])} | "
            f"{col(lambda r: r.check['fid_floor'][0])} |",
            f"| drop clear of 0 (95%) | | | {sum(r.sees_order() for r in self.rows)} of {n} | "
            f"{sum(r.sees_captions() for r in self.rows)} of {n} | |"])


def recipe_of(settings: Dict[str, Any]) -> Dict[str, Any]:
    """What makes two trainings the same recipe: their ``TrainSettings`` as a dict without ``seed`` and
    ``eval_draws``."""
    return {k: v for k, v in settings.items() if k not in ("seed", "eval_draws")}


def load_seed_table(path: str = SEEDS_FILE) -> Optional[SeedTable]:
    """The table in ``path`` (None when there is none); ValueError naming the file when malformed."""
    if not os.path.isfile(path):
        return None
    try:
        with open(path, encoding="utf-8") as f:
            return SeedTable.from_dict(json.load(f))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not an evaluator seed table ({e})") from None


def save_seed_table(table: SeedTable, path: str = SEEDS_FILE) -> str:
    """Write ``table`` to ``path`` atomically; returns the path."""
    from ...io.files import atomic_write_json

    atomic_write_json(path, table.to_dict())
    return path
