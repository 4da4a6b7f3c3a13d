"""What a value may be, in words: numeric intervals (:class:`Range`, shared by the config's checks
and the argparse types) and the closest valid name (``"; did you mean 'x'?"``)."""
from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import Iterable, Optional


class ConfigTypeError(TypeError, ValueError):
    """A config value of the wrong type (e.g. ``lipschitz="no"``). A ``TypeError`` that callers
    catching ``ValueError`` for bad configs also catch."""


@dataclass(frozen=True)
class Range:
    """A numeric interval: ``[lo, hi]``, open at an end when ``lo_open`` / ``hi_open``; a bound of
    None is unbounded."""

    lo: Optional[float] = None
    hi: Optional[float] = None
    lo_open: bool = False
    hi_open: bool = False

    def __contains__(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return not (self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi))

    def describe(self, integer: bool) -> str:
        """``"an integer >= 1"``, ``"a number in [0, 1)"``..."""
        name = "an integer" if integer else "a number"
        lo, hi = (None if b is None else str(b) if isinstance(b, int) else format(b, "g") for b in (self.lo, self.hi))
        if lo is not None and self.lo == self.hi and not (self.lo_open or self.hi_open):
            return f"{name} equal to {lo}"
        if lo is not None and hi is not None:
            return f"{name} in {'(' if self.lo_open else '['}{lo}, {hi}{')' if self.hi_open else ']'}"
        if lo is not None:
            return f"{name} {'>' if self.lo_open else '>='} {lo}"
        if hi is not None:
            return f"{name} {'<' if self.hi_open else '<='} {hi}"
        return name


def closest(word: str, candidates: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest candidate to ``word``, or ``""``."""
    cands = list(candidates)
    lower = {c.lower(): c for c in cands}
    hit = difflib.get_close_matches(str(word).lower(), list(lower), n=1, cutoff=0.6)
    return f"; did you mean {lower[hit[0]]!r}?" if hit else ""


