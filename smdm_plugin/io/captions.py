"""HumanML3D captions: ``texts/<id>.txt``, one caption per line as
``caption#tok/POS tok/POS ...#from#to`` (``from``/``to``: seconds of the motion the caption
covers; ``0.0#0.0`` = the whole motion)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Sequence, Tuple


@dataclass(frozen=True)
class Caption:
    """One caption line: ``text`` (the sentence), ``tokens`` (``(word, POS)`` pairs, lemmatised as
    HumanML3D writes them), ``start``/``end`` (seconds; 0.0 both = the whole motion)."""

    text: str
    tokens: Tuple[Tuple[str, str], ...]
    start: float = 0.0
    end: float = 0.0


def parse_caption_line(line: str, where: str = "caption") -> Caption:
    """One ``caption#tok/POS ...#from#to`` line (``#from#to`` and the tokens may be absent);
    a ``ValueError`` names ``where`` when the caption is empty or the times are not numbers."""
    parts = line.rstrip("\r\n").split("#")
    text = parts[0].strip()
    if not text:
        raise ValueError(f"{where}: empty caption in line {line.strip()!r} (expected 'caption#tok/POS ...#from#to')")
    tokens = []
    if len(parts) > 1:
        for t in parts[1].split():
            word, _, pos = t.rpartition("/")
            tokens.append((word or pos, pos if word else ""))
    try:
        start = float(parts[2]) if len(parts) > 2 and parts[2].strip() else 0.0
        end = float(parts[3]) if len(parts) > 3 and parts[3].strip() else 0.0
    except ValueError:
        raise ValueError(f"{where}: the #from#to fields of {line.strip()!r} must be numbers (seconds)") from None
    return Caption(text, tuple(tokens), start, end)


def read_captions(path: str) -> List[Caption]:
    """Every caption of one ``texts/<id>.txt`` file (blank lines skipped); a ``ValueError`` names the
    file when it holds none."""
    lines = [ln for ln in Path(path).read_text(encoding="utf-8").splitlines() if ln.strip()]
    caps = [parse_caption_line(ln, f"{path}:{i + 1}") for i, ln in enumerate(lines)]
    if not caps:
        raise ValueError(f"{path}: no caption (expected lines 'caption#tok/POS ...#from#to')")
    return caps


def load_captions(root: str, ids: Sequence[str]) -> Dict[str, List[str]]:
    """``{id: [caption text, ...]}`` from ``<root>/texts/<id>.txt`` for every id; a missing file is a
    ``FileNotFoundError`` naming it (text conditioning needs a caption for every motion)."""
    out: Dict[str, List[str]] = {}
    for i in ids:
        p = Path(root) / "texts" / f"{i}.txt"
        if not p.is_file():
            raise FileNotFoundError(f"{p}: missing caption file (text conditioning needs texts/<id>.txt for "
                                    "every motion of the split)")
        out[i] = [c.text for c in read_captions(str(p))]
    return out
