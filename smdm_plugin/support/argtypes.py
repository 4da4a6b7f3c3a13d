"""argparse ``type`` callables: range-checked numbers, booleans, ``none``/``auto`` for optional
values. A bad value is one argparse error line naming the option (exit status 2)."""
from __future__ import annotations

import argparse
import math
from typing import Any, Callable, Optional, Union

from .values import Range


def int_range(lo: Optional[int] = None, hi: Optional[int] = None) -> Callable[[str], int]:
    """argparse ``type``: an int in ``[lo, hi]`` (either bound may be None); a bad value is an
    argparse error naming the option (exit status 2)."""
    rng = Range(lo, hi)

    def parse(text: str) -> int:
        try:
            v = int(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v not in rng:
            raise argparse.ArgumentTypeError(f"must be {rng.describe(True)}, got {v}")
        return v

    parse.__name__ = "int"
    return parse


def float_range(lo: Optional[float] = None, hi: Optional[float] = None, *, lo_open: bool = False,
                hi_open: bool = False) -> Callable[[str], float]:
    """argparse ``type``: a finite float in ``[lo, hi]`` (``(lo`` / ``hi)`` when open)."""
    rng = Range(lo, hi, lo_open, hi_open)

    def parse(text: str) -> float:
        try:
            v = float(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(v) or v not in rng:
            raise argparse.ArgumentTypeError(f"must be a finite {rng.describe(False)[2:]}, got {text}")
        return v

    parse.__name__ = "float"
    return parse


def str2bool(text: Union[str, bool]) -> bool:
    """argparse ``type``: true/false, yes/no, on/off, 1/0 (any case)."""
    if isinstance(text, bool):
        return text
    s = str(text).strip().lower()
    if s in ("1", "true", "yes", "y", "on"):
        return True
    if s in ("0", "false", "no", "n", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected a boolean (true/false), got {text!r}")


def optional(parse: Callable[[str], Any]) -> Callable[[str], Any]:
    """``parse``, with ``none`` / ``auto`` (any case) giving None."""
    def parse_optional(text: str) -> Any:
        return None if text.strip().lower() in ("none", "auto") else parse(text)

    parse_optional.__name__ = getattr(parse, "__name__", "value")
    return parse_optional


def non_empty(text: str) -> str:
    """argparse ``type``: a non-empty string."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a non-empty string")
    return text
