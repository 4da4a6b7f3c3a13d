"""HumanML3D caption files: ``texts/<id>.txt``, one caption a line, ``caption#word/POS ...#from#to``
(``from``/``to`` in seconds; ``0#0``: the whole motion; the words are lemmas with their spaCy part
of speech). Read by the HumanML3D loader (:func:`~smdm_plugin.io.humanml3d.load_humanml3d`) and
the T2M evaluator (``metrics/evaluator``).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import List

import numpy as np


@dataclass
class Caption:
    """One caption: ``text``, ``tokens`` (``word/POS``), and the motion span ``start``/``end`` in seconds
    (both 0: the whole motion)."""

    text: str
    tokens: List[str]
    start: float = 0.0
    end: float = 0.0


def parse_caption_line(line: str, where: str = "caption") -> Caption:
    """``caption#word/POS ...#from#to`` -> :class:`Caption` (a line with no ``#``: the words, POS ``OTHER``)."""
    parts = line.strip().split("#")
    if len(parts) == 1:
        return Caption(parts[0], plain_tokens(parts[0]))
    if len(parts) < 2:
        raise ValueError(f"{where}: expected 'caption#word/POS ...#from#to', got {line.strip()!r}")
    tokens = [t for t in parts[1].split(" ") if t]
    if not tokens:
        tokens = plain_tokens(parts[0])
    tokens = [t if "/" in t else f"{t}/OTHER" for t in tokens]
    start = end = 0.0
    if len(parts) >= 4:
        try:
            start, end = float(parts[2]), float(parts[3])
        except ValueError:
            raise ValueError(f"{where}: from/to must be numbers (seconds), got {parts[2]!r}, {parts[3]!r}") from None
        start, end = (0.0 if np.isnan(start) else start), (0.0 if np.isnan(end) else end)
    return Caption(parts[0], tokens, start, end)


def plain_tokens(text: str) -> List[str]:
    """Lower-case words of ``text`` as ``word/OTHER`` tokens (captions without POS tags)."""
    return [f"{w}/OTHER" for w in re.findall(r"[a-z0-9']+", text.lower())]


def read_captions(path: str) -> List[Caption]:
    """Every caption of a HumanML3D ``texts/<id>.txt`` file (blank lines skipped); a file that is
    not UTF-8 text (or a folder) is a ``ValueError`` naming it."""
    try:
        with open(path, "rb") as f:
            text = f.read().decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text (byte {e.start}: {e.reason})") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: is a folder, expected a caption text file") from None
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")  # as open()'s universal newlines
    return [parse_caption_line(l, f"{path}:{i + 1}") for i, l in enumerate(lines) if l.strip()]
