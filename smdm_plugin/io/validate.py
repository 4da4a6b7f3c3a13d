"""Checks for what a load read: every error names the file and the field (``ValueError``).

One helper per idea, used by every loader (:mod:`~smdm_plugin.io.checkpoint_files`,
:mod:`~smdm_plugin.training.bundle`, :func:`smdm_plugin.training.trainer.load_trained`, the data loaders):
JSON decoded with an error naming the file, required fields present (a missing field is an error,
not a default), settings of the right type and range, mean/std real, finite, of the right length
and std > 0, arrays real and finite.
"""
from __future__ import annotations

import json
import math
import os
from typing import Any, Dict, Iterable, Mapping, Optional

import numpy as np

from ..core.scalars import as_float, is_int

__all__ = ["read_json_object", "require_fields", "int_field", "float_field", "check_stats", "check_array",
           "check_magnitude", "load_npy", "load_feature_motion", "MAX_ABS_VALUE"]

#: the largest float32: what is read is computed in float32
F32_MAX = float(np.finfo(np.float32).max)
#: no value of a motion goes beyond this (metres, radians, velocities, a BVH's own units): past it the
#: file is no motion, and every metric of it would overflow (the BVH reader's bound too)
MAX_ABS_VALUE = 1e7


def read_json_object(path: str) -> Dict[str, Any]:
    """The JSON object in ``path`` (UTF-8, optional BOM); ``ValueError`` naming the file when it
    is not valid UTF-8, not JSON or not an object; ``FileNotFoundError`` when missing."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except IsADirectoryError:
        raise ValueError(f"{path}: is a folder, expected a JSON file") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text (byte {e.start}: {e.reason})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON: {e}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def require_fields(d: Mapping[str, Any], names: Iterable[str], where: str) -> None:
    """``ValueError`` naming ``where`` and every field of ``names`` missing from ``d``."""
    missing = [n for n in names if n not in d]
    if missing:
        raise ValueError(f"{where}: missing field(s) {', '.join(missing)} (the file is incomplete; write it again)")


def int_field(d: Mapping[str, Any], name: str, where: str, lo: int = 1, hi: Optional[int] = None) -> int:
    """``d[name]`` as an int in ``[lo, hi]`` (required)."""
    require_fields(d, [name], where)
    v = d[name]
    if not is_int(v) or v < lo or (hi is not None and v > hi):
        rng = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ValueError(f"{where}: {name}={v!r}: expected an integer {rng}")
    return int(v)


def float_field(d: Mapping[str, Any], name: str, where: str, lo: float = 0.0, lo_open: bool = True) -> float:
    """``d[name]`` as a finite float ``> lo`` (``>= lo`` unless ``lo_open``) (required)."""
    require_fields(d, [name], where)
    x = as_float(d[name])
    if x is None or not math.isfinite(x) or x < lo or (lo_open and x == lo):
        raise ValueError(f"{where}: {name}={d[name]!r}: expected a finite number {'>' if lo_open else '>='} {lo}")
    return x


def check_array(a: Any, where: str, what: str = "values", shape: Optional[tuple] = None) -> np.ndarray:
    """``a`` as a real, finite numeric numpy array (of ``shape`` when given; ``-1`` = any)."""
    arr = np.asarray(a)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{where}: {what} must be real numbers, got dtype {arr.dtype}")
    if shape is not None and (arr.ndim != len(shape) or any(s not in (-1, n) for s, n in zip(shape, arr.shape))):
        want = "[" + ", ".join("*" if s == -1 else str(s) for s in shape) + "]"
        raise ValueError(f"{where}: {what} must have shape {want}, got {list(arr.shape)}")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0].tolist()
        raise ValueError(f"{where}: {what} holds a non-finite value ({arr[tuple(bad)]} at index {bad})")
    if arr.dtype.kind in "fiu" and arr.dtype.itemsize > 4 and arr.size:
        # what is read is computed in float32: a float64 beyond its range would become inf there
        big = float(np.abs(arr).max())
        if big > F32_MAX:
            bad = np.unravel_index(int(np.argmax(np.abs(arr))), arr.shape)
            raise ValueError(f"{where}: {what} holds {big:.3g} at index {list(map(int, bad))}, beyond float32's "
                             f"range (±{F32_MAX:.3g})")
    return arr


def check_magnitude(arr: np.ndarray, where: str, what: str = "motion values") -> np.ndarray:
    """``arr`` (real, finite) when every value is within ±:data:`MAX_ABS_VALUE`; else a ``ValueError``
    naming ``where``, ``what`` (plural: ``"joint positions"``), the largest value and its index."""
    if arr.size:
        i = int(np.argmax(np.abs(arr)))
        big = float(np.abs(arr.reshape(-1)[i]))
        if big > MAX_ABS_VALUE:
            at = [int(k) for k in np.unravel_index(i, arr.shape)]
            raise ValueError(f"{where}: {what} reach {big:.3g} at index {at} (beyond ±{MAX_ABS_VALUE:g}); expected "
                             "a motion in metres, radians or a BVH's own units")
    return arr


def check_stats(mean: Any, std: Any, dim: int, where: str) -> "tuple[np.ndarray, np.ndarray]":
    """Feature ``mean``/``std`` ``[dim]``: real, finite, std > 0; returned as float32."""
    m = check_array(mean, where, "mean", (dim,)).astype(np.float32)
    s = check_array(std, where, "std", (dim,)).astype(np.float32)
    if (s <= 0).any():
        i = int(np.argmax(s <= 0))
        raise ValueError(f"{where}: std must be > 0 everywhere, got {s[i]} at index {i}")
    return m, s


def load_npy(path: str, what: str = "array") -> np.ndarray:
    """``np.load`` of a ``.npy`` file (no pickles) with one-line errors naming it: a folder where
    the file belongs, an unreadable or truncated file."""
    if os.path.isdir(path):
        raise ValueError(f"{path}: is a folder, expected a .npy file ({what})")
    try:
        return np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise
    except (ValueError, OSError, EOFError) as e:
        raise ValueError(f"{path}: not a readable .npy file ({what}): {' '.join(str(e).split())}") from None


def load_feature_motion(path: str, dim: int, min_len: int = 4, what: str = "motion features") -> np.ndarray:
    """A ``.npy`` of raw per-frame features ``[L >= min_len, dim]`` (``smdm eval --motions``) as
    float32, with one-line errors naming the file: empty / truncated / not a ``.npy``, another
    shape, not real floats (complex, integers), NaN / inf, values beyond float32's range or
    :data:`MAX_ABS_VALUE`."""
    m = load_npy(path, what)
    if m.dtype.kind != "f" or m.ndim != 2 or m.shape[1] != dim or len(m) < min_len:
        raise ValueError(f"{path}: expected raw features [L >= {min_len}, {dim}] of real floats, got "
                         f"{list(m.shape)} {m.dtype}")
    return check_magnitude(check_array(m, path, what), path, what).astype(np.float32)
