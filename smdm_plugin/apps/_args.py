"""Argument types shared by the ``smdm`` commands: every numeric option range-checked by argparse
(a bad value is one line naming the option, exit status 2, no traceback), devices that exist,
output paths that are never overwritten without ``--overwrite``."""
from __future__ import annotations

import argparse
import math
from typing import Callable, Optional

import torch


def int_range(lo: Optional[int] = None, hi: Optional[int] = None) -> Callable[[str], int]:
    """argparse ``type``: an int in ``[lo, hi]`` (either bound may be None)."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"must be {_range_text(lo, hi, int)}, got {v}")
        return v
    parse.__name__ = "int"
    return parse


def float_range(lo: Optional[float] = None, hi: Optional[float] = None, *, lo_open: bool = False,
                hi_open: bool = False) -> Callable[[str], float]:
    """argparse ``type``: a finite float in ``[lo, hi]`` (``(lo`` / ``hi)`` when open)."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        bad = not math.isfinite(v)
        bad |= lo is not None and (v <= lo if lo_open else v < lo)
        bad |= hi is not None and (v >= hi if hi_open else v > hi)
        if bad:
            raise argparse.ArgumentTypeError(
                f"must be {_range_text(lo, hi, float, lo_open, hi_open)}, got {text}")
        return v
    parse.__name__ = "float"
    return parse


def _range_text(lo, hi, kind, lo_open: bool = False, hi_open: bool = False) -> str:
    name = "an integer" if kind is int else "a number"
    if lo is not None and hi is not None:
        return f"{name} in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{name} {'>' if lo_open else '>='} {lo}"
    if hi is not None:
        return f"{name} {'<' if hi_open else '<='} {hi}"
    return name


def device_type(text: str) -> str:
    """argparse ``type``: ``auto``, ``cpu``, ``cuda``/``cuda:N`` or ``mps``, and only one this machine has."""
    if text == "auto":
        return text
    try:
        dev = torch.device(text)
    except (RuntimeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda, cuda:N or mps, got {text!r}") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise argparse.ArgumentTypeError(f"{text}: CUDA is not available on this machine")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise argparse.ArgumentTypeError(f"{text}: this machine has {torch.cuda.device_count()} "
                                             "CUDA device(s)")
    elif dev.type == "mps":
        mps = getattr(torch.backends, "mps", None)
        if mps is None or not mps.is_available():
            raise argparse.ArgumentTypeError(f"{text}: MPS is not available on this machine")
    elif dev.type != "cpu":
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda, cuda:N or mps, got {text!r}")
    return text


def add_overwrite(p: argparse.ArgumentParser) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing output files / write into a non-empty output folder")
