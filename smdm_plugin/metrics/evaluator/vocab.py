"""Captions for the T2M evaluator: parts of speech, word vectors (the caption files: io/captions.py)."""
from __future__ import annotations

import io
import os
import pickle
from typing import Dict, List, Sequence, Tuple

import numpy as np


POS_CATEGORIES: Tuple[str, ...] = ("VERB", "NOUN", "DET", "ADP", "NUM", "AUX", "PRON", "ADJ", "ADV",
                                   "Loc_VIP", "Body_VIP", "Obj_VIP", "Act_VIP", "Desc_VIP", "OTHER")
POS_INDEX: Dict[str, int] = {p: i for i, p in enumerate(POS_CATEGORIES)}

#: word classes whose part of speech is replaced by the class (checked in this order)
VIP_WORDS: Tuple[Tuple[str, frozenset], ...] = (
    ("Loc_VIP", frozenset("left right clockwise counterclockwise anticlockwise forward back backward up down "
                          "straight curve".split())),
    ("Body_VIP", frozenset("arm chin foot feet face hand mouth leg waist eye knee shoulder thigh".split())),
    ("Obj_VIP", frozenset("stair dumbbell chair window floor car ball handrail baseball basketball".split())),
    ("Act_VIP", frozenset("walk run swing pick bring kick put squat throw hop dance jump turn stumble stop sit "
                          "lift lower raise wash stand kneel stroll rub bend balance flap jog shuffle lean rotate "
                          "spin spread climb".split())),
    ("Desc_VIP", frozenset("slowly carefully fast careful slow quickly happy angry sad happily angrily "
                           "sadly".split())),
)
SPECIAL_WORDS: Tuple[str, ...] = ("unk", "sos", "eos")
MAX_TEXT_LEN = 20


# ----------------------------------------------------------------------------------------- files
class _PlainUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):  # noqa: D102 - refuse every global
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}: only lists, dicts, str and numbers")


def safe_pickle_load(path: str) -> object:
    """Unpickle ``path`` allowing only built-in containers and scalars (no classes, no functions)."""
    with open(path, "rb") as f:
        data = f.read()
    try:
        return _PlainUnpickler(io.BytesIO(data)).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError) as e:
        raise ValueError(f"{path}: not a plain pickle of words / indices ({e})") from None


# ----------------------------------------------------------------------------------------- tokens
def token_pos(word: str, pos: str, known: bool) -> int:
    """Row of the one-hot part of speech: a VIP class for a known VIP word, else the tag (``OTHER``
    when unknown or the word is not in the vocabulary)."""
    if not known:
        return POS_INDEX["OTHER"]
    for name, words in VIP_WORDS:
        if word in words:
            return POS_INDEX[name]
    return POS_INDEX.get(pos, POS_INDEX["OTHER"])


def caption_tokens(tokens: Sequence[str], max_text_len: int = MAX_TEXT_LEN) -> List[str]:
    """``sos``, the first ``max_text_len`` tokens, ``eos`` (the evaluator's reading of a caption)."""
    return ["sos/OTHER"] + list(tokens[:max_text_len]) + ["eos/OTHER"]


def encode_tokens(tokens: Sequence[str], vocab: Dict[str, int], max_text_len: int = MAX_TEXT_LEN
                  ) -> Tuple[List[int], List[int]]:
    """Word rows and part-of-speech rows of a caption read as :func:`caption_tokens`; a word missing
    from ``vocab`` takes ``unk``'s row and ``OTHER``."""
    words, pos = [], []
    unk = vocab["unk"]
    for tok in caption_tokens(tokens, max_text_len):
        word, _, tag = tok.partition("/")
        row = vocab.get(word)
        words.append(unk if row is None else row)
        pos.append(token_pos(word, tag, row is not None))
    return words, pos


def load_glove(folder: str, prefix: str = "our_vab") -> Tuple[np.ndarray, Dict[str, int]]:
    """``(vectors [V, W] float32, word -> row)`` from T2M's GloVe files in ``folder``
    (``<prefix>_data.npy``, ``<prefix>_words.pkl``, ``<prefix>_idx.pkl``), read without running code."""
    paths = [os.path.join(folder, f"{prefix}_{s}") for s in ("data.npy", "words.pkl", "idx.pkl")]
    missing = [p for p in paths if not os.path.isfile(p)]
    if missing:
        raise FileNotFoundError(f"GloVe folder {folder!r}: missing {', '.join(os.path.basename(p) for p in missing)} "
                                "(T2M's glove.zip from the text-to-motion / MDM download scripts)")
    vectors = np.load(paths[0], allow_pickle=False)
    words, index = safe_pickle_load(paths[1]), safe_pickle_load(paths[2])
    if vectors.ndim != 2 or not isinstance(words, list) or not isinstance(index, dict):
        raise ValueError(f"GloVe folder {folder!r}: expected {prefix}_data.npy [V, W], a list of words and a "
                         f"dict word -> row; got shape {vectors.shape}, {type(words).__name__}, {type(index).__name__}")
    vocab: Dict[str, int] = {}
    for w in words:
        row = index.get(w)
        if not isinstance(w, str) or isinstance(row, bool) or not isinstance(row, (int, np.integer)) \
                or not 0 <= row < len(vectors):
            raise ValueError(f"GloVe folder {folder!r}: word {w!r} has row {row!r}, expected an int in "
                             f"[0, {len(vectors)})")
        vocab[w] = int(row)
    if "unk" not in vocab:
        raise ValueError(f"GloVe folder {folder!r}: the vocabulary has no 'unk' word")
    return vectors.astype(np.float32), vocab


def build_vocabulary(token_lists: Sequence[Sequence[str]], min_count: int = 1) -> Dict[str, int]:
    """Word -> row for word embeddings learned from a data set's own captions: ``unk``, ``sos``,
    ``eos`` then every word seen at least ``min_count`` times (sorted, so the table is reproducible)."""
    counts: Dict[str, int] = {}
    for tokens in token_lists:
        for tok in tokens:
            w = tok.partition("/")[0]
            counts[w] = counts.get(w, 0) + 1
    words = list(SPECIAL_WORDS) + sorted(w for w, c in counts.items() if c >= min_count and w not in SPECIAL_WORDS)
    return {w: i for i, w in enumerate(words)}
