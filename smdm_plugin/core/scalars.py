"""Numbers as users pass them: Python ``int``/``float``/``bool``, numpy scalars (``np.float32(0.8)``,
``np.int64(50)``, ``np.bool_(True)``) and 0-d arrays are accepted alike wherever a number is.

``np.float16``/``np.float32`` values become the Python float of their shortest decimal
(``np.float32(0.8)`` -> ``0.8``, not ``0.800000011920929``): what the user wrote, not its binary
rounding. Imports only numpy (``core.config`` and ``--help`` stay light).
"""
from __future__ import annotations

import numbers
from typing import Any, Optional

import numpy as np

__all__ = ["scalar", "is_bool", "is_int", "is_real", "as_float"]


def scalar(v: Any) -> Any:
    """``v`` with a 0-d numpy array unwrapped to its numpy scalar; anything else unchanged."""
    if isinstance(v, np.ndarray) and v.ndim == 0:
        return v[()]
    return v


def is_bool(v: Any) -> bool:
    """A Python or numpy bool."""
    return isinstance(scalar(v), (bool, np.bool_))


def is_int(v: Any) -> bool:
    """An integer (Python or numpy), not a bool."""
    v = scalar(v)
    return isinstance(v, (numbers.Integral, np.integer)) and not is_bool(v)


def is_real(v: Any) -> bool:
    """A real number (Python or numpy int/float), not a bool, not complex."""
    v = scalar(v)
    return isinstance(v, (numbers.Real, np.integer, np.floating)) and not is_bool(v)


def as_float(v: Any) -> Optional[float]:
    """``v`` as a Python float when :func:`is_real` (float16/32: their shortest decimal), else None.
    Huge integers that overflow a float give ``inf``."""
    v = scalar(v)
    if not is_real(v):
        return None
    if isinstance(v, (np.float16, np.float32)):
        return float(str(v)) if np.isfinite(v) else float(v)
    try:
        return float(v)
    except OverflowError:
        return float("inf")
